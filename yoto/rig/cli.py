"""`yoto rig ...`: the real rig's recordings in, calibrated and labelled contacts out (docs/rig.md)."""

from __future__ import annotations

import argparse

RIG_EPILOG = """examples (a session recorded by `yoto simulate recording --object fruit --out session/`):
  yoto rig inspect session/ros1/trials.bag
  yoto rig calibrate-rig session/ros1/gel_left.bag --name left --rig-body RigLeft --gel-ball GelBall \\
      --reference-ball RefBall --cad session/cad_left.json --plate session/ros1/plate_left.bag --plate-body Plate \\
      --out calib/left.rig.json
  yoto rig calibrate-object session/ros1/beads.bag --object fruit --picks session/beads.json --object-body Object \\
      --out calib/fruit.object.json
  yoto rig label session/ros1/trials.bag --object fruit --object-calibration calib/fruit.object.json \\
      --left-rig calib/left.rig.json --left-images /gelsight_left/image_raw \\
      --right-rig calib/right.rig.json --right-images /gelsight_right/image_raw --gelsight gelsight.npz --out labelled/
  yoto pose labelled/pairs/
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "rig",
        help="real rig: inspect recordings, calibrate rigs and objects, label contacts",
        description="Recordings of GelSight rigs and an object under mocap (ROS1/ROS2 bags, Motive CSV) -> rig and "
        "object calibrations -> labelled contacts for `yoto train --real-pairs` and `yoto pose`.",
        epilog=RIG_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="rig_command", required=True, metavar="ACTION")

    inspect = commands.add_parser("inspect", help="list a recording's topics (types, rates, spans) or bodies")
    inspect.add_argument("recording", help=".bag, ROS2 bag folder / .db3 / .mcap, Motive .csv, or a folder of PNGs")
    inspect.set_defaults(run=_run_inspect)

    rig = commands.add_parser(
        "calibrate-rig",
        help="gel centre and sensor frame in a rig's rigid body (dual-ball procedure, CAD rotation, plate presses)",
    )
    rig.add_argument("recording", help="the dual-ball recording (rig held still in 5+ poses)")
    rig.add_argument("--name", required=True, help="which rig (left, right, or a serial number)")
    rig.add_argument("--rig-body", required=True, help="the rig's rigid body: topic or name")
    rig.add_argument("--gel-ball", required=True, help="marker of the ball on the gel centre: topic or name")
    rig.add_argument("--reference-ball", help="marker of the reference ball on the rig (rigidity check)")
    rig.add_argument("--ball-height-mm", type=float, default=2.5, help="gel ball's centre above the gel (default 2.5)")
    rig.add_argument(
        "--cad", required=True, help="JSON with the rig's CAD T_rig_sensor, R_rig_sensor or quaternion_xyzw"
    )
    rig.add_argument("--plate", help="recording of flat presses on a plate (corrects the CAD's sensor axis)")
    rig.add_argument("--plate-body", help="the plate's rigid body: topic or name")
    rig.add_argument("--plate-normal", default="0,0,1", help="plate surface normal in its body frame (default 0,0,1)")
    rig.add_argument(
        "--plate-offset-mm", type=float, default=0.0, help="plate surface along the normal from its origin"
    )
    rig.add_argument("--out", required=True, help="rig calibration file to write (.json)")
    rig.set_defaults(run=_run_calibrate_rig)

    obj = commands.add_parser("calibrate-object", help="mesh frame in the object's rigid body (beads, SVD fit)")
    obj.add_argument("recording", help="a still capture of the object's rigid body and its bead markers")
    obj.add_argument("--object", required=True, help="object model: workspace name, built-in, model .npz or mesh file")
    obj.add_argument("--picks", required=True, help="JSON of the beads on the mesh (names, vertices or points)")
    obj.add_argument("--object-body", required=True, help="the object's rigid body: topic or name")
    obj.add_argument("--out", required=True, help="object calibration file to write (.json)")
    obj.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")
    obj.set_defaults(run=_run_calibrate_object)

    label = commands.add_parser(
        "label",
        help="find contact trials in recordings and label them (single contacts and dual-contact pair files)",
    )
    label.add_argument("recordings", nargs="+", help="recordings of contact trials")
    label.add_argument("--object", required=True, help="object model: workspace name, built-in, model .npz or mesh")
    label.add_argument("--object-calibration", required=True, help="from `yoto rig calibrate-object`")
    label.add_argument("--object-body", help="object rigid body (default: the one it was calibrated with)")
    for side in ("left", "right"):
        label.add_argument(f"--{side}-rig", help=f"{side} rig calibration (from `yoto rig calibrate-rig`)")
        label.add_argument(f"--{side}-images", help=f"{side} GelSight image topic, or PNG folder beside a Motive take")
        label.add_argument(f"--{side}-body", help=f"{side} rig body (default: the one it was calibrated with)")
        label.add_argument(f"--{side}-gelsight", help=f"{side} GelSight calibration (default: --gelsight)")
    label.add_argument("--gelsight", help="GelSight calibration (`yoto sensor calibrate`) for both sensors")
    label.add_argument("--time-offset", type=float, help="PNG stamps minus the Motive take's time (default: found)")
    label.add_argument("--out", required=True, help="output folder: contacts/ (training samples) and pairs/")
    label.add_argument("--workspace", help="workspace folder")
    label.add_argument("--strict", action="store_true", help="exit with status 1 when a trial is refused or flagged")
    label.add_argument(
        "--refine-object-calibration",
        metavar="PATH",
        help="refine the bead calibration with the labelled contacts (docs/rig.md), write it to PATH, label with it",
    )
    label.set_defaults(run=_run_label)

    bench = commands.add_parser("bench", help="the whole chain on simulated recordings, against their truth")
    bench.add_argument("--objects", nargs="+", default=["fruit"], help="objects (names, models or meshes)")
    bench.add_argument("--gelsight", required=True, help="GelSight calibration that renders the frames")
    bench.add_argument("--out", default="rig_bench", help="output folder (recordings, labels, rig_bench.md/json)")
    bench.add_argument("--formats", nargs="+", default=["ros1", "ros2-db3", "ros2-mcap", "motive"])
    bench.add_argument("--single-trials", type=int, default=6, help="single contacts per rig")
    bench.add_argument("--dual-trials", type=int, default=4)
    bench.add_argument(
        "--noise",
        choices=["paper", "mocap", "none"],
        default="paper",
        help="paper: mocap jitter, dropouts and bead picks giving the paper's residuals; mocap: careful picks; none",
    )
    bench.add_argument("--no-pose", action="store_true", help="skip `yoto pose` on the labelled dual contacts")
    bench.add_argument("--seed", type=int, default=0)
    bench.add_argument("--workspace", help="workspace folder")
    bench.set_defaults(run=_run_bench)


def load_model(name: str, workspace: str | None):
    from pathlib import Path

    from yoto.objects.build import build_object, load_object_model
    from yoto.objects.mesh import MESH_SUFFIXES

    candidate = Path(name)
    if candidate.suffix.lower() in MESH_SUFFIXES and candidate.is_file():
        return load_object_model(build_object(candidate, candidate.stem, workspace=workspace))
    return load_object_model(name, workspace)


def _run_inspect(args: argparse.Namespace) -> int:
    from pathlib import Path

    from yoto.rig.bags import bag_topics, is_bag
    from yoto.rig.motive import is_motive_csv, read_motive_csv
    from yoto.rig.streams import image_folder_stream

    path = Path(args.recording)
    if is_motive_csv(path):
        take = read_motive_csv(path)
        print(
            f"{path}: Motive take '{take.header.get('Take Name', '')}', {len(take.times_s)} frames at "
            f"{take.header.get('Export Frame Rate', '?')} Hz, {take.times_s[-1] - take.times_s[0]:.2f} s, started "
            f"{take.header.get('Capture Start Time', '?')}, lengths in {take.header.get('Length Units', 'Meters')}"
        )
        for kind in ("Rigid Body", "Marker", "Rigid Body Marker"):
            for name in take.names(kind):
                stream = take.rigid_body(name) if kind == "Rigid Body" else take.marker(name)
                print(f"  {kind:17s} {name:30s} {len(stream)} samples, {stream.dropped} dropped")
        return 0
    if path.is_dir() and not is_bag(path):
        frames = image_folder_stream(path)
        a, b = frames.span_s
        print(f"{path}: {len(frames)} GelSight frames, {a:.3f} to {b:.3f} s, {frames.rate_hz:.1f} Hz")
        return 0
    summaries = bag_topics(path)
    width = max((len(s.name) for s in summaries), default=10)
    print(f"{path}: {len(summaries)} topics")
    print(
        f"  {'topic':{width}s}  {'type':40s} {'messages':>8s} {'rate Hz':>8s}  {'start s':>17s}  {'end s':>17s}  "
        "frame / size"
    )
    for s in summaries:
        print(
            f"  {s.name:{width}s}  {s.msgtype:40s} {s.count:8d} {s.rate_hz:8.1f}  {s.start_s:17.6f}  {s.end_s:17.6f}  "
            f"{s.frame or ''} {s.size}"
        )
    return 0


def _run_calibrate_rig(args: argparse.Namespace) -> int:
    import numpy as np

    from yoto.errors import InputError
    from yoto.rig.calibration import GelCalibrationConfig, calibrate_rig, read_cad_rotation
    from yoto.rig.streams import open_recording

    try:
        normal = tuple(float(v) for v in args.plate_normal.split(","))
    except ValueError as exc:
        raise InputError(f"--plate-normal must be three numbers like 0,0,1, got '{args.plate_normal}'") from exc
    if len(normal) != 3 or np.linalg.norm(normal) < 1e-9:
        raise InputError(f"--plate-normal must be a non-zero 3-vector, got '{args.plate_normal}'")
    config = GelCalibrationConfig(
        ball_height_m=args.ball_height_mm * 1e-3,
        plate_normal_body=normal,  # type: ignore[arg-type]
        plate_surface_offset_m=args.plate_offset_mm * 1e-3,
    )
    R_cad, p_cad = read_cad_rotation(args.cad)
    calibration = calibrate_rig(
        open_recording(args.recording),
        name=args.name,
        rig_body=args.rig_body,
        gel_ball=args.gel_ball,
        reference_ball=args.reference_ball,
        R_rig_sensor_cad=R_cad,
        p_rig_gel_cad=p_cad,
        plate_recording=open_recording(args.plate) if args.plate else None,
        plate_body=args.plate_body,
        config=config,
    )
    path = calibration.save(args.out)
    print(calibration.summary())
    print(f"-> {path}")
    return 0


def _run_calibrate_object(args: argparse.Namespace) -> int:
    from yoto.rig.beads import calibrate_object, pick_vertices_mesh, read_bead_picks
    from yoto.rig.streams import open_recording

    model = load_model(args.object, args.workspace)
    picks = read_bead_picks(args.picks, lambda: pick_vertices_mesh(model))
    calibration = calibrate_object(
        open_recording(args.recording),
        picks,
        model.mesh_vertices_mesh,
        model.mesh_faces,
        object_name=model.name,
        object_body=args.object_body,
    )
    path = calibration.save(args.out)
    print(calibration.summary())
    print(f"-> {path}")
    return 0


def _run_label(args: argparse.Namespace) -> int:
    from pathlib import Path

    from yoto.errors import InputError
    from yoto.io import write_json_atomic, write_text_atomic
    from yoto.rig.beads import load_object_calibration
    from yoto.rig.calibration import load_rig_calibration
    from yoto.rig.labelling import (
        LabelConfig,
        LabelReport,
        RigSide,
        label_recording,
        refine_object_calibration,
        write_labels,
    )
    from yoto.rig.streams import open_recording
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.spec import GELSIGHT_MINI

    model = load_model(args.object, args.workspace)
    object_calibration = load_object_calibration(args.object_calibration)
    if object_calibration.object_name != model.name:
        raise InputError(
            f"this object calibration is for '{object_calibration.object_name}', not '{model.name}'",
            args.object_calibration,
        )
    sides = []
    for side in ("left", "right"):
        rig_path, images = getattr(args, f"{side}_rig"), getattr(args, f"{side}_images")
        if not rig_path and not images:
            continue
        if not (rig_path and images):
            raise InputError(f"the {side} rig needs both --{side}-rig and --{side}-images")
        gelsight_path = getattr(args, f"{side}_gelsight") or args.gelsight
        if not gelsight_path:
            raise InputError(f"the {side} GelSight needs a calibration: --{side}-gelsight or --gelsight")
        sides.append(
            RigSide(
                side,
                load_rig_calibration(rig_path),
                images,
                load_calibration(gelsight_path, GELSIGHT_MINI),
                getattr(args, f"{side}_body"),
            )
        )
    if not sides:
        raise InputError("no rig given: use --left-rig/--left-images and/or --right-rig/--right-images")
    out = Path(args.out)
    recordings = [open_recording(path, args.time_offset) for path in args.recordings]
    reports = [
        label_recording(recording, model, object_calibration, sides, object_body=args.object_body)
        for recording in recordings
    ]
    if args.refine_object_calibration:
        combined = LabelReport(trials=[trial for report in reports for trial in report.trials])
        refined, change = refine_object_calibration(combined, model, object_calibration, LabelConfig())
        if not change["refined"]:
            raise InputError(f"the object calibration cannot be refined: {change['reason']}", args.object_calibration)
        print(
            f"object calibration refined with {change['contacts']} contacts: moved {change['moved_at_centre_mm']:.2f} "
            f"mm at the object's centre, turned {change['rotated_deg']:.2f} deg; contact-to-mesh RMS "
            f"{change['surface_rms_before_mm']:.2f} -> {change['surface_rms_after_mm']:.2f} mm"
        )
        print(f"-> {refined.save(args.refine_object_calibration)}")
        reports = [
            label_recording(recording, model, refined, sides, object_body=args.object_body) for recording in recordings
        ]
    refused = flagged = 0
    rows = []
    for path, report in zip(args.recordings, reports):
        written = write_labels(report, out, Path(path).name.split(".")[0])
        print(report.summary())
        print(
            f"-> {len(written['contacts'])} contacts in {out / 'contacts'}, "
            f"{len(written['pairs'])} pairs in {out / 'pairs'}"
        )
        refused += sum(t.status == "refused" for t in report.trials)
        flagged += sum(bool(t.flags) for t in report.trials)
        rows += [t.row() for t in report.trials]
    write_json_atomic(out / "label_report.json", {"trials": rows})
    lines = [
        "| recording | side | trial | status | contact frames | rejected | spread mm | flags / reason |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['recording']} | {r['side']} | {r['trial']} | {r['status']} | {r.get('contact_frames', '-')} | "
            f"{r.get('rejected_frames', '-')} | {r.get('spread_mm', float('nan')):.2f} | "
            f"{', '.join(r['flags']) or r['reason']} |"
        )
    write_text_atomic(out / "label_report.md", "\n".join(lines) + "\n")
    return 1 if args.strict and (refused or flagged) else 0


def _run_bench(args: argparse.Namespace) -> int:
    import dataclasses

    from yoto.rig.bench import run_rig_benchmark
    from yoto.rig.recording import MocapNoise, RecordingConfig
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.spec import GELSIGHT_MINI

    models = [load_model(name, args.workspace) for name in args.objects]
    config = RecordingConfig(
        single_trials=args.single_trials,
        dual_trials=args.dual_trials,
        noise=MocapNoise.preset(args.noise),
        seed=args.seed,
    )
    pose_fn = None if args.no_pose else pose_function()
    markdown, _ = run_rig_benchmark(
        models, load_calibration(args.gelsight, GELSIGHT_MINI), args.out, config, tuple(args.formats), pose_fn
    )
    print(markdown)
    print(f"-> {args.out}/rig_bench.md, rig_bench.json; config {dataclasses.asdict(config)['noise']}")
    return 0


def pose_function():
    """`yoto pose` (matched filter, default settings) on pair files, for the rig benchmark."""
    from yoto.contacts import read_contact_pair
    from yoto.localize import make_localizer
    from yoto.pose.pipeline import estimate_pose

    localizer = make_localizer("match")

    def run(paths, model):
        results = []
        for path in paths:
            estimate = estimate_pose(read_contact_pair(path), model, localizer)
            results.append(
                {"pair": str(path), "T_world_mesh": estimate.T_world_mesh, "confidence": estimate.confidence}
            )
        return results

    return run


def add_recording_arguments(parser: argparse.ArgumentParser) -> None:
    """`yoto simulate recording`'s options (the command lives with the other simulators)."""
    parser.add_argument("--gelsight", required=True, help="GelSight calibration that renders the frames")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--formats", nargs="+", default=["ros1", "ros2-db3", "ros2-mcap", "motive"])
    parser.add_argument("--single-trials", type=int, default=4, help="single contacts per rig (default 4)")
    parser.add_argument("--dual-trials", type=int, default=3, help="dual contacts (default 3)")
    parser.add_argument("--miss-trials", type=int, default=0, help="approaches that stop short of the surface")
    parser.add_argument("--slip-trials", type=int, default=0, help="holds during which the gel slides 4 mm")
    parser.add_argument("--dropout-trials", type=int, default=0, help="holds with a 0.4 s occlusion of the rig")
    parser.add_argument(
        "--noise",
        choices=["paper", "mocap", "none"],
        default="paper",
        help="paper: mocap jitter, dropouts and bead picks giving the paper's residuals; mocap: careful picks; none",
    )
    parser.add_argument("--mocap-rate", type=float, default=120.0, help="mocap rate in Hz (default 120)")
    parser.add_argument("--camera-rate", type=float, default=25.0, help="GelSight frame rate in Hz (default 25)")
    parser.add_argument("--seed", type=int, default=0)
    parser.set_defaults(run=_run_recording)


def _run_recording(args: argparse.Namespace) -> int:
    from yoto.errors import InputError
    from yoto.rig.recording import MocapNoise, RecordingConfig, simulate_recording
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.spec import GELSIGHT_MINI

    for name in ("single_trials", "dual_trials", "miss_trials", "slip_trials", "dropout_trials"):
        if getattr(args, name) < 0:
            raise InputError(f"--{name.replace('_', '-')} must not be negative")
    model = load_model(args.object, args.workspace)
    config = RecordingConfig(
        mocap_rate_hz=args.mocap_rate,
        camera_rate_hz=args.camera_rate,
        single_trials=args.single_trials,
        dual_trials=args.dual_trials,
        miss_trials=args.miss_trials,
        slip_trials=args.slip_trials,
        dropout_trials=args.dropout_trials,
        noise=MocapNoise.preset(args.noise),
        seed=args.seed,
    )
    gelsight = load_calibration(args.gelsight, GELSIGHT_MINI)
    truth = simulate_recording(model, gelsight, args.out, config, tuple(args.formats), progress=print)
    print(f"{model.name}: {len(truth['trials'])} scripted contacts -> {args.out} (session.json names the streams)")
    return 0
