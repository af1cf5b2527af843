"""Contacts through GelSight images: the pose stage's per-contact depth scale against the truth, and what it adds.

For the benchmark's simulated pairs (seed 7, 1 mm / 1 deg calibration error), each contact's noise-free gel height
map is rendered into an image (`--renderer`: a calibration file's own optical model, or `shading[:SEED]`) and
reconstructed (`yoto bench --via-images`). Each pair is localized once (matched filter) and its pose estimated
twice on the same clouds: with the reconstruction's depth-scale prior (`TactileContact.depth_scale_sigma`, the
pose stage estimates a scale per contact) and with the heights taken as exact (sigma 0, the stage before). Per
contact it prints the true depth scale (least squares of the true heights on the reconstructed ones over the
contact's mask: the factor that would make the reconstruction's heights right) next to the estimated one; per
object, poses within 5 mm / 5 deg, truth among the hypotheses, and the pose stage's CPU time per pair, both ways.

    python benchmarks/image_depth_scale.py --renderer CAL.npz --objects figurine cracker_box.ply -n 20 --json out.json
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np


def true_depth_scale(true_height_m: np.ndarray, reconstructed_height_m: np.ndarray, mask: np.ndarray) -> float:
    """The factor s minimising |s z_reconstructed - z_true|^2 over the mask."""
    z = reconstructed_height_m[mask].astype(np.float64)
    return float(np.dot(z, true_height_m[mask]) / max(np.dot(z, z), 1e-30))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--renderer", required=True, help="calibration file, or shading[:SEED]")
    parser.add_argument("--objects", nargs="+", default=["figurine"])
    parser.add_argument("-n", type=int, default=20, help="pairs per object")
    parser.add_argument("--variation", type=float, default=0.0, help="image variation (yoto bench --image-variation)")
    parser.add_argument("--sigmas", type=float, nargs="+", help="also these priors (1-sigma of the log scale)")
    parser.add_argument("--workspace", help="workspace holding the object models")
    parser.add_argument("--json", help="write the per-pair rows here")
    args = parser.parse_args()

    from yoto.contacts import SIDES
    from yoto.errors import YotoError
    from yoto.evaluation.bench import BenchConfig, resolve_object, simulate_benchmark_pairs, symmetric_errors
    from yoto.io import write_json_atomic
    from yoto.localize import make_localizer
    from yoto.pose.hypotheses import pose_distances
    from yoto.pose.pipeline import localize_contacts, pose_from_candidates
    from yoto.provenance import run_info
    from yoto.sensor.optical import image_route

    config = BenchConfig(num_pairs=args.n)
    pose_config = replace(config.pose_config("full"), suggest_next_touch=False)
    route = image_route(args.renderer, args.variation)
    localizer = make_localizer("match")
    rows = []
    for name in args.objects:
        model = resolve_object(name, args.workspace)
        for simulated in simulate_benchmark_pairs(model, config):
            sides, truth_scale = {}, {}
            for side in SIDES:
                result = route.reconstruction(simulated.height_maps[side])
                if result is None or not result.contact:
                    break
                truth_scale[side] = true_depth_scale(simulated.height_maps[side], result.height_map_m, result.mask)
                contact = simulated.pair.contact(side)
                sides[side] = replace(
                    contact, points_sensor=result.points_sensor, depth_scale_sigma=result.depth_scale_sigma
                )
            if len(sides) < 2:
                rows.append({"object": model.name, "pair": simulated.index, "reconstructed": False})
                continue
            with_prior = replace(simulated.pair, **sides)
            variants = {"scale": with_prior}
            for sigma in [0.0, *(args.sigmas or [])]:
                label = "exact" if sigma == 0 else f"sigma {sigma:g}"
                variants[label] = replace(
                    with_prior, **{s: replace(c, depth_scale_sigma=sigma) for s, c in sides.items()}
                )
            row = {"object": model.name, "pair": simulated.index, "reconstructed": True, "true_scale": truth_scale}
            try:
                candidates, world, _ = localize_contacts(with_prior, model, localizer)
            except YotoError as exc:
                row["failed"] = str(exc)
                rows.append(row)
                continue
            T_true = simulated.pair.T_world_mesh_true @ model.T_mesh_object
            for label, pair in variants.items():
                tick = time.process_time()
                estimate = pose_from_candidates(pair, model, candidates, world, pose_config, "match")
                cpu_ms = 1000.0 * (time.process_time() - tick)
                errors = symmetric_errors(model, estimate.T_world_mesh, simulated.pair.T_world_mesh_true)
                translation, rotation = pose_distances(
                    estimate.hypotheses_mesh(model) @ model.T_mesh_object, T_true, model.symmetry
                )
                row[label] = {
                    "right": bool(errors["translation_mm"] < 5.0 and errors["rotation_deg"] < 5.0),
                    "truth_among": bool(np.any((translation < 0.005) & (np.degrees(rotation) < 5.0))),
                    "translation_mm": errors["translation_mm"],
                    "rotation_deg": errors["rotation_deg"],
                    "depth_scale": dict(zip(SIDES, estimate.depth_scale)),
                    "cpu_ms": cpu_ms,
                }
            rows.append(row)
            scale = row["scale"]
            print(
                f"{model.name} pair {simulated.index}: true scale "
                + ", ".join(f"{truth_scale[s]:.2f} -> {scale['depth_scale'][s]:.2f}" for s in SIDES)
                + f"; right {row['exact']['right']:d} -> {scale['right']:d}, "
                f"{row['exact']['translation_mm']:.1f} mm / {row['exact']['rotation_deg']:.1f} deg -> "
                f"{scale['translation_mm']:.1f} mm / {scale['rotation_deg']:.1f} deg",
                flush=True,
            )
    print()
    for name in dict.fromkeys(r["object"] for r in rows):
        done = [r for r in rows if r["object"] == name and "scale" in r]
        if not done:
            continue
        truth = np.array([r["true_scale"][s] for r in done for s in SIDES])
        found = np.array([r["scale"]["depth_scale"][s] for r in done for s in SIDES])
        right = [r for r in done if r["scale"]["right"]]
        on_right = np.array([abs(r["scale"]["depth_scale"][s] / r["true_scale"][s] - 1) for r in right for s in SIDES])
        print(
            f"{name}: {len(done)} pairs; true scale median {np.median(truth):.3f} (IQR {np.percentile(truth, 25):.3f}-"
            f"{np.percentile(truth, 75):.3f}); estimated / true median {np.median(found / truth):.3f}, "
            f"|estimated / true - 1| median on right poses {np.median(on_right) if len(on_right) else np.nan:.3f} "
            f"(heights as exact: {np.median(np.abs(1 / truth - 1)):.3f})"
        )
        for label in [k for k in done[0] if k == "exact" or k == "scale" or k.startswith("sigma")]:
            print(
                f"  {label:9s}: right {np.mean([r[label]['right'] for r in done]):.0%}, truth among "
                f"{np.mean([r[label]['truth_among'] for r in done]):.0%}, pose stage CPU median "
                f"{np.median([r[label]['cpu_ms'] for r in done]):.1f} ms per pair"
            )
    if args.json:
        write_json_atomic(args.json, {"run": run_info(), "args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()
