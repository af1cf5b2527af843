"""The pose stage's search budget for image contacts: poses right through images against clean clouds.

For the benchmark's pairs (seed 7 unless `--seed`, the standard 1 mm / 1 deg calibration error, matched filter,
full pose stage without re-touch, as `yoto bench --via-images` runs them), this localizes each pair once as clean
clouds and once through rendered GelSight images (`--renderer`: a calibration file's optical model or
`shading[:SEED]`), then runs the pose stage on the image pairs under each variant of its settings (`--variants`), and
on the clean pairs under the defaults. It prints per object and variant: poses right (within 5 mm and 5 deg) of N,
the difference to the clean clouds in percentage points, the truth among the hypotheses, the pairs gained and lost
against the first variant, and the pose stage's CPU seconds (median and sum over the pairs: run it with one BLAS
thread); with `--errors`, each row's pose error on every pair the rows disagree on. With `--cache DIR`, each
object's pairs and localizations (clean and through images) are kept in DIR as a pickle and reused by later runs
(only the pose stage runs again: a variant costs seconds per object); `benchmarks/image_rescue.py` reads them.
With `--relocalize FOLDER`, each object's pickle is read from that cache folder instead, its image pairs localized
again by the working tree's localizer (the clean pairs kept), and the result kept in `--cache` (a localizer change
measured without rendering again; the localizer's median CPU per image contact is printed). Every object's rows
begin with the localization of its clean and image contacts: the first candidate within 5 mm of the true contact,
and any of them.
With `--draws N`, every row is also run with N - 1 other draws of the points the pose stage's fit reads
(`RefineConfig.seed` + 1 ... N - 1: which 120 of a contact's points) and each row prints the poses right per draw and
their mean: one draw moves a row by 1-5 pairs in 40 (docs/journal/sensor.md, stop 13), as much as the 5-point target.
Run it from the repository root with `PYTHONPATH=$PWD` to measure the working tree's `yoto`.

A variant is `name:key=value,key=value`; keys are `PoseConfig` fields (`screened=1000`), or `SearchConfig`,
`RefineConfig`, `HypothesisConfig`, `CalibrationPrior` and `ImageBudget` fields with a `search.`, `refine.`,
`hypotheses.`, `calibration.` or `budget.` prefix
(`search.pair_budget=10000000`); `default` is `PoseConfig` as `yoto bench` sets it;
`images` is what the image rows use (`PoseConfig.for_pair` on a pair reconstructed from images), and
`images+NAME:key=value` that with settings changed (`images+r10:rescue_log_likelihood=-10`; the image budget's own
settings: `images+f30:budget.fit_noise_m=0.00003`, the fit noise main had before stop 14).

    python benchmarks/image_pose_budget.py --renderer CAL_GAIN.npz -n 40 \\
        --objects ../shared/data/meshes/mug/mug.ply ../shared/data/meshes/cracker_box/cracker_box.ply \\
        --variants default images "b10:search.pair_budget=10000000"
"""

from __future__ import annotations

import argparse
import pickle
import time
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

# Variant key prefixes -> the PoseConfig field holding that config.
NESTED = {
    "search": "search_config",
    "refine": "refine_config",
    "hypotheses": "hypotheses",
    "calibration": "calibration",
    "budget": "image_budget",
}


def parse_variant(text: str, base):
    """(name, PoseConfig) of a variant string over `base` (the benchmark's full-stage config). A variant named
    `images` or `images+...` keeps the pose stage's own image budget (`PoseConfig.image_budget`, which
    `pose_from_candidates` applies to pairs reconstructed from images) under its settings; every other variant
    runs as written on the image pairs, with that budget switched off."""
    if text == "images":
        return "images", base
    name, _, settings = text.partition(":")
    if name != "images" and not name.startswith("images+"):
        base = replace(base, image_budget=None)
    if text == "default":
        return "default", base
    config = base
    pose_fields = {f.name: f for f in fields(config)}
    for item in filter(None, settings.split(",")):
        key, value = item.split("=")
        group, _, leaf = key.rpartition(".")
        if group and group in NESTED:
            inner = getattr(config, NESTED[group])
            inner = replace(inner, **{leaf: type(getattr(inner, leaf))(float(value))})
            config = replace(config, **{NESTED[group]: inner})
        elif not group and key in pose_fields:
            config = replace(config, **{key: type(getattr(config, key))(float(value))})
        else:
            raise SystemExit(f"unknown setting {key!r} in variant {text!r}")
    return name, config


