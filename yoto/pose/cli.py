"""`yoto pose PAIRS...`: contact pairs -> pose results."""

from __future__ import annotations

import argparse
from contextlib import nullcontext
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "pose",
        help="estimate T_world_object from contact pair files",
        description="Estimate the object pose of each contact pair file (or every pair file in a folder). "
        "Writes one NAME.pose.json per pair (SPEC pose result, mesh file's frame).",
    )
    parser.add_argument("pairs", nargs="+", help="contact pair JSON files or folders of them")
    parser.add_argument(
        "--method",
        choices=["match", "yoto", "icp", "oracle"],
        default="match",
        help="contact localizer: the training-free matched filter (default), the YOTO network, ICP, or the "
        "ground truth",
    )
    parser.add_argument("--oracle", action="store_true", help="shorthand for --method oracle (ground-truth contacts)")
    parser.add_argument("--checkpoint", help="network weights for --method yoto (default: the weights shipped)")
    parser.add_argument("--model", help="object model file or name to use for every pair (default: each pair's object)")
    parser.add_argument("--workspace", help="workspace folder holding object models")
    parser.add_argument("--out", help="folder for the pose results (default: next to each pair file)")
    parser.add_argument(
        "--paper",
        action="store_true",
        help="the paper's pose stage exactly: each contact's top candidate, SVD, no verification or refinement",
    )
    parser.add_argument(
        "--search",
        choices=["auto", "always", "never"],
        default="auto",
        help="joint two-contact search over the whole surface: unless the localizers clearly agree (auto), always, "
        "or never",
    )
    # Named for the sensor poses, not "calibration": --calibration is the GelSight's calibration file below. The old
    # names stay as aliases.
    parser.add_argument(
        "--sensor-pose-error-mm",
        "--calibration-error-mm",
        dest="sensor_pose_error_mm",
        type=float,
        default=1.0,
        help="expected error of each reported sensor position, from the mocap / hand-eye calibration (mean, mm; "
        "1 mm is what mocap gives)",
    )
    parser.add_argument(
        "--sensor-pose-error-deg",
        "--calibration-error-deg",
        dest="sensor_pose_error_deg",
        type=float,
        default=1.0,
        help="expected error of each reported sensor orientation (mean, deg)",
    )
    parser.add_argument("--confidence-model", help="confidence parameters file (default: the one shipped)")
    parser.add_argument(
        "--calibration",
        help="sensor calibration (`yoto sensor calibrate`) for sides that give a GelSight 'image' and no "
        "'calibration' of their own",
    )
    parser.add_argument(
        "--retouch",
        metavar="TOUCH.json",
        help="fuse one more touch of one sensor (e.g. the suggested next_touch) with the single pair given: a file "
        'like one side of a pair file, {"points": PLY, "T_world_sensor": 4x4}, optionally with "sensor"; writes '
        "NAME.retouch.pose.json",
    )
    parser.add_argument(
        "--sensor",
        choices=["left", "right"],
        help="with --retouch: the sensor that moved and pressed again (default: the touch file's 'sensor')",
    )
    parser.add_argument(
        "--from-images",
        action="store_true",
        help="reconstruct every side that gives an 'image' from it, even when it also gives 'points'",
    )
    parser.add_argument(
        "--both-cores",
        action="store_true",
        help="localize each pair's right contact in a helper process while this one localizes the left, and score "
        "and refine half of the pose stage's batches there (the same poses, bit for bit; faster when a second core "
        "is idle, slower on a busy machine; docs/journal/pose.md)",
    )
    parser.set_defaults(run=run)


def _pose_config(args: argparse.Namespace):
    from dataclasses import replace

    import numpy as np

    from yoto.pose.pipeline import PAPER, PoseConfig
    from yoto.pose.refine import CalibrationPrior

    prior = CalibrationPrior(args.sensor_pose_error_mm / 1000.0, float(np.radians(args.sensor_pose_error_deg)))
    config = PAPER if args.paper else PoseConfig(calibration=prior, search=args.search)
    return replace(config, confidence_model=args.confidence_model) if args.confidence_model else config


def _describe(estimate, model, pair, result: dict) -> str:
    """One line about a pose result; adds the error to `result` when the pair has ground truth."""
    import numpy as np

    from yoto.metrics import pose_errors

    count = len(estimate.hypotheses)
    line = f"confidence {estimate.confidence:.2f}, {count} hypothes{'i' if count == 1 else 'e'}s"
    line += " (ambiguous)" if estimate.ambiguous else ""
    if estimate.next_touch is not None:
        line += f", touch next with the {estimate.next_touch.sensor} sensor"
    if pair.T_world_mesh_true is not None:
        result["error"] = pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model)
        result["error"]["rotation_deg_modulo_symmetry"] = float(
            np.degrees(
                model.symmetry.rotation_error_rad(
                    estimate.T_world_mesh @ model.T_mesh_object, pair.T_world_mesh_true @ model.T_mesh_object
                )
            )
        )
        line += (
            f", error {result['error']['translation_mm']:.1f} mm / "
            f"{result['error']['rotation_deg_modulo_symmetry']:.1f} deg"
        )
    return line + "".join(f"\n  warning: {w}" for w in estimate.solution.warnings)


