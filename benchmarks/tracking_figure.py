"""What the tracking figure scripts share: their arguments and the simulated touch each trajectory starts from.

Imported by `tracking_pad_map.py` and `tracking_drift_growth.py` (run from the repository root; Python puts this
folder on the path).
"""

from __future__ import annotations

import argparse

from yoto.evaluation.bench import resolve_object
from yoto.objects.model import ObjectModel
from yoto.simulate.trajectory import SimulatedTrajectory, TrajectorySimulator
from yoto.tracking.bench import TrackBenchConfig, scaled_trajectory, touch_estimate
from yoto.tracking.track import Touch, touch_from_pair


def figure_parser(description: str, default_out: str) -> argparse.ArgumentParser:
    """The arguments both figures take: which trajectories (object, index), how long, where the figure goes."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--objects", nargs="+", required=True, help="built-in object names or mesh files")
    parser.add_argument("--indices", nargs="+", type=int, required=True, help="trajectory index, one per object")
    parser.add_argument("--path-length-mm", type=float, default=200.0)
    parser.add_argument("--workspace", default="yoto_workspace", help="workspace holding the object models")
    parser.add_argument("--out", default=default_out)
    return parser


def parse_figure_arguments(parser: argparse.ArgumentParser) -> argparse.Namespace:
    args = parser.parse_args()
    if len(args.indices) != len(args.objects):
        parser.error("give one --indices entry per object")
    return args


def simulated_touch(
    spec: str, index: int, args: argparse.Namespace, bench: TrackBenchConfig, localizer
) -> tuple[ObjectModel, SimulatedTrajectory, Touch]:
    """The `yoto track-bench` trajectory `index` of an object, scaled to the path length, and its touch as the pose
    stage estimates it with the benchmark's localizer."""
    model = resolve_object(spec, args.workspace)
    scenario = scaled_trajectory(bench.trajectory, args.path_length_mm / 1e3)
    trajectory = TrajectorySimulator(model, scenario).trajectory(bench.seed, index)
    T_touch = touch_estimate(trajectory, model, localizer)
    return model, trajectory, touch_from_pair(trajectory.touch.pair, T_touch, trajectory.touch_time_s, "simulated")