def pose_outcome(pair, model, candidates, world, config) -> tuple[bool, bool, float, str]:
    """(right, truth among the hypotheses, pose-stage CPU seconds, "translation mm / rotation deg") of one pair
    under `config`."""
    from yoto.errors import YotoError
    from yoto.evaluation.bench import RIGHT_DEG, RIGHT_MM, symmetric_errors
    from yoto.pose.hypotheses import pose_distances
    from yoto.pose.pipeline import pose_from_candidates

    start = time.process_time()
    try:
        config = replace(config, suggest_next_touch=False)
        estimate = pose_from_candidates(pair, model, candidates, world, config, "match")
    except YotoError:
        return False, False, time.process_time() - start, "failed"
    seconds = time.process_time() - start
    errors = symmetric_errors(model, estimate.T_world_mesh, pair.T_world_mesh_true)
    right = errors["translation_mm"] < RIGHT_MM and errors["rotation_deg"] < RIGHT_DEG
    T_true = pair.T_world_mesh_true @ model.T_mesh_object
    T_hypotheses = estimate.hypotheses_mesh(model) @ model.T_mesh_object
    translation, rotation = pose_distances(T_hypotheses, T_true, model.symmetry)
    among = bool(np.any((translation < RIGHT_MM / 1000.0) & (rotation < np.radians(RIGHT_DEG))))
    return bool(right), among, seconds, f"{errors['translation_mm']:.1f} mm / {errors['rotation_deg']:.1f} deg"


LOCATED_MM = 5.0  # a candidate within this of the true contact location locates the contact


