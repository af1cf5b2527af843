"""`yoto track PAIR.json --left LEFT.tum --right RIGHT.tum --out OBJECT.tum` and `yoto track-bench`."""

from __future__ import annotations

import argparse

TRACK_EPILOG = """examples:
  yoto track touch.json --left left.tum --right right.tum --out object.tum
  yoto track touch.json --left left.tum --right right.tum --out object.tum \\
      --left-tactile left_tactile --right-tactile right_tactile --truth object_true.tum --figure error.png
  yoto track touch.json --left rec.bag --left-topic /vrpn_client_node/RigLeft/pose --left-rig left.rig.json \\
      --right rec.bag --right-topic /vrpn_client_node/RigRight/pose --right-rig right.rig.json --out object.tum
  yoto track-bench --objects fruit figurine ../shared/data/meshes/bunny/bunny.ply -n 5
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "track",
        help="track the object after one touch from the live sensor poses (and tactile frames)",
        description="After one dual touch, follow the object from the two sensors' live poses (open loop, the "
        "paper's Sec. 4.3) and, given tactile frames during the motion, correct slip by registering each frame on "
        "the object (closed loop). Writes T_world_object (mesh file's frame) at every timestamp of the sensor "
        "streams from the touch on, as a TUM file. With both sensors' frames, a gel that lets go leaves the other to "
        "carry the object; both letting go end the grasp (the pose held), and both touching again make a new touch "
        "whose pose is estimated from that pair (--method) and tracked on.",
        epilog=TRACK_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("pair", help="the touch: a contact pair file (SPEC)")
    parser.add_argument("--left", required=True, help="left sensor poses: a TUM file, a ROS bag or a Motive CSV")
    parser.add_argument("--right", required=True, help="right sensor poses (as --left)")
    parser.add_argument("--left-topic", help="for a bag: the left sensor's PoseStamped/TF topic; Motive: its body")
    parser.add_argument("--right-topic", help="as --left-topic, for the right sensor")
    parser.add_argument(
        "--left-rig",
        help="with --left-topic naming the rig's rigid body: its rig calibration (`yoto rig calibrate-rig`), which "
        "puts the GelSight in the body (without it the body's pose is taken for the GelSight's)",
    )
    parser.add_argument("--right-rig", help="as --left-rig, for the right sensor")
    parser.add_argument("--out", required=True, help="tracked poses, TUM file (T_world_object, mesh file's frame)")
    parser.add_argument(
        "--left-tactile", help="left tactile frames: a folder of <timestamp>.ply (or .png images), or a bag"
    )
    parser.add_argument("--right-tactile", help="right tactile frames (as --left-tactile)")
    parser.add_argument("--left-tactile-topic", help="for a bag: the left GelSight's image topic")
    parser.add_argument("--right-tactile-topic", help="for a bag: the right GelSight's image topic")
    parser.add_argument(
        "--calibration",
        help="sensor calibration, for GelSight images (the touch's sides, tactile frames) that name none",
    )
    parser.add_argument("--pose", help="the touch's pose from a `yoto pose` result file (default: estimate it)")
    parser.add_argument(
        "--method",
        choices=["match", "yoto", "icp", "oracle"],
        default="match",
        help="contact localizer for the touch's pose (default: the matched filter)",
    )
    parser.add_argument("--checkpoint", help="network weights for --method yoto")
    parser.add_argument("--model", help="object model name or file (default: the pair's object)")
    parser.add_argument("--workspace", help="workspace folder holding object models")
    parser.add_argument(
        "--touch-time", type=float, help="the touch's timestamp (default: the pair file's, else matched to the streams)"
    )
    parser.add_argument("--open-loop", action="store_true", help="ignore tactile frames: the paper's open loop")
    parser.add_argument("--truth", help="ground truth T_world_object (mesh frame): TUM, bag or Motive CSV")
    parser.add_argument("--truth-topic", help="for a bag or Motive CSV: the object's topic or rigid body")
    parser.add_argument(
        "--truth-calibration",
        help="with --truth-topic: the object calibration (`yoto rig calibrate-object`) that puts the mesh frame in "
        "the object's rigid body",
    )
    parser.add_argument("--report", help="JSON report: every tactile instant, the streams' jitter, errors")
    parser.add_argument("--figure", help="error plot against --truth (PNG), like the paper's Fig. 4")
    parser.set_defaults(run=run)

    bench = subparsers.add_parser(
        "track-bench",
        help="benchmark tracking on simulated trajectories (Table 3 and Fig. 4 of the paper, open and closed loop)",
        description="For each object, simulate N trajectories after a touch (fixed seed), estimate the touch's "
        "pose, and track them open and closed loop. Writes OUT/tracking.md, OUT/tracking.json and "
        "OUT/tracking.png; finished trajectories are cached, so an interrupted run resumes.",
    )
    bench.add_argument(
        "--objects",
        nargs="+",
        default=["tool", "fruit", "figurine"],
        help="object names (workspace or built-in), model files or mesh files",
    )
    bench.add_argument("-n", "--trajectories", type=int, default=5, help="trajectories per object (default 5)")
    bench.add_argument("--seed", type=int, default=11, help="trajectory seed (default 11)")
    bench.add_argument(
        "--method",
        choices=["match", "icp", "oracle"],
        default="match",
        help="the touch's localizer (oracle: true contacts, to isolate tracking)",
    )
    bench.add_argument(
        "--path-lengths-mm",
        type=float,
        nargs="+",
        default=[100.0],
        help="path lengths; the first makes the main table, more add drift against path length (default 100)",
    )
    bench.add_argument("--workspace", help="workspace folder")
    bench.add_argument("--out", default="bench_tracking", help="output folder (default bench_tracking)")
    bench.add_argument("--overwrite", action="store_true", help="recompute cached trajectories")
    bench.add_argument(
        "--no-pad-correction",
        action="store_true",
        help="the closed loop without learning and removing each pad's error (to compare; use another --out)",
    )
    bench.set_defaults(run=run_bench)


def _path(value: str | None):
    from pathlib import Path

    return Path(value) if value else None


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from yoto.tracking.job import Source, TrackJob, run_track_job

    tactile = {}
    if not args.open_loop:
        for side in ("left", "right"):
            path = getattr(args, f"{side}_tactile")
            if path:
                tactile[side] = Source(Path(path), getattr(args, f"{side}_tactile_topic"))
    job = TrackJob(
        pair=Path(args.pair),
        sensors={
            side: Source(Path(getattr(args, side)), getattr(args, f"{side}_topic"), _path(getattr(args, f"{side}_rig")))
            for side in ("left", "right")
        },
        out=Path(args.out),
        tactile=tactile,
        calibration=Path(args.calibration) if args.calibration else None,
        pose_result=Path(args.pose) if args.pose else None,
        method=args.method,
        checkpoint=args.checkpoint,
        model=args.model,
        workspace=args.workspace,
        touch_time_s=args.touch_time,
        truth=Source(Path(args.truth), args.truth_topic, _path(args.truth_calibration)) if args.truth else None,
        report=Path(args.report) if args.report else None,
        figure=Path(args.figure) if args.figure else None,
    )
    outcome = run_track_job(job)
    result = outcome.result
    print(
        f"touch at {result.touch.time_s:.6f} s ({result.touch.time_source}); pose from {outcome.touch_source}\n"
        f"{len(result.timestamps_s)} poses over {result.timestamps_s[-1] - result.timestamps_s[0]:.2f} s -> {job.out}"
    )
    for side, jitter in result.jitter.items():
        print(f"  {side} stream: {jitter.describe()}")
    if result.closed_loop:
        speed = result.correction_summary()
        unusable = ", ".join(f"{reason} {count}" for reason, count in speed["unusable"].items()) or "none"
        print(
            f"closed loop: {speed['frames_used']} of {speed['frames']} tactile frames used (unusable: {unusable}); "
            f"divergence guard: {speed['guard_checks']} checks, {speed['reanchored']} re-anchored, "
            f"{speed['held']} instants held along weakly pinned directions; "
            f"{speed['latency_median_ms']:.1f} ms per instant (median), {speed['instants_per_s']:.0f} instants/s"
        )
        for side in ("left", "right"):  # why frames could not be read: the first reason of each side
            unreadable = [c.unusable[side] for c in result.corrections if c.unusable.get(side, "").startswith("unread")]
            if unreadable:
                why = unreadable[0].removeprefix("unreadable (").removesuffix(")")
                print(f"  {side}: {len(unreadable)} frame(s) unreadable, the first: {why}")
    if result.pinning is not None:
        spread = result.pinning.spread
        print(
            f"  pinned by the contacts: {np.sum(spread <= 0.25)} of 6 directions to within 0.5 deg / 0.5 mm; weakest: "
            f"{result.pinning.describe(0)}"
        )
    if outcome.retouch is not None:
        print(f"  to pin it, touch again there: {outcome.retouch.describe()} (mesh file's frame)")
    grasps = [("", outcome.errors)] + [
        (f"new touch {k}: ", errors) for k, errors in enumerate(outcome.regrasp_errors, 1)
    ]
    for name, summary in [(prefix + name, summary) for prefix, errors in grasps for name, summary in errors.items()]:
        print(
            f"{name.replace('_', ' ')} vs truth: during motion {summary['motion_mean']['mm']:.2f} mm / "
            f"{summary['motion_mean']['deg']:.2f} deg, peak {summary['motion_peak']['mm']:.2f} / "
            f"{summary['motion_peak']['deg']:.2f}, settled {summary['settled']['mm']:.2f} / "
            f"{summary['settled']['deg']:.2f}, settled drift {summary['settled_drift']['mm']:.2f} / "
            f"{summary['settled_drift']['deg']:.2f}, final drift {summary['final_drift']['mm']:.2f} / "
            f"{summary['final_drift']['deg']:.2f} "
            f"(touch {summary['touch']['mm']:.2f} / {summary['touch']['deg']:.2f})"
        )
    for warning in outcome.warnings:
        print(f"warning: {warning}")
    return 0


def run_bench(args: argparse.Namespace) -> int:
    import dataclasses
    from pathlib import Path

    from yoto.errors import InputError
    from yoto.evaluation.bench import resolve_object
    from yoto.tracking.bench import TrackBenchConfig, run_track_benchmark
    from yoto.tracking.pad_error import PadErrorConfig

    if args.trajectories < 1:
        raise InputError(f"-n must be at least 1, got {args.trajectories}")
    if any(length <= 0 for length in args.path_lengths_mm):
        raise InputError(f"path lengths must be positive, got {args.path_lengths_mm}")
    models = [resolve_object(spec, args.workspace) for spec in args.objects]
    config = TrackBenchConfig(
        trajectories=args.trajectories,
        seed=args.seed,
        method=args.method,
        path_lengths_m=tuple(length * 1e-3 for length in args.path_lengths_mm),
    )
    if args.no_pad_correction:
        correction = dataclasses.replace(config.track.correction, pad_error=PadErrorConfig(enabled=False))
        config = dataclasses.replace(config, track=dataclasses.replace(config.track, correction=correction))
    run_track_benchmark(models, config, args.out, args.overwrite, progress=not args.quiet)
    print((Path(args.out) / "tracking.md").read_text())
    return 0
