"""Latency for a control loop: per contact and per pose, every localizer side by side on the same contacts.

For each object, dual contacts simulated exactly as `yoto bench` simulates them (same seed, same pairs), or
contact pairs read from files; every method localizes both contacts of every pair in this one process, and
the pose stage turns its candidates into a pose. Timed, per method:

- per contact: `localizer.localize` end to end (wall clock, and the process's CPU time beside it);
- pose stage: choosing, verifying and refining from the candidates (`pose_from_candidates`; the `next_touch`
  suggestion for ambiguous poses is left out, as in the stage's own `latency_ms["pose"]`);
- per pose: both contacts plus the pose stage, what a robot waits for after a grasp; with `--concurrent` also
  with the two contacts localized at once, the right one in a helper process (`localize_contacts(..., helper)`,
  `yoto.localize.helper.LocalizerProcess`), the pair's wall time (contacts and their world-side measurements);
  and the pose stage on two cores, half of each large batch of poses in that helper (`pose_from_candidates(...,
  helper=)`, `yoto.pose.executor`), run on the same candidates beside the one-process pose stage (which goes
  first alternates pair by pair), its result checked bitwise against the one-process one, the ratio of the two
  wall times per pair; "per pose, both cores" is both contacts at once plus that pose stage.

The first pair of each (object, method) is warm-up and not counted (anchor maps, KD-trees, block encodings,
lazy imports are built there; the once-per-object preparation is reported on its own). Medians and p90s,
and each method's speed-up over ICP measured in the same run: per contact one after the other (ICP's k-d queries
then use both cores, the matched filter one), and with `--concurrent` per pair and per contact with both contacts
at once, where each method has both cores. Wall times on a shared machine rise with its load (printed); the CPU
times are the steadier figure.

    python benchmarks/pose_latency.py --objects tool fruit figurine MESHES/mug/mug.ply -n 30 --methods match icp
    python benchmarks/pose_latency.py --pairs PAIRS/ --methods match yoto --checkpoint RUN/model.pt
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from dataclasses import replace

import numpy as np


class CpuTimed:
    """A localizer that also records the process's CPU time of each `localize` call (ms)."""

    def __init__(self, localizer):
        self.localizer = localizer
        self.name = localizer.name
        self.needs_ground_truth = localizer.needs_ground_truth
        self.cpu_ms: list[float] = []

    def localize(self, points_sensor, model, truth_p_object=None):
        tick = time.process_time()
        candidates = self.localizer.localize(points_sensor, model, truth_p_object)
        self.cpu_ms.append(1000.0 * (time.process_time() - tick))
        return candidates


def timed_pose_stage(*arguments, helper=None):
    """`pose_from_candidates(*arguments, helper=helper)` and this process's CPU time for it (ms)."""
    from yoto.pose.pipeline import pose_from_candidates

    tick = time.process_time()
    estimate = pose_from_candidates(*arguments, helper=helper)
    return estimate, 1000.0 * (time.process_time() - tick)


def same_estimate(first, second) -> bool:
    """Whether two pose estimates hold the same numbers, bit for bit (latencies aside)."""

    def same(a, b) -> bool:
        if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            return (
                isinstance(a, np.ndarray)
                and isinstance(b, np.ndarray)
                and a.dtype == b.dtype
                and (a.shape == b.shape and a.tobytes() == b.tobytes())
            )
        if isinstance(a, dict):
            return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        if isinstance(a, (list, tuple)):
            return type(a) is type(b) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
        if isinstance(a, float):
            return isinstance(b, float) and np.float64(a).tobytes() == np.float64(b).tobytes()
        if hasattr(a, "__dataclass_fields__"):
            return type(a) is type(b) and all(same(getattr(a, n), getattr(b, n)) for n in a.__dataclass_fields__)
        return a == b

    fields = [n for n in first.__dataclass_fields__ if n != "latency_ms"]
    return all(same(getattr(first, n), getattr(second, n)) for n in fields)


