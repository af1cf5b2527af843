"""Checking and sharpening a pose with the tactile clouds themselves.

Given a pose hypothesis T_world_object, both tactile clouds (mapped into the object frame through their
sensor poses) must lie on the object's surface. `surface_fit` measures that (verification: a wrong
pair of contact candidates leaves the clouds floating or buried by millimetres), and `refine_pose` runs a
joint point-to-plane ICP of both clouds onto the parent cloud, starting from the SVD pose. Two contacts
constrain all six degrees of freedom, and the start is already close, so a few iterations converge;
unlike the ICP baseline there is no global search.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.geometry import invert_transform, make_transform, rotation_about_axis, transform_points
from yoto.objects.model import ObjectModel
from yoto.pointcloud import voxel_downsample


@dataclass(frozen=True)
class RefineConfig:
    """How hypotheses are verified and the chosen pose refined."""

    points_per_contact: int = 300  # tactile points used per contact (after down-sampling to the model spacing)
    iterations: int = 30  # ICP iterations at most
    max_distance_m: float = 0.008  # correspondences farther than this are ignored (the capture range)
    inlier_distance_m: float = 0.0005  # a point within this of the surface counts as lying on it
    max_step_m: float = 0.02  # refinement may move the pose at most this far in total (a guard)
    prior_rotation_rad: float = float(np.radians(5.0))  # the SVD pose as a weak prior: 1-sigma rotation ...
    prior_translation_m: float = 0.005  # ... and translation, so symmetric surfaces cannot slide the pose away
    surface_noise_m: float = 0.00005  # 1-sigma of a tactile point's distance from the true surface
    translation_only_iterations: int = 5  # first iterations move translation only (see refine_pose)
    seed: int = 0


@dataclass
class SurfaceFit:
    """How well the tactile clouds lie on the model surface under a pose."""

    rms_m: float  # RMS point-to-plane distance of the matched points (capped at max_distance_m)
    inlier_fraction: float  # fraction of points within inlier_distance_m of the surface


def contact_samples(points_sensor: np.ndarray, T_world_sensor: np.ndarray, spacing_m: float, config: RefineConfig):
    """A fixed, deterministic subset of a tactile cloud in the world frame, at the model's point spacing."""
    (points,) = voxel_downsample(points_sensor, spacing_m)
    if len(points) > config.points_per_contact:
        rng = np.random.default_rng(config.seed)
        points = points[rng.choice(len(points), config.points_per_contact, replace=False)]
    return transform_points(T_world_sensor, points)


def _matches(model: ObjectModel, points_object: np.ndarray, config: RefineConfig):
    distances, index = model.kdtree.query(points_object, distance_upper_bound=config.max_distance_m)
    valid = np.isfinite(distances)
    index = np.where(valid, index, 0)
    normals = model.normals_object[index].astype(np.float64)
    targets = model.points_object[index].astype(np.float64)
    plane = np.einsum("ij,ij->i", points_object - targets, normals)
    return valid, normals, targets, plane


def surface_fit(
    model: ObjectModel, T_world_object: np.ndarray, points_world: np.ndarray, config: RefineConfig
) -> SurfaceFit:
    """Point-to-plane fit of world-frame tactile points to the model under a pose hypothesis."""
    points_object = transform_points(invert_transform(T_world_object), points_world)
    valid, _, _, plane = _matches(model, points_object, config)
    residual = np.where(valid, np.abs(plane), config.max_distance_m)
    return SurfaceFit(
        rms_m=float(np.sqrt(np.mean(np.minimum(residual, config.max_distance_m) ** 2))),
        inlier_fraction=float(np.mean(valid & (np.abs(plane) < config.inlier_distance_m))),
    )


def refine_pose(
    model: ObjectModel, T_world_object: np.ndarray, points_world: np.ndarray, config: RefineConfig
) -> tuple[np.ndarray, SurfaceFit]:
    """Joint point-to-plane ICP of the tactile points (world frame) onto the parent cloud.

    Solves for a small object-frame correction each iteration (Gauss-Newton on the linearised point-to-plane
    residuals, Huber-weighted), with the starting pose as a weak Gaussian prior: where the surface constrains
    the pose (most places) the data wins; where it does not (rotation about a sphere-like patch's centre)
    the pose stays. The first iterations correct translation alone: while a translation error dominates the
    residuals, tiny noise in the normals would otherwise leak it into rotations the surface cannot observe.
    Returns the refined T_world_object and its surface fit; if refinement does not improve the fit, or wanders
    further than `max_step_m`, the input pose is returned unchanged.
    """
    T_object_world = invert_transform(T_world_object)
    T_start = T_object_world.copy()
    start_fit = surface_fit(model, T_world_object, points_world, config)
    prior = np.diag([1.0 / config.prior_rotation_rad**2] * 3 + [1.0 / config.prior_translation_m**2] * 3)
    for iteration in range(config.iterations):
        points_object = transform_points(T_object_world, points_world)
        valid, normals, _, plane = _matches(model, points_object, config)
        if valid.sum() < 12:
            break
        p, n, r = points_object[valid], normals[valid], plane[valid]
        jacobian = np.hstack([np.cross(p, n), n])  # d r / d (omega, tau) for p -> p + omega x p + tau
        scale = max(config.surface_noise_m, 1.4826 * np.median(np.abs(r)))
        weights = np.minimum(1.0, scale / np.maximum(np.abs(r), 1e-12)) / config.surface_noise_m**2  # Huber
        deviation = _log_se3(T_object_world @ invert_transform(T_start))
        hessian = (jacobian * weights[:, None]).T @ jacobian + prior
        gradient = (jacobian * weights[:, None]).T @ r + prior @ deviation
        if iteration < config.translation_only_iterations:
            step = np.concatenate([np.zeros(3), -np.linalg.solve(hessian[3:, 3:], gradient[3:])])
        else:
            step = -np.linalg.solve(hessian, gradient)
        angle = np.linalg.norm(step[:3])
        rotation = rotation_about_axis(step[:3], angle) if angle > 1e-12 else np.eye(3)
        T_object_world = make_transform(rotation, step[3:]) @ T_object_world
        if np.linalg.norm(step[3:]) < 1e-7 and angle < 1e-6:
            break
    refined = invert_transform(T_object_world)
    fit = surface_fit(model, refined, points_world, config)
    moved = np.linalg.norm(refined[:3, 3] - T_world_object[:3, 3])  # the object's centroid, in the world
    if fit.rms_m >= start_fit.rms_m or moved > config.max_step_m:
        return T_world_object, start_fit
    return refined, fit


def _log_se3(transform: np.ndarray) -> np.ndarray:
    """(rotation vector, translation) of a rigid transform: its deviation in the update's coordinates."""
    rotation = transform[:3, :3]
    angle = np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    rotvec = axis * (0.5 if angle < 1e-9 else angle / (2.0 * np.sin(angle)))
    return np.concatenate([rotvec, transform[:3, 3]])
