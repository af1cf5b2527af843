"""A reconstructed contact's shape against the clean contact of the same press, and where its error arises.

For the benchmark's simulated pairs (`--seed`, as `yoto bench` and `benchmarks/image_pose_budget.py` simulate them),
each side's noise-free gel height map is rendered into a GelSight image (`--renderer`: a calibration file's fitted
optical model or `shading[:SEED]`, with the same per-image noise the benchmark draws), reconstructed, and compared with
the truth over the true contact. Three reconstructions of each contact split the error:
- `true`: the TRUE gradients of the height map integrated by our solver in the box the reconstruction chose (the
  integration's and the boundary's share);
- `clean`: the image rendered without noise, reconstructed (adds the colour -> gradient model's share);
- `image`: the image as the benchmark renders it (adds the noise's share).
Per contact and reconstruction: the depth ratio (2nd-percentile depth over the true contact, reconstructed / true), a
quadric over the deeper half of the true contact (pixels at least half as deep as the deepest): its mean curvature
ratio and its anisotropy (|H_rec - s H_true|_F / |H_true|_F with s the mean curvature ratio: the part of the curvature
error that is no scale), and the RMS height error over the true contact after a plane and a depth scale (mm), and
after a plane and a depth scale that leans (true heights z times s + a u + b v, (u, v) the sensor (x, y) about the
contact's centre per its RMS radius: what the pose stage's depth scale and its slopes could take up), with the lean
|(a, b)|. For the `clean` reconstruction also the gradients read against the true ones over the contact: the
least-squares gains (x, y) and the RMS gradient error. Prints one line per contact (with `--verbose`) and, per object
and over all, the median and p10-p90 of each figure. With `--bases`, also the RMS of the `image` reconstruction's
height error left after nested bases in (u, v): an offset, + a tilt, + u^2 + v^2, + u^2 - v^2 and u v, + the cubics;
and after the pose stage's own freedoms (offset, tilt, depth scale: true heights z), + the lean (z u, z v), + the
anisotropic quadratic, + the cubics. `--flat-change-off` renders through the table renderer (`table:FOLDER`) with its
pressed gel's colour change at zero slope switched off (faded in at no depth: what stops 17-18 compared with).

    python benchmarks/image_contact_shape.py --renderer CAL_GAIN.npz -n 20 --seed 7 \\
        --objects figurine ../shared/data/meshes/avocado/avocado.ply ../shared/data/meshes/mug/mug.ply
"""

from __future__ import annotations

import argparse

import numpy as np

STAGES = ("true", "clean", "image")


def quadric_hessian(height_m: np.ndarray, mask: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """2x2 Hessian (1/m) of the quadric z = c + a x + b y + (h_xx x^2 + 2 h_xy x y + h_yy y^2) / 2 fitted on `mask`."""
    xs, ys = x[mask] - x[mask].mean(), y[mask] - y[mask].mean()
    design = np.stack([np.ones_like(xs), xs, ys, xs * xs, xs * ys, ys * ys], axis=1)
    c, *_ = np.linalg.lstsq(design, height_m[mask].astype(np.float64), rcond=None)
    return np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])


def shape_figures(height_m, truth_m, felt, deep, x, y) -> dict[str, float]:
    """Depth ratio, mean curvature ratio, anisotropy and RMS after a plane and a depth scale (mm) of one height map."""
    depth = float(np.percentile(height_m[felt], 2) / np.percentile(truth_m[felt], 2))
    h_true = quadric_hessian(truth_m, deep, x, y)
    h_rec = quadric_hessian(height_m, deep, x, y)
    ratio = float(np.trace(h_rec) / np.trace(h_true))
    anisotropy = float(np.linalg.norm(h_rec - ratio * h_true) / np.linalg.norm(h_true))
    design = np.stack([truth_m[felt], np.ones(int(felt.sum())), x[felt], y[felt]], axis=1).astype(np.float64)
    target = height_m[felt].astype(np.float64)
    c, *_ = np.linalg.lstsq(design, target, rcond=None)
    rms = float(np.sqrt(np.mean((target - design @ c) ** 2)) * 1e3)
    u, v = contact_uv(felt, x, y)
    leaning = np.column_stack([design, design[:, 0] * u, design[:, 0] * v])
    c, *_ = np.linalg.lstsq(leaning, target, rcond=None)
    rms_lean = float(np.sqrt(np.mean((target - leaning @ c) ** 2)) * 1e3)
    return {
        "depth": depth,
        "curvature": ratio,
        "anisotropy": anisotropy,
        "rms_mm": rms,
        "rms_lean_mm": rms_lean,
        "lean": float(np.hypot(c[4], c[5]) / max(c[0], 1e-9)),
    }


