"""`yoto simulate ...`: simulated GelSight contact pairs, trajectories after a touch, single presses, phone scans."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from yoto.simulate.trajectory import TrajectoryConfig

SIMULATE_EPILOG = """examples:
  yoto simulate pairs --object fruit -n 100 --seed 0
  yoto simulate pairs --object drill -n 100 --sensor-noise-mm 1 --sensor-noise-deg 1 --out pairs/drill_noisy
  yoto simulate press --object figurine --seed 3 --out press.png
  yoto simulate scan meshes/drill.ply --out drill_scan.ply --seed 0
  yoto simulate trajectory --object fruit -n 5 --out trajectories/fruit
  yoto simulate trajectory --object fruit -n 5 --tactile-fps 15 --tactile-phase-ms 33 --pose-hz 30 --whole-pad
  yoto simulate trajectory --object fruit -n 5 --pose-outliers 1 --pose-flips 1 --pose-dropouts 2
  yoto simulate recording --object fruit --gelsight gelsight.npz --out session/
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate GelSight contact pairs and phone scans (test and benchmark data)",
        description="Simulated GelSight Mini contacts pressed into an object's mesh, and simulated phone scans.",
        epilog=SIMULATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="simulate_command", required=True, metavar="ACTION")

    pairs = commands.add_parser(
        "pairs",
        help="write N simulated dual contacts (pair files with ground truth)",
        description="Draw random object poses and two reachable GelSight contacts each; write SPEC pair files. "
        "Pair i depends only on (seed, i): rerunning with a larger N keeps earlier pairs; existing files are "
        "kept unless --overwrite.",
    )
    _object_arguments(pairs)
    pairs.add_argument("-n", "--count", type=int, required=True, help="number of pairs (indices 0..N-1)")
    pairs.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    pairs.add_argument("--out", help="output folder (default: WORKSPACE/pairs/OBJECT)")
    pairs.add_argument(
        "--sensor-noise-mm", type=float, default=0.0, help="mean translation error of the reported sensor poses"
    )
    pairs.add_argument(
        "--sensor-noise-deg", type=float, default=0.0, help="mean rotation error of the reported sensor poses"
    )
    pairs.add_argument(
        "--depth-noise-mm", type=float, help="per-pixel height noise of the tactile clouds (default 0.015 mm)"
    )
    pairs.add_argument("--noise-free", action="store_true", help="tactile clouds without reconstruction noise")
    pairs.add_argument("--max-tilt-deg", type=float, help="largest sensor tilt from the surface normal (default 10)")
    pairs.add_argument(
        "--min-conditioning", type=float, help="floor on sigma_2/sigma_1 of [d, n_L, n_R] (default 0.15)"
    )
    pairs.add_argument("--overwrite", action="store_true", help="regenerate pairs that already exist")
    pairs.set_defaults(run=_run_pairs)

    press = commands.add_parser("press", help="simulate one press and save a figure of it")
    _object_arguments(press)
    press.add_argument("--seed", type=int, default=0, help="which press (the first accepted one for this seed)")
    press.add_argument("--out", default="simulate_press.png", help="figure file (PNG)")
    press.set_defaults(run=_run_press)

    trajectory = commands.add_parser(
        "trajectory",
        help="simulate N trajectories after a dual touch (sensor pose streams, tactile frames, ground truth)",
        description="After a simulated dual touch (pair i of `yoto simulate pairs --seed SEED`), both sensors carry "
        "the object along a smooth random SE(3) path while it slips in the gels; writes per trajectory the touch "
        "(pair file), both sensor pose streams (TUM, with jitter), the tactile frames (<timestamp>.ply folders) "
        "and the true object poses (TUM), what `yoto track` reads. Existing trajectories are kept unless "
        "--overwrite.",
    )
    _object_arguments(trajectory)
    trajectory.add_argument("-n", "--count", type=int, required=True, help="number of trajectories (0..N-1)")
    trajectory.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    trajectory.add_argument("--out", help="output folder (default: WORKSPACE/trajectories/OBJECT)")
    trajectory.add_argument("--path-mm", type=float, help="path length of the object's centroid (default 100)")
    trajectory.add_argument("--slip-mm", type=float, help="plastic slip at the end of the path (default 2)")
    trajectory.add_argument("--slip-deg", type=float, help="plastic slip rotation at the end (default 1.5)")
    trajectory.add_argument("--jitter-mm", type=float, help="per-axis jitter of each sensor pose (default 0.2)")
    trajectory.add_argument("--pose-hz", type=float, help="rate of both sensor pose streams (default 120 and 100)")
    trajectory.add_argument("--tactile-fps", type=float, help="tactile frame rate of each gel (default 25)")
    trajectory.add_argument(
        "--tactile-phase-ms", type=float, help="the right gel's frames this long after the left's (default random)"
    )
    trajectory.add_argument("--pixel-stride", type=int, help="clouds keep every n-th pixel row and column (default 2)")
    trajectory.add_argument(
        "--whole-pad",
        action="store_true",
        help="clouds of every pad pixel, untouched gel at z = 0",
    )
    trajectory.add_argument(
        "--pose-outliers",
        type=float,
        metavar="PERCENT",
        help="percent of each pose stream's samples mis-fitted (bursts of 1-5 samples off by 5-30 mm / 5-30 deg)",
    )
    trajectory.add_argument("--pose-flips", type=int, help="per pose stream: 1 s stretches fitted turned half a turn")
    trajectory.add_argument("--pose-dropouts", type=int, help="per pose stream: 0.2-1 s stretches without samples")
    trajectory.add_argument("--arm-error-mm", type=float, help="an arm's smooth pose-dependent kinematic error")
    trajectory.add_argument("--arm-error-deg", type=float, help="... and its rotation (amplitudes per component)")
    trajectory.add_argument("--sensor-noise-mm", type=float, default=0.0, help="sensor calibration error, position")
    trajectory.add_argument("--sensor-noise-deg", type=float, default=0.0, help="sensor calibration error, rotation")
    trajectory.add_argument(
        "--frames-via",
        metavar="SOURCE",
        help="tactile frames as GelSight images (<timestamp>.png, and the calibration.npz that reconstructs them) "
        "rendered from the gel's height map: a sensor calibration file (its fitted optical model) or shading[:SEED]",
    )
    trajectory.add_argument("--overwrite", action="store_true", help="regenerate trajectories that already exist")
    trajectory.set_defaults(run=_run_trajectory)

    scan = commands.add_parser(
        "scan",
        help="degrade a mesh like a consumer phone scan",
        description="Smooth fine detail, add surface noise, cut and bridge small holes, re-mesh and apply a "
        "small scale error: a stand-in for a phone photogrammetry scan of the object.",
    )
    scan.add_argument("mesh", help="input mesh file (PLY, OBJ, STL, ...)")
    scan.add_argument("--out", required=True, help="output mesh file (.ply, .obj, .stl)")
    scan.add_argument("--seed", type=int, default=0, help="random seed (same seed, same scan)")
    scan.add_argument("--units", default="m", choices=["m", "cm", "mm", "auto"], help="unit of the input mesh")
    scan.add_argument("--resolution-mm", type=float, help="finest detail kept (default 1.5)")
    scan.add_argument("--noise-mm", type=float, help="surface noise standard deviation (default 0.3)")
    scan.add_argument("--scale-error", type=float, help="relative scale error, e.g. 0.007 (default)")
    scan.add_argument("--holes", type=int, help="number of holes cut and bridged (default 4)")
    scan.set_defaults(run=_run_scan)

    recording = commands.add_parser(
        "recording",
        help="a scripted rig session (calibrations, hand-held contacts) as ROS bags and a Motive CSV",
        description="Simulate a lab session with two hand-held GelSight rigs and OptiTrack on a known mesh: the "
        "dual-ball and plate calibrations, a bead capture, single and dual contacts with mocap noise and dropouts, "
        "GelSight frames rendered from a sensor calibration. See docs/rig.md.",
    )
    _object_arguments(recording)
    from yoto.rig.cli import add_recording_arguments

    add_recording_arguments(recording)


