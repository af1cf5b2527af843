"""`yoto patches ...`: generate virtual tactile patches and report their statistics."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("patches", help="virtual tactile patches for training (object model -> dataset)")
    commands = parser.add_subparsers(dest="patches_command", required=True, metavar="ACTION")
    generate = commands.add_parser("generate", help="sample labelled virtual patches from object models")
    generate.add_argument("objects", nargs="+", help="object names (workspace or built-in) or model files")
    generate.add_argument("--seed", type=int, default=0, help="generator seed")
    generate.add_argument(
        "--variants", type=int, default=14, help="fixed and random parent rotations, each (paper: 14)"
    )
    generate.add_argument("--attempts", type=int, default=300, help="patches attempted per variant (paper: 300)")
    generate.add_argument("--workers", type=int, help="processes (default: one per CPU core)")
    generate.add_argument("--workspace", help="workspace folder")
    generate.add_argument("--overwrite", action="store_true", help="regenerate even if an up-to-date dataset exists")
    generate.set_defaults(run=_run_generate)


def _run_generate(args: argparse.Namespace) -> int:
    from yoto.patches.generate import generate_patches, statistics_table
    from yoto.patches.virtual import VirtualPatchConfig

    config = VirtualPatchConfig(
        fixed_variants=args.variants, random_variants=args.variants, attempts_per_variant=args.attempts, seed=args.seed
    )
    names = []
    for name in args.objects:
        path = generate_patches(name, config, args.workspace, args.workers, args.overwrite)
        names.append(path.stem)
    print(statistics_table(names, args.workspace))
    return 0