def localization_hits(model, localized_pairs) -> tuple[int, int, int]:
    """(top-1 candidates within `LOCATED_MM` of the true contact, contacts with one among their candidates, contacts)
    of localized pairs (pair, candidates, world); a pair the localizer refused counts as missed."""
    from yoto.contacts import SIDES
    from yoto.geometry import transform_points

    top1 = top10 = 0
    for pair, candidates, _ in localized_pairs:
        for side in SIDES:
            if candidates is None:
                continue
            truth = transform_points(model.T_object_mesh, pair.p_mesh_true[side][None])[0]
            distances = np.array([np.linalg.norm(c.p_object - truth) for c in candidates[side]])
            top1 += bool(distances[0] < LOCATED_MM / 1000.0)
            top10 += bool(np.any(distances < LOCATED_MM / 1000.0))
    return top1, top10, 2 * len(localized_pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--renderer", required=True, help="calibration file, shading[:SEED] or table:FOLDER")
    parser.add_argument("--objects", nargs="+", required=True)
    parser.add_argument("-n", type=int, default=40)
    parser.add_argument("--seed", type=int, default=7, help="the benchmark's evaluation seed (yoto bench --seed)")
    parser.add_argument("--variants", nargs="+", default=["default", "images"])
    parser.add_argument("--errors", action="store_true", help="print the pose errors of pairs the rows disagree on")
    parser.add_argument(
        "--draws", type=int, default=1, help="also run each row on this many draws of the fit's points (mean)"
    )
    parser.add_argument(
        "--cache", help="folder to keep each object's pairs and localizations in (pickles; reused when present)"
    )
    parser.add_argument(
        "--relocalize",
        metavar="FOLDER",
        help="read each object's pickle from this --cache folder, localize its image pairs again with this tree's "
        "localizer (the clean pairs as they are) and keep the result in --cache",
    )
    parser.add_argument(
        "--depth-scales",
        type=float,
        nargs="+",
        help="the matched filter's MatchConfig.image_depth_scales for image contacts (default: the config's)",
    )
    args = parser.parse_args()
    if args.relocalize and not args.cache:
        raise SystemExit("--relocalize needs --cache (where the re-localized pairs are kept)")

    from yoto.errors import YotoError
    from yoto.evaluation.bench import BenchConfig, pairs_via_images, resolve_object, simulate_benchmark_pairs
    from yoto.localize import make_localizer
    from yoto.pose.pipeline import localize_contacts

    bench = BenchConfig(num_pairs=args.n, seed=args.seed, image_calibration=args.renderer)
    base = bench.pose_config("full")
    variants = [parse_variant(text, base) for text in args.variants]
    localizer = make_localizer("match")
    if args.depth_scales:
        from yoto.localize.match import MatchConfig
        from yoto.localize.scaled_match import ScaledMatchLocalizer

        localizer = ScaledMatchLocalizer(MatchConfig(image_depth_scales=tuple(args.depth_scales)))

    def localized(pair, model):
        """(pair, candidates, world) of one pair, or (pair, None, None) where the localizer refuses it."""
        try:
            candidates, world, _ = localize_contacts(pair, model, localizer)
        except YotoError:
            return pair, None, None
        return pair, candidates, world

    for name in args.objects:
        model = resolve_object(name, None)
        cache = None
        if args.cache:
            renderer = Path(args.renderer).stem.replace(":", "_")
            if args.renderer.startswith("table:"):  # table:FOLDER
                renderer = "table_" + Path(args.renderer.partition(":")[2]).name
            cache = Path(args.cache) / f"{model.name}_{renderer}_seed{args.seed}_n{args.n}.pkl"
        localize_seconds: list[float] = []  # CPU seconds per image contact localized in this run
        if cache is not None and args.relocalize and not cache.exists():
            with open(Path(args.relocalize) / cache.name, "rb") as file:
                cases = pickle.load(file)
            for k, (clean_case, (pair, _, _)) in enumerate(cases):
                start = time.process_time()
                cases[k] = (clean_case, localized(pair, model))
                localize_seconds.append((time.process_time() - start) / 2.0)
            with open(cache, "wb") as file:
                pickle.dump(cases, file)
        elif cache is not None and cache.exists():
            with open(cache, "rb") as file:
                cases = pickle.load(file)
        else:
            simulated = simulate_benchmark_pairs(model, bench)
            cases = [
                (localized(clean.pair, model), localized(image.pair, model))
                for clean, image in zip(simulated, pairs_via_images(simulated, bench))
            ]
            if cache is not None:
                cache.parent.mkdir(parents=True, exist_ok=True)
                with open(cache, "wb") as file:
                    pickle.dump(cases, file)
        rows: dict[str, list[tuple[bool, bool, float, str]]] = {"clean": []}
        rows.update({label: [] for label, _ in variants})
        draws: dict[str, list[int]] = {row: [0] * args.draws for row in rows}  # poses right per draw of the points
        for clean_case, image_case in cases:
            for (pair, candidates, world), configs in ((clean_case, [("clean", base)]), (image_case, variants)):
                for row, config in configs:
                    for draw in range(args.draws):
                        if candidates is None:
                            outcome = (False, False, 0.0, "failed")
                        else:
                            refine = replace(config.refine_config, seed=config.refine_config.seed + draw)
                            drawn = replace(config, refine_config=refine)
                            outcome = pose_outcome(pair, model, candidates, world, drawn)
                        draws[row][draw] += outcome[0]
                        if draw == 0:
                            rows[row].append(outcome)
        clean_right = sum(outcome[0] for outcome in rows["clean"])
        first = [outcome[0] for outcome in rows[variants[0][0]]]
        print(f"{model.name} ({args.renderer}, {args.n} pairs)")
        for label, index in (("clean", 0), ("images", 1)):
            top1, top10, contacts = localization_hits(model, [case[index] for case in cases])
            print(f"  localization {label:>6}: top-1 within {LOCATED_MM:.0f} mm {top1}/{contacts}, top-10 {top10}")
        if localize_seconds:
            print(f"  re-localized image contacts: CPU median {1000 * np.median(localize_seconds):.1f} ms per contact")
        for row, outcomes in rows.items():
            right, among = [outcome[0] for outcome in outcomes], sum(outcome[1] for outcome in outcomes)
            seconds = np.array([outcome[2] for outcome in outcomes])
            gained = [i for i, (a, b) in enumerate(zip(first, right)) if b and not a]
            lost = [i for i, (a, b) in enumerate(zip(first, right)) if a and not b]
            points = 100.0 * (sum(right) - clean_right) / args.n
            mean_points = 100.0 * (np.mean(draws[row]) - np.mean(draws["clean"])) / args.n
            over_draws = (
                f"; over {args.draws} draws {draws[row]}, mean {np.mean(draws[row]):.2f} ({mean_points:+.1f} points)"
                if args.draws > 1
                else ""
            )
            print(
                f"  {row:>12}: right {sum(right):2d} ({points:+.1f} points), truth among "
                f"{among:2d}, pose stage CPU median {1000 * np.median(seconds):.0f} ms, "
                f"sum {seconds.sum():.1f} s"
                + ("" if row == "clean" else f"; gained {gained} lost {lost}")
                + over_draws,
                flush=True,
            )
        if args.errors:  # every pair whose outcome differs between the rows: each row's pose error
            for i in range(args.n):
                if len({outcomes[i][0] for outcomes in rows.values()}) > 1:
                    print(f"    pair {i}: " + "; ".join(f"{row} {outcomes[i][3]}" for row, outcomes in rows.items()))


if __name__ == "__main__":
    main()
