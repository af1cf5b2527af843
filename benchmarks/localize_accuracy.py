"""Accuracy and latency of a localizer's candidates on contact pairs with ground truth: a trained point-network
localizer (`--method yoto`, the `paper` and `cpu-points` presets; the `cpu` preset's network is measured by
benchmarks/network_ablation.py and `yoto bench --yoto LABEL=CHECKPOINT`), the matched filter or ICP.

Per object: contact localization error (mm) of the top candidate and of the best returned candidate, the share
of top candidates within 1 and 5 mm, top-1 block recall (the network), per-contact latency (the paper's way:
every call timed end to end, warm-up excluded; and the process's CPU time), and the pose error of
`estimate_pose` (joint candidate selection) with its confidence, binned so a user can pick a re-touch threshold.
Pairs come from files, or are simulated as `yoto bench` simulates them (`--objects`, same seed, same pairs).

    python benchmarks/localize_accuracy.py --checkpoint RUN/model.pt --pairs PAIRS/tool PAIRS/fruit ...
    python benchmarks/localize_accuracy.py --method match --objects fruit MESHES/mug/mug.ply -n 10 --no-pose
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from collections import defaultdict

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", choices=["yoto", "match", "icp"], default="yoto", help="the localizer")
    parser.add_argument("--checkpoint", help="a point-network localizer checkpoint (RUN/model.pt; --method yoto)")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--pairs", nargs="+", help="pair files or folders")
    source.add_argument("--objects", nargs="+", help="object names or mesh files: pairs simulated as yoto bench does")
    parser.add_argument("-n", "--num-pairs", type=int, default=20, help="simulated pairs per object (--objects)")
    parser.add_argument("--seed", type=int, default=7, help="simulation seed (yoto bench's default)")
    parser.add_argument("--workspace", help="workspace holding the object models")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-pose", action="store_true", help="skip the pose estimates")
    parser.add_argument("--rotations", type=int, help="test-time in-plane rotations")
    parser.add_argument("--hypotheses", type=int, help="coarse hypotheses")
    parser.add_argument("--json", help="write results here")
    args = parser.parse_args()

    from yoto.contacts import SIDES, read_contact_pair
    from yoto.evaluation.bench import BenchConfig, resolve_object, simulate_benchmark_pairs
    from yoto.geometry import invert_transform, transform_points
    from yoto.localize import make_localizer
    from yoto.metrics import pose_errors, summarize
    from yoto.objects.build import load_object_model
    from yoto.pose.pipeline import estimate_pose
    from yoto.provenance import run_info
    from yoto.training.data import find_pair_files_recursive

    options = {
        "rotations": args.rotations,
        "hypotheses": args.hypotheses,
    }
    if args.method == "yoto":
        import torch

        from yoto.localize.network import NetworkLocalizer

        torch.set_num_threads(args.threads)
        localizer = NetworkLocalizer.from_checkpoint(
            args.checkpoint, **{k: v for k, v in options.items() if v is not None}
        )
    else:
        localizer = make_localizer(args.method)
    work = []  # (model, pair)
    if args.objects:
        for spec in args.objects:
            model = resolve_object(spec, args.workspace)
            simulated = simulate_benchmark_pairs(model, BenchConfig(num_pairs=args.num_pairs, seed=args.seed))
            work += [(model, s.pair) for s in simulated]
    else:
        models: dict = {}
        for path in find_pair_files_recursive(args.pairs):
            pair = read_contact_pair(path)
            if pair.object_name not in models:
                models[pair.object_name] = load_object_model(pair.object_name, args.workspace)
            work.append((models[pair.object_name], pair))
    rows: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    warnings.simplefilter("once")
    for model, pair in work:
        row = rows[model.name]
        if not row:
            if hasattr(localizer, "prepare_object"):
                localizer.prepare_object(model)
            localizer.localize(pair.left.points_sensor, model)  # warm-up
        T_object_world = model.T_object_mesh @ invert_transform(pair.T_world_mesh_true)
        for side in SIDES:
            contact = pair.contact(side)
            p_true = transform_points(model.T_object_mesh, pair.p_mesh_true[side])
            tick, cpu = time.perf_counter(), time.process_time()
            candidates = localizer.localize(contact.points_sensor, model)
            row["latency_ms"].append(1000 * (time.perf_counter() - tick))
            row["cpu_ms"].append(1000 * (time.process_time() - cpu))
            errors = [1000 * np.linalg.norm(c.p_object - p_true) for c in candidates]
            row["error_mm"].append(errors[0])
            row["best_candidate_error_mm"].append(min(errors))
            row["candidates"].append(len(candidates))
            row["probability"].append(candidates[0].probability)
            if "coarse_top_blocks" in candidates[0].details:  # the network's coarse stage: which block it chose
                from yoto.training.data import dominant_block

                points_object = transform_points(T_object_world @ contact.T_world_sensor, contact.points_sensor[::20])
                true_block = dominant_block(model, points_object)
                row["top1"].append(candidates[0].details["coarse_top_blocks"][0] == true_block)
                row["answer_block"].append(candidates[0].block == true_block)
        if not args.no_pose:
            estimate = estimate_pose(pair, model, localizer)
            error = pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model)
            row["pose_translation_mm"].append(error["translation_mm"])
            row["pose_rotation_deg"].append(error["rotation_deg"])
            row["pose_confidence"].append(estimate.confidence)
            chosen = [estimate.contacts[s].p_object for s in SIDES]
            truths = [transform_points(model.T_object_mesh, pair.p_mesh_true[s]) for s in SIDES]
            row["pose_contact_error_mm"] += [1000 * np.linalg.norm(c - t) for c, t in zip(chosen, truths, strict=True)]

    results = {
        **run_info(),
        "method": args.method,
        "checkpoint": str(getattr(localizer, "source", None)),
        "options": {k: v for k, v in options.items() if v is not None},
        "load_average": os.getloadavg(),
        "objects": {},
    }
    all_errors = []
    for name, row in rows.items():
        errors = np.array(row["error_mm"])
        all_errors += list(errors)
        entry = {
            "contacts": len(errors),
            "error_mm": summarize(errors),
            "within_1mm": float((errors <= 1).mean()),
            "within_5mm": float((errors <= 5).mean()),
            "best_candidate_error_mm": summarize(row["best_candidate_error_mm"]),
            "latency_ms": {
                "median": float(np.median(row["latency_ms"])),
                "p90": float(np.percentile(row["latency_ms"], 90)),
            },
            "cpu_ms": {"median": float(np.median(row["cpu_ms"])), "p90": float(np.percentile(row["cpu_ms"], 90))},
            "mean_candidates": float(np.mean(row["candidates"])),
        }
        if row["top1"]:
            entry["top1_block"] = float(np.mean(row["top1"]))
            entry["answer_block"] = float(np.mean(row["answer_block"]))
        if row["pose_translation_mm"]:
            t, r, c = (np.array(row[k]) for k in ("pose_translation_mm", "pose_rotation_deg", "pose_confidence"))
            entry["pose_translation_mm"] = summarize(t)
            entry["pose_rotation_deg"] = summarize(r)
            entry["pose_contact_error_mm"] = summarize(row["pose_contact_error_mm"])
            bins = []
            for low, high in ((0.5, 1.01), (0.2, 0.5), (0.05, 0.2), (0.0, 0.05)):
                sel = (c >= low) & (c < high)
                if sel.any():
                    bins.append(
                        {
                            "confidence": [low, min(high, 1.0)],
                            "pairs": int(sel.sum()),
                            "translation_mm_median": float(np.median(t[sel])),
                            "rotation_deg_median": float(np.median(r[sel])),
                        }
                    )
            entry["pose_by_confidence"] = bins
        results["objects"][name] = entry
        line = (
            f"{name:9s} n={len(errors):3d}  loc error mean {entry['error_mm']['mean']:.2f} median "
            f"{entry['error_mm']['median']:.2f} p90 {entry['error_mm']['p90']:.2f} mm, "
            f"<=1mm {entry['within_1mm']:.2f}, <=5mm {entry['within_5mm']:.2f}, "
            f"best-cand mean {entry['best_candidate_error_mm']['mean']:.2f}"
            + (f", top-1 block {entry['top1_block']:.2f}" if "top1_block" in entry else "")
            + f", latency {entry['latency_ms']['median']:.1f}/{entry['latency_ms']['p90']:.1f} ms"
            f" (CPU {entry['cpu_ms']['median']:.1f}/{entry['cpu_ms']['p90']:.1f})"
        )
        if "pose_translation_mm" in entry:
            line += (
                f" | pose median {entry['pose_translation_mm']['median']:.1f} mm / "
                f"{entry['pose_rotation_deg']['median']:.1f} deg, chosen-contact error mean "
                f"{entry['pose_contact_error_mm']['mean']:.2f} mm"
            )
        print(line)
        for b in entry.get("pose_by_confidence", []):
            print(
                f"    confidence {b['confidence'][0]:.2f}-{b['confidence'][1]:.2f}: {b['pairs']:3d} pairs, median "
                f"{b['translation_mm_median']:.1f} mm / {b['rotation_deg_median']:.1f} deg"
            )
    all_cpu = [ms for row in rows.values() for ms in row["cpu_ms"]]
    errors = np.array(all_errors)
    results["all"] = {
        "error_mm": summarize(all_errors),
        "within_1mm": float((errors <= 1).mean()),
        "within_5mm": float((errors <= 5).mean()),
        "cpu_ms": {"median": float(np.median(all_cpu)), "p90": float(np.percentile(all_cpu, 90))},
    }
    print(
        f"all       n={len(errors)} loc error mean {errors.mean():.2f} mm, median {np.median(errors):.2f} mm, "
        f"<=1mm {results['all']['within_1mm']:.2f}, <=5mm {results['all']['within_5mm']:.2f}, CPU per contact "
        f"median {np.median(all_cpu):.1f} ms (p90 {np.percentile(all_cpu, 90):.1f})"
    )
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=2)


if __name__ == "__main__":
    main()
