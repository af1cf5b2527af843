"""Localization error and per-contact latency of the ICP baseline on pressed patches of the built-in objects.

    python benchmarks/icp_timing.py                      # 8 patches per object, models at the default density
    python benchmarks/icp_timing.py --patches 20 --points 40000 --out bench_out/icp
    python benchmarks/icp_timing.py --set estimation=generalized --set voxel_spacing_m=0.001

Until the contact simulator lands, contacts are made here: a flat pad (GelSight Mini, 20.3 x 15.2 mm) is
pressed 0.5-1.5 mm into the mesh along the inward normal at a random surface point, with a random spin; the
tactile cloud is the dense mesh surface (0.1 mm sampling) inside the pad footprint that crosses the gel plane,
facing the sensor, plus 0.03 mm Gaussian noise, in the sensor frame (z toward the object, contact at z <= 0).
No gel smoothing, no collision test of the sensor body: these contacts are kinder than real ones. Ground
truth, as in SPEC: the parent point nearest the tactile cloud's centroid.

Latency is per `localize` call (one contact), wall clock and process CPU time, the first call per object
excluded as warm-up; reported as median and p90. The machine's load average goes into the output: on a
shared machine the wall clock says more about the neighbours than about ICP. Output: a Markdown table on
stdout and JSON (with commit, versions, device, load, seed) under --out.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import trimesh

from yoto.geometry import invert_transform, make_transform, rotation_about_axis, rotation_between, transform_points
from yoto.localize.icp import IcpConfig, IcpLocalizer
from yoto.metrics import summarize
from yoto.objects.builtin import builtin_mesh
from yoto.objects.model import ObjectModel, ObjectModelConfig, build_object_model
from yoto.provenance import git_commit
from yoto.sensor.spec import GELSIGHT_MINI

SAMPLING_M = 1e-4  # dense surface sampling of a pressed patch (a GelSight pixel is 0.063 mm)
NOISE_M = 3e-5  # Gaussian noise on the tactile points
DEPTH_RANGE_M = (0.0005, 0.0015)  # indentation depth (SPEC)
MIN_CONTACT_POINTS = 300  # fewer dense points: the pad barely touched, draw another contact


def pressed_contact(model: ObjectModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """(points_sensor, p_true_object) of a pad pressed into the model at a random point, or None if too small."""
    mesh = model.mesh_object
    index = int(rng.integers(len(model.points_object)))
    p_touch = model.points_object[index].astype(np.float64)
    z_object = -model.aggregated_normal(p_touch, 20)  # sensor z points into the object
    rotation = rotation_between(np.array([0.0, 0.0, 1.0]), z_object) @ rotation_about_axis(
        np.array([0.0, 0.0, 1.0]), rng.uniform(0.0, 2.0 * np.pi)
    )
    depth = rng.uniform(*DEPTH_RANGE_M)
    T_object_sensor = make_transform(rotation, p_touch + depth * z_object)
    pad_x, pad_y = GELSIGHT_MINI.pad_size_m
    reach = 0.5 * np.hypot(pad_x, pad_y) + 0.002
    near_vertices = np.linalg.norm(mesh.vertices - p_touch, axis=1) < reach
    faces = np.flatnonzero(near_vertices[mesh.faces].any(axis=1))
    local = mesh.submesh([faces], append=True)
    points, face_index = trimesh.sample.sample_surface(
        local, int(local.area / SAMPLING_M**2), seed=int(rng.integers(2**31))
    )
    points_sensor = transform_points(invert_transform(T_object_sensor), points)
    normals_sensor = local.face_normals[face_index] @ rotation
    inside = (
        (np.abs(points_sensor[:, 0]) <= 0.5 * pad_x)
        & (np.abs(points_sensor[:, 1]) <= 0.5 * pad_y)
        & (points_sensor[:, 2] <= 0.0)
        & (points_sensor[:, 2] >= -3.0 * DEPTH_RANGE_M[1])  # the sheet the pad touches, not a far side behind it
        & (normals_sensor[:, 2] < 0.0)  # facing the sensor
    )
    if inside.sum() < MIN_CONTACT_POINTS:
        return None
    points_sensor = points_sensor[inside] + rng.normal(scale=NOISE_M, size=(int(inside.sum()), 3))
    p_true = model.nearest_surface_point(transform_points(T_object_sensor, points_sensor.mean(axis=0)))
    return points_sensor, p_true


def load_or_build(name: str, points: int | None, cache: Path) -> ObjectModel:
    path = cache / f"{name}_{points or 'default'}.npz"
    if path.exists():
        return ObjectModel.load(path)
    model = build_object_model(builtin_mesh(name), name, ObjectModelConfig(num_points=points))
    model.save(path)
    return model


def run(args: argparse.Namespace) -> dict:
    import open3d

    config = replace(IcpConfig(), seed=args.seed, **config_overrides(args.set))
    localizer = IcpLocalizer(config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name in args.objects:
        model = load_or_build(name, args.points, out)
        rng = np.random.default_rng([args.seed, sum(map(ord, name))])
        contacts = []
        while len(contacts) < args.patches + 1:  # +1: the warm-up contact
            contact = pressed_contact(model, rng)
            if contact is not None:
                contacts.append(contact)
        errors_mm, best_of_candidates_mm, latency_ms, cpu_ms, probability, residual_mm = [], [], [], [], [], []
        for i, (points_sensor, p_true) in enumerate(contacts):
            tick, cpu_tick = time.perf_counter(), time.process_time()
            candidates = localizer.localize(points_sensor, model)
            elapsed, cpu = 1000.0 * (time.perf_counter() - tick), 1000.0 * (time.process_time() - cpu_tick)
            if i == 0:
                continue  # warm-up: builds the cached Open3D cloud and the model's KD-tree
            latency_ms.append(elapsed)
            cpu_ms.append(cpu)
            distances = [1000.0 * float(np.linalg.norm(c.p_object - p_true)) for c in candidates]
            errors_mm.append(distances[0])
            best_of_candidates_mm.append(min(distances))
            probability.append(candidates[0].probability)
            residual_mm.append(candidates[0].details["icp_residual_mm"])
        rows[name] = {
            "parent_points": len(model.points_object),
            "point_spacing_mm": 1000.0 * model.point_spacing_m,
            "contacts": len(errors_mm),
            "error_mm": summarize(errors_mm),
            "best_of_candidates_error_mm": summarize(best_of_candidates_mm),
            "within_5mm": float(np.mean(np.array(errors_mm) < 5.0)),
            "latency_ms": summarize(latency_ms),
            "cpu_time_ms": summarize(cpu_ms),  # process CPU time (all threads): less sensitive to a busy machine
            "top_probability_mean": float(np.mean(probability)),
            "top_residual_mm_mean": float(np.mean(residual_mm)),
            "per_contact_error_mm": errors_mm,
        }
        print(f"{name}: done", file=sys.stderr, flush=True)
    return {
        "benchmark": "icp localization on pressed patches",
        "commit": git_commit(short=False),
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "open3d": open3d.__version__},
        "device": {
            "cpu": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "load_average_1_5_15min": list(os.getloadavg()),  # a shared machine inflates every latency
        },
        "seed": args.seed,
        "icp_config": asdict(config),
        "contact_model": {"sampling_m": SAMPLING_M, "noise_m": NOISE_M, "depth_range_m": DEPTH_RANGE_M},
        "objects": rows,
    }


def config_overrides(assignments: list[str]) -> dict[str, object]:
    """`--set key=value` pairs as IcpConfig fields, each value parsed as the field's default is typed."""
    defaults = asdict(IcpConfig())
    overrides: dict[str, object] = {}
    for assignment in assignments:
        key, _, value = assignment.partition("=")
        if key not in defaults:
            raise SystemExit(f"--set {assignment}: IcpConfig has no field {key!r} (fields: {', '.join(defaults)})")
        default = defaults[key]
        overrides[key] = (
            value if isinstance(default, str) else (float(value) if default is None else type(default)(value))
        )
    return overrides


