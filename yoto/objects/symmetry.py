"""An object's rotational symmetries, found when its model is built, and pose distances modulo them.

A symmetry is a rotation about the object frame's origin (the parent cloud's centroid, which every symmetry
keeps fixed) that maps the surface onto itself, as far as touch can tell. Two kinds are found:
- a continuous axis: a surface of revolution (a can, a bottle, a ball's three axes count as one);
- discrete rotations: n-fold turns about an axis (n = 2..12) and 2-fold flips (a box turned over).
Candidate axes are the canonical frame's principal axes: a rotational symmetry's axis is always a principal
axis of the cloud (for n >= 3 the other two variances are equal, so any axis in that plane is one, and those
orthogonal to the symmetry axis are tried as 2-fold flips).

The test of a rotation S: rotate a subset of the parent cloud by S and measure how far each rotated point lies
from the surface (its nearest parent point, with a normal that must agree). S is a symmetry when nearly all
points land back on the surface: the `quantile` of those distances is below `tolerance_m`. The tolerance is
what a tactile contact can tell apart under realistic sensor-pose calibration error: a shape difference of a
fraction of a millimetre between two poses is not evidence either way.

Poses of a symmetric object are compared modulo its symmetries (`rotation_error_rad`): the pose stage merges
hypotheses that differ by a symmetry, and the benchmark reports errors modulo them (and ADD-S, MSSD).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from yoto.geometry import normalize, rotation_about_axis, rotation_angle_rad

CONTINUOUS_TEST_ANGLES_DEG = (17.0, 53.0, 90.0, 127.0, 163.0, 211.0, 293.0)  # a continuous axis passes all of these
MAX_FOLD = 12  # n-fold symmetries tried: n = 2..MAX_FOLD
MAX_GROUP_SIZE = 48  # the discrete group's closure stops here (a cube's rotation group has 24 elements)
SAME_ROTATION_RAD = float(np.radians(2.0))  # rotations closer than this are one group element
FAR_M = 1.0  # the distance of a test point with no surface of agreeing normal nearby


@dataclass(frozen=True)
class SymmetryConfig:
    """How symmetries are detected at model build time."""

    tolerance_m: float = 0.001  # a rotation is a symmetry when the rotated surface lies this close to itself ...
    quantile: float = 0.9  # ... for this share of the test points
    normal_agreement: float = 0.8  # cos of the largest angle between a rotated normal and the surface's there
    test_points: int = 4000  # parent points used in the test (a deterministic stride through the cloud)


@dataclass
class Symmetry:
    """The symmetry group of an object, object frame: an optional continuous axis and discrete rotations."""

    axis_object: np.ndarray | None = None  # (3,) unit axis through the origin of a continuous symmetry, or None
    rotations: np.ndarray = field(default_factory=lambda: np.eye(3)[None])  # (G, 3, 3) discrete group, identity first
    scores_mm: dict[str, float] = field(default_factory=dict)  # test distance of each accepted generator (report)
    spherical: bool = False  # every rotation about the origin is a symmetry (a ball): orientation is meaningless

    @property
    def is_trivial(self) -> bool:
        return self.axis_object is None and len(self.rotations) == 1 and not self.spherical

    def describe(self) -> str:
        """One line for people, e.g. 'continuous about z, 2-fold flip' or 'none'."""
        if self.spherical:
            return "spherical (every rotation)"
        parts = []
        if self.axis_object is not None:
            parts.append(f"continuous about {_axis_name(self.axis_object)}")
        discrete = [name for name in sorted(self.scores_mm) if not name.startswith("continuous")]
        if discrete:
            parts.append(f"{', '.join(discrete)} ({len(self.rotations)} discrete rotations with the identity)")
        return ", ".join(parts) if parts else "none"

    def to_json(self) -> dict[str, Any]:
        return {
            "axis_object": None if self.axis_object is None else [float(v) for v in self.axis_object],
            "rotations": np.round(self.rotations, 12).tolist(),
            "scores_mm": {key: float(value) for key, value in self.scores_mm.items()},
            "spherical": self.spherical,
            "description": self.describe(),
        }

    @classmethod
    def from_json(cls, value: dict[str, Any]) -> Symmetry:
        axis = value.get("axis_object")
        rotations = np.asarray(value.get("rotations", [np.eye(3).tolist()]), dtype=np.float64).reshape(-1, 3, 3)
        return cls(
            None if axis is None else np.asarray(axis, dtype=np.float64),
            rotations,
            dict(value.get("scores_mm", {})),
            bool(value.get("spherical", False)),
        )

    # ------------------------------------------------------------------------------------------ distances
    def rotation_error_rad(self, rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
        """Geodesic angle between two object orientations, modulo the symmetries (accepts 3x3 or 4x4)."""
        return float(self.rotation_errors_rad(np.asarray(rotation_a)[None], np.asarray(rotation_b)[None])[0])

    def rotation_errors_rad(self, rotations_a: np.ndarray, rotations_b: np.ndarray) -> np.ndarray:
        """Batched `rotation_error_rad` of (K, 3, 3) (or 4x4) orientations pairwise: (K,) angles."""
        a = np.asarray(rotations_a, dtype=np.float64)[..., :3, :3]
        b = np.asarray(rotations_b, dtype=np.float64)[..., :3, :3]
        if self.spherical:
            return np.zeros(len(a))
        relative = np.einsum("kji,kjl->kil", a, b)  # R_a^T R_b
        # (K, G, 3, 3): the relative rotation composed with each discrete symmetry, on the object side
        composed = np.einsum("kij,gjl->kgil", relative, self.rotations)
        if self.axis_object is None:
            cos_angle = (np.trace(composed, axis1=-2, axis2=-1) - 1.0) / 2.0
        else:
            # Any twist about the axis is free: what remains is the swing, the angle between u and M u.
            u = self.axis_object
            cos_angle = np.einsum("i,kgij,j->kg", u, composed, u)
        return np.arccos(np.clip(cos_angle.max(axis=1), -1.0, 1.0))

    def equivalent_rotations(self, continuous_steps: int = 72) -> np.ndarray:
        """(G', 3, 3) rotations S with T @ S equivalent to T: the discrete group, times `continuous_steps` turns
        about the continuous axis when there is one (for MSSD, which BOP evaluates on a discretised group)."""
        if self.axis_object is None:
            return self.rotations
        turns = np.array(
            [rotation_about_axis(self.axis_object, a) for a in np.linspace(0, 2 * np.pi, continuous_steps, False)]
        )
        return np.einsum("gij,tjk->gtik", self.rotations, turns).reshape(-1, 3, 3)


def _axis_name(axis: np.ndarray) -> str:
    index = int(np.argmax(np.abs(axis)))
    return "xyz"[index] if abs(axis[index]) > 0.999 else "(" + ", ".join(f"{v:.2f}" for v in axis) + ")"


# ------------------------------------------------------------------------------------------------ detection
class _SelfMatch:
    """How far a rotated copy of the surface lies from the surface: the test behind every symmetry."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, config: SymmetryConfig):
        self.config = config
        self.tree = cKDTree(points)
        self.points = points
        self.normals = normals
        stride = max(1, len(points) // config.test_points)
        self.test_points = points[::stride]
        self.test_normals = normals[::stride]

    def distance_m(self, rotation: np.ndarray, stride: int = 1) -> float:
        """The `quantile` of the rotated test points' distances to the surface (normals must agree)."""
        points, normals = self.test_points[::stride], self.test_normals[::stride]
        rotated = points @ rotation.T
        reach = 3.0 * self.config.tolerance_m  # far points fail anyway; bounding the search keeps it fast
        gaps, index = self.tree.query(rotated, k=4, distance_upper_bound=reach)
        found = np.isfinite(gaps)
        index = np.where(found, index, 0)
        # Point-to-plane distances to the nearest few surface points: the parent cloud's own sampling adds nothing.
        distance = np.abs(np.einsum("ikj,ikj->ik", rotated[:, None, :] - self.points[index], self.normals[index]))
        agree = found & (
            np.einsum("ij,ikj->ik", normals @ rotation.T, self.normals[index]) > self.config.normal_agreement
        )
        nearest = np.where(agree, distance, FAR_M).min(axis=1)
        return float(np.quantile(nearest, self.config.quantile))

    def accepts(self, rotation: np.ndarray) -> tuple[bool, float]:
        """Whether `rotation` maps the surface onto itself, and the test distance. A tenth of the points first:
        most rotations fail there."""
        if self.distance_m(rotation, stride=10) > 2.0 * self.config.tolerance_m:
            return False, FAR_M
        distance = self.distance_m(rotation)
        return distance <= self.config.tolerance_m, distance


def detect_symmetry(
    points_object: np.ndarray, normals_object: np.ndarray, config: SymmetryConfig = SymmetryConfig()
) -> Symmetry:
    """The symmetries of a parent cloud given in its canonical (PCA, centroid-origin) frame."""
    test = _SelfMatch(np.asarray(points_object, dtype=np.float64), np.asarray(normals_object, np.float64), config)
    axes = candidate_axes(test.test_normals)
    axis_object, spherical = None, False
    scores: dict[str, float] = {}
    for axis in axes:
        if axis_object is not None and abs(axis @ axis_object) > 0.5:
            continue
        worst = 0.0
        for angle in CONTINUOUS_TEST_ANGLES_DEG:
            ok, distance = test.accepts(rotation_about_axis(axis, np.radians(angle)))
            worst = max(worst, distance)
            if not ok:
                break
        else:
            scores[f"continuous about {_axis_name(axis)}"] = 1000.0 * worst
            if axis_object is not None:  # a second continuous axis: every rotation is a symmetry (a ball)
                spherical = True
                break
            axis_object = axis.copy()
    if spherical:
        return Symmetry(axis_object, np.eye(3)[None], scores, spherical=True)
    generators: list[tuple[float, str, np.ndarray]] = []  # (test distance, name, rotation)
    for axis in axes:
        if axis_object is not None:
            if abs(axis @ axis_object) > 0.5 or generators:
                continue  # turns about the continuous axis are free, and one flip across it gives all the others
            ok, distance = test.accepts(rotation_about_axis(axis, np.pi))
            if ok:
                generators.append((distance, f"2-fold flip about {_axis_name(axis)}", rotation_about_axis(axis, np.pi)))
            continue
        for fold in range(MAX_FOLD, 1, -1):
            worst = 0.0
            for k in range(1, fold):
                ok, distance = test.accepts(rotation_about_axis(axis, 2.0 * np.pi * k / fold))
                worst = max(worst, distance)
                if not ok:
                    break
            else:
                name = f"{fold}-fold about {_axis_name(axis)}"
                generators.append((worst, name, rotation_about_axis(axis, 2.0 * np.pi / fold)))
                break
    # The group the generators close to must pass the test element by element (approximate symmetries compound):
    # add generators best first, each only if the group stays one.
    group = np.eye(3)[None]
    kept: list[tuple[float, str, np.ndarray]] = []
    for distance, name, rotation in sorted(generators, key=lambda item: item[0]):
        larger = close_group([r for _, _, r in kept] + [rotation])
        if len(larger) > len(group) and all(test.accepts(element)[0] for element in larger[1:]):
            group, kept = larger, kept + [(distance, name, rotation)]
    scores.update({name: 1000.0 * distance for distance, name, _ in kept})
    return Symmetry(axis_object, group, scores)


def candidate_axes(normals: np.ndarray, extra: int = 6, bins: int = 600) -> np.ndarray:
    """Axes a symmetry may turn about: the canonical frame's (principal) axes, then the most common surface
    normal directions (a cube's or a prism's faces: where equal variances leave the principal axes arbitrary).

    An axis with many surface normals near it (a box's face, a can's lid) is also tried snapped to their mean: the
    principal axes of a sampled cloud are off by a degree or so, which turns a 2-fold flip of a 10 cm box into a
    2 mm miss.
    """

    def snapped(axis: np.ndarray) -> np.ndarray:
        alignment = normals @ axis
        near = np.abs(alignment) > np.cos(np.radians(8.0))
        if near.mean() < 0.01:
            return axis
        return normalize((normals[near] * np.sign(alignment[near])[:, None]).sum(axis=0))

    golden = np.pi * (3.0 - np.sqrt(5.0))
    z = np.linspace(1.0, 0.0, bins)  # a Fibonacci half-sphere: axes, not directions
    radius = np.sqrt(1.0 - z**2)
    directions = np.stack([radius * np.cos(golden * np.arange(bins)), radius * np.sin(golden * np.arange(bins)), z], 1)
    counts = np.bincount(np.argmax(np.abs(normals @ directions.T), axis=1), minlength=bins)
    axes = list(np.eye(3))
    for axis in np.eye(3):
        candidate = snapped(axis)
        if abs(candidate @ axis) < np.cos(np.radians(0.25)):
            axes.append(candidate)
    for index in np.argsort(counts)[::-1][: 4 * extra]:
        if len(axes) >= 6 + extra or counts[index] == 0:
            break
        axis = snapped(directions[index])
        if all(abs(axis @ other) < np.cos(np.radians(10.0)) for other in axes):
            axes.append(axis)
    return np.array(axes)


def close_group(generators: list[np.ndarray]) -> np.ndarray:
    """The finite rotation group generated by `generators`: (G, 3, 3), identity first."""
    elements = [np.eye(3)]
    frontier = [np.asarray(g, dtype=np.float64) for g in generators]
    while frontier and len(elements) < MAX_GROUP_SIZE:
        candidate = frontier.pop()
        if any(rotation_angle_rad(candidate, e) < SAME_ROTATION_RAD for e in elements):
            continue
        elements.append(candidate)
        frontier += [candidate @ g for g in generators] + [g @ candidate for g in generators]
    return np.array(elements)
