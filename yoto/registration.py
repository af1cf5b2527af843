"""Point-to-plane registration of tactile points onto a surface cloud: the residual and the local solver.

Every stage that asks "how well do these points lie on the object?" or "move this pose until they do" calls
these two functions: the matched filter (per-candidate refinement and ranking), the ICP baseline (ranking
registrations), the pose stage (verification and joint refinement of both contacts) and tracking.

`surface` is anything with `points_object` (N, 3), `normals_object` (N, 3) outward unit normals and a
`kdtree` over the points (an `ObjectModel`, or a crop of one). Poses map a `source` frame (the sensor, or the
world) into the surface's frame, written `T_surface_source`, batched as (K, 4, 4).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import ThreadpoolController

from yoto.geometry import cross_into, so3_exp, so3_log

NORMAL_AGREEMENT = 0.5  # cos 60 deg: a point's expected normal and the surface normal must agree this well


class NearestPoints(Protocol):
    """A nearest-neighbour index over a surface's points (SciPy's `cKDTree`, pykdtree's `KDTree`): distances
    (inf beyond the bound) and indices of the nearest point."""

    def query(self, x: np.ndarray, /, *, distance_upper_bound: float) -> tuple[np.ndarray, np.ndarray]: ...


class SurfaceCloud(Protocol):
    """What registration needs of a surface (an ObjectModel has it)."""

    @property
    def points_object(self) -> np.ndarray: ...

    @property
    def normals_object(self) -> np.ndarray: ...

    @property
    def kdtree(self) -> cKDTree | NearestPoints: ...


def one_blas_thread():
    """A context in which BLAS runs on one thread: what the localizers and the pose stage compute are many small
    matrix products, and BLAS threads wait for one another (on a busy 2-core machine a product that took 2 ms on
    one thread took 50 ms on two; the pose stage ran at half its speed)."""
    return _blas_libraries().limit(limits=1, user_api="blas")


@functools.cache
def _blas_libraries() -> ThreadpoolController:
    """The BLAS libraries numpy and scipy loaded (found once, on first use)."""
    return ThreadpoolController()


def transform_batch(T_surface_source: np.ndarray, points_source: np.ndarray) -> np.ndarray:
    """(K, M, 3) points under each of K poses; `points_source` is (M, 3) shared or (K, M, 3)."""
    rotation, translation = T_surface_source[:, :3, :3], T_surface_source[:, :3, 3]
    return np.matmul(points_source, np.transpose(rotation, (0, 2, 1))) + translation[:, None, :]


def plane_distances(
    surface: SurfaceCloud,
    points_surface: np.ndarray,
    reach_m: float,
    facing_surface: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Signed point-to-plane distance of each point (..., 3) to its nearest surface point within `reach_m`.

    Returns (distance, matched, nearest_points, nearest_normals), each of the points' leading shape (the last two
    with a trailing 3). `matched` is False where no surface point lies within reach or, when `facing_surface`
    (unit normals the points should have, broadcastable to the points) is given, where the surface normal
    disagrees with it by more than 60 degrees (the other side of a thin part). Unmatched distances are 0.
    """
    shape = points_surface.shape[:-1]
    flat = points_surface.reshape(-1, 3)
    gaps, index = surface.kdtree.query(flat, distance_upper_bound=reach_m)
    found = np.isfinite(gaps)
    index = np.where(found, index, 0)
    nearest = surface.points_object.take(index, axis=0).astype(np.float64)  # take: faster than fancy indexing
    normals = surface.normals_object.take(index, axis=0).astype(np.float64)
    if facing_surface is not None:
        agreement = np.einsum("...i,...i->...", normals.reshape(points_surface.shape), facing_surface)
        found &= agreement.reshape(-1) > NORMAL_AGREEMENT
    distance = np.where(found, np.einsum("ij,ij->i", flat - nearest, normals), 0.0)
    return distance.reshape(shape), found.reshape(shape), nearest.reshape(shape + (3,)), normals.reshape(shape + (3,))


@dataclass
class PlaneFit:
    """How well points lie on the surface under each of K poses (arrays of shape (K,))."""

    rms_m: np.ndarray  # truncated RMS: each point's |distance| capped at tau, unmatched points count tau
    inlier_fraction: np.ndarray  # share of points matched within `inlier_m` of the surface
    inlier_rms_m: np.ndarray  # RMS distance over the matched points (0 where there are none)