def markdown(result: dict) -> str:
    lines = [
        f"ICP baseline, commit {result['commit'][:10]}, seed {result['seed']}, "
        f"open3d {result['versions']['open3d']}, {result['device']['cpu_count']} CPUs "
        f"(load average {result['device']['load_average_1_5_15min'][0]:.1f} at the end)",
        "",
        "| object | parent pts | contacts | error mean (mm) | median | p90 | <5 mm | best of candidates, median "
        "| latency median (ms) | p90 | CPU time median (ms) | top prob. |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in result["objects"].items():
        error, latency = row["error_mm"], row["latency_ms"]
        lines.append(
            f"| {name} | {row['parent_points']} | {row['contacts']} | {error['mean']:.1f} | {error['median']:.1f} "
            f"| {error['p90']:.1f} | {row['within_5mm']:.0%} | {row['best_of_candidates_error_mm']['median']:.1f} "
            f"| {latency['median']:.0f} | {latency['p90']:.0f} | {row['cpu_time_ms']['median']:.0f} "
            f"| {row['top_probability_mean']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", nargs="+", default=["tool", "fruit", "figurine"])
    parser.add_argument("--patches", type=int, default=8, help="timed contacts per object (plus one warm-up)")
    parser.add_argument("--points", type=int, default=None, help="parent cloud size (default: the model default)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override an IcpConfig field")
    parser.add_argument("--out", default="bench_out/icp", help="JSON output and object-model cache folder")
    args = parser.parse_args(argv)
    result = run(args)
    table = markdown(result)
    print(table)
    out = Path(args.out)
    (out / "icp_timing.json").write_text(json.dumps(result, indent=2))
    (out / "icp_timing.md").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
