"""`yoto pose PAIRS...`: contact pairs -> pose results."""

from __future__ import annotations

import argparse


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
    parser.add_argument(
        "--calibration-error-mm",
        type=float,
        default=1.0,
        help="expected calibration error of each reported sensor position (mean, mm; 1 mm is what mocap gives)",
    )
    parser.add_argument(
        "--calibration-error-deg",
        type=float,
        default=1.0,
        help="expected calibration error of each reported sensor orientation (mean, deg)",
    )
    parser.add_argument("--confidence-model", help="confidence parameters file (default: the one shipped)")
    parser.add_argument(
        "--calibration",
        help="sensor calibration (`yoto sensor calibrate`) for sides that give a GelSight 'image' and no "
        "'calibration' of their own",
    )
    parser.add_argument(
        "--from-images",
        action="store_true",
        help="reconstruct every side that gives an 'image' from it, even when it also gives 'points'",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from yoto.contacts import find_pair_files, read_contact_pair
    from yoto.errors import NoContactError, YotoError
    from yoto.io import write_json_atomic
    from yoto.localize import make_localizer
    from yoto.metrics import pose_errors
    from yoto.objects.build import load_object_model
    from yoto.objects.model import ObjectModel
    from yoto.pose.pipeline import PAPER, PoseConfig, estimate_pose, pose_result_path
    from yoto.pose.refine import CalibrationPrior
    from yoto.sensor.pair_images import ImageSides

    method = "oracle" if args.oracle else args.method
    prior = CalibrationPrior(args.calibration_error_mm / 1000.0, float(np.radians(args.calibration_error_deg)))
    pose_config = PAPER if args.paper else PoseConfig(calibration=prior, search=args.search)
    if args.confidence_model:
        pose_config = replace(pose_config, confidence_model=args.confidence_model)
    localizer = make_localizer(method, args.checkpoint)
    images = ImageSides(args.calibration)
    models: dict[str, ObjectModel] = {}
    failures, no_contact, errors = 0, 0, []
    for path in find_pair_files(args.pairs):
        try:
            pair = read_contact_pair(path, images, args.from_images)
            key = args.model or pair.object_name
            if key not in models:
                models[key] = load_object_model(key, args.workspace)
            model = models[key]
            estimate = estimate_pose(pair, model, localizer, pose_config)
            result = estimate.to_json(model)
            count = len(estimate.hypotheses)
            line = f"{path.name}: confidence {estimate.confidence:.2f}, {count} hypothes{'i' if count == 1 else 'e'}s"
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
                errors.append(result["error"])
                line += (
                    f", error {result['error']['translation_mm']:.1f} mm / "
                    f"{result['error']['rotation_deg_modulo_symmetry']:.1f} deg"
                )
            write_json_atomic(pose_result_path(path, args.out), result)
            print(line + "".join(f"\n  warning: {w}" for w in estimate.solution.warnings))
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