def contact_uv(felt, x, y) -> tuple[np.ndarray, np.ndarray]:
    """The felt pixels' sensor (x, y) about their centre, per their RMS radius."""
    xs, ys = x[felt] - x[felt].mean(), y[felt] - y[felt].mean()
    radius = max(float(np.sqrt(np.mean(xs**2 + ys**2))), 1e-9)
    return xs / radius, ys / radius


# `--bases`: nested bases of the height error (u, v about the contact's centre per its RMS radius; z the true height
# over the deepest's depth); each set is the one before it plus its own terms.
NESTED_BASES = {
    "offset": ("1",),
    "+tilt": ("u", "v"),
    "+isotropic quadratic": ("uu+vv",),
    "+anisotropic quadratic": ("uu-vv", "uv"),
    "+cubic": ("uuu", "uuv", "uvv", "vvv"),
}
POSE_STAGE_BASES = {
    "offset+tilt+depth scale": ("1", "u", "v", "z"),
    "+lean": ("zu", "zv"),
    "+anisotropic quadratic, after the lean": ("uu-vv", "uv"),
    "+isotropic quadratic and cubics": ("uu+vv", "uuu", "uuv", "uvv", "vvv"),
}


def basis_residuals(height_m, truth_m, felt, x, y) -> dict[str, float]:
    """RMS (mm) of the height error over the true contact left after each nested basis set (`NESTED_BASES`, then
    `POSE_STAGE_BASES`)."""
    u, v = contact_uv(felt, x, y)
    z = truth_m[felt].astype(np.float64) / -float(truth_m[felt].min())
    terms = {
        "1": np.ones_like(u),
        "u": u,
        "v": v,
        "uu+vv": u * u + v * v,
        "uu-vv": u * u - v * v,
        "uv": u * v,
        "uuu": u**3,
        "uuv": u * u * v,
        "uvv": u * v * v,
        "vvv": v**3,
        "z": z,
        "zu": z * u,
        "zv": z * v,
    }
    error = (height_m[felt] - truth_m[felt]).astype(np.float64)
    out = {}
    for sets in (NESTED_BASES, POSE_STAGE_BASES):
        names: list[str] = []
        for label, added in sets.items():
            names += added
            design = np.column_stack([terms[name] for name in names])
            c, *_ = np.linalg.lstsq(design, error, rcond=None)
            out[label] = float(np.sqrt(np.mean((error - design @ c) ** 2)) * 1e3)
    return out


def gradient_figures(read, true, felt) -> dict[str, float]:
    """Least-squares gain of the read gradients on the true ones (x, y) over `felt`, and the RMS error."""
    out = {}
    for axis, name in enumerate("xy"):
        t, r = true[axis][felt], read[axis][felt]
        out[f"gain_{name}"] = float(np.dot(t, r) / max(np.dot(t, t), 1e-12))
    error = np.hypot(read[0][felt] - true[0][felt], read[1][felt] - true[1][felt])
    out["gradient_rms"] = float(np.sqrt(np.mean(error**2)))
    out["slope_rms"] = float(np.sqrt(np.mean(true[0][felt] ** 2 + true[1][felt] ** 2)))
    return out


def contact_rows(route, height_m, x, y, calibration, bases: bool = False) -> dict[str, dict[str, float]] | None:
    """Figures of one contact's three reconstructions (module docstring), or None where it gives no contact."""
    from yoto.errors import InputError
    from yoto.sensor.optical import height_gradients, render_image
    from yoto.sensor.reconstruction import block_change, integrate_box, reconstruct

    spec = calibration.spec
    felt = height_m < -5e-5
    deep = height_m <= 0.5 * height_m.min()
    if felt.sum() < 40 or deep.sum() < 20:
        return None
    try:
        noisy_image = route.image(height_m)
        clean_image = route.render(height_m, None) if route.render is not None else render_image(height_m, calibration)
        noisy = reconstruct(noisy_image, calibration)
        clean = reconstruct(clean_image, calibration, keep_gradients=True)
    except InputError:
        return None
    if not (noisy.contact and clean.contact) or clean.box is None or clean.gradients is None:
        return None
    true_gradients = height_gradients(height_m, spec.pixel_size_m)
    row0, row1, col0, col1 = clean.box
    in_box = np.zeros(height_m.shape, bool)
    in_box[row0:row1, col0:col1] = True
    gx = np.where(in_box, true_gradients[0], 0.0).astype(np.float32)
    gy = np.where(in_box, true_gradients[1], 0.0).astype(np.float32)
    integrated = integrate_box(
        gx, gy, clean.box, block_change(clean_image, calibration.background_i16), spec.pixel_size_m
    )
    rows = {
        "true": shape_figures(integrated, height_m, felt, deep, x, y),
        "clean": shape_figures(clean.height_map_m, height_m, felt, deep, x, y),
        "image": shape_figures(noisy.height_map_m, height_m, felt, deep, x, y),
    }
    rows["clean"].update(gradient_figures(clean.gradients, true_gradients, felt))
    if bases:
        rows["bases"] = basis_residuals(noisy.height_map_m, height_m, felt, x, y)
    rows["where"] = {"x": float(x[felt].mean() * 1e3), "y": float(y[felt].mean() * 1e3), "area": float(felt.mean())}
    return rows


