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
    """Inverse of a rigid 4x4 pose, or of each of (..., 4, 4) poses (uses R^T, not a general matrix inverse)."""
    if np.ndim(transform) > 2:
        rotations_t = np.swapaxes(np.asarray(transform, dtype=np.float64)[..., :3, :3], -1, -2)
        inverses = np.zeros(np.shape(transform))
        inverses[..., :3, :3] = rotations_t
        inverses[..., :3, 3] = -np.einsum("...ij,...j->...i", rotations_t, np.asarray(transform)[..., :3, 3])
        inverses[..., 3, 3] = 1.0
        return inverses
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


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]_x of (..., 3) vectors, shape (..., 3, 3): [v]_x @ w = v x w."""
    v = np.asarray(vectors, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


def so3_exp(rotation_vectors: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (axis times angle in radians; Rodrigues)."""
    omega = np.asarray(rotation_vectors, dtype=np.float64)
    out = np.empty(omega.shape[:-1] + (3, 3))
    _rodrigues_into(omega, out)
    return out


def _rodrigues_into(omega: np.ndarray, out: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Write exp(omega) (..., 3, 3) into `out` (a view may be strided), per element: (1 - cos(angle)) a a^T +
    cos(angle) I + sin(angle) [a]_x for the unit axis a, no stacked 3 x 3 product (the refinement builds thousands
    of small rotations per pose). Returns the angles, their cosines and sines (...,) for `se3_exp` to reuse."""
    angle = np.linalg.norm(omega, axis=-1)
    axis = omega / np.maximum(angle, 1e-300)[..., None]
    cos_angle, sin_angle = np.cos(angle), np.sin(angle)
    sin_axis = sin_angle[..., None] * axis
    np.multiply(((1.0 - cos_angle)[..., None] * axis)[..., :, None], axis[..., None, :], out=out)
    for i in range(3):
        out[..., i, i] += cos_angle
    out[..., 2, 1] += sin_axis[..., 0]
    out[..., 1, 2] -= sin_axis[..., 0]
    out[..., 0, 2] += sin_axis[..., 1]
    out[..., 2, 0] -= sin_axis[..., 1]
    out[..., 1, 0] += sin_axis[..., 2]
    out[..., 0, 1] -= sin_axis[..., 2]
    return angle, cos_angle, sin_angle


def so3_log(rotations: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3), angles in [0, pi]; the inverse of `so3_exp`."""
    r = np.asarray(rotations, dtype=np.float64)[..., :3, :3]
    axis_sin = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], -1)
    cos_angle = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arctan2(np.linalg.norm(axis_sin, axis=-1) / 2.0, cos_angle)  # accurate at every angle
    # angle / (2 sin angle), with its limit 1/2 at angle 0
    factor = np.where(angle < 1e-9, 0.5, angle / (2.0 * np.sin(np.maximum(angle, 1e-9))))
    out = axis_sin * factor[..., None]
    # Near pi, sin(angle) vanishes and the antisymmetric part loses the axis: read it off the symmetric part,
    # (R + R^T) / 2 = cos(angle) I + (1 - cos(angle)) a a^T, and take its sign from the antisymmetric part.
    near_pi = (angle > np.pi - 0.1).reshape(-1)
    if near_pi.any():
        flat_r, flat_cos = r.reshape(-1, 3, 3)[near_pi], cos_angle.reshape(-1)[near_pi]
        outer = ((flat_r + np.swapaxes(flat_r, 1, 2)) / 2.0 - flat_cos[:, None, None] * np.eye(3)) / (1.0 - flat_cos)[
            :, None, None
        ]
        column = np.argmax(np.diagonal(outer, axis1=1, axis2=2), axis=1)
        axis = normalize(outer[np.arange(len(flat_r)), :, column])
        axis *= np.where(np.einsum("ij,ij->i", axis, axis_sin.reshape(-1, 3)[near_pi]) < 0.0, -1.0, 1.0)[:, None]
        flat_out = out.reshape(-1, 3).copy()
        flat_out[near_pi] = axis * angle.reshape(-1)[near_pi][:, None]
        out = flat_out.reshape(out.shape)
    return out


