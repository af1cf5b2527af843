"""Why an object's image pairs lose the poses its clean pairs win: each lost pair put down to one cause.

Reads one pickle that `benchmarks/image_pose_budget.py --cache DIR` stored (an object's clean pairs and the same
pairs through rendered images, with their localizations), runs the pose stage as that script's `images` row does
(the pose stage's own settings, image budget included) on each clean and image pair for `--draws` draws of the fit's
points, and compares each image contact with its clean cloud in the sensor frame (the same pixels: an image point's
nearest clean point within 0.1 mm across the pad). It prints per pair: the poses right and the truth among the
hypotheses (of the draws) clean and through images, the image pose's error (first draw), and per contact (left,
right): the clean cloud's points, the image cloud's share of them, its level (mean height of the image cloud over
the clean one at the same pixels, mm; positive: read shallower) and its shape error (RMS of that difference after a
plane, mm). Then the poses right (mean over the draws), those gained, the median shape error, and the poses lost
(clean right, image wrong; mean over the draws), each pair put down to the first cause that holds:

- refused: the localizer or reconstruction gave no candidates (a frame read as no contact);
- pad-wide face: a contact whose clean cloud fills the pad (more than `--pad-wide` points) is seen in less than 70%
  of it or read more than 0.3 mm shallow (a face pressed over the whole pad leaves no untouched gel to anchor its
  depth, and a uniform tilt reads like a lighting change: docs/sensor.md, Known limits);
- shape misread: a contact's shape error is above `--shape-mm` (0.09 mm: box edges and corners that leave the frame
  read 0.1-0.2 mm off, the typical contact 0.03-0.05 mm);
- outscored: every contact reads within those limits; the pose stage ranks a wrong pose first (truth among the
  hypotheses or not, printed).

    python benchmarks/image_pair_causes.py --cache DIR/cracker_box_table_gelsight_mini_seed11_n40.pkl \\
        --object ../shared/data/meshes/cracker_box/cracker_box.ply --seed 11 \\
        --renderer table:../shared/data/gelsight_mini

`--seed`, `-n` and `--renderer` must be those the cache was made with (they set the benchmark's pose settings);
run it from the repository root with `PYTHONPATH=$PWD` to measure the working tree's `yoto`.
"""

from __future__ import annotations

import argparse
import importlib.util
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

SAME_PIXEL_M = 1e-4  # an image point and a clean point this close across the pad are the same pixel
SEEN_SHARE = 0.7  # a pad-wide face seen in less than this share of its clean points is partly unseen
SHALLOW_M = 3e-4  # ... or read this much shallower on average


