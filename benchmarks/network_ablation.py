"""What each part of the `cpu` localizer buys (docs/network.md): its stages switched on one at a time, every row
measured through YOTO's pose stage on the same simulated contacts (the benchmark's simulator and seed).

    python benchmarks/network_ablation.py --checkpoint RUN/model.pt --stage1 RUN/model_stage1.pt \
        --objects drill monkey avocado bunny -n 25 --workspace WS --json ablation.json

Rows (each adds one thing to the row before, unless it says otherwise):
  descriptors only        the best anchors by descriptor score, at the anchors' places (no geometry at all)
  + roll/plane fit        the contact's height map fitted at every roll to the 128 best anchors, best fits kept
  + free space            fits whose surface would push into the gel where nothing was seen pay for it
  + ICP                   each kept fit refined by point-to-plane ICP and ranked by its residual
  shortlist 512           512 anchors fitted instead of 128 (the default)
  virtual only            the default, with the network of the end of stage 1 (no fine-tuning contacts)
  every anchor fitted     the default, every anchor shortlisted: the geometric stages alone, no learning
  beliefs x descriptor score  the default, candidate beliefs also weighted by the network's logits
With --match-shortlists K ...: the matched filter (`yoto bench --methods match`, no training) as a row, and per K the
matched filter whose coarse stage is the network's K best anchors by descriptor score instead of its 600 best by
the roll-free ring distance (the network as the matched filter's coarse stage; the two share their anchors; the
network reads the matched filter's contact image). Latency: wall and process CPU time per contact.
Per row: the localizer's first candidate (top-1) and the candidate the pose stage chose, errors in mm in the mesh
frame; the pose's error; per-contact latency (first two pairs of each object excluded, as the benchmark does).
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from dataclasses import replace

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True, help="the trained `cpu` localizer (RUN/model.pt)")
    parser.add_argument("--stage1", help="the same run's virtual-only network (RUN/model_stage1.pt)")
    parser.add_argument("--objects", nargs="+", required=True, help="object names in the workspace")
    parser.add_argument("-n", "--pairs", type=int, default=25, help="simulated pairs per object")
    parser.add_argument("--seed", type=int, default=7, help="simulation seed (the benchmark's)")
    parser.add_argument("--rows", nargs="*", help="only these rows (their names, as printed)")
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME:FIELD=VALUE,...",
        help="an extra row: the default localizer config with these fields (JSON values) changed; repeatable",
    )
    parser.add_argument(
        "--match-shortlists",
        nargs="*",
        type=int,
        default=[],
        metavar="K",
        help="rows: the matched filter, and it with the network's K best anchors as its coarse stage",
    )
    parser.add_argument("--workspace", help="workspace holding the object models")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()

    import torch

    from yoto.contacts import SIDES
    from yoto.evaluation.bench import BenchConfig, simulate_benchmark_pairs
    from yoto.geometry import transform_points
    from yoto.localize.descriptor import DescriptorLocalizerConfig
    from yoto.localize.network import load_localizer
    from yoto.metrics import pose_errors, summarize
    from yoto.objects.build import load_object_model
    from yoto.pose.pipeline import PoseConfig, localize_contacts, pose_from_candidates
    from yoto.provenance import run_info

    torch.set_num_threads(args.threads)
    default = DescriptorLocalizerConfig()
    narrow = replace(default, shortlist=128)
    rows = {
        "descriptors only": (args.checkpoint, replace(default, fine_stage=False)),
        "+ roll/plane fit": (args.checkpoint, replace(narrow, free_space=False, refine=False)),
        "+ free space": (args.checkpoint, replace(narrow, refine=False)),
        "+ ICP": (args.checkpoint, narrow),
        "shortlist 512": (args.checkpoint, default),
        "virtual only": (args.stage1, default),
        "every anchor fitted": (args.checkpoint, replace(default, shortlist=10**7)),
        "beliefs x descriptor score": (args.checkpoint, replace(default, score_weight=1.0)),
    }
    rows: dict[str, tuple] = {k: v for k, v in rows.items() if v[0] is not None and (not args.rows or k in args.rows)}
    for variant in args.variant:
        name, _, fields = variant.partition(":")
        overrides = {k: json.loads(v) for k, v in (item.split("=", 1) for item in fields.split(",") if item)}
        rows[name] = (args.checkpoint, replace(default, **overrides))
    if args.match_shortlists:
        rows["matched filter"] = (None, None)
        for count in args.match_shortlists:
            rows[f"matched filter, network shortlist {count}"] = (args.checkpoint, count)
    models = {name: load_object_model(name, args.workspace) for name in args.objects}
    pairs = {
        name: simulate_benchmark_pairs(model, BenchConfig(args.pairs, args.seed)) for name, model in models.items()
    }
    results: dict[str, dict] = {}
    warnings.simplefilter("ignore")
    for label, (checkpoint, config) in rows.items():
        if label.startswith("matched filter"):
            localizer = network_shortlist_match(None if checkpoint is None else load_localizer(checkpoint), config)
        else:
            localizer = load_localizer(checkpoint, config=config)
        record: dict[str, list[float]] = {
            k: [] for k in ("top1", "chosen", "translation", "rotation", "latency", "cpu")
        }
        started = time.perf_counter()
        for name, model in models.items():
            localizer.prepare_object(model)
            for number, simulated in enumerate(pairs[name]):
                pair = simulated.pair
                tick = time.process_time()
                candidates, world, latency = localize_contacts(pair, model, localizer)
                if number >= 2:
                    record["cpu"].append(500.0 * (time.process_time() - tick))  # per contact
                estimate = pose_from_candidates(pair, model, candidates, world, PoseConfig(), "yoto")
                for side in SIDES:
                    for key, contact in (("top1", candidates[side][0]), ("chosen", estimate.contacts[side])):
                        p_mesh = transform_points(model.T_mesh_object, contact.p_object)
                        record[key].append(1000.0 * float(np.linalg.norm(p_mesh - pair.p_mesh_true[side])))
                    if number >= 2:
                        record["latency"].append(latency[f"localize_{side}"])
                errors = pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model)
                record["translation"].append(errors["translation_mm"])
                record["rotation"].append(errors["rotation_deg"])
        translation, rotation = np.array(record["translation"]), np.array(record["rotation"])
        results[label] = {
            "checkpoint": str(checkpoint),
            "config": (
                {"shortlist": config}
                if not hasattr(config, "__dict__")
                else {
                    k: v for k, v in config.__dict__.items() if k in ("shortlist", "fine_stage", "refine", "free_space")
                }
            ),
            "top1_mm": summarize(record["top1"]),
            "chosen_mm": summarize(record["chosen"]),
            "translation_mm": summarize(record["translation"]),
            "rotation_deg": summarize(record["rotation"]),
            "right_pose_share": float(np.mean((translation < 5.0) & (rotation < 5.0))),
            "latency_ms": summarize(record["latency"]),
            "cpu_ms": summarize(record["cpu"]),
            "wall_s": time.perf_counter() - started,
        }
        r = results[label]
        print(
            f"{label:22s} top-1 {r['top1_mm']['mean']:6.2f} ({r['top1_mm']['median']:5.2f}) mm | chosen "
            f"{r['chosen_mm']['mean']:6.2f} ({r['chosen_mm']['median']:5.2f}) mm | pose "
            f"{r['translation_mm']['median']:.2f} mm / {r['rotation_deg']['median']:.2f} deg, right "
            f"{r['right_pose_share']:.2f} | "
            f"{r['latency_ms']['median']:.1f} / {r['latency_ms']['p90']:.1f} ms, CPU {r['cpu_ms']['median']:.1f} / "
            f"{r['cpu_ms']['p90']:.1f} ms",
            flush=True,
        )
    if args.json:
        payload = {"run": run_info(), "objects": args.objects, "pairs": args.pairs, "seed": args.seed, "rows": results}
        with open(args.json, "w") as handle:
            json.dump(payload, handle, indent=1)


def network_shortlist_match(network, count):
    """The bench's matched filter (`ScaledMatchLocalizer`); with `network` (a `DescriptorLocalizer`) its default
    level's coarse stage is the network's `count` best anchors by descriptor score: the network reads its polar
    cells off the matched filter's own contact image (no second image), and where the contact covers fewer than
    the network's minimum of cells the ring distance shortlists as before."""
    import torch

    from yoto.localize.descriptor import MIN_COVERED_CELLS
    from yoto.localize.match import MatchLocalizer
    from yoto.localize.scaled_match import ScaledMatchLocalizer

    if network is None:
        return ScaledMatchLocalizer()

    class NetworkShortlist(MatchLocalizer):
        model = None

        def _shortlist(self, image, anchors):
            x, y = network.grid.centres[..., 0], network.grid.centres[..., 1]
            heights, covered = image.sample(x, y, image.mask)
            if covered.sum() < MIN_COVERED_CELLS:
                return super()._shortlist(image, anchors)
            cache = network.prepare_object(self.model)
            if len(cache.anchors.points_object) != len(anchors.points_object):
                raise RuntimeError("the network's anchors are not the matched filter's")
            unit = network.network.height_unit_m
            maps = np.stack([np.where(covered, heights / unit, 0.0), covered]).astype(np.float32)
            with torch.inference_mode():
                descriptor = network.net(torch.from_numpy(maps)[None])[0]
            scores = (cache.descriptors @ descriptor).numpy()
            k = min(count, len(scores))
            return np.sort(np.argpartition(-scores, k - 1)[:k]) if k < len(scores) else np.arange(len(scores))

    class Hybrid(ScaledMatchLocalizer):
        def localize(self, points_sensor, model, truth_p_object=None):
            self.default.model = model
            return super().localize(points_sensor, model, truth_p_object)

        def prepare_object(self, model):
            cache = network.prepare_object(model)
            maps = super().prepare_object(model)
            if not np.array_equal(cache.anchors.points_object, maps.points_object):
                raise RuntimeError("the network's anchors are not the matched filter's")
            return maps

    hybrid = Hybrid()
    hybrid.default = NetworkShortlist(hybrid.config)
    hybrid._levels[0] = hybrid.default
    return hybrid


if __name__ == "__main__":
    main()
