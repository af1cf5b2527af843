"""How the closed loop reads a tactile frame and weighs its registration: the frame's samples (`contact_samples`),
how deep it reads its press and how deep the object should press (`frame_indentation_m`, `predicted_indentation_m`),
the Gauss-Newton settings (`registration_solver`, `pad_rest_solver`, `registration_prior`), and the information a
registered contact carries, checked against the surface (`contact_information`, `secant_scaling`; `observable_unit`
is where rotation and translation meet); the registration itself (`register_contacts`), where a contact read from
an image may tilt about its centre (`tilt_jacobian`, `without_tilt`); a frame read from an image with its depth
scale error taken out of its shape (`without_depth_scale`).

Frames: a frame's points in its sensor's frame (the gel's rest surface z = 0, pressed points below it); registered
points and twists in the canonical `object` frame (rotation about the centroid first).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
from scipy import ndimage

from yoto.contacts import MIN_TACTILE_POINTS, MINI_PAD_M
from yoto.geometry import invert_transform, pose_from_twist, so3_exp, so3_log, transform_points
from yoto.objects.model import ObjectModel
from yoto.registration import (
    GaussNewtonConfig,
    SurfaceCloud,
    huber_weights,
    plane_distances,
    point_to_plane_gauss_newton,
    point_to_plane_jacobian,
)
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


def tilt_jacobian(points: np.ndarray, normals: np.ndarray, pad_axes: np.ndarray) -> np.ndarray:
    """(M, 2) d r / d (tilt about the pad's x, about its y) of one contact's point-to-plane residuals: the contact
    turned about its own centre (its points' mean) about the two axes of its pad plane, `pad_axes` (2, 3), the
    sensor's x and y in the points' frame."""
    return point_to_plane_jacobian(points - points.mean(axis=0), normals)[:, :3] @ pad_axes.T


def without_tilt(normal: np.ndarray, cross: np.ndarray, tilt: np.ndarray, ratio: float) -> np.ndarray:
    """A contact's normal matrix (6, 6) with its tilt (`tilt_jacobian`) marginalised: the Schur complement
    N - B (C + ratio I)^-1 B^T of the joint normal matrix [[N, B], [B^T, C]] of (object twist, tilt), `ratio` the
    points' noise over the tilt's prior sigma, squared (0: the tilt free; large: the tilt known to be none)."""
    return normal - cross @ np.linalg.solve(tilt + ratio * np.eye(2), cross.T)


def contact_information(
    model: ObjectModel,
    points_object: dict[str, np.ndarray],
    config: CorrectionConfig,
    check_surface: bool = True,
    tilts: dict[str, tuple[np.ndarray, float]] | None = None,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per side, the Gauss-Newton normal matrices (6, 6) of its contact's registered points (object frame, rotation
    about the origin): for the noise new in every frame (all points, `pixel_noise_m`) and for the error the contact's
    points share (`bias_points` points of `bias_noise_m`: a reconstruction's smooth error), checked against the
    surface (`secant_scaling`, over all sides together) when `check_surface`. With `tilts` (per side, its pad's x
    and y in the object frame (2, 3), and a sigma > 0), that contact's own tilt about its centre in its pad plane is
    marginalised out of both (`without_tilt`): what the contact tells only through the tilt its reconstruction reads
    is discounted to what a tilt error of that size leaves."""
    normals, counts = {}, {}
    tilted: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # side -> (B, C) of the joint normal matrix
    for side, side_points in points_object.items():
        _, matched, _, surface_normals = plane_distances(model, side_points, config.max_distance_m)
        jacobian = point_to_plane_jacobian(side_points, surface_normals)[matched]
        normals[side], counts[side] = jacobian.T @ jacobian, len(jacobian)
        pad_axes, sigma = (tilts or {}).get(side, (None, 0.0))
        if pad_axes is not None and sigma > 0.0 and matched.any():
            tilt = tilt_jacobian(side_points[matched], surface_normals[matched], pad_axes)
            tilted[side] = (jacobian.T @ tilt, tilt.T @ tilt)
            normals[side] = without_tilt(normals[side], *tilted[side], (config.pixel_noise_m / sigma) ** 2)
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


def tilts_leaving_the_landing(normal: np.ndarray, tilt_sigma: np.ndarray, move_limit: np.ndarray) -> np.ndarray:
    """(T, K) the tilt combinations (columns, in the T tilt angles) the registration may estimate: those of which a
    tilt of its prior's sigma moves the object's correction by at most `move_limit` (6,) (rad, m) along any twist
    direction. From the joint normal matrix [[N, B], [B^T, C]] ((6 + T) square, the twist first, N with the
    registration's prior on it): a tilt q held fixed moves the correction by -N^-1 B q; the singular directions of
    that map, each tilt scaled by its sigma and each twist component by its limit, whose singular value is at most 1.
    Along a turn the pair pins only through their planes (a spin about the line through two flat contacts whose
    planes stand a few degrees off square to it) a tilt of 1 mrad is the object turning by tens."""
    twist, cross = normal[:6, :6], normal[:6, 6:]
    response = np.linalg.solve(twist, cross) * tilt_sigma[None, :] / move_limit[:, None]
    _, values, directions = np.linalg.svd(response)
    values = np.r_[values, np.zeros(len(tilt_sigma) - len(values))]
    return tilt_sigma[:, None] * directions.T[:, values <= 1.0]


def register_contacts(
    surface: SurfaceCloud,
    points: dict[str, np.ndarray],
    T_predicted_sensor: dict[str, np.ndarray],
    solver: GaussNewtonConfig,
    tilt_rad: dict[str, float] | None = None,
    move_limit: np.ndarray | None = None,
) -> np.ndarray:
    """(4, 4) the correction T_object_predicted bringing the sides' points (predicted object frame) onto the
    surface: point-to-plane Gauss-Newton from the prediction (`yoto.registration`; rotation about the origin, the
    prediction its prior). Each side's points match only surface facing its sensor (`T_predicted_sensor`'s -z).

    With `tilt_rad` (per side, a sigma > 0) that side's contact may also turn about its own centre in its pad plane
    (two angles, about its sensor's x and y, a Gaussian prior of that sigma), estimated jointly and so marginalised out
    of the correction: a reconstruction reads a contact's plane a few mrad off, and that error changes as the contact
    slides over the pad (journal, stop 17); along a direction the pair pins only through their tilts it would move the
    pose by degrees. Huber weights at a robust scale as `point_to_plane_gauss_newton`'s.

    With `move_limit` (6,) (rad, m) only the tilt combinations of which a tilt of its sigma moves the correction by
    at most that (`tilts_leaving_the_landing`, chosen once at the prediction's matches) are estimated: along a turn
    two flat contacts pin only through their planes, their tilts would move the landing by degrees (stop 21)."""
    sides = list(points)
    stacked = np.vstack([points[side] for side in sides])
    # The surface's outward normal at a contact is against the sensor's z (which points into the object).
    facing = np.vstack([np.broadcast_to(-T_predicted_sensor[side][:3, 2], (len(points[side]), 3)) for side in sides])
    sigmas = {side: sigma for side, sigma in (tilt_rad or {}).items() if side in points and sigma > 0.0}
    if not sigmas:
        return point_to_plane_gauss_newton(surface, stacked, np.eye(4)[None], solver, facing_source=facing)[0]
    tilting = list(sigmas)  # the sides whose tilts are estimated, their points' rows in `stacked`
    starts = dict(zip(sides, np.cumsum([0] + [len(points[side]) for side in sides]), strict=False))
    bounds = [(starts[side], starts[side] + len(points[side])) for side in tilting]
    axes = [T_predicted_sensor[side][:3, :2].T for side in tilting]  # (2, 3) each pad's x and y, predicted frame
    prior = np.zeros((6 + 2 * len(tilting),) * 2)
    prior[:6, :6] = np.diag(solver.prior_information())
    prior[6:, 6:] = np.diag(np.repeat([sigmas[side] ** -2.0 for side in tilting], 2))
    pose, tilts = np.eye(4), np.zeros(2 * len(tilting))
    tilted = stacked.copy()  # each side's points turned by its tilt so far (predicted frame)
    free = None  # (6 + tilts, 6 + kept) the coordinates solved for: the twist and the tilt combinations kept
    for _ in range(solver.iterations):
        rotation = pose[:3, :3]
        current = tilted @ rotation.T + pose[:3, 3]
        r, use, _, n = plane_distances(surface, current, solver.max_distance_m, facing @ rotation.T)
        weights = huber_weights(np.abs(r)[None], use[None], solver.surface_noise_m)[0] / solver.surface_noise_m**2
        jacobian = np.zeros((len(current), len(prior)))
        jacobian[:, :6] = point_to_plane_jacobian(current, n)
        for k, (start, end) in enumerate(bounds):
            pad_axes = axes[k] @ rotation.T  # carried into the current frame
            jacobian[start:end, 6 + 2 * k : 8 + 2 * k] = tilt_jacobian(current[start:end], n[start:end], pad_axes)
        weighted = jacobian * weights[:, None]
        deviation = np.concatenate([so3_log(rotation), pose[:3, 3], tilts])
        data = weighted.T @ jacobian
        if free is None:  # chosen once, at the prediction's matches
            free = np.eye(len(prior))
            if move_limit is not None:
                with_twist_prior = data + np.diag(np.r_[np.diag(prior)[:6], np.zeros(len(tilts))])
                kept = tilts_leaving_the_landing(with_twist_prior, np.diag(prior)[6:] ** -0.5, move_limit)
                free = scipy.linalg.block_diag(np.eye(6), kept)
        hessian = free.T @ (data + prior) @ free
        step = free @ -np.linalg.solve(hessian, free.T @ (weighted.T @ r + prior @ deviation))
        # a side's tilt turns its points about their centre (pad axes carried into the predicted frame) ...
        for k, (start, end) in enumerate(bounds):
            turn = so3_exp((step[6 + 2 * k : 8 + 2 * k] @ axes[k])[None])[0]
            centre = tilted[start:end].mean(axis=0)
            tilted[start:end] = (tilted[start:end] - centre) @ turn.T + centre
        tilts += step[6:]
        # ... and the object's correction turns about the origin and shifts
        delta = so3_exp(step[:3][None])[0]
        pose[:3, :3], pose[:3, 3] = delta @ rotation, delta @ pose[:3, 3] + step[3:6]
        if np.sum(step[3:6] ** 2) < solver.step_tolerance_m**2 and np.sum(step[:3] ** 2) < solver.step_tolerance_rad**2:
            break
    return pose


def without_depth_scale(
    surface: SurfaceCloud,
    points_sensor: np.ndarray,
    T_object_sensor: np.ndarray,
    sigma: float,
    config: CorrectionConfig,
) -> tuple[np.ndarray, float]:
    """A contact's samples (sensor frame) with the reconstruction's depth scale error taken out of their shape, and
    that error (the share by which the frame reads its depths about their mean too deep; negative: too shallow).

    A reconstruction from an image reads a press some 5-15% shallow, by a share that changes as the contact slides
    over the pad (journal, stop 22); registered, the flattened or steepened patch turns the object along a direction
    the pair pins weakly by degrees. The share is estimated jointly with a rigid motion of the contact (so neither
    the prediction's error nor the slip enters it) by Huber-weighted Gauss-Newton from `T_object_sensor` (the
    predicted pose of the sensor in the object frame), the twist under the registration's prior, the share under a
    prior of `sigma` (against the points' shape counted as `bias_points` points); only the scale's shape (each
    point's depth about the samples' mean depth, times the share) is removed: the mean depth is the press, which the
    pair's registration reads as a push."""
    if sigma <= 0.0:
        raise ValueError(f"the depth scale's prior sigma must be positive, got {sigma}")
    depth = points_sensor[:, 2] - points_sensor[:, 2].mean()
    solver = registration_solver(config)
    # the points' errors are not independent in their shape: weighed against its prior, the share is told only as
    # well as `bias_points` points of `bias_noise_m` tell it (a smooth error over a shallow patch mimics a scale)
    sigma *= np.sqrt(config.bias_points / len(points_sensor)) * config.surface_noise_m / config.bias_noise_m
    prior = np.diag(np.r_[solver.prior_information(), sigma**-2.0])
    estimate = np.zeros(7)  # (the object's twist, the share of the depths about their mean added)
    for _ in range(3):
        T_moved = pose_from_twist(estimate[:6]) @ T_object_sensor
        shaped = points_sensor + np.outer(estimate[6] * depth, [0.0, 0.0, 1.0])
        points_object = transform_points(T_moved, shaped)
        r, use, _, normals = plane_distances(surface, points_object, config.max_distance_m)
        if np.count_nonzero(use) < 7:
            return points_sensor, 0.0
        weights = huber_weights(np.abs(r)[None], use[None], config.surface_noise_m)[0] / config.surface_noise_m**2
        jacobian = np.column_stack(
            [point_to_plane_jacobian(points_object, normals), (normals @ T_moved[:3, 2]) * depth]
        )
        weighted = jacobian * weights[:, None]
        estimate -= np.linalg.solve(weighted.T @ jacobian + prior, weighted.T @ r + prior @ estimate)
    shape = estimate[6]
    return points_sensor + np.outer(shape * depth, [0.0, 0.0, 1.0]), float(-shape / (1.0 + shape))
