"""Why image pairs lose what clean pairs win: the rescue step, the truth's likelihood and its residual per pair.

Reads the pairs and localizations `benchmarks/image_pose_budget.py --cache DIR` stored (one pickle per object,
renderer, seed and N: clean pairs and the same pairs through images), runs the full pose stage (without re-touch)
on each clean and image pair under a variant of the settings (`--variant`, the syntax of image_pose_budget.py;
default: the pose stage's own, image budget included) and prints, per pair and path:

- right (R) or wrong (-) and the pose error, the first hypothesis's log-likelihood when the rescue step was called
  (`pipeline._rescue`, which runs when the most likely hypothesis explains the contacts worse than
  `rescue_log_likelihood`; "-": not called), the rank of the first hypothesis within 5 mm / 5 deg of the truth;
- three poses refined as the family step refines a hypothesis (`refined_log_likelihood`), each with its
  log-likelihood split into the fit, free-space and correction terms (the last with the depth scales' prior), each
  contact's fit RMS (um) and depth scale, each sensor's correction (rotation deg, translation mm, left/right): the
  chosen pose, the truth, and the first right hypothesis if any.

Then a summary per path: pairs right, rescue calls, the median fit RMS at the refined truth over the pairs'
contacts (the residual a right pose leaves, which the likelihood's `fit_noise_m` stands for), the truth's median
log-likelihood and correction term; and for the pairs right clean and wrong through images, which are rankings
(the truth among the hypotheses, or explaining the clouds no better than the chosen pose) and which were never
reached, and on which the rescue ran. `PYTHONPATH=$PWD` makes it import the working tree's `yoto`.

    python benchmarks/image_rescue.py --cache DIR/mug_CAL_GAIN_seed7_n40.pkl --object ../shared/data/meshes/mug/mug.ply
"""

from __future__ import annotations

import argparse
import pickle
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))


def refit(pair, model, config, T_world_object):
    """A pose refined as the family step refines a hypothesis (`refined_log_likelihood`), as a dict: its
    log-likelihood and the terms it is made of (fit, free space, corrections with the depth scales: each already
    -1/2 x), each contact's fit RMS (m) and depth scale."""
    from yoto.pose.field import surface_field
    from yoto.pose.hypotheses import log_likelihoods
    from yoto.pose.pipeline import _pair_clouds
    from yoto.pose.refine import refine_hypotheses
    from yoto.registration import one_blas_thread

    field = surface_field(model, config.field_config)
    contacts = _pair_clouds(pair, model, config)
    poses = T_world_object[None]
    with one_blas_thread():
        for _ in range(max(config.family_passes, 1)):
            refined = refine_hypotheses(field, contacts, poses, config.calibration, config.refine_config)
            poses = refined.T_world_object
    h = config.hypotheses
    return {
        "ll": float(log_likelihoods(refined, h)[0]),
        "fit": float(-0.5 * h.effective_points * np.sum((refined.fit_rms_m[0] / h.fit_noise_m) ** 2)),
        "free": float(-0.5 * h.free_effective_points * np.sum((refined.free_rms_m[0] / h.free_noise_m) ** 2)),
        "corr": float(-0.5 * refined.correction_cost[0]),
        "rms": refined.fit_rms_m[0],
        "scale": refined.depth_scale[0],
        "rotation_deg": np.degrees(np.linalg.norm(refined.corrections[0, :, :3], axis=1)),
        "translation_mm": 1000.0 * np.linalg.norm(refined.corrections[0, :, 3:], axis=1),
    }