def cross_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """out = a x b over the last axis (..., 3); `out` may be a strided view (a Jacobian's columns). np.cross is slow
    on many short vectors (its axis shuffling costs more than the arithmetic)."""
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        np.multiply(a[..., j], b[..., k], out=out[..., i])
        out[..., i] -= a[..., k] * b[..., j]
    return out


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis, (..., 3), as `cross_into` computes it."""
    return cross_into(a, b, np.empty(np.broadcast_shapes(a.shape, b.shape)))


def se3_exp(twists: np.ndarray) -> np.ndarray:
    """Poses (..., 4, 4) of twists (..., 6) = (rotation vector omega, rho): the group exponential of SE(3)."""
    xi = np.asarray(twists, dtype=np.float64)
    omega, rho = xi[..., :3], xi[..., 3:]
    out = np.zeros(xi.shape[:-1] + (4, 4))
    angle, cos_angle, sin_angle = _rodrigues_into(omega, out[..., :3, :3])
    # t = V(omega) rho, V = I + a [omega]_x + b [omega]_x^2: a = (1 - cos(angle)) / angle^2 and b = (angle -
    # sin(angle)) / angle^3, by their series below 0.01 rad (where the differences cancel)
    small = angle < 1e-2
    safe = np.where(small, 1.0, angle)
    square = angle**2
    a = np.where(small, 0.5 - square / 24.0 + square**2 / 720.0, (1.0 - cos_angle) / safe**2)
    b = np.where(small, 1.0 / 6.0 - square / 120.0 + square**2 / 5040.0, (safe - sin_angle) / safe**3)
    omega_rho = cross(omega, rho)
    out[..., :3, 3] = rho + a[..., None] * omega_rho + b[..., None] * cross(omega, omega_rho)
    out[..., 3, 3] = 1.0
    return out


def se3_log(transforms: np.ndarray) -> np.ndarray:
    """Twists (..., 6) = (omega, rho) of poses (..., 4, 4); the inverse of `se3_exp`.

    rho = V(omega)^-1 t in closed form: V^-1 = I - [omega]_x / 2 + c [omega]_x^2 with c = (1 - (angle / 2)
    cot(angle / 2)) / angle^2, whose series 1/12 + angle^2 / 720 + angle^4 / 30240 is used below 0.01 rad (where
    the difference cancels)."""
    t = np.asarray(transforms, dtype=np.float64)
    omega = so3_log(t[..., :3, :3])
    translation = t[..., :3, 3]
    angle = np.linalg.norm(omega, axis=-1)
    small = angle < 1e-2
    half = np.where(small, 1.0, angle / 2.0)
    square = angle**2
    series = 1.0 / 12.0 + square / 720.0 + square**2 / 30240.0
    c = np.where(small, series, (1.0 - half / np.tan(half)) / (4.0 * half**2))
    omega_t = cross(omega, translation)
    rho = translation - 0.5 * omega_t + c[..., None] * cross(omega, omega_t)
    return np.concatenate([omega, rho], axis=-1)


def pose_from_twist(twists: np.ndarray) -> np.ndarray:
    """Poses (..., 4, 4) [exp(omega) | t] of (..., 6) (omega, t): a rotation about the origin by the rotation vector,
    then the translation t. (Not SE(3)'s exponential, whose translation is V(omega) t: here t is where the origin
    goes, which keeps rotation and translation errors apart for frames centred on an object.)"""
    xi = np.asarray(twists, dtype=np.float64)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = so3_exp(xi[..., :3])
    out[..., :3, 3] = xi[..., 3:]
    out[..., 3, 3] = 1.0
    return out


def twist_of_pose(poses: np.ndarray) -> np.ndarray:
    """(omega, t) (..., 6) of poses (..., 4, 4); the inverse of `pose_from_twist`."""
    t = np.asarray(poses, dtype=np.float64)
    return np.concatenate([so3_log(t[..., :3, :3]), t[..., :3, 3]], axis=-1)


def rotation_about_axis(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation by `angle_rad` about the (not necessarily unit) `axis` (Rodrigues' formula)."""
    axis = np.asarray(axis, dtype=np.float64)
    return so3_exp(axis / np.linalg.norm(axis) * angle_rad)


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