def truncated_plane_fit(
    surface: SurfaceCloud,
    points_surface: np.ndarray,
    tau_m: float,
    reach_m: float | None = None,
    facing_surface: np.ndarray | None = None,
    inlier_m: float | None = None,
) -> PlaneFit:
    """Truncated point-to-plane fit of (K, M, 3) surface-frame points (see `PlaneFit`).

    The truncation tau makes one number of fit and coverage: a right pose scores near the sensor's noise, a wrong
    one near tau. `reach_m` (default tau) is how far a nearest surface point may lie; search a little further than
    tau when the surface cloud is coarse, since a point on the surface can lie a point spacing from the nearest
    sample. `inlier_m` (default tau) defines the inlier fraction.
    """
    distance, matched, _, _ = plane_distances(
        surface, points_surface, tau_m if reach_m is None else reach_m, facing_surface
    )
    magnitude = np.abs(distance)
    residual = np.where(matched, np.minimum(magnitude, tau_m), tau_m)
    inliers = matched & (magnitude < (tau_m if inlier_m is None else inlier_m))
    count = matched.sum(axis=-1)
    inlier_rms = np.sqrt(np.sum(np.where(matched, magnitude**2, 0.0), axis=-1) / np.maximum(count, 1))
    return PlaneFit(
        rms_m=np.sqrt(np.mean(residual**2, axis=-1)),
        inlier_fraction=inliers.mean(axis=-1),
        inlier_rms_m=np.where(count > 0, inlier_rms, 0.0),
    )


@dataclass(frozen=True)
class GaussNewtonConfig:
    """Damped point-to-plane Gauss-Newton with the starting pose as a Gaussian prior."""

    iterations: int = 8  # iterations at most
    max_distance_m: float = 0.002  # correspondences further than this are ignored
    surface_noise_m: float = 3e-5  # 1-sigma of a point's distance from the true surface (weights)
    prior_rotation_rad: float = float(np.radians(10.0))  # 1-sigma of the prior on the start: rotation ...
    prior_translation_m: float = 0.003  # ... and translation of the pivot
    translation_only_iterations: int = 0  # first iterations move translation only
    step_tolerance_m: float = 1e-7  # a pose stops when its translation update is below this ...
    step_tolerance_rad: float = 1e-7  # ... and its rotation update below this (also in translation-only
    # iterations: a start that needs no translation is not rotated); each pose of a batch stops on its own

    def prior_information(self) -> np.ndarray:
        """(6,) the prior's information (its diagonal): the rotation's (rad^-2), then the pivot translation's (m^-2)."""
        return np.array([1.0 / self.prior_rotation_rad**2] * 3 + [1.0 / self.prior_translation_m**2] * 3)


# Refining a localizer's candidate from where the candidate put the sensor: a few iterations, the start as a
# weak prior (the matched filter's and the `cpu` network's fine stages).
CANDIDATE_REFINEMENT = GaussNewtonConfig(
    iterations=8,
    max_distance_m=0.002,
    surface_noise_m=0.00003,
    prior_rotation_rad=float(np.radians(10.0)),
    prior_translation_m=0.003,
)


