"""`yoto object ...`: build and inspect object models."""

from __future__ import annotations

import argparse

from yoto.objects.builtin import BUILTIN_OBJECTS


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("object", help="build and inspect object models (mesh -> object model)")
    commands = parser.add_subparsers(dest="object_command", required=True, metavar="ACTION")

    build = commands.add_parser("build", help="build the object model of a mesh file or a built-in object")
    build.add_argument("mesh", nargs="?", help="mesh file (PLY, OBJ, STL, GLB, OFF); omit with --builtin")
    build.add_argument("--name", help="object name (default: the mesh file's stem)")
    build.add_argument("--builtin", choices=[*BUILTIN_OBJECTS, "all"], help="build a built-in default object")
    build.add_argument(
        "--units", default="m", choices=["m", "cm", "mm", "in", "auto"], help="unit of the mesh file (in: inches)"
    )
    build.add_argument("--points", type=int, help="parent cloud size (default: 500 points per cm^2 of surface)")
    build.add_argument("--seed", type=int, default=0, help="surface sampling seed")
    build.add_argument(
        "--symmetry-tolerance-mm",
        type=float,
        default=1.0,
        help="a rotation counts as a symmetry when the rotated surface lies this close to itself on 90%% of it",
    )
    build.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")
    build.add_argument("--out", help="write the model here instead of WORKSPACE/objects/NAME.npz")
    build.add_argument("--overwrite", action="store_true", help="rebuild even if an up-to-date model exists")
    build.set_defaults(run=_run_build)

    show = commands.add_parser("show", help="print an object model's statistics")
    show.add_argument("object", nargs="+", help="object names (in the workspace) or model files")
    show.add_argument("--workspace", help="workspace folder")
    show.set_defaults(run=_run_show)


def _run_build(args: argparse.Namespace) -> int:
    from yoto.errors import InputError
    from yoto.objects.build import build_object
    from yoto.objects.model import ObjectModelConfig
    from yoto.objects.symmetry import SymmetryConfig

    symmetry = SymmetryConfig(tolerance_m=args.symmetry_tolerance_mm / 1000.0)
    config = ObjectModelConfig(num_points=args.points, seed=args.seed, symmetry=symmetry)
    if args.builtin:
        if args.mesh:
            raise InputError("give either a mesh file or --builtin, not both")
        names = list(BUILTIN_OBJECTS) if args.builtin == "all" else [args.builtin]
        if args.out and len(names) > 1:
            raise InputError("--out names one model file: build the built-ins one at a time, or into the workspace")
        for name in names:
            build_object(None, name, config, workspace=args.workspace, out=args.out, overwrite=args.overwrite)
        return 0
    if not args.mesh:
        raise InputError("give a mesh file, or --builtin NAME")
    from pathlib import Path

    name = args.name or Path(args.mesh).stem
    build_object(
        args.mesh, name, config, units=args.units, workspace=args.workspace, out=args.out, overwrite=args.overwrite
    )
    return 0


def _run_show(args: argparse.Namespace) -> int:
    from yoto.objects.build import load_object_model

    for name in args.object:
        model = load_object_model(name, args.workspace)
        meta = model.meta
        bbox = " x ".join(f"{v * 1000:.1f}" for v in meta["bbox_object_m"])
        grid = meta["build_config"]["grid_shape"]
        print(
            f"{model.name}: {len(model.points_object)} parent points, {model.num_blocks}/{grid[0] * grid[1] * grid[2]} "
            f"valid blocks, bbox {bbox} mm, area {meta['surface_area_m2'] * 1e4:.1f} cm^2, "
            f"watertight {meta['watertight']}, symmetry: {model.symmetry.describe()}, source {meta['source']}"
        )
    return 0
