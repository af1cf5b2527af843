"""The pose stage's rescue step (`pipeline._rescue`) replayed on stored localizations: what it finds and what it costs.

The benchmark's pairs (`yoto bench`'s simulation: seed 7 unless `--seed`, the standard 1 mm / 1 deg calibration error)
are localized once by the matched filter and stored (`--cache`, a pickle; built on first use). The pose stage (full,
as `yoto bench` configures it, without the re-touch) then runs on them under each variant (`--variants`), on every
pair or, with `--rescued`, only on the pairs whose first variant runs the rescue step. Printed per variant: pairs,
pairs rescued, poses right (5 mm / 5 deg), truth among the hypotheses, confident (confidence >= `--threshold`, the
trust benchmark's 99% threshold), the stage's CPU time per pair (this process, median / mean; min of `--repeat`), the
rescue step's own CPU time (mean over the pairs it ran on), and how many estimates are bitwise those of the first
variant (pose, hypotheses, probabilities, confidence); with `--changes`, every pair whose outcome differs from the
first variant's. With `--both-cores`, half of each large batch runs in a helper process (`executor.SplitExecutor`,
its no-free-core guard off so that a loaded machine still splits) and the CPU time is the critical path's (this
process's plus the helper's beyond it). Run with one BLAS thread (OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1).

A variant is `name:key=value,key=value` of `PoseConfig` fields (numbers), or `default`.

    M=../shared/data/meshes
    python benchmarks/rescue_replay.py --objects \\
        $M/{cracker_box,tomato_soup_can,mug,mustard_bottle,banana,drill}/*.ply fruit figurine -n 30 \\
        --workspace WS --cache PAIRS.pkl --rescued --variants default "s1200:rescue_screened=1200"
"""

from __future__ import annotations

import argparse
import hashlib
import os
import pickle
import time
from dataclasses import fields, replace

import numpy as np


def parse_variant(text: str, base):
    """(name, PoseConfig) of a variant string over `base`."""
    if text == "default":
        return "default", base
    name, _, settings = text.partition(":")
    known = {f.name for f in fields(base)}
    config = base
    for item in filter(None, settings.split(",")):
        key, value = item.split("=")
        if key not in known:
            raise SystemExit(f"unknown PoseConfig field {key!r} in variant {text!r}")
        config = replace(config, **{key: type(getattr(config, key))(float(value))})
    return name, config


