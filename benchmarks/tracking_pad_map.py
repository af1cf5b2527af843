"""The pad error maps the closed loop learns while the contact slides, and what they do to the drift.

    python benchmarks/tracking_pad_map.py --objects fruit ../shared/data/meshes/monkey/monkey.ply \\
        --indices 1 0 --path-length-mm 200 --out docs/figures/tracking_pad_map.png

For each (object, trajectory index) pair: the `yoto track-bench` trajectory (same seed, the scenario scaled to the
path length, the touch from the pose stage with the matched filter), tracked open loop, closed loop with the map
learnt at rest only (`PadErrorConfig(rest_map=True, online=False)`, the previous default) and closed loop with the
sliding map (the default). One row per trajectory: each sensor's learnt map over its pad (um, sensor x and y; the
line is the path of the contact's centre, its start marked), and the rotation error against the truth along time.
The maps hold only what no rigid motion explains under each frame: slip, which is rigid, cannot enter them. Printed:
each track's settled drift.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from tracking_figure import figure_parser, parse_figure_arguments, simulated_touch

from yoto.contacts import SIDES
from yoto.io import write_bytes_atomic
from yoto.localize import make_localizer
from yoto.tracking.bench import TrackBenchConfig, tactile_streams
from yoto.tracking.evaluate import motion_interval, summarize_errors, tracking_errors
from yoto.tracking.pad_error import PadErrorConfig
from yoto.tracking.track import track


def main() -> None:
    args = parse_figure_arguments(figure_parser(__doc__.split("\n\n")[0], "tracking_pad_map.png"))

    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bench = TrackBenchConfig()
    rest_only = dataclasses.replace(bench.track.correction, pad_error=PadErrorConfig(rest_map=True, online=False))
    variants = {
        "rest map only (before)": dataclasses.replace(bench.track, correction=rest_only),
        "sliding map": bench.track,
    }
    localizer = make_localizer(bench.method)
    rows = len(args.objects)
    figure, axes = plt.subplots(rows, 3, figsize=(13.0, 3.8 * rows), squeeze=False)
    for row, spec, index in zip(axes, args.objects, args.indices, strict=True):
        model, trajectory, touch = simulated_touch(spec, index, args, bench, localizer)
        results = {
            label: track(touch, trajectory.streams, model, tactile_streams(trajectory), config)
            for label, config in variants.items()
        }
        result = results["sliding map"]
        truth, _ = trajectory.truth.interpolate(result.timestamps_s)
        motion = motion_interval(trajectory.streams, result.timestamps_s)
        title = f"{model.name} #{index}, {args.path_length_mm:.0f} mm"
        for axis, side in zip(row[:2], SIDES, strict=True):
            pad = result.pad_errors[side]
            assert pad.sliding is not None
            sliding = pad.sliding
            c = sliding.config
            values = np.where(sliding.values == 0.0, np.nan, sliding.values).reshape(sliding.per_axis, sliding.per_axis)
            extent_mm = 1e3 * (c.extent_m + c.node_m / 2)
            image = axis.imshow(
                1e6 * values,
                origin="lower",
                extent=(-extent_mm, extent_mm, -extent_mm, extent_mm),
                cmap="RdBu_r",
                vmin=-40,
                vmax=40,
            )
            centres = np.array(
                [1e3 * f.points_sensor[:, :2].mean(axis=0) for f in trajectory.tactile[side] if len(f.points_sensor)]
            )
            axis.plot(centres[:, 0], centres[:, 1], color="k", lw=0.8)
            axis.plot(centres[0, 0], centres[0, 1], "o", color="k", ms=3)
            known = np.isfinite(values)
            ys, xs = np.nonzero(known)
            if len(xs):
                grid = 1e3 * (-c.extent_m + c.node_m * np.arange(sliding.per_axis))
                axis.set_xlim(grid[xs.min()] - 1, grid[xs.max()] + 1)
                axis.set_ylim(grid[ys.min()] - 1, grid[ys.max()] + 1)
            axis.set_title(f"{title}: {side} pad's learnt error", fontsize=9)
            axis.set_xlabel("sensor x (mm)", fontsize=8)
            axis.set_ylabel("sensor y (mm)", fontsize=8)
            axis.tick_params(labelsize=7)
            figure.colorbar(image, ax=axis, label="um along the sensor's z", shrink=0.8)
        axis = row[2]
        times = result.timestamps_s - (motion[0] if motion else result.timestamps_s[0])
        lines = {"open loop": result.T_world_object_open_loop} | {
            label: r.T_world_object for label, r in results.items()
        }
        for (label, poses), color in zip(lines.items(), ("tab:red", "tab:orange", "tab:blue"), strict=True):
            errors = tracking_errors(
                result.timestamps_s, poses, truth, touch.T_world_object, trajectory.touch.T_world_object
            )
            drift = summarize_errors(errors, motion)["settled_drift"]
            axis.plot(
                times,
                np.degrees(errors.rotation_rad),
                color=color,
                lw=1.0,
                label=f"{label} (drift {drift['deg']:.2f} deg)",
            )
            print(f"{title}: {label}: settled drift {drift['mm']:.2f} mm / {drift['deg']:.2f} deg")
        if motion:
            axis.axvline(motion[1] - motion[0], color="0.4", lw=0.6)
        axis.set_title(f"{title}: rotation error against the truth", fontsize=9)
        axis.set_xlabel("time since the motion started (s); line: its end", fontsize=8)
        axis.set_ylabel("deg", fontsize=8)
        axis.tick_params(labelsize=7)
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    write_bytes_atomic(args.out, buffer.getvalue())
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
