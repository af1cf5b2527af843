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

from yoto.geometry import invert_transform, transform_points
from yoto.objects.model import ObjectModel
from yoto.pointcloud import voxel_downsample
from yoto.registration import GaussNewtonConfig, point_to_plane_gauss_newton, truncated_plane_fit


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


def surface_fit(
    model: ObjectModel, T_world_object: np.ndarray, points_world: np.ndarray, config: RefineConfig
) -> SurfaceFit:
    """Point-to-plane fit of world-frame tactile points to the model under a pose hypothesis."""
    points_object = transform_points(invert_transform(T_world_object), points_world)
    fit = truncated_plane_fit(model, points_object[None], config.max_distance_m, inlier_m=config.inlier_distance_m)
    return SurfaceFit(rms_m=float(fit.rms_m[0]), inlier_fraction=float(fit.inlier_fraction[0]))


def refine_pose(
    model: ObjectModel, T_world_object: np.ndarray, points_world: np.ndarray, config: RefineConfig
) -> tuple[np.ndarray, SurfaceFit]:
    """Joint point-to-plane ICP of the tactile points (world frame) onto the parent cloud.

    `yoto.registration.point_to_plane_gauss_newton` on both clouds at once, rotating about the object frame's
    origin, with the SVD pose as a weak Gaussian prior: where the surface constrains the pose (most places) the
    data wins; where it does not (rotation about a sphere-like patch's centre) the pose stays. The first
    iterations correct translation alone. Returns the refined T_world_object and its surface fit; if refinement
    does not improve the fit, or wanders further than `max_step_m`, the input pose is returned unchanged.
    """
    start_fit = surface_fit(model, T_world_object, points_world, config)
    solver = GaussNewtonConfig(
        iterations=config.iterations,
        max_distance_m=config.max_distance_m,
        surface_noise_m=config.surface_noise_m,
        prior_rotation_rad=config.prior_rotation_rad,
        prior_translation_m=config.prior_translation_m,
        translation_only_iterations=config.translation_only_iterations,
        step_tolerance_rad=1e-6,
    )
    T_object_world = point_to_plane_gauss_newton(model, points_world, invert_transform(T_world_object)[None], solver)
    refined = invert_transform(T_object_world[0])
    fit = surface_fit(model, refined, points_world, config)
    moved = np.linalg.norm(refined[:3, 3] - T_world_object[:3, 3])  # the object's centroid, in the world
    if fit.rms_m >= start_fit.rms_m or moved > config.max_step_m:
        return T_world_object, start_fit
    return refined, fit
