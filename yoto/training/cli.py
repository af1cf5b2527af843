"""`yoto train`: train the contact localization network on object models (virtual, then real contacts)."""

from __future__ import annotations

import argparse

TRAIN_EPILOG = """examples:
  yoto train --objects tool fruit figurine --preset cpu
  yoto train --objects tool fruit figurine --preset cpu --real-pairs pairs/finetune --val-pairs pairs/heldout
  yoto train --objects drill --preset paper --run drill_gpu --device cuda

A run folder (WORKSPACE/runs/RUN) holds model.pt (the localizer), state.pt (resume point), log.jsonl,
log.csv and curves.png. Rerunning the same command keeps a finished run and resumes an interrupted one.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train the contact localization network (object models -> localizer checkpoint)",
        description="Stage 1 on virtual contacts (or patches) of every object; stage 2 (with --real-pairs) on them "
        "plus real or simulated contacts with ground truth. One network serves all the objects.",
        epilog=TRAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--objects", nargs="+", required=True, help="object names (workspace or built-in) or files")
    parser.add_argument(
        "--preset",
        default="cpu",
        help="training preset: cpu (the anchor-descriptor network, minutes per object on a 2-core CPU), paper (the "
        "paper's point network, for a GPU) or cpu-points (the paper's network at CPU sizes)",
    )
    parser.add_argument("--stage1-epochs", type=int, help="override the preset's stage-1 epochs")
    parser.add_argument("--stage2-epochs", type=int, help="override the preset's stage-2 epochs")
    parser.add_argument(
        "--real-pairs", help="folder of contact pairs with ground truth for stage 2 (searched recursively)"
    )
    parser.add_argument("--val-pairs", help="folder of held-out pairs validated every epoch (not the --real-pairs)")
    parser.add_argument(
        "--pair-objects",
        nargs="+",
        default=[],
        metavar="PAIR_OBJECT=MODEL",
        help="train MODEL with the pairs of PAIR_OBJECT, e.g. drill=drill_scan (a scan's model with contacts "
        "recorded on the real object)",
    )
    parser.add_argument(
        "--run", dest="run_name", default="default", help="run name: WORKSPACE/runs/RUN (default: default)"
    )
    parser.add_argument("--run-dir", help="run folder (overrides --run)")
    parser.add_argument("--seed", type=int, help="override the preset's seed")
    parser.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    parser.add_argument("--overwrite", action="store_true", help="retrain even if the run folder holds a model")
    parser.add_argument("--no-resume", action="store_true", help="start afresh instead of resuming")
    parser.add_argument(
        "--export",
        metavar="PATH",
        help="after training, copy the model here with a JSON card (e.g. yoto/weights/default.pt)",
    )
    parser.add_argument(
        "--speed-test", action="store_true", help="time training steps instead of training (see benchmarks/)"
    )
    parser.set_defaults(run=run)


def parse_pair_objects(values: list[str]) -> dict[str, str]:
    from yoto.errors import InputError

    mapping = {}
    for value in values:
        source, _, target = value.partition("=")
        if not source or not target:
            raise InputError(f"--pair-objects {value!r}: expected PAIR_OBJECT=MODEL, e.g. drill=drill_scan")
        mapping[source] = target
    return mapping


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from yoto.errors import require_torch

    torch = require_torch("training the localization network")
    from yoto.training.config import preset, with_overrides
    from yoto.training.train import train
    from yoto.workspace import runs_dir

    if args.threads:
        torch.set_num_threads(args.threads)
    config = with_overrides(preset(args.preset), stage1_epochs=args.stage1_epochs, stage2_epochs=args.stage2_epochs)
    if args.seed is not None:
        config = replace(config, seed=args.seed)
    if args.speed_test:
        from yoto.training.speed import measure_training_speed

        result = measure_training_speed(config, args.objects, args.workspace, device=args.device or "cpu")
        print(result.summary())
        return 0
    run_dir = args.run_dir or runs_dir(args.workspace) / args.run_name
    path = train(
        config,
        args.objects,
        workspace=args.workspace,
        run_dir=run_dir,
        real_pairs_dir=args.real_pairs,
        val_pairs_dir=args.val_pairs,
        pair_objects=parse_pair_objects(args.pair_objects),
        resume=not args.no_resume,
        overwrite=args.overwrite,
        device=args.device,
        progress=not args.quiet,
    )
    print(f"localizer checkpoint: {path}")
    if args.export:
        import shlex
        import sys

        from yoto.training.export import export_weights

        command = "yoto " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        weights, card = export_weights(path.parent, args.export, command)
        print(f"exported {weights} ({weights.stat().st_size / 1e6:.2f} MB) and {card}")
    return 0
