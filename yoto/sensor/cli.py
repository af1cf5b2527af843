"""`yoto sensor ...`: calibrate a GelSight from ball presses, reconstruct point clouds, validate, time."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from yoto.sensor.spec import GelSightSpec

log = logging.getLogger("yoto")

VIDEO_SUFFIXES = (".gif", ".tif", ".tiff", ".npy", ".mp4", ".avi", ".mov", ".mkv")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "sensor", help="GelSight sensor: calibration from ball presses, image -> tactile point cloud"
    )
    commands = parser.add_subparsers(dest="sensor_command", required=True, metavar="ACTION")

    calibrate = commands.add_parser("calibrate", help="calibrate from a background image and ball presses")
    _add_press_arguments(calibrate)
    calibrate.add_argument("--out", help="calibration file to write (default: WORKSPACE/sensors/SENSOR.npz)")
    calibrate.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")
    calibrate.add_argument("--overwrite", action="store_true", help="replace an existing calibration file")
    calibrate.set_defaults(run=_run_calibrate)

    recon = commands.add_parser(
        "reconstruct", help="image(s) -> tactile point cloud(s) in the sensor frame (PLY, metres)"
    )
    recon.add_argument("input", help="an image, a folder of images, or a multi-frame file (GIF, TIFF, .npy)")
    recon.add_argument("--calibration", required=True, help="calibration file from `yoto sensor calibrate`")
    recon.add_argument("--out", required=True, help="PLY file for one image; a folder for several frames")
    recon.add_argument("--background", help="a fresh no-contact image of the same sensor (default: the calibration's)")
    recon.add_argument("--height-maps", action="store_true", help="also write each height map (.npy, metres)")
    recon.set_defaults(run=_run_reconstruct)

    validate = commands.add_parser("validate", help="k-fold validation on ball presses (sphere fits)")
    _add_press_arguments(validate)
    validate.add_argument("--folds", type=int, default=4, help="number of folds (default 4)")
    validate.add_argument(
        "--figure",
        default="sensor_validation.png",
        help="figure to write (default sensor_validation.png in the current folder; '' for none)",
    )
    validate.add_argument("--table", help="also write the Markdown table here")
    validate.set_defaults(run=_run_validate)

    bench = commands.add_parser("bench", help="time image -> point cloud (median, p90, per step)")
    bench.add_argument("--calibration", required=True, help="calibration file")
    bench.add_argument("--frames", help="a folder of real frames to time (default: rendered ball presses)")
    bench.add_argument("--repeats", type=int, default=300, help="timed frames (default 300)")
    bench.add_argument("--json", help="also write the result as JSON here")
    bench.set_defaults(run=_run_bench)

    render = commands.add_parser("render", help="render the image of a ball press (optical simulator)")
    render.add_argument("--calibration", required=True, help="calibration file")
    render.add_argument("--out", required=True, help="PNG to write")
    render.add_argument("--ball-diameter-mm", type=float, default=6.31, help="ball diameter (default 6.31)")
    render.add_argument("--contact-radius-mm", type=float, default=1.6, help="contact radius (default 1.6)")
    render.add_argument(
        "--centre-px",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        help="contact centre (pixels; default: the image centre)",
    )
    render.add_argument("--seed", type=int, help="add sensor noise drawn with this seed")
    render.set_defaults(run=_run_render)


def _add_press_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--background", required=True, help="image of the sensor with nothing touching it")
    parser.add_argument(
        "--presses",
        required=True,
        help="folder of ball-press images, or of one sub-folder per press, or of one sub-folder per ball "
        "(presses/6.310mm/0/gelsight.png)",
    )
    parser.add_argument("--ball-diameter-mm", type=float, required=True, help="diameter of the ball (mm)")


def _load_presses(args: argparse.Namespace):
    from yoto.sensor.presses import list_press_images, load_image

    background = load_image(args.background)
    paths = list_press_images(args.presses)
    root = Path(args.presses)
    names = [str(p.relative_to(root)) for p in paths]
    return background, [load_image(p) for p in paths], names


def _run_calibrate(args: argparse.Namespace) -> int:
    from yoto.errors import InputError
    from yoto.sensor.ball_calibration import calibrate
    from yoto.workspace import workspace_dir

    out = Path(args.out) if args.out else workspace_dir(args.workspace) / "sensors" / "gelsight_mini.npz"
    if out.exists() and not args.overwrite:
        raise InputError("calibration file exists; pass --overwrite to replace it", out)
    background, presses, names = _load_presses(args)
    calibration, report = calibrate(
        background, presses, args.ball_diameter_mm * 1e-3, names=names, background_path=args.background
    )
    for press in report.presses:
        if press.used:
            print(
                f"  {press.name}: contact circle ({press.contact_x_px:.1f}, {press.contact_y_px:.1f}) "
                f"r={press.contact_radius_px:.1f} px, gradient RMSE {press.gradient_rmse:.3f}"
            )
        else:
            print(f"  {press.name}: not used: {press.reason}")
    calibration.save(out)
    print(f"{report.summary()}\nwrote {out}")
    return 0


def _read_frames(path: Path, spec: GelSightSpec | None = None):
    """(name, frame) pairs of an image, a folder of images, or a multi-frame file, at the size of `spec`'s sensor
    (default: the GelSight Mini's)."""
    import numpy as np

    from yoto.errors import InputError, MissingDependencyError
    from yoto.sensor.presses import IMAGE_SUFFIXES, list_press_images, load_image
    from yoto.sensor.spec import GELSIGHT_MINI

    spec = spec or GELSIGHT_MINI

    if path.is_dir():
        for frame_path in list_press_images(path):
            yield str(frame_path.relative_to(path).with_suffix("")).replace("/", "_"), load_image(frame_path, spec)
        return
    if not path.is_file():
        raise InputError("input not found", path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        stack = np.load(path, allow_pickle=False)
        if stack.ndim != 4:
            raise InputError(f"a frame stack must be (frames, rows, cols, 3) uint8, got shape {stack.shape}", path)
        for k, frame in enumerate(stack):
            yield f"frame_{k:05d}", frame
        return
    if suffix in (".gif", ".tif", ".tiff"):
        from PIL import Image, ImageSequence

        with Image.open(path) as handle:
            frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(handle)]
        if len(frames) > 1:
            for k, frame in enumerate(frames):
                yield f"frame_{k:05d}", frame
            return
        yield path.stem, frames[0]
        return
    if suffix in VIDEO_SUFFIXES:
        try:
            import imageio.v3 as iio
        except ImportError as exc:
            raise MissingDependencyError("imageio", "video", f"reading the video {path}") from exc
        try:
            for k, frame in enumerate(iio.imiter(path)):
                yield f"frame_{k:05d}", np.ascontiguousarray(frame[..., :3])
        except Exception as exc:  # imageio raises many types for an undecodable file or a missing video plugin
            raise InputError(
                f"cannot decode this video ({type(exc).__name__}: {exc}); install the video plugin "
                "(`pip install 'yoto[video]'`) or extract the frames to PNG files",
                path,
            ) from exc
        return
    if suffix in IMAGE_SUFFIXES:
        yield path.stem, load_image(path, spec)
        return
    raise InputError(f"unknown input type '{suffix}' (expected an image, a folder, GIF/TIFF, .npy or a video)", path)


def _run_reconstruct(args: argparse.Namespace) -> int:

    from yoto.io import save_npz_atomic, write_ply_points
    from yoto.sensor.calibration import load_calibration, with_background
    from yoto.sensor.pair_images import in_rgb_order, read_frame
    from yoto.sensor.reconstruction import reconstruct

    calibration = load_calibration(args.calibration)
    if args.background:
        calibration = with_background(calibration, read_frame(args.background, calibration), args.background)
    source = Path(args.input)
    frames = _read_frames(source, calibration.spec)
    single = source.is_file() and source.suffix.lower() not in VIDEO_SUFFIXES
    out = Path(args.out)
    written = empty = 0
    swapped = 0
    for name, frame in frames:
        label = f"{source}:{name}" if not single else source
        rgb = in_rgb_order(frame, calibration.background, label, warn=swapped == 0)  # BGR files: warned once
        swapped += rgb is not frame
        result = reconstruct(rgb, calibration, source=label)
        target = out if single else out / f"{name}.ply"
        write_ply_points(target, result.points_sensor)
        if args.height_maps:
            save_npz_atomic(
                target.with_suffix(".height.npz"),
                {"height_map_m": result.height_map_m, "mask": result.mask},
                {"source": str(label)},
            )
        written += 1
        if not result.contact:
            empty += 1
            log.info("%s: %s (wrote an empty cloud)", label, result.reason)
        else:
            log.info(
                "%s: %d points, depth %.3f mm%s",
                label,
                len(result.points_sensor),
                result.max_depth_m * 1e3,
                ", touches the frame's edge" if result.touches_border else "",
            )
    if swapped > 1:
        log.warning("%d of %d frames were in BGR order (read as RGB)", swapped, written)
    print(f"wrote {written} point cloud(s) to {out} ({empty} without contact)")
    return 0 if written else 1


def _run_validate(args: argparse.Namespace) -> int:
    from yoto.io import write_text_atomic
    from yoto.sensor.validation import validate

    background, presses, names = _load_presses(args)
    result = validate(
        background,
        presses,
        args.ball_diameter_mm * 1e-3,
        folds=args.folds,
        names=names,
        figure=args.figure or None,
    )
    table = result.table()
    print(table)
    if args.table:
        write_text_atomic(args.table, table + "\n")
    if args.figure:
        print(f"wrote {args.figure}")
    return 0


def _run_bench(args: argparse.Namespace) -> int:
    from yoto.io import write_json_atomic
    from yoto.sensor.bench import run_benchmark, synthetic_frames
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.presses import list_press_images, load_image

    calibration = load_calibration(args.calibration)
    if args.frames:
        frames = [load_image(p, calibration.spec) for p in list_press_images(args.frames)]
        kind = f"real frames from {args.frames}"
    else:
        frames = synthetic_frames(calibration, 20)
        kind = "rendered ball presses"
    result = run_benchmark(calibration, frames, args.repeats)
    print(f"image -> point cloud, {kind}:\n{result.table()}")
    if args.json:
        write_json_atomic(args.json, {**result.to_json(), "frames_kind": kind})
    return 0


def _run_render(args: argparse.Namespace) -> int:
    import numpy as np

    from yoto.io import png_bytes, write_bytes_atomic
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.optical import render_image
    from yoto.sensor.sphere import press_height_map

    calibration = load_calibration(args.calibration)
    spec = calibration.spec
    cx, cy = args.centre_px if args.centre_px else ((spec.width_px - 1) / 2, (spec.height_px - 1) / 2)
    height = press_height_map(cx, cy, args.contact_radius_mm / spec.mm_per_px, args.ball_diameter_mm * 5e-4, spec)
    rng = None if args.seed is None else np.random.default_rng(args.seed)
    image = render_image(height, calibration, rng)
    write_bytes_atomic(args.out, png_bytes(image))
    print(f"wrote {args.out} (press depth {-height.min() * 1e3:.3f} mm)")
    return 0