def run_retouch(args: argparse.Namespace) -> int:
    """`yoto pose PAIR.json --retouch TOUCH.json [--sensor SIDE]`: the pair's pose, then the pose with the touch."""
    from pathlib import Path

    from yoto.contacts import POSE_RESULT_SUFFIX, find_pair_files, read_contact_pair, read_touch
    from yoto.errors import InputError, YotoError
    from yoto.io import write_json_atomic
    from yoto.localize import make_localizer
    from yoto.objects.build import load_object_model
    from yoto.pose.pipeline import estimate_pose_with_touch, pose_result_path
    from yoto.sensor.pair_images import ImageSides

    try:
        paths = find_pair_files(args.pairs)
        if len(paths) != 1:
            raise InputError(f"--retouch fuses one touch with one pair file, got {len(paths)} pair files")
        path = paths[0]
        if args.paper:
            raise InputError("--retouch needs the full pose stage (not --paper)")
        images = ImageSides(args.calibration)
        pair = read_contact_pair(path, images, args.from_images)
        touch, named = read_touch(args.retouch, images, args.from_images)
        sensor = args.sensor or named
        if sensor is None:
            raise InputError("the touch file names no 'sensor': say which sensor moved with --sensor", args.retouch)
        if args.sensor and named and args.sensor != named:
            raise InputError(f"--sensor {args.sensor} but the touch file says {named!r}", args.retouch)
        model = load_object_model(args.model or pair.object_name, args.workspace)
        localizer = make_localizer("oracle" if args.oracle else args.method, args.checkpoint)
        first, fused = estimate_pose_with_touch(pair, model, localizer, touch, sensor, _pose_config(args))
    except YotoError as exc:
        print(f"error: {exc}")
        return 1
    first_line = _describe(first, model, pair, {})
    result = fused.to_json(model)
    result["retouch"] = {"sensor": sensor, "touch": str(Path(args.retouch).resolve())}
    line = _describe(fused, model, pair, result)
    out = pose_result_path(path, args.out)
    out = out.with_name(out.name.removesuffix(POSE_RESULT_SUFFIX) + ".retouch" + POSE_RESULT_SUFFIX)
    write_json_atomic(out, result)
    print(f"{path.name}: before the touch: {first_line}")
    print(f"{path.name}: with the {sensor} sensor's touch: {line} -> {out}")
    return 0


def _pairs_and_results(inputs: list[str | Path], out: str | None) -> list[tuple[Path, Path]]:
    """(pair file, its pose result path) for every pair the inputs name; a pair named twice (a file and its folder)
    counts once, and two pairs whose results would overwrite each other (`a/pair_0000.json`, `b/pair_0000.json`
    with one --out) are refused before anything is written."""
    from yoto.contacts import find_pair_files
    from yoto.errors import InputError
    from yoto.pose.pipeline import pose_result_path

    writers: dict[Path, tuple[Path, Path]] = {}  # resolved result path -> (pair file, result path)
    for path in find_pair_files(inputs):
        result = pose_result_path(path, out)
        other, _ = writers.setdefault(result.resolve(), (path, result))
        if other.resolve() != path.resolve():
            raise InputError(
                f"{other} and {path} would both write {result}: give them separate --out folders (or no --out: "
                "each result goes next to its pair)"
            )
    return list(writers.values())


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from yoto.contacts import read_contact_pair
    from yoto.errors import NoContactError, YotoError
    from yoto.io import write_json_atomic
    from yoto.localize import make_localizer
    from yoto.localize.helper import LocalizerProcess
    from yoto.objects.build import load_object_model
    from yoto.objects.model import ObjectModel
    from yoto.pose.executor import prepare_pose_helper
    from yoto.pose.pipeline import estimate_pose
    from yoto.sensor.pair_images import ImageSides

    if args.retouch:
        return run_retouch(args)
    pairs = _pairs_and_results(args.pairs, args.out)
    method = "oracle" if args.oracle else args.method
    pose_config = _pose_config(args)
    localizer = make_localizer(method, args.checkpoint)
    images = ImageSides(args.calibration)
    models: dict[str, ObjectModel] = {}
    failures, no_contact, errors = 0, 0, []
    with LocalizerProcess(localizer) if args.both_cores else nullcontext() as helper:
        for path, result_path in pairs:
            try:
                pair = read_contact_pair(path, images, args.from_images)
                key = args.model or pair.object_name
                if key not in models:
                    models[key] = load_object_model(key, args.workspace)
                    if helper is not None:  # the helper builds its copy of the field while this process works
                        prepare_pose_helper(helper, models[key], pose_config.field_config)
                model = models[key]
                estimate = estimate_pose(pair, model, localizer, pose_config, helper)
                result = estimate.to_json(model)
                line = _describe(estimate, model, pair, result)
                write_json_atomic(result_path, result)
                if "error" in result:
                    errors.append(result["error"])
                print(f"{path.name}: {line}")
            except NoContactError as exc:
                no_contact += 1
                print(f"{path}: no pose, a sensor shows no contact: {exc}")
            except YotoError as exc:
                failures += 1
                print(f"{path}: error: {exc}")
    if errors:
        t = np.array([e["translation_mm"] for e in errors])
        r = np.array([e["rotation_deg_modulo_symmetry"] for e in errors])
        print(
            f"{len(errors)} poses vs ground truth ({method}): translation median {np.median(t):.2f} mm "
            f"(mean {t.mean():.2f}), rotation median {np.median(r):.2f} deg (mean {r.mean():.2f}; modulo symmetry)"
        )
    if no_contact:
        print(f"{no_contact} pair(s) without a contact on one sensor: no pose")
    if failures:
        print(f"{failures} pair(s) failed; see the errors above")
    return 1 if failures or no_contact else 0
