"""How the closed loop reads a tactile frame and weighs its registration: the frame's samples (`contact_samples`),
how deep it reads its press and how deep the object should press (`frame_indentation_m`, `predicted_indentation_m`),
the Gauss-Newton settings (`registration_solver`, `pad_rest_solver`, `registration_prior`), and the information a
registered contact carries, checked against the surface (`contact_information`, `secant_scaling`; `observable_unit`
is where rotation and translation meet).

Frames: a frame's points in its sensor's frame (the gel's rest surface z = 0, pressed points below it); registered
points and twists in the canonical `object` frame (rotation about the centroid first).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from yoto.contacts import MIN_TACTILE_POINTS, MINI_PAD_M
from yoto.geometry import invert_transform, pose_from_twist, transform_points
from yoto.objects.model import ObjectModel
from yoto.registration import GaussNewtonConfig, SurfaceCloud, plane_distances, point_to_plane_jacobian
from yoto.tracking.config import CorrectionConfig


def contact_samples(points_sensor: np.ndarray, config: CorrectionConfig) -> np.ndarray:
    """A fixed, spatially even subset of a tactile cloud's firmly pressed points: the means of square bins over the
    pad (`voxel_m`, x and y only), those pressed at least `min_depth_fraction` of the deepest bin's depth, then at
    most `points_per_contact`.

    Binned and chosen so that a reconstruction's pixel noise leaves no pattern: 3-d voxels would split each column
    of the gel by its noisy depth (which points a voxel keeps shifts its mean), and choosing single points by their
    noisy depth keeps, along the chosen patch's edge, those whose noise made them deeper; both are errors fixed on
    the pad or the contact that move the registrations as the contact slides. Bins are chosen by their depth
    averaged with their neighbours'."""
    step = max(1, len(points_sensor) // (40 * config.points_per_contact))  # thin huge clouds before binning
    thinned = points_sensor[::step]
    cells = np.floor(thinned[:, :2] / config.voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    shape = tuple(cells.max(axis=0) + 1)
    counts = np.zeros(shape)
    sums = np.zeros(shape + (3,))
    np.add.at(counts, (cells[:, 0], cells[:, 1]), 1.0)
    np.add.at(sums, (cells[:, 0], cells[:, 1]), thinned)
    occupied = counts > 0
    means = sums[occupied] / counts[occupied, None]
    depth = ndimage.uniform_filter(sums[..., 2], 3, mode="constant") / np.maximum(
        ndimage.uniform_filter(counts, 3, mode="constant"), 1e-12
    )
    depth = depth[occupied]
    deepest = float(depth.min())
    points = means[depth <= config.min_depth_fraction * deepest] if deepest < 0 else means
    if len(points) < MIN_TACTILE_POINTS:  # a shallow, noisy frame: keep what there is
        points = means
    if len(points) > config.points_per_contact:
        points = points[np.random.default_rng(0).choice(len(points), config.points_per_contact, replace=False)]
    return points


def frame_indentation_m(points_sensor: np.ndarray) -> float:
    """How deep a tactile frame reads its press: its deepest points' depth (the 99th percentile, against pixel
    noise; the gel's rest surface is z = 0, pressed points lie below it)."""
    return max(float(np.percentile(-points_sensor[:, 2], 99.0)), 0.0)


def predicted_indentation_m(model: ObjectModel, T_object_sensor: np.ndarray) -> float:
    """How deep the object, placed at T_object_sensor, presses into the pad: the deepest of its surface points that
    face the sensor over the pad (sensor frame, below the gel's rest surface z = 0; negative: the gap to the pad);
    nan where no surface faces the pad."""
    half = np.array(MINI_PAD_M) / 2.0
    near = model.kdtree.query_ball_point(T_object_sensor[:3, 3], float(np.hypot(*half)))
    if not near:
        return float("nan")
    points = transform_points(invert_transform(T_object_sensor), model.points_object[near].astype(np.float64))
    facing = model.normals_object[near] @ T_object_sensor[:3, 2] < 0.0  # outward normal against the sensor's z
    over = facing & (np.abs(points[:, 0]) <= half[0]) & (np.abs(points[:, 1]) <= half[1])
    return float(-points[over, 2].min()) if over.any() else float("nan")


def registration_solver(config: CorrectionConfig) -> GaussNewtonConfig:
    """The Gauss-Newton settings with which the closed loop registers a tactile instant."""
    return GaussNewtonConfig(
        iterations=config.iterations,
        max_distance_m=config.max_distance_m,
        surface_noise_m=config.surface_noise_m,
        prior_rotation_rad=config.registration_prior_rotation_rad,
        prior_translation_m=config.registration_prior_translation_m,
        step_tolerance_m=config.step_tolerance_m,
        step_tolerance_rad=config.step_tolerance_rad,
    )


def pad_rest_solver(config: CorrectionConfig) -> GaussNewtonConfig:
    """The Gauss-Newton settings with which a sensor's frames at rest are registered before its pad's error is
    read off them (`PadError.settle`)."""
    return dataclasses.replace(
        registration_solver(config),
        prior_rotation_rad=config.pad_error.rest_fit_rotation_rad,
        prior_translation_m=config.pad_error.rest_fit_translation_m,
    )


def registration_prior(config: CorrectionConfig) -> np.ndarray:
    """(6, 6) the information of the registration's prior on the prediction: rotation (rad^-2), translation (m^-2)."""
    return np.diag([config.registration_prior_rotation_rad**-2] * 3 + [config.registration_prior_translation_m**-2] * 3)


def secant_scaling(
    surface: SurfaceCloud, normal: np.ndarray, points_object: np.ndarray, unit: np.ndarray, config: CorrectionConfig
) -> np.ndarray:
    """The map S (6, 6) that scales a registration's normal matrix N (of `points_object`, registered, object frame,
    rotation about the origin), as S N S^T, down along its `secant_directions` weakest directions (in `unit`s of
    each twist component) to the curvature the surface shows: the truncated sum of squared plane distances with
    every point matched afresh at +-`secant_step` along each direction, its second difference against the planes'
    prediction (step^2 times N there). The planes of the nearest surface samples predict a rise wherever they are
    tilted to the motion, also where the surface itself slides along (a scanned mug's wall under a spin about its
    axis); matched afresh, the points find the surface where it is. S is the identity where the check is off."""
    if config.secant_directions <= 0:
        return np.eye(6)
    values, vectors = np.linalg.eigh(normal * np.outer(unit, unit))
    reach = config.max_distance_m

    def cost(T_object_moved: np.ndarray) -> float:
        distance, matched, _, _ = plane_distances(surface, transform_points(T_object_moved, points_object), reach)
        return float(np.sum(np.where(matched, np.minimum(distance**2, reach**2), reach**2)))

    at_fit = cost(np.eye(4))
    shrink = np.eye(6)  # in units: I - sum (1 - sqrt(keep)) v v^T over the orthonormal directions v checked
    for value, vector in zip(values[: config.secant_directions], vectors.T[: config.secant_directions]):
        predicted = config.secant_step**2 * value
        if predicted <= 0.0:
            continue
        step = pose_from_twist(config.secant_step * vector * unit)
        rise = 0.5 * (cost(step) + cost(invert_transform(step))) - at_fit
        keep = min(max(rise / predicted, 0.0), 1.0)
        shrink -= (1.0 - np.sqrt(keep)) * np.outer(vector, vector)
    return (1.0 / unit)[:, None] * shrink * unit[None, :]


def contact_information(
    model: ObjectModel, points_object: dict[str, np.ndarray], config: CorrectionConfig, check_surface: bool = True
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per side, the Gauss-Newton normal matrices (6, 6) of its contact's registered points (object frame, rotation
    about the origin): for the noise new in every frame (all points, `pixel_noise_m`) and for the error the contact's
    points share (`bias_points` points of `bias_noise_m`: a reconstruction's smooth error), checked against the
    surface (`secant_scaling`, over all sides together) when `check_surface`."""
    normals, counts = {}, {}
    for side, side_points in points_object.items():
        _, matched, _, surface_normals = plane_distances(model, side_points, config.max_distance_m)
        jacobian = point_to_plane_jacobian(side_points, surface_normals)[matched]
        normals[side], counts[side] = jacobian.T @ jacobian, len(jacobian)
    unit = observable_unit(config)
    scaling = (
        secant_scaling(model, sum(normals.values()), np.vstack(list(points_object.values())), unit, config)
        if check_surface
        else np.eye(6)
    )
    information = {}
    for side, normal in normals.items():
        normal = scaling @ normal @ scaling.T
        bias_share = config.bias_points / max(counts[side], 1)
        information[side] = (normal / config.pixel_noise_m**2, normal * bias_share / config.bias_noise_m**2)
    return information


def observable_unit(config: CorrectionConfig) -> np.ndarray:
    """(6,) one observable unit of each twist component (rad, m): where rotation and translation meet."""
    return np.array([config.observable_rotation_rad] * 3 + [config.observable_translation_m] * 3)