def tangent_basis(axes: np.ndarray, reference: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (u, v) completing each unit axis z (..., 3) to a right-handed frame (u, v, z).

    u is `reference` (one (3,) vector for all) projected onto the plane normal to z when given (e.g. the sensor's
    x axis, to keep a contact's frame aligned with the image); otherwise z x e, with e the coordinate axis least
    aligned with z (deterministic). v = z x u.
    """
    z = np.asarray(axes, dtype=np.float64)
    if reference is None:
        helper = np.eye(3)[np.argmin(np.abs(z), axis=-1)]
        u = normalize(np.cross(z, helper))
    else:
        ref = np.asarray(reference, dtype=np.float64)
        u = normalize(ref - np.sum(ref * z, axis=-1, keepdims=True) * z)
    return u, np.cross(z, u)


def quaternion_xyzw_to_rotation(quaternions: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in (x, y, z, w) order (ROS, TUM); normalised first."""
    q = normalize(np.asarray(quaternions, dtype=np.float64))
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def rotation_to_quaternion_xyzw(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), (x, y, z, w) order with w >= 0, of rotation matrices (..., 3, 3)."""
    r = np.asarray(rotations, dtype=np.float64)[..., :3, :3]
    # Shepperd's method: start from the largest of the four squared components, which is never small.
    diagonal = np.diagonal(r, axis1=-2, axis2=-1)
    squares = np.stack(
        [
            1 + diagonal[..., 0] - diagonal[..., 1] - diagonal[..., 2],
            1 - diagonal[..., 0] + diagonal[..., 1] - diagonal[..., 2],
            1 - diagonal[..., 0] - diagonal[..., 1] + diagonal[..., 2],
            1 + diagonal[..., 0] + diagonal[..., 1] + diagonal[..., 2],
        ],
        axis=-1,
    )
    largest = np.argmax(squares, axis=-1)
    big = np.sqrt(np.maximum(np.take_along_axis(squares, largest[..., None], -1)[..., 0], 1e-300)) / 2.0
    sxy, sxz, syz = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    dx, dy, dz = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    quarter = 1.0 / (4.0 * big)
    candidates = np.stack(
        [
            np.stack([big, sxy * quarter, sxz * quarter, dx * quarter], -1),
            np.stack([sxy * quarter, big, syz * quarter, dy * quarter], -1),
            np.stack([sxz * quarter, syz * quarter, big, dz * quarter], -1),
            np.stack([dx * quarter, dy * quarter, dz * quarter, big], -1),
        ],
        axis=-2,
    )
    q = np.take_along_axis(candidates, largest[..., None, None], -2)[..., 0, :]
    q = normalize(q)
    return q * np.where(q[..., 3:] < 0.0, -1.0, 1.0)


def random_rotations(rng: np.random.Generator, count: int) -> np.ndarray:
    """`count` rotations drawn uniformly from SO(3), shape (count, 3, 3)."""
    quaternions = rng.normal(size=(count, 4))  # uniform on the unit 3-sphere once normalised
    return quaternion_xyzw_to_rotation(quaternions[:, [1, 2, 3, 0]])


def random_perturbation(rng: np.random.Generator, translation_std_m: float, rotation_std_rad: float) -> np.ndarray:
    """A small random 4x4 pose: Gaussian translation and a rotation about a random axis by a Gaussian angle."""
    axis = rng.normal(size=3)
    rotation = rotation_about_axis(axis, rng.normal() * rotation_std_rad)
    return make_transform(rotation, rng.normal(size=3) * translation_std_m)


def rotation_angle_rad(rotation_a: np.ndarray, rotation_b: np.ndarray) -> float:
    """Geodesic angle between two rotations (or the rotation parts of two poses), accurate down to 1e-15 rad."""
    return float(np.linalg.norm(so3_log(rotation_a[:3, :3].T @ rotation_b[:3, :3])))


def mean_rotation(rotations: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The weighted chordal L2 mean of (K, 3, 3) rotations (or the rotation parts of poses): the rotation nearest
    (Frobenius) their weighted sum, i.e. the minimiser of sum_k w_k |R - R_k|_F^2 over SO(3)."""
    rotations = np.asarray(rotations, dtype=np.float64)[..., :3, :3]
    weights = np.ones(len(rotations)) if weights is None else np.asarray(weights, dtype=np.float64)
    # Procrustes of each R_k's columns onto the axes: the cross-covariance is sum_k w_k R_k.
    columns = np.transpose(rotations, (1, 0, 2)).reshape(3, -1)
    return procrustes_rotation(columns, np.tile(np.eye(3), len(rotations)), np.repeat(weights, 3))[0]


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


def validate_transform(matrix: object, what: str, path: str | Path | None = None, tol: float = 3e-3) -> np.ndarray:
    """Check a value read from a file is a finite rigid 4x4 pose; return it as float64.

    Rotations written with a few digits are re-orthonormalised when they are within `tol` of SO(3) (entries printed
    with 3 decimals are within 1.6e-3, ~0.1 deg); anything further off raises an InputError naming `what` and the
    file.
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
        transposed = np.allclose(transform[:, 3], [0.0, 0.0, 0.0, 1.0], atol=tol)
        hint = " (its last column is: written column-major? the matrices are row-major)" if transposed else ""
        raise InputError(f"{what} has last row {transform[3].tolist()}, expected [0, 0, 0, 1]{hint}", path)
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
