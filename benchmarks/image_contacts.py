"""Contacts through GelSight images: how much of a contact's shape the reconstruction keeps, and where it localizes.

For simulated contacts on each object (the benchmark's pairs, seed 7), the noise-free gel height map is rendered
into an image (`--renderer`: a calibration file's own optical model, or `shading[:SEED]`, the second optical model
calibrated from ball presses it renders), reconstructed, and compared with the truth:
- depth (deepest point) ratio, RMS height error over the felt contact (raw, and after removing a plane, which the
  matched filter ignores), principal curvature radii of a quadric fitted over the contact (true / reconstructed);
- the share of the felt contact (true depth > 0.05 mm) covered by the localization mask and by the core;
- the share of the mask steeper than the calibration's slope range (truly, and as read: above 0.9 of it);
- the matched filter's top-1 localization error for the clean cloud and for the image's cloud.
With `--figures DIR`, one PNG per contact: the image, the reconstructed height, the localization mask (and its
core), and the localized contact on the object next to the truth.

    python benchmarks/image_contacts.py --renderer CAL.npz --objects fruit figurine -n 6 --figures docs/figures/contacts
"""

from __future__ import annotations

import argparse
import io
import itertools
from pathlib import Path

import numpy as np


def quadric_radii_mm(height_m: np.ndarray, mask: np.ndarray, spec) -> tuple[float, float]:
    """Principal curvature radii (mm, signed: positive for a convex object) of the quadric fitted to the mask."""
    x, y = spec.pixel_xy_sensor()
    xs, ys = x[mask], y[mask]
    design = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys], axis=1)
    c, *_ = np.linalg.lstsq(design, height_m[mask].astype(np.float64), rcond=None)
    curvatures = np.linalg.eigvalsh(np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]]))
    return tuple(float(1e3 / k) if abs(k) > 1e-6 else float("inf") for k in curvatures[::-1])  # type: ignore[return-value]


def plane_residual_mm(error_m: np.ndarray, mask: np.ndarray, spec) -> float:
    x, y = spec.pixel_xy_sensor()
    design = np.stack([np.ones(int(mask.sum())), x[mask], y[mask]], axis=1)
    c, *_ = np.linalg.lstsq(design, error_m[mask], rcond=None)
    return float(np.sqrt(np.mean((error_m[mask] - design @ c) ** 2)) * 1e3)


