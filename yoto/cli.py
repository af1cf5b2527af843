"""The `yoto` command. Each pipeline stage registers its own subcommands from its `cli` module.

A stage's `register(subparsers)` adds its parser and sets `run=callable(args) -> int | None`. Heavy
imports (torch, Open3D) happen inside the run functions, so `yoto --help` stays instant.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from yoto import __version__
from yoto.errors import YotoError

# Order here is the order in `yoto --help`.
STAGE_CLI_MODULES = [
    "yoto.demo",
    "yoto.objects.cli",
    "yoto.patches.cli",
    "yoto.simulate.cli",
    "yoto.training.cli",
    "yoto.localize.cli",
    "yoto.pose.cli",
    "yoto.tracking.cli",
    "yoto.evaluation.cli",
    "yoto.sensor.cli",
    "yoto.rig.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="yoto",
        description="6-DoF object pose from one simultaneous pair of GelSight contacts.",
    )
    parser.add_argument("--version", action="version", version=f"yoto {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="print debug messages")
    parser.add_argument("-q", "--quiet", action="store_true", help="print warnings and errors only")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name in STAGE_CLI_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s: %(message)s" if level != logging.INFO else "%(message)s")
    try:
        return int(args.run(args) or 0)
    except YotoError as exc:
        print(f"yoto {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"yoto {args.command}: interrupted; finished outputs are kept and a rerun resumes", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
