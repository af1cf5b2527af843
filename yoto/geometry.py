"""Rigid-body geometry on plain numpy arrays.

Poses are 4x4 homogeneous matrices named by the frames they map between: `T_world_object` maps
object-frame coordinates to world coordinates, so adjacent subscripts cancel
(`T_world_sensor = T_world_object @ T_object_sensor`). Rotations are 3x3 matrices. Every function here
is the one place its operation is implemented; other modules call these instead of juggling matrices.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from yoto.errors import InputError


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Build a 4x4 pose from a 3x3 rotation and a 3-vector translation."""
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = translation
    return transform


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose (uses R^T, not a general matrix inverse)."""
    rotation = transform[:3, :3]
    inverse = np.eye(4)
    inverse[:3, :3] = rotation.T
    inverse[:3, 3] = -rotation.T @ transform[:3, 3]
    return inverse


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 pose to (..., 3) points."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def rotate_vectors(rotation_or_transform: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Apply the rotation part of a 3x3 or 4x4 matrix to (..., 3) direction vectors."""
    return vectors @ rotation_or_transform[:3, :3].T


def normalize(vectors: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Unit vectors along the last axis; zero vectors stay zero."""
    norms = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return vectors / np.maximum(norms, eps)


def rotation_about_axis(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation by `angle_rad` about the unit `axis` (Rodrigues' formula)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def rotation_between(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R @ source = target (both unit or non-zero vectors).

    For antiparallel vectors the rotation is by pi about an axis perpendicular to `source`, chosen
    deterministically.
    """
    a = np.asarray(source, dtype=np.float64)
    b = np.asarray(target, dtype=np.float64)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin_angle = np.linalg.norm(axis)
    cos_angle = float(np.clip(a @ b, -1.0, 1.0))
    if sin_angle < 1e-12:
        if cos_angle > 0:
            return np.eye(3)
        helper = np.eye(3)[np.argmin(np.abs(a))]
        return rotation_about_axis(np.cross(a, helper), np.pi)
    return rotation_about_axis(axis / sin_angle, np.arctan2(sin_angle, cos_angle))


def random_rotations(rng: np.random.Generator, count: int) -> np.ndarray:
    """`count` rotations drawn uniformly from SO(3), shape (count, 3, 3)."""
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    w, x, y, z = quaternions.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def random_perturbation(rng: np.random.Generator, translation_std_m: float, rotation_std_rad: float) -> np.ndarray:
    """A small random 4x4 pose: Gaussian translation and a rotation about a random axis by a Gaussian angle."""
    axis = rng.normal(size=3)
    rotation = rotation_about_axis(axis, rng.normal() * rotation_std_rad)
    return make_transform(rotation, rng.normal(size=3) * translation_std_m)


def rotation_angle_rad(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Geodesic angle between two rotations (or the rotation parts of two poses)."""
    relative = rotation_a[:3, :3].T @ rotation_b[:3, :3]
    return float(np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))


def procrustes_rotation(
    directions_target: np.ndarray, directions_source: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Proper rotation R minimising sum_i w_i |t_i - R s_i|^2 over matched direction columns.

    `directions_target` and `directions_source` are (3, M): one direction per column. Returns R and
    the singular values of the weighted cross-covariance, which say how well the directions
    constrain R (a zero second singular value means a rotation about one axis is free).
    """
    if weights is None:
        weights = np.ones(directions_source.shape[1])
    cross_covariance = (directions_target * weights) @ directions_source.T
    u, singular_values, vt = np.linalg.svd(cross_covariance)
    reflection_fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    return u @ reflection_fix @ vt, singular_values


def validate_transform(matrix: object, what: str, path: str | Path | None = None, tol: float = 1e-4) -> np.ndarray:
    """Check a value read from a file is a finite rigid 4x4 pose; return it as float64.

    Rotations written with a few digits are re-orthonormalised when they are within `tol` of SO(3);
    anything further off raises an InputError naming `what` and the file.
    """
    try:
        transform = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what} is not a numeric 4x4 matrix", path) from exc
    if transform.shape != (4, 4):
        raise InputError(f"{what} must be a 4x4 matrix (4 rows of 4 numbers), got shape {transform.shape}", path)
    if not np.all(np.isfinite(transform)):
        raise InputError(f"{what} contains NaN or infinite values", path)
    if not np.allclose(transform[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise InputError(f"{what} has last row {transform[3].tolist()}, expected [0, 0, 0, 1]", path)
    rotation = transform[:3, :3]
    orthogonality_error = np.abs(rotation.T @ rotation - np.eye(3)).max()
    if orthogonality_error > tol or np.linalg.det(rotation) < 0:
        raise InputError(
            f"{what} is not a rigid transform (rotation part is off SO(3) by {orthogonality_error:.2g}"
            f", det {np.linalg.det(rotation):.3f})",
            path,
        )
    u, _, vt = np.linalg.svd(rotation)
    transform = transform.copy()
    transform[:3, :3] = u @ vt
    transform[3] = [0.0, 0.0, 0.0, 1.0]
    return transform