def summary(label: str, contacts: list[dict]) -> None:
    def spread(stage: str, key: str, digits: int = 3) -> str:
        values = np.array([c[stage][key] for c in contacts])
        p10, p50, p90 = np.percentile(values, [10, 50, 90])
        return f"{p50:.{digits}f} ({p10:.{digits}f}-{p90:.{digits}f})"

    print(f"{label} ({len(contacts)} contacts)")
    for stage in STAGES:
        print(
            f"  {stage:>5}: depth {spread(stage, 'depth')}, curvature {spread(stage, 'curvature')}, anisotropy "
            f"{spread(stage, 'anisotropy')}, rms after plane+scale {spread(stage, 'rms_mm', 4)} mm, + lean "
            f"{spread(stage, 'rms_lean_mm', 4)} mm (lean {spread(stage, 'lean')})"
        )
    print(
        f"  gradients (clean image): gain x {spread('clean', 'gain_x')}, y {spread('clean', 'gain_y')}, "
        f"rms {spread('clean', 'gradient_rms', 4)} at slope rms {spread('clean', 'slope_rms', 3)}"
    )
    if "bases" in contacts[0]:
        for sets in (NESTED_BASES, POSE_STAGE_BASES):
            print(
                "  image height error left (mm): " + ", ".join(f"{label} {spread('bases', label, 4)}" for label in sets)
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--renderer", required=True, help="calibration file, shading[:SEED] or table:FOLDER")
    parser.add_argument("--objects", nargs="+", required=True)
    parser.add_argument("-n", type=int, default=20, help="pairs per object (two contacts each)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument(
        "--variation",
        type=float,
        default=0.0,
        help="optics varied per benchmark image (0: none, 1: large); the noise-free stage keeps the nominal optics",
    )
    parser.add_argument("--verbose", action="store_true", help="one line per contact")
    parser.add_argument("--bases", action="store_true", help="the height error left after nested bases")
    parser.add_argument(
        "--flat-change-off", action="store_true", help="table:FOLDER without its pressed gel's zero-slope change"
    )
    args = parser.parse_args()

    from yoto.evaluation.bench import BenchConfig, benchmark_simulator, resolve_object
    from yoto.sensor.optical import image_path_reconstructor, image_route

    route = image_route(args.renderer, args.variation)
    if args.flat_change_off:
        from dataclasses import replace
        from pathlib import Path

        from yoto.sensor.table import table_sensor_and_calibration

        if not args.renderer.startswith("table:"):
            parser.error("--flat-change-off needs --renderer table:FOLDER")
        sensor, table_calibration = table_sensor_and_calibration(str(Path(args.renderer.partition(":")[2]).resolve()))
        # faded in over an unreachable depth: every pixel's zero-slope change taken off again, pressed or not
        route = image_path_reconstructor(table_calibration, render=replace(sensor, pressed_depth_m=1e12).render)
    calibration = route.calibration
    x, y = calibration.spec.pixel_xy_sensor()
    bench = BenchConfig(num_pairs=args.n, seed=args.seed)
    everything = []
    for name in args.objects:
        model = resolve_object(name, None)
        simulator = benchmark_simulator(model, bench)
        contacts = []
        for index in range(args.n):
            simulated = simulator.pair(args.seed, index)
            for side in ("left", "right"):
                rows = contact_rows(route, simulated.height_maps[side], x, y, calibration, args.bases)
                if rows is None:
                    continue
                contacts.append(rows)
                if args.verbose:
                    where = rows["where"]
                    print(
                        f"{model.name} {index} {side} at ({where['x']:+.1f}, {where['y']:+.1f}) mm, area "
                        f"{where['area']:.0%}: "
                        + "; ".join(
                            f"{stage} depth {rows[stage]['depth']:.3f} curv {rows[stage]['curvature']:.3f} "
                            f"aniso {rows[stage]['anisotropy']:.3f} rms {rows[stage]['rms_mm']:.4f}"
                            for stage in STAGES
                        )
                        + f"; gains {rows['clean']['gain_x']:.3f} / {rows['clean']['gain_y']:.3f}",
                        flush=True,
                    )
        summary(f"{model.name} ({args.renderer}, seed {args.seed})", contacts)
        everything += contacts
    if len(args.objects) > 1:
        summary(f"all ({args.renderer}, seed {args.seed})", everything)


if __name__ == "__main__":
    main()
