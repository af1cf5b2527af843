"""Procedural objects for fitting and checking the pose stage's confidence: many shapes, none of them tuned on.

The confidence must mean the same on every object, so it is fitted on many: beside the built-in and shared
meshes, families of household-like shapes generated from a seed, with the regions that make tactile poses hard
(flat faces, cylinders, bodies of revolution, rounded edges) and some that make them easy (handles, bumps,
asymmetric parts). Each is a signed distance function meshed by marching cubes (`mesh_of_sdf`), so a name such
as `proc_box_3` always gives the same mesh. The fitting command uses one seed range; held-out checks another.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from yoto.errors import InputError
from yoto.objects.builtin import mesh_of_sdf

FAMILIES = ("box", "can", "bottle", "mug", "prism", "tool", "egg")
PREFIX = "proc"


def _box(p: np.ndarray, half: np.ndarray, radius: float) -> np.ndarray:
    q = np.abs(p) - (half - radius)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0) - radius


def _cylinder_z(p: np.ndarray, radius: float, half_height: float, rounding: float) -> np.ndarray:
    d = np.stack(
        [np.linalg.norm(p[..., :2], axis=-1) - radius + rounding, np.abs(p[..., 2]) - half_height + rounding], -1
    )
    return np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1) - rounding


def _ellipsoid(p: np.ndarray, radii: np.ndarray) -> np.ndarray:
    q = p / radii
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / radii, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _torus_x(p: np.ndarray, major: float, minor: float) -> np.ndarray:
    """A ring in the y-z plane (a handle's loop) of radius `major` and tube radius `minor`."""
    q = np.stack([np.linalg.norm(p[..., 1:], axis=-1) - major, p[..., 0]], -1)
    return np.linalg.norm(q, axis=-1) - minor


def _hex_prism_z(p: np.ndarray, radius: float, half_height: float) -> np.ndarray:
    k = np.array([-0.8660254, 0.5, 0.57735])
    q = np.abs(p)
    xy = q[..., :2] - 2.0 * np.minimum(q[..., :2] @ k[:2], 0.0)[..., None] * k[:2]
    edge = np.clip(xy[..., 0], -k[2] * radius, k[2] * radius)
    side = np.linalg.norm(np.stack([xy[..., 0] - edge, xy[..., 1] - radius], -1), axis=-1) * np.sign(
        xy[..., 1] - radius
    )
    d = np.stack([side, q[..., 2] - half_height], -1)
    return np.minimum(d.max(axis=-1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1)


def _smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _shape(family: str, rng: np.random.Generator) -> tuple[Callable[[np.ndarray], np.ndarray], float]:
    """A random member of a family: its SDF (metres) and a bounding half-extent."""
    if family == "box":
        half = rng.uniform([0.02, 0.015, 0.01], [0.11, 0.07, 0.04])
        radius = float(rng.uniform(0.001, 0.006))
        return (lambda p: _box(p, half, radius)), float(half.max())
    if family == "can":
        radius, half_height = float(rng.uniform(0.02, 0.045)), float(rng.uniform(0.025, 0.09))
        rounding = float(rng.uniform(0.001, 0.006))
        return (lambda p: _cylinder_z(p, radius, half_height, rounding)), max(radius, half_height)
    if family == "bottle":
        radius, half_height = float(rng.uniform(0.025, 0.045)), float(rng.uniform(0.05, 0.09))
        neck = float(rng.uniform(0.008, 0.015))

        def bottle(p: np.ndarray) -> np.ndarray:
            body = _cylinder_z(p, radius, half_height, 0.008)
            top = _cylinder_z(p - [0.0, 0.0, half_height + 0.02], neck, 0.025, 0.002)
            return _smooth_union(body, top, 0.012)

        return bottle, half_height + 0.05
    if family == "mug":
        radius, half_height = float(rng.uniform(0.03, 0.045)), float(rng.uniform(0.035, 0.055))
        major = float(rng.uniform(0.018, 0.026))

        def mug(p: np.ndarray) -> np.ndarray:
            body = _cylinder_z(p, radius, half_height, 0.004)
            handle = _torus_x(p - [0.0, radius + 0.4 * major, 0.0], major, 0.006)
            return _smooth_union(body, handle, 0.004)

        return mug, radius + 2.2 * major
    if family == "prism":
        radius, half_height = float(rng.uniform(0.02, 0.04)), float(rng.uniform(0.03, 0.08))
        return (lambda p: _hex_prism_z(p, radius, half_height) - 0.001), max(radius * 1.2, half_height)
    if family == "tool":
        length = float(rng.uniform(0.06, 0.1))
        grip = rng.uniform([0.012, 0.01], [0.02, 0.018])

        def tool(p: np.ndarray) -> np.ndarray:
            head = _box(p - [length, 0.0, 0.0], np.array([0.02, 0.03, 0.012]), 0.003)
            handle = _cylinder_z(np.stack([p[..., 1], p[..., 2], p[..., 0]], -1), float(grip[0]), length, 0.004)
            knob = _ellipsoid(p + [length, 0.0, 0.0], np.array([0.015, grip[1] * 1.5, grip[1] * 1.5]))
            return _smooth_union(_smooth_union(handle, head, 0.006), knob, 0.006)

        return tool, length + 0.04
    if family == "egg":
        radii = rng.uniform([0.02, 0.018, 0.025], [0.04, 0.035, 0.06])
        bumps = rng.normal(size=(int(rng.integers(0, 12)), 3))
        bumps /= np.linalg.norm(bumps, axis=1, keepdims=True) + 1e-12

        def egg(p: np.ndarray) -> np.ndarray:
            surface = _ellipsoid(p, radii)
            radial = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-9)
            return surface - 0.0015 * np.exp((radial @ bumps.T - 1.0) / 0.02).sum(axis=-1)

        return egg, float(radii.max())
    raise InputError(f"unknown procedural family {family!r} (families: {', '.join(FAMILIES)})")


def procedural_names(count: int, first: int = 0) -> list[str]:
    """`count` object names cycling through the families: proc_box_0, proc_can_1, ..."""
    return [f"{PREFIX}_{FAMILIES[i % len(FAMILIES)]}_{i}" for i in range(first, first + count)]


def procedural_mesh(name: str) -> trimesh.Trimesh:
    """The mesh of a procedural object named `proc_<family>_<index>` (metres; voxels of 1 mm, coarser for large
    shapes). Deterministic."""
    parts = name.split("_")
    if len(parts) != 3 or parts[0] != PREFIX or not parts[2].isdigit():
        raise InputError(f"{name!r} is not a procedural object name (expected {PREFIX}_<family>_<index>)")
    rng = np.random.default_rng([2024, int(parts[2])])
    sdf, extent = _shape(parts[1], rng)
    margin = extent + 0.01
    return mesh_of_sdf(sdf, (-margin,) * 3, (margin,) * 3, max(0.001, margin / 80.0))


def is_procedural(name: str) -> bool:
    return name.startswith(PREFIX + "_")