def contact_figures(clean_points: np.ndarray, image_points: np.ndarray) -> tuple[float, float, float]:
    """(share of the clean points the image cloud has, level in m, shape error in m) of one contact, sensor frame."""
    share = len(image_points) / max(len(clean_points), 1)
    if len(image_points) < 100 or len(clean_points) < 100:
        return share, float("nan"), float("nan")
    distance, index = cKDTree(clean_points[:, :2]).query(image_points[:, :2], distance_upper_bound=SAME_PIXEL_M)
    matched = np.isfinite(distance)
    if matched.sum() < 100:
        return share, float("nan"), float("nan")
    height = image_points[matched, 2] - clean_points[index[matched], 2]  # positive: the image reads it shallower
    design = np.c_[image_points[matched, :2], np.ones(matched.sum())]
    residual = height - design @ np.linalg.lstsq(design, height, rcond=None)[0]
    return share, float(height.mean()), float(np.sqrt(np.mean(residual**2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", required=True, help="one pickle image_pose_budget.py --cache stored")
    parser.add_argument("--object", required=True, help="the object's mesh or name")
    parser.add_argument("--renderer", required=True, help="the renderer the cache was made with")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("-n", type=int, default=40)
    parser.add_argument("--draws", type=int, default=2)
    parser.add_argument("--pad-wide", type=int, default=60000, help="clean points of a contact that fills the pad")
    parser.add_argument("--shape-mm", type=float, default=0.09, help="a contact's shape error counted as misread")
    args = parser.parse_args()

    from yoto.evaluation.bench import BenchConfig, resolve_object

    spec = importlib.util.spec_from_file_location("image_pose_budget", Path(__file__).with_name("image_pose_budget.py"))
    budget = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(budget)
    model = resolve_object(args.object, None)
    base = BenchConfig(num_pairs=args.n, seed=args.seed, image_calibration=args.renderer).pose_config("full")
    with open(args.cache, "rb") as file:
        cases = pickle.load(file)

    def outcomes(pair, candidates, world) -> list[tuple[bool, bool, str]]:
        if candidates is None:
            return [(False, False, "refused")] * args.draws
        rows = []
        for draw in range(args.draws):
            refine = replace(base.refine_config, seed=base.refine_config.seed + draw)
            right, among, _, error = budget.pose_outcome(
                pair, model, candidates, world, replace(base, refine_config=refine)
            )
            rows.append((right, among, error))
        return rows

    lost: dict[str, list[str]] = {}
    lost_draws: dict[str, int] = {}
    right_draws = {"clean": 0, "images": 0, "gained": 0}
    shapes = []  # every contact's shape error (m)
    for i, ((clean, clean_candidates, clean_world), (image, image_candidates, image_world)) in enumerate(cases):
        clean_rows = outcomes(clean, clean_candidates, clean_world)
        image_rows = outcomes(image, image_candidates, image_world)
        figures = {
            side: contact_figures(clean.contact(side).points_sensor, image.contact(side).points_sensor)
            for side in ("left", "right")
        }
        sizes = {side: len(clean.contact(side).points_sensor) for side in figures}
        print(
            f"pair {i:2d}: clean right {sum(r[0] for r in clean_rows)} among {sum(r[1] for r in clean_rows)}, "
            f"images right {sum(r[0] for r in image_rows)} among {sum(r[1] for r in image_rows)} "
            f"({image_rows[0][2]}); "
            + "; ".join(
                f"{side} {sizes[side]} pts, seen {share:.2f}, level {1e3 * level:+.2f} mm, shape {1e3 * shape:.3f} mm"
                for side, (share, level, shape) in figures.items()
            ),
            flush=True,
        )
        right_draws["clean"] += sum(r[0] for r in clean_rows)
        right_draws["images"] += sum(r[0] for r in image_rows)
        right_draws["gained"] += sum(m[0] and not c[0] for c, m in zip(clean_rows, image_rows))
        shapes += [shape for _, _, shape in figures.values() if np.isfinite(shape)]
        count = sum(c[0] and not m[0] for c, m in zip(clean_rows, image_rows))
        if count == 0:
            continue
        if image_candidates is None:
            cause = "refused"
        elif any(
            sizes[side] > args.pad_wide and (share < SEEN_SHARE or level > SHALLOW_M)
            for side, (share, level, _) in figures.items()
        ):
            cause = "pad-wide face"
        elif any(shape > args.shape_mm / 1e3 for _, _, shape in figures.values()):
            cause = "shape misread"
        else:
            cause = "outscored"
        among = "truth among" if all(m[1] for m in image_rows) else "truth not among"
        lost.setdefault(cause, []).append(f"{i} ({count} of {args.draws}, {among})")
        lost_draws[cause] = lost_draws.get(cause, 0) + count
    mean = {key: value / args.draws for key, value in right_draws.items()}
    print(
        f"{model.name}: right clean {mean['clean']:.1f}, images {mean['images']:.1f} of {len(cases)} "
        f"(mean over {args.draws} draws; images gained {mean['gained']:.1f}); median shape error "
        f"{1e3 * np.median(shapes):.3f} mm over {len(shapes)} contacts; poses lost (clean right, images wrong):"
    )
    for cause, pairs in lost.items():
        print(f"  {cause}: {lost_draws[cause] / args.draws:.1f}: pairs {', '.join(pairs)}")


if __name__ == "__main__":
    main()