def describe(fitted: dict | None) -> str:
    if fitted is None:
        return "-"
    return (
        f"{fitted['ll']:6.1f} = fit {fitted['fit']:6.1f} free {fitted['free']:5.1f} corr {fitted['corr']:5.1f} "
        f"(rms {1e6 * fitted['rms'][0]:3.0f}/{1e6 * fitted['rms'][1]:3.0f} um, "
        f"scale {fitted['scale'][0]:.2f}/{fitted['scale'][1]:.2f}, corrections "
        f"{fitted['rotation_deg'][0]:.1f}/{fitted['rotation_deg'][1]:.1f} deg "
        f"{fitted['translation_mm'][0]:.1f}/{fitted['translation_mm'][1]:.1f} mm)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", required=True, help="a pickle image_pose_budget.py --cache wrote")
    parser.add_argument("--object", required=True)
    parser.add_argument("--variant", default="images")
    parser.add_argument("--quiet", action="store_true", help="summary only")
    args = parser.parse_args()

    from image_pose_budget import parse_variant

    import yoto.pose.pipeline as pipeline
    from yoto.errors import YotoError
    from yoto.evaluation.bench import RIGHT_DEG, RIGHT_MM, BenchConfig, resolve_object, symmetric_errors
    from yoto.pose.hypotheses import pose_distances

    model = resolve_object(args.object, None)
    with open(args.cache, "rb") as file:
        cases = pickle.load(file)
    base = BenchConfig().pose_config("full")
    _, variant = parse_variant(args.variant, base)

    calls: list[float] = []
    original = pipeline._rescue

    def recording(field, contacts, seeds, score, refined, symmetry, config, run=pipeline.LOCAL):
        hypotheses = pipeline.group_hypotheses(refined, symmetry, config.hypotheses)
        calls.append(float(hypotheses.log_likelihood[0]))
        return original(field, contacts, seeds, score, refined, symmetry, config, run)

    pipeline._rescue = recording
    rows: dict[str, list[dict]] = {"clean": [], "images": []}
    for index, (clean_case, image_case) in enumerate(cases):
        for path, (pair, candidates, world), config in (("clean", clean_case, base), ("images", image_case, variant)):
            row: dict = {"right": False, "rescued": None, "chosen": np.nan, "rank": None}
            config = replace(config, suggest_next_touch=False)
            calls.clear()
            estimate = None
            if candidates is not None:
                try:
                    estimate = pipeline.pose_from_candidates(pair, model, candidates, world, config, "match")
                except YotoError:
                    estimate = None
                if estimate is not None:
                    errors = symmetric_errors(model, estimate.T_world_mesh, pair.T_world_mesh_true)
                    row["right"] = errors["translation_mm"] < RIGHT_MM and errors["rotation_deg"] < RIGHT_DEG
                    row["error"] = f"{errors['translation_mm']:.1f} mm / {errors['rotation_deg']:.0f} deg"
                    row["chosen"] = float(estimate.hypotheses.log_likelihood[0])
                    T_true = pair.T_world_mesh_true @ model.T_mesh_object
                    translation, rotation = pose_distances(estimate.hypotheses.T_world_object, T_true, model.symmetry)
                    near = np.flatnonzero((translation < RIGHT_MM / 1000.0) & (rotation < np.radians(RIGHT_DEG)))
                    row["rank"] = int(near[0]) if len(near) else None
                    row["rescued"] = calls[0] if calls else None
            row["truth_fit"] = row["chosen_fit"] = row["right_fit"] = None
            if (
                candidates is not None
                and len(pair.contact("left").points_sensor)
                and len(pair.contact("right").points_sensor)
            ):
                full = config.for_pair(pair)
                row["truth_fit"] = refit(pair, model, full, pair.T_world_mesh_true @ model.T_mesh_object)
                if estimate is not None:
                    row["chosen_fit"] = refit(pair, model, full, estimate.hypotheses.T_world_object[0])
                    if row["rank"]:
                        row["right_fit"] = refit(pair, model, full, estimate.hypotheses.T_world_object[row["rank"]])
            rows[path].append(row)
        if not args.quiet:
            print(f"pair {index:2d}")
            for path in rows:
                r = rows[path][index]
                rescued = "-" if r["rescued"] is None else f"{r['rescued']:.1f}"
                rank = "-" if r["rank"] is None else str(r["rank"])
                print(
                    f"  {path:>6} {'R' if r['right'] else '-'} {r.get('error', 'failed'):>17} rescue at {rescued:>6}, "
                    f"truth's rank {rank:>2}\n"
                    f"      chosen {describe(r['chosen_fit'])}\n       truth {describe(r['truth_fit'])}"
                    + (f"\n       right {describe(r['right_fit'])}" if r["right_fit"] else ""),
                    flush=True,
                )

    print(f"{model.name}: {args.cache}, images under {args.variant!r}")
    for path, found in rows.items():
        found = [r for r in found if r["truth_fit"] is not None]
        rms = np.concatenate([r["truth_fit"]["rms"] for r in found])
        print(
            f"  {path:>6}: right {sum(r['right'] for r in found)} of {len(found)}, rescue ran on "
            f"{sum(r['rescued'] is not None for r in found)}, truth's fit RMS median {1e6 * np.median(rms):.0f} um "
            f"(p25 {1e6 * np.percentile(rms, 25):.0f}, p75 {1e6 * np.percentile(rms, 75):.0f}), truth's "
            f"log-likelihood median {np.median([r['truth_fit']['ll'] for r in found]):.1f}, correction term median "
            f"{np.median([r['truth_fit']['corr'] for r in found]):.1f}"
        )
    lost = [i for i in range(len(cases)) if rows["clean"][i]["right"] and not rows["images"][i]["right"]]
    gained = [i for i in range(len(cases)) if rows["images"][i]["right"] and not rows["clean"][i]["right"]]
    ranked = [
        i
        for i in lost
        if rows["images"][i]["rank"] is not None
        or (rows["images"][i]["truth_fit"] or {"ll": -np.inf})["ll"] <= rows["images"][i]["chosen"]
    ]
    print(
        f"  lost through images {lost} (gained {gained}): the truth ranked below the chosen pose in {ranked}, "
        f"never reached in {[i for i in lost if i not in ranked]}; rescue ran on "
        f"{[i for i in lost if rows['images'][i]['rescued'] is not None]}"
    )


if __name__ == "__main__":
    main()
