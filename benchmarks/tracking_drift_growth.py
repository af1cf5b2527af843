"""Why the closed loop's rotation drift grows with the path: does it follow its frames, or sum a per-frame bias?

    python benchmarks/tracking_drift_growth.py --objects fruit ../shared/data/meshes/monkey/monkey.ply \\
        --indices 1 0 --path-length-mm 200 --out docs/figures/tracking_drift_growth.png

For each (object, trajectory index) pair: the `yoto track-bench` trajectory (same seed, same scenario scaled to the
path length, the touch from the pose stage with the matched filter), tracked open and closed loop, and every fourth
two-frame instant registered from the true pose (`yoto.tracking.bench.truth_registrations`): the frames' own offset,
which no filter can tell from slip. One panel per trajectory, along time since the motion started: the change of
each rotation error from the motion's start, projected on the direction of the closed loop's final drift (object
frame). A closed loop summing a constant per-frame bias would leave its frames' offset behind, growing steadily;
one that follows its frames sits on their offset. Printed: each curve's final change and the correlation of the
closed loop with the frames' offset from the motion's start on. `--without bias scale pixel` simulates the same
trajectories with those parts of the reconstruction error switched off (the smooth field fixed on each pad, the
depth scale error, the per-frame pixel noise), to tell which of them moves the frames.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from tracking_figure import figure_parser, parse_figure_arguments, simulated_touch

from yoto.geometry import so3_log
from yoto.io import write_bytes_atomic
from yoto.localize import make_localizer
from yoto.tracking.bench import TrackBenchConfig, tactile_streams, truth_registrations
from yoto.tracking.evaluate import motion_interval
from yoto.tracking.track import track

NOISE_FIELDS = {"bias": "bias_std_m", "scale": "scale_std", "pixel": "pixel_std_m"}  # --without -> noise field


def rotation_errors(truth: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Object-frame rotation vectors (N, 3) of truth^-1 @ pose."""
    return so3_log(np.einsum("nji,njk->nik", truth[:, :3, :3], poses[:, :3, :3]))


def main() -> None:
    parser = figure_parser(__doc__.split("\n\n")[0], "tracking_drift_growth.png")
    parser.add_argument(
        "--without", nargs="*", default=[], choices=sorted(NOISE_FIELDS), help="reconstruction errors switched off"
    )
    args = parse_figure_arguments(parser)

    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bench = TrackBenchConfig()
    scenario = bench.trajectory.scenario
    noise = dataclasses.replace(scenario.press.noise, **{NOISE_FIELDS[name]: 0.0 for name in args.without})
    scenario = dataclasses.replace(scenario, press=dataclasses.replace(scenario.press, noise=noise))
    bench = dataclasses.replace(bench, trajectory=dataclasses.replace(bench.trajectory, scenario=scenario))
    correction = bench.track.correction
    localizer = make_localizer(bench.method)
    figure, axes = plt.subplots(1, len(args.objects), figsize=(4.2 * len(args.objects), 3.6), squeeze=False)
    for axis, spec, index in zip(axes[0], args.objects, args.indices, strict=True):
        model, trajectory, touch = simulated_touch(spec, index, args, bench, localizer)
        result = track(touch, trajectory.streams, model, tactile_streams(trajectory), bench.track)
        truth, _ = trajectory.truth.interpolate(result.timestamps_s)
        motion = motion_interval(trajectory.streams, result.timestamps_s)
        if motion is None:
            raise SystemExit(f"{model.name} #{index}: the sensors never move")
        times = result.timestamps_s - motion[0]
        start = int(np.searchsorted(times, 0.0))
        open_loop = rotation_errors(truth, result.T_world_object_open_loop)
        closed_loop = rotation_errors(truth, result.T_world_object)
        stamps, twists = truth_registrations(trajectory, model, correction)
        frames = -twists[:, :3]  # the registration moves the object by the twist: a believing loop holds its inverse
        frame_times = stamps - motion[0]
        resting = frame_times < 0.0
        direction = closed_loop[-1] - closed_loop[start]
        direction /= max(float(np.linalg.norm(direction)), 1e-12)
        open_change = np.degrees((open_loop - open_loop[start]) @ direction)
        closed_change = np.degrees((closed_loop - closed_loop[start]) @ direction)
        frame_change = np.degrees((frames - frames[resting].mean(axis=0)) @ direction)
        axis.plot(times, open_change, color="tab:red", lw=1.0, label="open loop (the slip)")
        axis.plot(times, closed_change, color="tab:blue", lw=1.0, label="closed loop")
        axis.plot(frame_times, frame_change, ".", color="tab:green", label="frames registered from the truth")
        axis.axvline(motion[1] - motion[0], color="0.4", lw=0.6)
        off = f", without {' and '.join(args.without)}" if args.without else ""
        axis.set_title(f"{model.name} #{index}, {args.path_length_mm:.0f} mm{off}", fontsize=9)
        axis.set_xlabel("time since the motion started (s); line: its end", fontsize=8)
        axis.tick_params(labelsize=7)
        axis.grid(alpha=0.3)
        moving = ~resting
        correlation = np.corrcoef(np.interp(frame_times[moving], times, closed_change), frame_change[moving])[0, 1]
        print(
            f"{model.name} #{index}: change along the drift axis, closed loop {closed_change[-1]:+.2f} deg, "
            f"frames {frame_change[-3:].mean():+.2f} deg, open loop {open_change[-1]:+.2f} deg; "
            f"correlation closed loop / frames {correlation:.2f}"
        )
    axes[0][0].set_ylabel("rotation error change along the drift axis (deg)", fontsize=8)
    axes[0][0].legend(fontsize=7)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    plt.close(figure)
    print(f"wrote {write_bytes_atomic(Path(args.out), buffer.getvalue())}")


if __name__ == "__main__":
    main()