def point_to_plane_gauss_newton(
    surface: SurfaceCloud,
    points_source: np.ndarray,
    T_surface_source: np.ndarray,
    config: GaussNewtonConfig,
    pivot_source: np.ndarray | None = None,
    facing_source: np.ndarray | None = None,
    keep_best: int | None = None,
) -> np.ndarray:
    """(K, 4, 4) poses that bring the (M, 3) source points onto the surface, from K starting poses at once.

    Each iteration solves a small rigid correction by Gauss-Newton on the linearised point-to-plane residuals,
    Huber-weighted at a robust scale (at least `surface_noise_m`), plus a Gaussian prior that ties the pose to
    its start: where the surface constrains the pose the data wins; directions it leaves free (sliding on a
    plane, spinning on a sphere) stay where they started.

    The correction rotates about a pivot: the source point `pivot_source` as it moves with the pose (a contact's
    centre: rotation and translation then decouple), or, when None, the surface frame's origin. The prior is on the
    rotation and on the pivot's displacement since the start. `facing_source` (3,): the points' expected outward
    normal in the source frame, or (M, 3) one per point (contacts of two sensors); correspondences whose surface
    normal disagrees are dropped. The first `translation_only_iterations` move translation only: while a translation
    error dominates the residuals, noise in the normals would otherwise leak it into rotations the surface cannot
    observe. `keep_best`: after the first iteration only this many poses, those whose points then lie best on the
    surface (truncated at `max_distance_m`), iterate further; the others keep their one-step pose (None: all
    iterate).
    """
    poses = np.array(T_surface_source, dtype=np.float64).reshape(-1, 4, 4)
    start = poses.copy()
    prior = np.diag(config.prior_information())
    # The source point whose displacement the prior measures: the pivot, or the source point at the origin.
    if pivot_source is None:
        anchor_source = np.einsum("kji,kj->ki", start[:, :3, :3], -start[:, :3, 3])  # T_start^-1 @ 0
    else:
        anchor_source = np.broadcast_to(np.asarray(pivot_source, dtype=np.float64), (len(poses), 3))
    anchor_start = np.einsum("kij,kj->ki", start[:, :3, :3], anchor_source) + start[:, :3, 3]
    active = np.arange(len(poses))  # poses still moving: each stops on its own
    for iteration in range(config.iterations):
        count = len(active)
        rotation, translation = poses[active, :3, :3], poses[active, :3, 3]
        source = points_source if np.ndim(points_source) == 2 else points_source[active]
        p = transform_batch(poses[active], source)
        facing = None
        if facing_source is not None and np.ndim(facing_source) == 1:  # one normal for all points
            facing = (rotation @ facing_source)[:, None, :]
        elif facing_source is not None:  # one per point
            facing = np.einsum("kij,mj->kmi", rotation, facing_source)
        r, use, _, n = plane_distances(surface, p, config.max_distance_m, facing)
        if iteration == 1 and keep_best is not None and count > keep_best:
            truncated = np.where(use, np.minimum(np.abs(r), config.max_distance_m), config.max_distance_m)
            best = np.sort(np.argsort(np.mean(truncated * truncated, axis=1), kind="stable")[:keep_best])
            active, count, rotation, translation = active[best], len(best), rotation[best], translation[best]
            p, r, use, n = p[best], r[best], use[best], n[best]
        anchor_now = np.einsum("kij,kj->ki", rotation, anchor_source[active]) + translation
        centres = np.zeros((count, 3)) if pivot_source is None else anchor_now
        jacobian = point_to_plane_jacobian(p - centres[:, None, :], n)
        # The prior's deviation from the start (none before the first step).
        deviation = np.zeros((count, 6))
        if iteration > 0:
            deviation[:, :3] = so3_log(rotation @ np.transpose(start[active, :3, :3], (0, 2, 1)))
            deviation[:, 3:] = anchor_now - anchor_start[active]
        hessian, gradient = weighted_normal_equations(jacobian, r, use, config.surface_noise_m)
        hessian += prior
        gradient += deviation @ prior
        if iteration < config.translation_only_iterations:
            step = np.zeros((count, 6))
            step[:, 3:] = -np.linalg.solve(hessian[:, 3:, 3:], gradient[:, 3:, None])[:, :, 0]
        else:
            step = -np.linalg.solve(hessian, gradient[:, :, None])[:, :, 0]
        delta = so3_exp(step[:, :3])
        # p -> delta (p - c) + c + tau, composed onto each pose
        poses[active, :3, :3] = delta @ rotation
        poses[active, :3, 3] = np.einsum("kij,kj->ki", delta, translation - centres) + centres + step[:, 3:]
        squared = step * step  # squared norms against squared tolerances: no square roots
        moving = (squared[:, 3:].sum(axis=1) >= config.step_tolerance_m**2) | (
            squared[:, :3].sum(axis=1) >= config.step_tolerance_rad**2
        )
        active = active[moving]
        if len(active) == 0:
            break
    return poses


def point_to_plane_jacobian(lever: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(..., 6) d r / d (w, tau) of point-to-plane residuals, (lever x n, n): the lever is the point's offset from
    the rotation's centre (the point itself for rotation about the origin), the normal the surface's there."""
    jacobian = np.empty(lever.shape[:-1] + (6,))
    cross_into(lever, normals, jacobian[..., :3])
    jacobian[..., 3:] = normals
    return jacobian


def weighted_normal_equations(
    jacobian: np.ndarray, distance: np.ndarray, use: np.ndarray, noise_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton normal matrices J^T W J (..., P, P) and gradients J^T W r (..., P) of point-to-plane
    residuals `distance` (..., M) (one set of M points, or a batch of sets) with their Jacobians `jacobian`
    (..., M, P): the twist's 6 columns (`point_to_plane_jacobian`) and any a caller adds for its own unknowns. W: each
    set's Huber weights (`huber_weights`, used where `use`) over `noise_m` squared, the residuals' noise."""
    rows = distance.reshape(-1, distance.shape[-1])
    weights = huber_weights(np.abs(rows), use.reshape(rows.shape), noise_m).reshape(distance.shape) / noise_m**2
    weighted = np.swapaxes(jacobian * weights[..., None], -1, -2)
    return weighted @ jacobian, (weighted @ distance[..., None])[..., 0]


def huber_weights(magnitude: np.ndarray, use: np.ndarray, noise_m: float) -> np.ndarray:
    """(K, M) Huber weights of K rows of residual magnitudes |r| (M each): 1 within a row's robust scale, scale / |r|
    beyond it, 0 where `use` is False. The scale is 1.4826 times the row's median |r| over its used points (the
    residuals' MAD about zero), at least `noise_m`: a fit whose residuals are mostly noise keeps every point whole."""
    scale = np.maximum(noise_m, 1.4826 * masked_row_medians(magnitude, use))
    return np.where(use, np.minimum(1.0, scale[:, None] / np.maximum(magnitude, 1e-12)), 0.0)


def masked_row_medians(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median of each row's masked entries (0 for a row with none), without NaN warnings."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(len(values))
    low = ordered[rows, np.maximum(count - 1, 0) // 2]
    high = ordered[rows, np.maximum(count, 1) // 2 - (count == 0)]
    return np.where(count > 0, 0.5 * (low + high), 0.0)