def _object_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--object",
        required=True,
        help="object: a name in the workspace, a built-in (tool, fruit, figurine), a model file (.npz) or a "
        "mesh file (its model is built first)",
    )
    parser.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")


def _load_model(args: argparse.Namespace):
    from pathlib import Path

    from yoto.objects.build import build_object, load_object_model
    from yoto.objects.mesh import MESH_SUFFIXES

    candidate = Path(args.object)
    if candidate.suffix.lower() in MESH_SUFFIXES and candidate.is_file():
        return load_object_model(build_object(candidate, candidate.stem, workspace=args.workspace))
    return load_object_model(args.object, args.workspace)


def _run_pairs(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np

    from yoto.errors import InputError
    from yoto.simulate.gel import ReconstructionNoise
    from yoto.simulate.scenarios import ScenarioConfig, write_pairs
    from yoto.workspace import pairs_dir

    if args.count < 1:
        raise InputError(f"-n must be at least 1, got {args.count}")
    for name in ("sensor_noise_mm", "sensor_noise_deg", "depth_noise_mm"):
        value = getattr(args, name)
        if value is not None and value < 0:
            raise InputError(f"--{name.replace('_', '-')} must not be negative, got {value}")
    model = _load_model(args)
    config = ScenarioConfig(
        calibration_translation_m=args.sensor_noise_mm * 1e-3,
        calibration_rotation_rad=float(np.radians(args.sensor_noise_deg)),
    )
    press = config.press
    if args.noise_free:
        press = dataclasses.replace(press, noise=ReconstructionNoise.none())
    if args.depth_noise_mm is not None:
        noise = dataclasses.replace(press.noise, pixel_std_m=args.depth_noise_mm * 1e-3)
        press = dataclasses.replace(press, noise=noise)
    if args.max_tilt_deg is not None:
        press = dataclasses.replace(press, max_tilt_deg=args.max_tilt_deg)
    config = dataclasses.replace(config, press=press)
    if args.min_conditioning is not None:
        config = dataclasses.replace(config, min_conditioning=args.min_conditioning)

    from yoto.pose.solver import oracle_pose_errors

    out_dir = args.out or pairs_dir(model.name, args.workspace)
    report = write_pairs(
        model,
        out_dir,
        args.count,
        seed=args.seed,
        config=config,
        overwrite=args.overwrite,
        progress=not args.quiet,
        check=lambda pair: oracle_pose_errors(model, pair),
    )
    print(report.summary())
    return 0


def trajectory_config(args: argparse.Namespace) -> TrajectoryConfig:
    """The `TrajectoryConfig` that `yoto simulate trajectory`'s options ask for (checked)."""
    import dataclasses

    import numpy as np

    from yoto.errors import InputError
    from yoto.simulate.scenarios import ScenarioConfig
    from yoto.simulate.trajectory import TrajectoryConfig

    for name in (
        "path_mm",
        "slip_mm",
        "slip_deg",
        "jitter_mm",
        "sensor_noise_mm",
        "sensor_noise_deg",
        "pose_outliers",
        "pose_flips",
        "pose_dropouts",
        "arm_error_mm",
        "arm_error_deg",
    ):
        value = getattr(args, name)
        if value is not None and value < 0:
            raise InputError(f"--{name.replace('_', '-')} must not be negative, got {value}")
    for name in ("path_mm", "pose_hz", "tactile_fps", "pixel_stride"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            raise InputError(f"--{name.replace('_', '-')} must be positive, got {value}")
    config = TrajectoryConfig(
        scenario=ScenarioConfig(
            calibration_translation_m=args.sensor_noise_mm * 1e-3,
            calibration_rotation_rad=float(np.radians(args.sensor_noise_deg)),
        )
    )
    if args.path_mm is not None:
        config = dataclasses.replace(config, path_length_m=args.path_mm * 1e-3)
    if args.slip_mm is not None:
        config = dataclasses.replace(config, slip_translation_per_m=args.slip_mm * 1e-3 / config.path_length_m)
    if args.slip_deg is not None:
        config = dataclasses.replace(
            config, slip_rotation_per_m=float(np.radians(args.slip_deg)) / config.path_length_m
        )
    if args.jitter_mm is not None:
        config = dataclasses.replace(config, jitter_translation_m=args.jitter_mm * 1e-3)
    if args.pose_hz is not None:
        config = dataclasses.replace(config, left_rate_hz=args.pose_hz, right_rate_hz=args.pose_hz)
    if args.tactile_fps is not None:
        config = dataclasses.replace(config, tactile_rate_hz=args.tactile_fps)
    if args.tactile_phase_ms is not None:
        config = dataclasses.replace(config, tactile_phase_s=args.tactile_phase_ms * 1e-3)
    if args.pixel_stride is not None:
        config = dataclasses.replace(config, tactile_pixel_stride=args.pixel_stride)
    if args.pose_outliers is not None:
        config = dataclasses.replace(config, pose_outlier_share=args.pose_outliers / 100.0)
    if args.pose_flips is not None:
        config = dataclasses.replace(config, pose_flips=args.pose_flips)
    if args.pose_dropouts is not None:
        config = dataclasses.replace(config, pose_dropouts=args.pose_dropouts)
    if args.arm_error_mm is not None:
        config = dataclasses.replace(config, arm_error_m=args.arm_error_mm * 1e-3)
    if args.arm_error_deg is not None:
        config = dataclasses.replace(config, arm_error_rad=float(np.radians(args.arm_error_deg)))
    return dataclasses.replace(config, tactile_whole_pad=bool(args.whole_pad))


def _run_trajectory(args: argparse.Namespace) -> int:
    from yoto.errors import InputError
    from yoto.simulate.trajectory import write_trajectories
    from yoto.workspace import workspace_dir

    if args.count < 1:
        raise InputError(f"-n must be at least 1, got {args.count}")
    config = trajectory_config(args)
    model = _load_model(args)
    out_dir = args.out or workspace_dir(args.workspace) / "trajectories" / model.name
    report = write_trajectories(
        model,
        out_dir,
        args.count,
        seed=args.seed,
        config=config,
        overwrite=args.overwrite,
        progress=not args.quiet,
        frames_via=args.frames_via,
    )
    print(report.summary())
    return 0


def _run_press(args: argparse.Namespace) -> int:
    import numpy as np

    from yoto.simulate.press import PressSimulator, simulate_contact

    model = _load_model(args)
    simulator = PressSimulator(model.mesh_object)
    rng = np.random.default_rng(args.seed)
    for _ in range(1000):
        p_object = simulator.sample_surface(rng)[0]
        contact = simulate_contact(simulator, p_object, model.aggregated_normal(p_object), rng)
        if contact.accepted:
            break
    else:  # pragma: no cover - only for meshes no sensor can touch
        from yoto.errors import InputError

        raise InputError(f"{model.name}: no reachable press in 1000 attempts")
    path = press_figure(model, contact, args.out)
    press = contact.press
    print(
        f"{model.name}: press at depth {press.depth_m * 1e3:.2f} mm, tilt {contact.approach['tilt_deg']:.1f} deg, "
        f"{press.contact_pixels} contact pixels, {len(contact.points_sensor)} tactile points -> {path}"
    )
    return 0


def _run_scan(args: argparse.Namespace) -> int:
    import dataclasses
    from pathlib import Path

    import numpy as np

    from yoto.errors import InputError
    from yoto.objects.mesh import MESH_SUFFIXES, load_mesh
    from yoto.simulate.scan import ScanConfig, degrade_mesh

    out = Path(args.out)
    if out.suffix.lower() not in (".ply", ".obj", ".stl", ".off", ".glb"):
        raise InputError(f"unsupported output format '{out.suffix}' (use one of {', '.join(MESH_SUFFIXES)})", out)
    mesh, _, _ = load_mesh(args.mesh, args.units)
    config = ScanConfig()
    overrides = {
        "resolution_m": None if args.resolution_mm is None else args.resolution_mm * 1e-3,
        "noise_std_m": None if args.noise_mm is None else args.noise_mm * 1e-3,
        "scale_error": args.scale_error,
        "holes": args.holes,
    }
    config = dataclasses.replace(config, **{key: value for key, value in overrides.items() if value is not None})
    scan = degrade_mesh(mesh, config, np.random.default_rng(args.seed))
    from yoto.io import write_bytes_atomic

    data = scan.export(file_type=out.suffix.lower().lstrip("."))
    write_bytes_atomic(out, data.encode("utf-8") if isinstance(data, str) else data)
    print(
        f"{args.mesh}: simulated scan with {len(scan.faces)} faces (source {len(mesh.faces)}), scale error "
        f"{config.scale_error * 100:+.2f} %, noise {config.noise_std_m * 1e3:.2f} mm -> {out}"
    )
    return 0


def press_figure(model, contact, path):
    """Save a figure of one press: the noise-free gel height map, the reconstructed (noisy) tactile cloud with
    the true contact outlined, and where the contact lies on the object. Returns the path."""
    import io
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from yoto.geometry import transform_points
    from yoto.io import write_bytes_atomic
    from yoto.sensor.spec import GELSIGHT_MINI

    press = contact.press
    spec = GELSIGHT_MINI
    figure = plt.figure(figsize=(13, 3.8), dpi=64)
    grid = figure.add_gridspec(1, 3, width_ratios=[1, 1, 0.9])
    height = figure.add_subplot(grid[0])
    image = height.imshow(press.height_map_m * 1e3, cmap="viridis")
    height.contour(press.contact_mask, levels=[0.5], colors="white", linewidths=0.8)
    height.set_title(
        f"noise-free gel surface, depth {press.depth_m * 1e3:.2f} mm\nwhite: where the gel touches", fontsize=9
    )
    figure.colorbar(image, ax=height, label="z (mm)", shrink=0.85)

    cloud_panel = figure.add_subplot(grid[1])
    points = contact.points_sensor
    columns = np.rint(points[:, 0] / spec.pixel_size_m + (spec.width_px - 1) / 2).astype(int)
    rows = np.rint(points[:, 1] / spec.pixel_size_m + (spec.height_px - 1) / 2).astype(int)
    noisy = np.full((spec.height_px, spec.width_px), np.nan)
    noisy[rows, columns] = (points[:, 2] - press.height_map_m[rows, columns]) * 1e3
    limit = float(np.nanmax(np.abs(noisy)))
    image = cloud_panel.imshow(noisy, cmap="coolwarm", vmin=-limit, vmax=limit)
    cloud_panel.contour(press.contact_mask, levels=[0.5], colors="black", linewidths=0.8)
    cloud_panel.set_title(f"tactile cloud, {len(points)} points\nreconstruction error (black: contact)", fontsize=9)
    figure.colorbar(image, ax=cloud_panel, label="error (mm)", shrink=0.85)
    for axis in (height, cloud_panel):
        axis.set_xlabel("column (sensor x)")
        axis.set_ylabel("row (sensor y)")

    scene = figure.add_subplot(grid[2], projection="3d")
    cloud = model.points_object[:: max(1, len(model.points_object) // 5000)]
    scene.scatter(*cloud.T, s=0.3, c="0.65", depthshade=False)
    patch = transform_points(press.T_object_sensor, press.contact_points_sensor())[::30]
    scene.scatter(*patch.T, s=1.5, c="tab:red", depthshade=False)
    start = press.T_object_sensor[:3, 3]
    scene.plot(*np.stack([start, start - 0.04 * press.T_object_sensor[:3, 2]], axis=1), c="tab:blue", lw=2.5)
    scene.set_title(f"{model.name}: contact (red), sensor axis (blue)", fontsize=9)
    scene.set_box_aspect(np.ptp(cloud, axis=0), zoom=1.5)
    scene.view_init(elev=20, azim=np.degrees(np.arctan2(-press.T_object_sensor[1, 2], -press.T_object_sensor[0, 2])))
    scene.set_axis_off()
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    plt.close(figure)
    return write_bytes_atomic(Path(path), buffer.getvalue())
