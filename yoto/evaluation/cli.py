"""`yoto bench`: the benchmark, every method side by side on the same simulated contacts."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="benchmark localization, pose and latency of every method on simulated contacts",
        description="For each object, simulate N dual contacts (fixed seed) and measure every method on them: "
        "contact localization error, pose error, latency. Writes OUT/bench.md and OUT/bench.json; "
        "finished (object, method) results are cached, so an interrupted run resumes.",
    )
    parser.add_argument(
        "--objects",
        nargs="+",
        default=["tool", "fruit", "figurine"],
        help="object names (workspace or built-in), model files or mesh files",
    )
    parser.add_argument("-n", "--pairs", type=int, default=100, help="dual contacts per object")
    parser.add_argument("--seed", type=int, default=7, help="evaluation seed (training pairs must use others)")
    parser.add_argument(
        "--methods",
        nargs="*",
        default=["oracle", "icp", "match"],
        choices=["oracle", "icp", "match"],
        help="rows without a checkpoint to run",
    )
    parser.add_argument(
        "--yoto",
        action="append",
        default=[],
        metavar="LABEL=CHECKPOINT[:SUFFIX]",
        help="a YOTO row: its label, its checkpoint ('default' = shipped weights), and optionally "
        "a suffix naming the object models it localizes on (e.g. ':_scan' for NAME_scan). Repeatable.",
    )
    parser.add_argument(
        "--sensor-noise-mm",
        type=float,
        default=1.0,
        help="mean calibration error of each simulated sensor's reported position (standard condition: 1 mm)",
    )
    parser.add_argument(
        "--sensor-noise-deg",
        type=float,
        default=1.0,
        help="mean calibration error of each simulated sensor's reported orientation (standard condition: 1 deg)",
    )
    parser.add_argument(
        "--prior-mm", type=float, default=1.0, help="the pose stage's expected sensor calibration error, position"
    )
    parser.add_argument(
        "--prior-deg", type=float, default=1.0, help="the pose stage's expected sensor calibration error, orientation"
    )
    parser.add_argument(
        "--search",
        choices=["auto", "always", "never"],
        default="auto",
        help="joint two-contact search: unless the localizers clearly agree (auto), always, or never",
    )
    parser.add_argument(
        "--no-retouch", action="store_true", help="do not simulate the suggested re-touch of ambiguous pairs"
    )
    parser.add_argument(
        "--both-cores",
        action="store_true",
        help="localize each pair's right contact in a helper process while this one localizes the left, and compute "
        "half of the pose stage's batches there (the same poses, bit for bit): per pose latency as a robot with two "
        "free cores waits for it (on a busy machine, slower)",
    )
    parser.add_argument(
        "--via-images",
        metavar="CALIBRATION",
        help="add a row per method on the same pairs with every contact sent through a rendered GelSight image "
        "and its reconstruction: a calibration file from `yoto sensor calibrate` (images from its own optical "
        "model), 'shading[:SEED]' (images from a second, physically based optical model, calibrated from ball "
        "presses it renders), or 'table:FOLDER' (a lookup table read off the real ball presses in FOLDER, laid out "
        "as the shared gelsight_mini data, reconstructed with a calibration from the same presses)",
    )
    parser.add_argument(
        "--image-variation",
        type=float,
        default=0.0,
        help="with --via-images: vary each image's lighting, noise, blur and gel response around the sensor's "
        "(0: none, 1: LEDs +-15%%, noise x/÷2, blur +-1 px, gel smoothing up to 0.1 mm)",
    )
    parser.add_argument(
        "--pose-stages",
        nargs="+",
        default=["full", "paper"],
        choices=["full", "paper"],
        help="pose stages reported for every method on the same localizations: 'full' (joint choice, "
        "verification, refinement) and 'paper' (top candidates, SVD only)",
    )
    parser.add_argument("--workspace", help="workspace folder")
    parser.add_argument("--out", default="bench_out", help="output folder")
    parser.add_argument("--overwrite", action="store_true", help="recompute cached results")
    parser.set_defaults(run=run)

    calibrate = subparsers.add_parser(
        "calibrate-confidence",
        help="fit the pose confidence on simulated contacts of many objects, check it on held-out ones",
        description="Simulate dual contacts (1 mm / 1 deg calibration error) on every object, run the pose stage, "
        "fit P(pose within 5 mm and 5 deg) by logistic regression on the --objects and report it on the "
        "--held-out objects. Objects: workspace/built-in names, mesh files, or procedural shapes "
        "(proc_<family>_<index>, or --procedural N for N of them). Rows are cached in --work-dir.",
    )
    calibrate.add_argument("--objects", nargs="*", default=[], help="objects to fit on")
    calibrate.add_argument(
        "--procedural", type=int, default=0, help="also fit on this many procedural shapes (proc_*_0 ...)"
    )
    calibrate.add_argument("--held-out", nargs="*", default=[], help="objects never fitted on, to check the fit")
    calibrate.add_argument(
        "--held-out-procedural",
        type=int,
        default=0,
        help="also check on this many procedural shapes numbered after the fitted ones",
    )
    calibrate.add_argument("-n", "--pairs", type=int, default=40, help="dual contacts per object")
    calibrate.add_argument("--seed", type=int, default=11, help="simulation seed (the benchmark uses 7)")
    calibrate.add_argument("--out", default="confidence.json", help="where to write the model (JSON)")
    calibrate.add_argument("--work-dir", default="calibration_out", help="cached rows and the report")
    calibrate.add_argument("--workspace", help="workspace folder")
    calibrate.set_defaults(run=run_calibrate)


def parse_yoto_rows(values: list[str]):
    from yoto.errors import InputError
    from yoto.evaluation.bench import MethodSpec

    rows = []
    for value in values:
        if "=" not in value:
            raise InputError(f"--yoto {value!r}: expected LABEL=CHECKPOINT[:SUFFIX]")
        label, rest = value.split("=", 1)
        checkpoint, _, suffix = rest.partition(":")
        rows.append(
            MethodSpec(
                label=label,
                method="yoto",
                checkpoint=None if checkpoint == "default" else checkpoint,
                model_suffix=suffix,
            )
        )
    return rows


def run(args: argparse.Namespace) -> int:
    from yoto.evaluation.bench import BenchConfig, MethodSpec, run_benchmark

    labels = {"oracle": "Oracle (true contacts)", "icp": "ICP (30 starts)", "match": "Matched filter (no training)"}
    methods = [MethodSpec(label=labels[m], method=m) for m in args.methods] + parse_yoto_rows(args.yoto)
    if args.via_images:
        from dataclasses import replace

        methods += [replace(m, label=f"{m.label}, via images", via_images=True) for m in methods]
    config = BenchConfig(
        num_pairs=args.pairs,
        seed=args.seed,
        sensor_noise_mm=args.sensor_noise_mm,
        sensor_noise_deg=args.sensor_noise_deg,
        prior_mm=args.prior_mm,
        prior_deg=args.prior_deg,
        search=args.search,
        retouch=not args.no_retouch,
        pose_stages=tuple(args.pose_stages),
        image_calibration=args.via_images,
        image_variation=args.image_variation,
        both_cores=args.both_cores,
    )
    run_benchmark(args.objects, methods, config, args.out, args.workspace, args.overwrite)
    from pathlib import Path

    print((Path(args.out) / "bench.md").read_text())
    return 0


def run_calibrate(args: argparse.Namespace) -> int:
    from pathlib import Path

    from yoto.errors import InputError
    from yoto.evaluation.calibrate import CalibrationConfig, calibrate_confidence
    from yoto.evaluation.shapes import procedural_names

    fit = list(args.objects) + procedural_names(args.procedural)
    held_out = list(args.held_out) + procedural_names(args.held_out_procedural, first=args.procedural)
    if not fit:
        raise InputError("give objects to fit on (--objects and/or --procedural N)")
    overlap = set(fit) & set(held_out)
    if overlap:
        raise InputError(f"objects both fitted on and held out: {sorted(overlap)}")
    config = CalibrationConfig(pairs_per_object=args.pairs, seed=args.seed)
    calibrate_confidence(fit, held_out, config, args.out, args.work_dir, args.workspace)
    print((Path(args.work_dir) / "calibration.md").read_text())
    return 0
