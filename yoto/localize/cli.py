"""`yoto localize CLOUD.ply|FRAME.png --object NAME`: where on the object is this tactile contact?"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from yoto.sensor.pair_images import ImageSides


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "localize",
        help="locate tactile contacts on an object model",
        description="Locate each tactile cloud (PLY, sensor frame, metres) or GelSight image (reconstructed with "
        "--calibration) on the object model: the contact location and outward normal (mesh file's frame and YOTO's "
        "object frame), its block, scores and the other candidates, best first. An input that shows no contact "
        "(a cloud not pressed into the gel, an image where nothing touches it) is reported as such.",
    )
    parser.add_argument(
        "clouds", nargs="+", help="tactile point clouds (PLY, sensor frame, metres) or GelSight images (PNG, ...)"
    )
    parser.add_argument("--calibration", help="sensor calibration for image inputs (from `yoto sensor calibrate`)")
    parser.add_argument("--background", help="a fresh no-contact frame of the sensor for image inputs")
    parser.add_argument("--object", required=True, help="object name (workspace or built-in) or model file")
    parser.add_argument(
        "--method",
        choices=["match", "yoto", "icp"],
        default="match",
        help="localizer: the training-free matched filter (default), the YOTO network, or the ICP baseline",
    )
    parser.add_argument("--checkpoint", help="network weights for --method yoto (default: the weights shipped)")
    parser.add_argument("--workspace", help="workspace folder holding object models")
    parser.add_argument("--out", help="write the results as JSON here (one file; a list when several clouds)")
    parser.add_argument("--candidates", type=int, default=3, help="candidates to print per cloud")
    parser.set_defaults(run=run)


def result_json(estimates: list, model, cloud: str, latency_ms: float) -> dict:
    """A localization result: every candidate in the mesh file's frame and in YOTO's object frame."""
    from yoto.geometry import rotate_vectors, transform_points

    candidates = []
    for estimate in estimates:
        candidates.append(
            {
                "p_mesh": transform_points(model.T_mesh_object, estimate.p_object).tolist(),
                "n_mesh": rotate_vectors(model.T_mesh_object, estimate.n_object).tolist(),
                "p_object": estimate.p_object.tolist(),
                "n_object": estimate.n_object.tolist(),
                "block": int(estimate.block),
                "score": float(estimate.score),
                "probability": float(estimate.probability),
                **estimate.details,
            }
        )
    return {
        "cloud": cloud,
        "object": model.name,
        "frames": "p_mesh/n_mesh: the mesh file's frame; p_object/n_object: YOTO's canonical object frame (metres)",
        "contact": candidates[0],
        "candidates": candidates,
        "latency_ms": latency_ms,
    }


def read_tactile_input(path: str, images: ImageSides) -> tuple[np.ndarray, float]:
    """The tactile cloud of a PLY file, or of a GelSight image reconstructed by `images` (ImageSides), and its depth
    scale's uncertainty (`TactileContact.depth_scale_sigma`: 0 for a cloud given as a cloud)."""
    from pathlib import Path

    from yoto.contacts import TactileImage, read_tactile_cloud, validate_tactile_points
    from yoto.sensor.presses import IMAGE_SUFFIXES

    if Path(path).suffix.lower() in IMAGE_SUFFIXES:
        points, depth_scale_sigma = images(TactileImage(Path(path), images.background))
        return validate_tactile_points(points, path), depth_scale_sigma
    return read_tactile_cloud(Path(path)), 0.0


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from yoto.errors import NoContactError
    from yoto.io import write_json_atomic
    from yoto.localize import make_localizer
    from yoto.localize.base import localize_cloud
    from yoto.objects.build import load_object_model
    from yoto.sensor.pair_images import ImageSides

    localizer = make_localizer(args.method, args.checkpoint)
    model = load_object_model(args.object, args.workspace)
    if hasattr(localizer, "prepare_object"):
        localizer.prepare_object(model)  # per-object set-up outside the timed localization
    images = ImageSides(args.calibration, Path(args.background) if args.background else None)
    results = []
    for cloud in args.clouds:
        try:
            points, depth_scale_sigma = read_tactile_input(cloud, images)
        except NoContactError as exc:
            results.append({"cloud": cloud, "object": model.name, "contact": None, "no_contact": exc.problem})
            print(f"{cloud}: {exc.problem}")
            continue
        tick = time.perf_counter()
        estimates = localize_cloud(localizer, points, model, depth_scale_sigma=depth_scale_sigma)
        latency = 1000.0 * (time.perf_counter() - tick)
        result = result_json(estimates, model, cloud, latency)
        results.append(result)
        print(f"{cloud}: {len(estimates)} candidate(s), {latency:.1f} ms")
        for rank, candidate in enumerate(result["candidates"][: args.candidates]):
            p = " ".join(f"{v * 1000:8.2f}" for v in candidate["p_mesh"])
            n = " ".join(f"{v:6.3f}" for v in candidate["n_mesh"])
            print(
                f"  #{rank + 1} p_mesh [{p}] mm  n_mesh [{n}]  block {candidate['block']:3d}  "
                f"score {candidate['score']:7.3f}  probability {candidate['probability']:.3f}"
            )
    if args.out:
        write_json_atomic(args.out, results[0] if len(results) == 1 else results)
        print(f"results written to {args.out}")
    return 0