def stored_pairs(args) -> dict:
    """{object name: [(index, pair, candidates, world)]}: the cache, or localized now and stored there."""
    if args.cache and os.path.exists(args.cache):
        with open(args.cache, "rb") as file:
            return pickle.load(file)
    from yoto.evaluation.bench import BenchConfig, resolve_object, simulate_benchmark_pairs
    from yoto.localize import make_localizer
    from yoto.pose.pipeline import localize_contacts

    localizer = make_localizer("match")
    stored = {}
    for spec in args.objects:
        model = resolve_object(spec, args.workspace)
        simulated = simulate_benchmark_pairs(model, BenchConfig(num_pairs=args.n, seed=args.seed))
        stored[model.name] = [(s.index, s.pair, *localize_contacts(s.pair, model, localizer)[:2]) for s in simulated]
    if args.cache:
        with open(args.cache, "wb") as file:
            pickle.dump(stored, file)
    return stored


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", nargs="+", required=True, help="object names or mesh files")
    parser.add_argument("-n", type=int, default=30, help="pairs per object")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--workspace", help="workspace folder for object models")
    parser.add_argument("--cache", help="pickle of the localized pairs (written when missing)")
    parser.add_argument("--variants", nargs="+", default=["default"])
    parser.add_argument("--rescued", action="store_true", help="only the pairs the first variant rescues")
    parser.add_argument("--both-cores", action="store_true", help="half of each large batch in a helper process")
    parser.add_argument("--repeat", type=int, default=1, help="runs per pair and variant (the least CPU is kept)")
    parser.add_argument("--threshold", type=float, default=0.486, help="confidence counted as confident")
    parser.add_argument("--changes", action="store_true", help="print the pairs whose outcome differs")
    args = parser.parse_args()

    from yoto.evaluation.bench import RIGHT_DEG, RIGHT_MM, BenchConfig, symmetric_errors
    from yoto.localize import make_localizer
    from yoto.localize.helper import LocalizerProcess
    from yoto.objects.build import load_object_model
    from yoto.pose import executor, pipeline
    from yoto.pose.hypotheses import pose_distances

    stored = stored_pairs(args)
    base = replace(BenchConfig(seed=args.seed).pose_config("full"), suggest_next_touch=False)
    variants = [parse_variant(text, base) for text in args.variants]
    rescue_ms: list[float] = []  # the rescue step's CPU time in the pose stage just run (empty: it did not run)
    rescue = pipeline._rescue

    def timed_rescue(*arguments, **keywords):
        tick = time.process_time()
        result = rescue(*arguments, **keywords)
        rescue_ms.append(1000.0 * (time.process_time() - tick))
        return result

    pipeline._rescue = timed_rescue
    helper = LocalizerProcess(make_localizer("match")) if args.both_cores else None
    split = executor.SplitConfig(slow_splits=10**9)  # split even where the helper finds no free core
    results: dict[str, dict[str, dict]] = {name: {} for name, _ in variants}
    for object_name, rows in stored.items():
        model = load_object_model(object_name, args.workspace)
        if helper is not None:
            helper.prepare_object(model)
            executor.prepare_pose_helper(helper, model).result()
        for index, pair, candidates, world in rows:
            key = f"{object_name} #{index}"
            for number, (name, config) in enumerate(variants):
                if number and args.rescued and key not in results[variants[0][0]]:
                    break
                best: tuple[float, float, bool] | None = None
                for _ in range(args.repeat):
                    rescue_ms.clear()
                    tick = time.process_time()
                    if helper is None:
                        estimate = pipeline.pose_from_candidates(pair, model, candidates, world, config, "match")
                    else:  # the stage's own split, with the guard off
                        run = executor.SplitExecutor(helper, model, config.field_config, split)
                        with pipeline.one_blas_thread():
                            estimate = pipeline._pose_from_candidates(
                                pair, model, candidates, world, config, "match", None, run
                            )
                    cpu = 1000.0 * (time.process_time() - tick)
                    cpu += run.helper_extra_cpu_ms if helper is not None else 0.0
                    if best is None or cpu < best[0]:
                        best = (cpu, sum(rescue_ms), bool(rescue_ms))
                assert best is not None
                if number == 0 and args.rescued and not best[2]:
                    break
                errors = symmetric_errors(model, estimate.T_world_mesh, pair.T_world_mesh_true)
                T_true = pair.T_world_mesh_true @ model.T_mesh_object
                translation, rotation = pose_distances(
                    estimate.hypotheses_mesh(model) @ model.T_mesh_object, T_true, model.symmetry
                )
                digest = hashlib.sha1()
                for array in (estimate.T_world_object, estimate.hypotheses.T_world_object):
                    digest.update(array.tobytes())
                digest.update(estimate.hypotheses.probability.tobytes())
                digest.update(np.float64(estimate.confidence).tobytes())
                results[name][key] = {
                    "right": errors["translation_mm"] < RIGHT_MM and errors["rotation_deg"] < RIGHT_DEG,
                    "among": bool(np.any((translation < RIGHT_MM / 1000.0) & (rotation < np.radians(RIGHT_DEG)))),
                    "confidence": float(estimate.confidence),
                    "cpu_ms": best[0],
                    "rescue_ms": best[1] if best[2] else None,
                    "digest": digest.hexdigest(),
                    "error": f"{errors['translation_mm']:.1f} mm / {errors['rotation_deg']:.1f} deg",
                }
    if helper is not None:
        helper.close()
    first = results[variants[0][0]]
    print(f"{'cores: two, critical path' if args.both_cores else 'cores: one'}; confident at {args.threshold}")
    print(
        "| variant | pairs | rescued | right | truth among | confident | CPU ms median / mean | rescue CPU ms mean "
        "| bitwise the first's |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, _ in variants:
        outcomes = results[name]
        cpu_ms = [row["cpu_ms"] for row in outcomes.values()]
        rescued = [row["rescue_ms"] for row in outcomes.values() if row["rescue_ms"] is not None]
        print(
            f"| {name} | {len(outcomes)} | {len(rescued)} | {sum(r['right'] for r in outcomes.values())} "
            f"| {sum(r['among'] for r in outcomes.values())} "
            f"| {sum(r['confidence'] >= args.threshold for r in outcomes.values())} "
            f"| {np.median(cpu_ms):.1f} / {np.mean(cpu_ms):.1f} | {np.mean(rescued) if rescued else float('nan'):.1f} "
            f"| {sum(outcomes[k]['digest'] == first[k]['digest'] for k in outcomes)} |"
        )
        if args.changes and name != variants[0][0]:
            for key, row in outcomes.items():
                was = first[key]
                if (row["right"], row["among"]) != (was["right"], was["among"]) or abs(
                    row["confidence"] - was["confidence"]
                ) > 0.05:
                    print(
                        f"  {key}: right {was['right']} -> {row['right']}, among {was['among']} -> {row['among']}, "
                        f"confidence {was['confidence']:.2f} -> {row['confidence']:.2f} ({was['error']} -> "
                        f"{row['error']})"
                    )


if __name__ == "__main__":
    main()