def percentiles(values: list[float]) -> dict[str, float]:
    array = np.asarray(values, dtype=np.float64)
    if len(array) == 0:
        return {"median": float("nan"), "p90": float("nan"), "count": 0}
    return {"median": float(np.median(array)), "p90": float(np.percentile(array, 90)), "count": len(array)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--objects", nargs="+", help="object names (workspace or built-in) or mesh files")
    source.add_argument("--pairs", nargs="+", help="contact pair files or folders (their objects in --workspace)")
    parser.add_argument("-n", "--num-pairs", type=int, default=20, help="simulated pairs per object (--objects)")
    parser.add_argument("--seed", type=int, default=7, help="simulation seed (yoto bench's default)")
    parser.add_argument("--methods", nargs="+", default=["match", "icp"], choices=["match", "icp", "yoto", "oracle"])
    parser.add_argument("--checkpoint", help="checkpoint of the yoto method (default: the shipped weights)")
    parser.add_argument(
        "--pose-stage",
        choices=["full", "no-search", "paper"],
        default="full",
        help="pose stage to time: YOTO's (full), YOTO's without the joint two-contact search, or the paper's",
    )
    parser.add_argument(
        "--concurrent",
        action="store_true",
        help="also localize the two contacts of each pair at once, the right one in a helper process, and time that "
        "pose (per pose, concurrent): a robot waits for both contacts, not for each",
    )
    parser.add_argument("--workspace", help="workspace folder for object models")
    parser.add_argument("--json", help="write the figures here as JSON")
    args = parser.parse_args()

    from tqdm import tqdm

    from yoto.contacts import SIDES, read_contact_pair
    from yoto.evaluation.bench import BenchConfig, resolve_object, simulate_benchmark_pairs
    from yoto.io import write_json_atomic
    from yoto.localize import make_localizer
    from yoto.localize.helper import LocalizerProcess
    from yoto.objects.build import load_object_model
    from yoto.pose.executor import prepare_pose_helper
    from yoto.pose.pipeline import PAPER, PoseConfig, localize_contacts
    from yoto.provenance import run_info
    from yoto.training.data import find_pair_files_recursive

    pose_config = {"full": PoseConfig(), "no-search": PoseConfig(search="never"), "paper": PAPER}[args.pose_stage]
    # `next_touch` (a suggestion for ambiguous poses, after the pose) is not timed: the pose stage's wall time
    # excludes it, and its CPU time must too (`yoto bench` reports next_touch on its own).
    pose_config = replace(pose_config, suggest_next_touch=False)
    work: dict[str, tuple] = {}  # object name -> (model, pairs)
    if args.objects:
        for spec in args.objects:
            model = resolve_object(spec, args.workspace)
            simulated = simulate_benchmark_pairs(model, BenchConfig(num_pairs=args.num_pairs, seed=args.seed))
            work[model.name] = (model, [s.pair for s in simulated])
    else:
        grouped = defaultdict(list)
        for path in find_pair_files_recursive(args.pairs):
            pair = read_contact_pair(path)
            grouped[pair.object_name].append(pair)
        work = {name: (load_object_model(name, args.workspace), pairs) for name, pairs in grouped.items()}

    # --concurrent: each method's copy in a helper process localizes the right contact while this one does the left.
    helpers = {
        method: LocalizerProcess(make_localizer(method, args.checkpoint if method == "yoto" else None))
        for method in (args.methods if args.concurrent else [])
    }
    load_before = os.getloadavg()
    results: dict = {**run_info(), "pose_stage": args.pose_stage, "seed": args.seed, "objects": {}, "all": {}}
    pooled: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    unequal: dict[str, list[str]] = defaultdict(list)  # method -> pairs whose two-core pose differs (none expected)
    checked: dict[str, int] = defaultdict(int)  # method -> pairs checked (the warm-up pairs too)
    for name, (model, pairs) in work.items():
        results["objects"][name] = {}
        for method in args.methods:
            localizer = CpuTimed(make_localizer(method, args.checkpoint if method == "yoto" else None))
            tick = time.perf_counter()
            if hasattr(localizer.localizer, "prepare_object"):
                localizer.localizer.prepare_object(model)
            prepare_s = time.perf_counter() - tick
            times: dict[str, list[float]] = defaultdict(list)
            if method in helpers:
                helpers[method].prepare_object(model)
                prepare_pose_helper(helpers[method], model, pose_config.field_config).result()
            for number, pair in enumerate(tqdm(pairs, desc=f"{name}: {method}", unit="pair", leave=False)):
                candidates, world, latency = localize_contacts(pair, model, localizer)
                helper = helpers.get(method)
                stage = (pair, model, candidates, world, pose_config, method)
                if helper is not None and number % 2:  # the two-core pose stage first on every other pair
                    split, cpu_split = timed_pose_stage(*stage, helper=helper)
                estimate, cpu_pose = timed_pose_stage(*stage)
                if helper is not None:
                    if number % 2 == 0:
                        split, cpu_split = timed_pose_stage(*stage, helper=helper)
                    checked[method] += 1
                    if not same_estimate(estimate, split):
                        unequal[method].append(f"{name} #{number}")
                    _, _, both = localize_contacts(pair, model, localizer.localizer, helper)
                if number == 0:
                    continue  # warm-up
                contact_ms = [latency[f"localize_{side}"] for side in SIDES]
                times["contact_ms"] += contact_ms
                times["pose_stage_ms"].append(estimate.latency_ms["pose"])
                times["pose_stage_cpu_ms"].append(cpu_pose)
                times["pose_ms"].append(sum(contact_ms) + estimate.latency_ms["pose"])
                times["contact_cpu_ms"] += localizer.cpu_ms[-2:]
                times["pose_cpu_ms"].append(sum(localizer.cpu_ms[-2:]) + cpu_pose)
                times["pair_ms"].append(latency["localize_pair"])
                if helper is not None:
                    times["pair_concurrent_ms"].append(both["localize_pair"])
                    # each contact's own time where it ran (left here, right in the helper), both at once
                    times["contact_concurrent_ms"] += [both[f"localize_{side}"] for side in SIDES]
                    times["pose_concurrent_ms"].append(both["localize_pair"] + estimate.latency_ms["pose"])
                    times["pose_stage_split_ms"].append(split.latency_ms["pose"])
                    times["pose_stage_split_cpu_ms"].append(cpu_split)  # this process's share only
                    times["pose_stage_split_ratio"].append(split.latency_ms["pose"] / estimate.latency_ms["pose"])
                    times["pose_both_cores_ms"].append(both["localize_pair"] + split.latency_ms["pose"])
                    # CPU time on the critical path (what two free cores would take, round trips aside): this
                    # process's plus the time the helper's halves outlasted its own; for the contacts the slower.
                    critical = cpu_split + split.latency_ms["pose_helper_extra_cpu"]
                    times["pose_stage_split_critical_cpu_ms"].append(critical)
                    times["pose_both_cores_critical_cpu_ms"].append(max(localizer.cpu_ms[-2:]) + critical)
            for key, values in times.items():
                pooled[method][key] += values
            results["objects"][name][method] = {
                "prepare_s": prepare_s,
                **{key: percentiles(values) for key, values in times.items()},
            }
    for helper in helpers.values():
        helper.close()
    results["all"] = {method: {key: percentiles(v) for key, v in times.items()} for method, times in pooled.items()}
    results["load_average"] = {"start": load_before, "end": os.getloadavg()}
    results["two_core_pose_unequal"] = dict(unequal)

    def row(label: str, stats: dict) -> str:
        def cell(key: str) -> str:
            return f"{stats[key]['median']:7.1f} / {stats[key]['p90']:7.1f}"

        concurrent = (
            f" {cell('pair_concurrent_ms')} | {cell('pose_concurrent_ms')} | {cell('pose_stage_split_ms')} "
            f"| {stats['pose_stage_split_ratio']['median']:5.3f} | {cell('pose_both_cores_ms')} |"
            if args.concurrent
            else ""
        )
        return (
            f"| {label} | {cell('contact_ms')} | {stats['contact_cpu_ms']['median']:6.1f} | {cell('pose_stage_ms')} "
            f"| {stats['pose_stage_cpu_ms']['median']:6.1f} | {cell('pose_ms')} "
            f"| {stats['pose_cpu_ms']['median']:6.1f} |{concurrent}"
        )

    lines = [
        f"commit {results['commit']} | {results['device']} | pose stage {args.pose_stage} | seed {args.seed} | "
        f"load average {load_before[0]:.1f} at start, {results['load_average']['end'][0]:.1f} at end",
        "",
        "Latency in ms, median / p90 (warm-up pair excluded); CPU: the process's CPU time, median",
        "",
        "| object: method | per contact | CPU | pose stage | CPU | per pose | CPU |"
        + (
            " both contacts at once | per pose, contacts at once | pose stage, two cores | two / one core, per "
            "pair | per pose, both cores |"
            if args.concurrent
            else ""
        ),
        "|---|---|---|---|---|---|---|" + ("---|---|---|---|---|" if args.concurrent else ""),
    ]
    for name, methods in results["objects"].items():
        lines += [row(f"{name}: {method}", stats) for method, stats in methods.items()]
    lines += [row(f"**all: {method}**", stats) for method, stats in results["all"].items()]
    for method, stats in results["all"].items():
        if "pair_concurrent_ms" in stats:
            lines.append(
                f"\n{method}: both contacts of a pair one after the other {stats['pair_ms']['median']:.1f} ms, at once "
                f"{stats['pair_concurrent_ms']['median']:.1f} ms (medians, wall clock). Pose stage on one core "
                f"{stats['pose_stage_ms']['median']:.1f} ms, on two {stats['pose_stage_split_ms']['median']:.1f} ms "
                f"(per-pair ratio {stats['pose_stage_split_ratio']['median']:.3f}); per pose, both cores: "
                f"{stats['pose_both_cores_ms']['median']:.1f} ms. CPU time on the critical path (this process's, "
                f"plus the helper's beyond it; what two free cores would take): pose stage on one core "
                f"{stats['pose_stage_cpu_ms']['median']:.1f} ms, on two "
                f"{stats['pose_stage_split_critical_cpu_ms']['median']:.1f} ms; per pose "
                f"{stats['pose_cpu_ms']['median']:.1f} ms, both cores "
                f"{stats['pose_both_cores_critical_cpu_ms']['median']:.1f} ms. "
                "Two-core poses bitwise equal to one core's: "
                f"{checked[method] - len(unequal[method])} of {checked[method]}"
                + (f" (unequal, checked on every pair: {', '.join(unequal[method])})" if unequal[method] else "")
                + "."
            )
    if "icp" in results["all"]:
        icp = results["all"]["icp"]
        for method, stats in results["all"].items():
            if method in ("icp", "oracle"):
                continue
            keys = ["contact_ms", "contact_cpu_ms", "pose_ms", "contact_concurrent_ms", "pair_concurrent_ms"]
            ratios = {key: icp[key]["median"] / stats[key]["median"] for key in keys if key in stats and key in icp}
            results["all"][method]["speedup_over_icp"] = ratios
            lines.append(
                f"\n{method} is {ratios['contact_ms']:.1f}x faster than ICP per contact "
                f"({ratios['contact_cpu_ms']:.1f}x in CPU time), {ratios['pose_ms']:.1f}x per pose (medians, same run)."
            )
            if "pair_concurrent_ms" in ratios:
                # ICP's k-d queries use both cores on their own; here both methods have the two cores: like with like
                lines.append(
                    f"Both contacts of a pair at once, each method on both cores (the right contact in its helper "
                    f"process): {method} {stats['pair_concurrent_ms']['median']:.1f} ms per pair, ICP "
                    f"{icp['pair_concurrent_ms']['median']:.1f} ms: {ratios['pair_concurrent_ms']:.1f}x per pair; per "
                    f"contact (each timed where it ran) {stats['contact_concurrent_ms']['median']:.1f} against "
                    f"{icp['contact_concurrent_ms']['median']:.1f} ms: {ratios['contact_concurrent_ms']:.1f}x."
                )
    print("\n".join(lines))
    if args.json:
        write_json_atomic(args.json, results)


if __name__ == "__main__":
    main()