def draw(path: Path, title: str, image, recon, model, estimate, truth_p, T_object_sensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from yoto.io import write_bytes_atomic

    figure = plt.figure(figsize=(15, 3.4))
    axes = [figure.add_subplot(1, 4, k + 1) for k in range(3)] + [figure.add_subplot(1, 4, 4, projection="3d")]
    axes[0].imshow(image)
    axes[0].set_title("GelSight image", fontsize=9)
    shown = axes[1].imshow(recon.height_map_m * 1e3, cmap="viridis")
    figure.colorbar(shown, ax=axes[1], fraction=0.046, label="z (mm)")
    axes[1].set_title("reconstructed height", fontsize=9)
    overlay = np.zeros(recon.mask.shape + (3,))
    overlay[recon.mask] = (0.2, 0.6, 1.0)
    overlay[recon.core_mask] = (1.0, 0.8, 0.2)
    axes[2].imshow(overlay)
    axes[2].set_title("localization mask (blue) and its core (yellow)", fontsize=9)
    for axis in axes[:3]:
        axis.set_xticks([])
        axis.set_yticks([])
    # The object around the true contact, seen along its normal; the contact placed by the true sensor pose and
    # by the pose the localizer found.
    near = np.linalg.norm(model.points_object - truth_p, axis=1) < 0.03
    cloud = model.points_object[near][:: max(1, int(near.sum()) // 5000)]
    axes[3].scatter(*cloud.T, s=0.4, c="0.7", alpha=0.5)
    samples = recon.points_sensor[:: max(1, len(recon.points_sensor) // 800)]
    placements = [(T_object_sensor, "tab:green", "contact, true pose")]
    if "match_T_object_sensor" in estimate.details:
        placements.append((np.asarray(estimate.details["match_T_object_sensor"]), "tab:red", "contact, localized"))
    for T, colour, label in placements:
        axes[3].scatter(*((T[:3, :3] @ samples.T).T + T[:3, 3]).T, s=1.5, c=colour, label=label)
    axes[3].scatter(*estimate.p_object, s=80, c="tab:red", marker="x")
    normal = model.aggregated_normal(truth_p)
    axes[3].view_init(
        elev=float(np.degrees(np.arcsin(np.clip(normal[2], -1, 1)))),
        azim=float(np.degrees(np.arctan2(normal[1], normal[0]))),
    )
    axes[3].set_axis_off()
    axes[3].legend(fontsize=7, loc="lower left", markerscale=4)
    axes[3].set_title("on the object (30 mm around the true contact)", fontsize=9)
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=64)
    plt.close(figure)
    # A 256-colour palette: the figures live in the repository, a third of the size and the same to the eye.
    from PIL import Image

    buffer.seek(0)
    small = io.BytesIO()
    Image.open(buffer).convert("RGB").quantize(256).save(small, format="png", optimize=True)
    write_bytes_atomic(path, small.getvalue())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--renderer", required=True, help="calibration file, or shading[:SEED]")
    parser.add_argument("--objects", nargs="+", default=["fruit", "figurine", "tool"])
    parser.add_argument("-n", type=int, default=10, help="contacts per object")
    parser.add_argument("--pairs", type=int, nargs="+", help="these pair indices (both sides), not the first")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--workspace", help="workspace holding the object models")
    parser.add_argument("--figures", help="write one PNG per contact into this folder")
    parser.add_argument("--json", help="write the per-contact rows here")
    args = parser.parse_args()

    from yoto.evaluation.bench import resolve_object
    from yoto.localize import make_localizer
    from yoto.provenance import run_info
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.reconstruction import reconstruct
    from yoto.simulate.scenarios import PairSimulator

    if args.renderer.startswith("shading"):
        from yoto.sensor.shading import ShadingSensor, calibrate_shading_sensor

        seed = int(args.renderer.partition(":")[2] or 0)
        rng = np.random.default_rng(seed)
        sensor = ShadingSensor() if seed == 0 else ShadingSensor().varied(rng, 1.0)
        calibration = calibrate_shading_sensor(sensor, rng)
        render = sensor.render
    else:
        from yoto.sensor.optical import render_image

        calibration = load_calibration(args.renderer)

        def render(height, rng):
            return render_image(height, calibration, rng)

    spec = calibration.spec
    slope_limit = calibration.image_model.max_gradient  # the largest slope the calibration saw (its 99.5th percentile)
    localizer = make_localizer("match")
    rows = []
    for name in args.objects:
        model = resolve_object(name, args.workspace)
        simulator = PairSimulator(model)
        limit = 2 * len(args.pairs) if args.pairs else args.n
        done = 0
        for index in args.pairs or itertools.count():
            if done >= limit:
                break
            simulated = simulator.pair(args.seed, index)
            for side in ("left", "right"):
                if done >= limit:
                    break
                press = simulated.contacts[side].press
                truth = press.height_map_m
                image = render(truth, np.random.default_rng(1000 * (index + 1) + done))
                recon = reconstruct(image, calibration, keep_gradients=True)
                felt = truth < -5e-5
                row = {
                    "object": model.name,
                    "pair": index,
                    "side": side,
                    "contact_mm2": float(press.contact_mask.sum() * spec.pixel_size_m**2 * 1e6),
                    "touches_border": bool(recon.touches_border),
                    "reconstructed": bool(recon.contact),
                }
                done += 1
                if not recon.contact:
                    rows.append(row)
                    continue
                error = recon.height_map_m.astype(np.float64) - truth
                assert recon.gradients is not None
                true_slope = np.hypot(*np.gradient(truth, spec.pixel_size_m))
                row.update(
                    depth_ratio=float(recon.max_depth_m / -truth.min()),
                    rms_mm=float(np.sqrt(np.mean(error[felt] ** 2)) * 1e3),
                    rms_after_plane_mm=plane_residual_mm(error, felt, spec),
                    radii_true_mm=quadric_radii_mm(truth, press.contact_mask, spec),
                    radii_reconstructed_mm=quadric_radii_mm(recon.height_map_m, press.contact_mask, spec),
                    mask_covers=float((recon.mask & felt).sum() / felt.sum()),
                    steep_true=float(np.mean(true_slope[recon.mask] > slope_limit)),
                    steep_read=float(np.mean(np.hypot(*recon.gradients)[recon.mask] > 0.9 * slope_limit)),
                    core_covers=float((recon.core_mask & felt).sum() / felt.sum()),
                )
                p_true = simulated.contacts[side].p_object
                clean = localizer.localize(simulated.pair.contact(side).points_sensor, model)[0]
                found = localizer.localize(recon.points_sensor, model)[0]
                row["localization_clean_mm"] = float(1e3 * np.linalg.norm(clean.p_object - p_true))
                row["localization_image_mm"] = float(1e3 * np.linalg.norm(found.p_object - p_true))
                rows.append(row)
                print(
                    f"{model.name} pair {row['pair']} {side}: depth x{row['depth_ratio']:.2f}, rms "
                    f"{row['rms_mm']:.3f} mm ({row['rms_after_plane_mm']:.3f} after a plane), radii "
                    f"{row['radii_true_mm'][0]:.0f}/{row['radii_true_mm'][1]:.0f} -> "
                    f"{row['radii_reconstructed_mm'][0]:.0f}/{row['radii_reconstructed_mm'][1]:.0f} mm, mask covers "
                    f"{row['mask_covers']:.0%} (core {row['core_covers']:.0%}), beyond the calibrated slope: true "
                    f"{row['steep_true']:.0%}, read {row['steep_read']:.0%}, localization clean "
                    f"{row['localization_clean_mm']:.1f} mm, image {row['localization_image_mm']:.1f} mm"
                )
                if args.figures:
                    title = (
                        f"{model.name}, pair {row['pair']} {side}: depth x{row['depth_ratio']:.2f}, "
                        f"localized {row['localization_image_mm']:.1f} mm from the truth "
                        f"(clean cloud: {row['localization_clean_mm']:.1f} mm)"
                    )
                    path = Path(args.figures) / f"{model.name}_{row['pair']:03d}_{side}.png"
                    draw(path, title, image, recon, model, found, p_true, press.T_object_sensor)
    ok = [r for r in rows if r["reconstructed"]]
    print(f"\n{len(ok)}/{len(rows)} contacts reconstructed")
    for name in [*args.objects, None]:
        sel = [r for r in ok if name is None or r["object"] == Path(name).stem]
        if not sel:
            continue

        def med(key, sel=sel):
            return float(np.median([r[key] for r in sel]))

        def share(key, sel=sel):
            return float(np.mean([r[key] < 5.0 for r in sel]))

        print(
            f"{name or 'all':10s} n={len(sel)}: depth x{med('depth_ratio'):.3f}, rms {med('rms_mm'):.3f} mm "
            f"({med('rms_after_plane_mm'):.3f} after a plane), mask covers {med('mask_covers'):.0%} (core "
            f"{med('core_covers'):.0%}); localization within 5 mm: clean {share('localization_clean_mm'):.0%}, "
            f"image {share('localization_image_mm'):.0%}"
        )
    if args.json:
        from yoto.io import write_json_atomic

        write_json_atomic(args.json, {"run": run_info(), "renderer": args.renderer, "contacts": rows})


if __name__ == "__main__":
    main()
