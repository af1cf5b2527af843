"""Checking and sharpening pose hypotheses with the tactile clouds, under sensor-pose calibration error.

Under the true pose both tactile clouds lie on the object's surface, but only under the true sensor poses.
The calibrated `T_world_sensor` of each sensor is off by a small rigid error (about 1 mm / 1 deg with motion
capture), so under any one object pose the two clouds cannot both lie exactly on the surface. The refinement
therefore estimates, for each pose hypothesis, the object pose together with a small correction per sensor:

    p_object = T_world_object^-1  T_world_sensor  E_sensor  p_sensor,     E_sensor = exp(xi_sensor)

minimising the point-to-surface residuals of both clouds (Huber-weighted, read off `field.SurfaceField`) plus
the prior xi_sensor ~ N(0, calibration covariance) of each correction, and a weak prior that keeps the object
pose near its start where the surface leaves it free (sliding on a plane, spinning on a ball). Two contacts
fix all six degrees of freedom wherever the surface is not featureless, so a few Gauss-Newton steps from a
closed-form start converge. `refine_hypotheses` runs K hypotheses at once (an 18 x 18 system each) and reports
what verification needs: each side's residual after the corrections, and the size of the corrections that
were needed (a wrong hypothesis needs large ones, or fits badly even with them).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from yoto.geometry import cross_into, invert_transform, se3_exp, se3_log, skew
from yoto.pointcloud import voxel_downsample
from yoto.pose.field import SurfaceField
from yoto.pose.kernels import KERNELS
from yoto.registration import huber_weights, transform_batch
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.simulate.body import SensorBody

_MEAN_NORM_3D = float(np.sqrt(8.0 / np.pi))  # E|x| of a 3-D standard normal vector
_ANGLE_TO_AXIS_STD = float(np.sqrt(np.pi / 2.0) / np.sqrt(3.0))  # per-axis std of a rotation vector whose angle
# is N(0, s) about a uniform axis, in units of the mean |angle|


@dataclass(frozen=True)
class CalibrationPrior:
    """How far each reported sensor pose may be from the truth (the same meaning as the simulator's settings)."""

    translation_m: float = 0.001  # mean |translation error| of each sensor's T_world_sensor
    rotation_rad: float = float(np.radians(1.0))  # mean rotation error angle of each sensor's T_world_sensor

    def information(self) -> np.ndarray:
        """(6,) inverse variances of a correction twist (rotation vector, translation), per axis."""
        rotation_std = max(self.rotation_rad, 1e-4) * _ANGLE_TO_AXIS_STD
        translation_std = max(self.translation_m, 1e-5) / _MEAN_NORM_3D
        return np.array([1.0 / rotation_std**2] * 3 + [1.0 / translation_std**2] * 3)


@dataclass(frozen=True)
class RefineConfig:
    """How hypotheses are verified and refined."""

    points_per_contact: int = 120  # tactile points used per contact (after down-sampling to the model spacing)
    verify_points: int = 10  # of these, the points used to score unrefined seeds ...
    verify_free_points: int = 0  # ... with this many of each contact's free-space points (0: none; 12 measured) ...
    verify_free_noise_m: float = 5e-5  # ... an RMS depth of the object inside them costing what a cloud's spread
    # of this does (the hypotheses' free-space weight: 0.1 mm over 4 effectively independent points)
    verify_capture_truncated: bool = False  # points beyond the capture range count as truncated in that score
    seed_tilt_rad: float = float(np.radians(4.0))  # how far an unrefined seed's normals may be off (sampling) ...
    seed_offset_m: float = 0.0  # ... and its clouds off the surface (sampling, key tolerance; 2 mm measured)
    screen_points: int = 24  # of these, the points used by the short refinement that screens many seeds
    screen_iterations: int = 3  # iterations of that short refinement
    screen_free_points: int = 48  # free-space points per contact that score that short refinement
    iterations: int = 8  # Gauss-Newton iterations at most
    max_distance_m: float = 0.003  # points further than this from the surface are ignored (the capture range)
    surface_noise_m: float = 5e-5  # 1-sigma of a tactile point's distance from the true surface (weights)
    prior_rotation_rad: float = float(np.radians(10.0))  # the starting pose as a weak prior: rotation ...
    prior_translation_m: float = 0.01  # ... and translation, so featureless surfaces cannot slide the pose away
    fit_tau_m: float = 0.0005  # residuals are truncated here when the fit is scored (a point off the surface
    # counts as much as one this far)
    inlier_distance_m: float = 0.0002  # a point within this of the surface counts as lying on it
    skirt_tau_m: float | None = 6e-5  # the gel's skirt: a point outside the object over which the object does not
    # reach the undeformed pad plane (its foot, sensor (x, y, 0), lies this far outside too) is gel sunk in beside
    # the contact, touching nothing, and counts at most this in the fit's score (None: as any point, `fit_tau_m`);
    # 60 um, two right-pose residuals: a pose still pays for leaning on its skirt (0 measured worse,
    # docs/journal/pose.md)
    free_spacing_m: float = 0.0015  # free space: grid spacing over the pad
    free_depth_m: float = 0.0002  # ... the points lie this far into the gel (the object would have pressed there)
    free_clearance_m: float = 0.001  # ... and at least this (one cell of that size) from the contact, across the pad
    free_tau_m: float = 0.001  # a free-space point inside the object counts at most this deep
    step_tolerance: float = 1e-5  # stop when every update is below this (radians and metres)
    seed: int = 0  # which tactile points are used


# The seeds' cheap score with floating clouds truncated, a seed's own offset allowed and free space checked
# (docs/journal/pose.md: truth among 95 -> 96%, right 88 -> 89%, but confident 77 -> 74% at the shipped confidence fit
# and +12 ms CPU per searched pair): not default until the confidence is refitted on the features it moves.
STRICT_SEED_SCORE = RefineConfig(verify_capture_truncated=True, seed_offset_m=0.002, verify_free_points=12)


@dataclass
class ContactPoints:
    """One contact's tactile points prepared for refinement, and the sensor that made it."""

    points_sensor: np.ndarray  # (M, 3) a fixed subset of the tactile cloud, sensor frame
    T_world_sensor: np.ndarray  # (4, 4) the reported sensor pose
    sensor: int  # which sensor (0: left, 1: right): contacts of one sensor share its calibration error
    free_sensor: np.ndarray  # (F, 3) points the object cannot occupy: the gel where it saw no contact (just
    # inside the gel surface), and the face of the housing around it
    depth_scale_sigma: float = 0.0  # 1-sigma of the log of the cloud's depth scale (its heights below the pad plane
    # may be off by a factor, e.g. reconstructed from an image): estimated per contact when > 0; 0: exact


def free_space_points(points_sensor: np.ndarray, config: RefineConfig) -> np.ndarray:
    """Where the object cannot be, sensor frame: a grid over the pad, `free_depth_m` into the gel, away from the
    contact (outside the cells of `free_clearance_m` that hold tactile points and their neighbours), and the
    housing's face around the gel."""
    width, height = GELSIGHT_MINI.pad_size_m
    points_sensor = points_sensor[:: max(1, len(points_sensor) // 4000)]
    cell = config.free_clearance_m
    columns, rows = int(np.ceil(width / cell)) + 2, int(np.ceil(height / cell)) + 2
    index = np.floor((points_sensor[:, :2] + [width / 2 + cell, height / 2 + cell]) / cell).astype(np.int64)
    inside = (index[:, 0] >= 0) & (index[:, 0] < columns) & (index[:, 1] >= 0) & (index[:, 1] < rows)
    touched = np.zeros((columns, rows), dtype=bool)
    touched[index[inside, 0], index[inside, 1]] = True
    touched = ndimage.binary_dilation(touched)  # a cell away from the contact, not just beside a point
    step = config.free_spacing_m
    x, y = np.meshgrid(np.arange(-width / 2, width / 2 + 1e-9, step), np.arange(-height / 2, height / 2 + 1e-9, step))
    pad = np.stack([x.ravel(), y.ravel()], axis=1)
    cells = np.floor((pad + [width / 2 + cell, height / 2 + cell]) / cell).astype(np.int64)
    pad = pad[~touched[cells[:, 0], cells[:, 1]]]
    gel = np.column_stack([pad, np.full(len(pad), -config.free_depth_m)])
    body = SensorBody()
    hx, hy = body.housing_size_m[0] / 2, body.housing_size_m[1] / 2
    x, y = np.meshgrid(np.arange(-hx, hx + 1e-9, 2 * step), np.arange(-hy, hy + 1e-9, 2 * step))
    rim = (np.abs(x) > width / 2 + step) | (np.abs(y) > height / 2 + step)  # the housing face around the gel
    housing = np.column_stack([x[rim], y[rim], np.full(int(rim.sum()), -body.gel_protrusion_m)])
    return np.vstack([gel, housing])


def contact_points(
    points_sensor: np.ndarray,
    T_world_sensor: np.ndarray,
    sensor: int,
    spacing_m: float,
    config: RefineConfig,
    depth_scale_sigma: float = 0.0,
) -> ContactPoints:
    """A fixed, deterministic subset of a tactile cloud at the model's point spacing, and its free space;
    `depth_scale_sigma` as in `ContactPoints`."""
    stride = max(1, len(points_sensor) // (20 * config.points_per_contact))  # thin dense clouds before voxelising
    (points,) = voxel_downsample(points_sensor[::stride], spacing_m)
    if len(points) > config.points_per_contact:
        rng = np.random.default_rng(config.seed)
        points = points[np.sort(rng.choice(len(points), config.points_per_contact, replace=False))]
    free = free_space_points(points_sensor, config)
    return ContactPoints(points, np.asarray(T_world_sensor, dtype=np.float64), sensor, free, depth_scale_sigma)


@dataclass
class Refined:
    """K refined hypotheses: poses, sensor corrections and how well the clouds fit (arrays over K)."""

    T_world_object: np.ndarray  # (K, 4, 4)
    corrections: np.ndarray  # (K, 2, 6) twist (rotation vector, translation) of each sensor's correction E
    fit_rms_m: np.ndarray  # (K, C) truncated RMS residual of each contact after the corrections
    inlier_fraction: np.ndarray  # (K, C) share of each contact's points within inlier_distance_m of the surface
    free_rms_m: np.ndarray  # (K, C) RMS depth (truncated) of each contact's free-space points inside the object
    correction_cost: np.ndarray  # (K,) Mahalanobis square of both corrections under the calibration prior, plus
    # that of each estimated depth scale's log under its prior
    start_offset: np.ndarray  # (K, 6) twist from the starting pose (object frame)
    depth_scale: np.ndarray = dataclasses.field(default_factory=lambda: np.ones((0, 0)))  # (K, C) each estimated
    # depth scale (1 where its depth is taken as exact; left out: 1 everywhere)

    def __post_init__(self) -> None:
        if self.depth_scale.size == 0:  # left out
            self.depth_scale = np.ones(self.fit_rms_m.shape)

    def subset(self, index: np.ndarray) -> Refined:
        return Refined(*(getattr(self, name)[index] for name in self.__dataclass_fields__))


def thinned(contacts: list[ContactPoints], count: int, free_count: int | None = None) -> list[ContactPoints]:
    """The contacts with at most `count` points each, and at most `free_count` free-space points (None: all; an
    even stride through them; 0: none)."""

    def stride(points: np.ndarray, most: int | None) -> np.ndarray:
        if most is None:
            return points
        return points[:: max(1, -(-len(points) // most))] if most > 0 else points[:0]

    return [
        ContactPoints(
            stride(c.points_sensor, count),
            c.T_world_sensor,
            c.sensor,
            stride(c.free_sensor, free_count),
            c.depth_scale_sigma,
        )
        for c in contacts
    ]


def evaluate_fit(
    field: SurfaceField,
    contacts: list[ContactPoints],
    T_world_object: np.ndarray,
    corrections: np.ndarray | None,
    config: RefineConfig,
    depth_scale: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truncated RMS residual, inlier fraction and free-space violation (each (K, C)) of every contact under K
    poses (and sensor corrections, or none; and each contact's depth scale (K, C), or none: its heights as given)."""
    if KERNELS is not None:  # all contacts in one compiled pass, no (K, M, 3) temporaries
        matrices = np.tile(np.eye(4), (len(T_world_object), 2, 1, 1)) if corrections is None else se3_exp(corrections)
        return _compiled_fit(field, contacts, T_world_object, matrices, depth_scale, config)
    T_object_world = invert_transform(T_world_object)
    rms, inliers, free = [], [], []
    for c, contact in enumerate(contacts):
        T = T_object_world @ contact.T_world_sensor
        if corrections is not None:
            T = T @ se3_exp(corrections[:, contact.sensor])
        factor = depth_scale[:, c] if depth_scale is not None and contact.depth_scale_sigma > 0 else None
        if factor is None:
            q = transform_batch(T, np.vstack([contact.points_sensor, contact.free_sensor]))
        else:  # the points' heights scaled per pose, the free space as it is
            points = _scaled_heights(contact.points_sensor, factor)
            q = transform_batch(
                T,
                np.concatenate(
                    [points, np.broadcast_to(contact.free_sensor, (len(T), *contact.free_sensor.shape))], axis=1
                ),
            )
        distance, _ = field.distance(q, with_gradient=False)
        count = len(contact.points_sensor)
        magnitude = np.abs(distance[:, :count])
        limit = np.full(magnitude.shape, config.fit_tau_m)
        if config.skirt_tau_m is not None:
            heights = np.broadcast_to(contact.points_sensor[:, 2], (len(T), count))
            if factor is not None:
                heights = heights * factor[:, None]  # as `_scaled_heights` scales them
            skirt = _on_skirt(
                field,
                T,
                contact.points_sensor,
                distance[:, :count],
                heights,
                config.inlier_distance_m,
                config.skirt_tau_m,
            )
            limit[skirt] = config.skirt_tau_m
        rms.append(np.sqrt(np.mean(np.minimum(magnitude, limit) ** 2, axis=1)))
        inliers.append(np.mean(magnitude < config.inlier_distance_m, axis=1))
        depth = np.clip(-distance[:, count:], 0.0, config.free_tau_m)
        free.append(np.sqrt(np.mean(depth**2, axis=1)) if depth.shape[1] else np.zeros(len(T)))
    return np.stack(rms, axis=1), np.stack(inliers, axis=1), np.stack(free, axis=1)


def _on_skirt(
    field: SurfaceField,
    T: np.ndarray,
    points_sensor: np.ndarray,
    distance: np.ndarray,
    heights: np.ndarray,
    touching_m: float,
    clearance_m: float,
) -> np.ndarray:
    """(K, M) which of a contact's (M, 3) points lie on the gel's skirt under K poses T (K, 4, 4) (object <- sensor),
    given their distances and heights (K, M; heights below the pad plane negative): outside the object, no deeper
    than the deepest point within `touching_m` of it (the gel sinks in beside a contact, never deeper than the
    contact itself: a cloud floating clear of the object has no skirt), and their foot on the undeformed pad plane
    more than `clearance_m` outside too (the object does not reach the gel there: the point touches nothing; a foot
    within a contact point's error of the surface, a shallow point at the cloud's edge, tells nothing)."""
    feet = np.column_stack([points_sensor[:, :2], np.zeros(len(points_sensor))])
    foot_distance, _ = field.distance(transform_batch(T, feet), with_gradient=False)
    deepest = np.max(np.where(np.abs(distance) < touching_m, -heights, -np.inf), axis=1, keepdims=True)
    return (distance > 0.0) & (-heights <= deepest) & (foot_distance > clearance_m)


def _packed(contacts: list[ContactPoints]) -> tuple[np.ndarray, ...]:
    """The contacts as the compiled loops read them: all points (sum M, 3) and where each contact's start (C + 1,),
    the same for the free-space points, each contact's T_world_sensor (C, 4, 4) and sensor (C,)."""
    points, free = (
        [np.asarray(getattr(contact, name), dtype=np.float64) for contact in contacts]
        for name in ("points_sensor", "free_sensor")
    )
    return (
        np.ascontiguousarray(np.concatenate(points)),
        np.cumsum([0] + [len(part) for part in points]),
        np.ascontiguousarray(np.concatenate(free)),
        np.cumsum([0] + [len(part) for part in free]),
        np.stack([contact.T_world_sensor for contact in contacts]),
        np.array([contact.sensor for contact in contacts]),
    )


def _compiled_fit(
    field: SurfaceField,
    contacts: list[ContactPoints],
    T_world_object: np.ndarray,
    corrections: np.ndarray,
    depth_scale: np.ndarray | None,
    config: RefineConfig,
    packed: tuple[np.ndarray, ...] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`evaluate_fit` by `kernels.fit_all`, the corrections as matrices (K, 2, 4, 4); `packed`: `_packed(contacts)`
    where the caller has it."""
    count = len(T_world_object)
    scaled = np.array([contact.depth_scale_sigma > 0 and depth_scale is not None for contact in contacts])
    scores = np.empty((len(contacts), count, 3))
    assert KERNELS is not None
    KERNELS.fit_all(
        *field.kernel_arguments(),
        *(packed or _packed(contacts)),
        np.ascontiguousarray(T_world_object, dtype=np.float64),
        np.ascontiguousarray(corrections, dtype=np.float64),
        np.ones((count, len(contacts))) if depth_scale is None else np.ascontiguousarray(depth_scale, dtype=np.float64),
        scaled,
        config.fit_tau_m,
        config.inlier_distance_m,
        config.free_tau_m,
        -1.0 if config.skirt_tau_m is None else config.skirt_tau_m,
        scores,
    )
    return scores[:, :, 0].T, scores[:, :, 1].T, scores[:, :, 2].T


def evaluate_offsets(
    field: SurfaceField,
    contacts: list[ContactPoints],
    T_world_object: np.ndarray,
    prior: CalibrationPrior,
    config: RefineConfig,
) -> np.ndarray:
    """A cheap score (K,) of K unrefined poses, higher is better.

    Each cloud may sit off the surface by an offset along the normal and a small tilt (what a sensor's calibration
    error, and a seed's own error, do to it): a plane a + b x + c y (sensor x, y) is fitted to its points' signed
    distances; what remains is the shape's disagreement (truncated at `fit_tau_m`; with `verify_capture_truncated`
    a point beyond the capture range `max_distance_m` touches nothing and counts as truncated: the field is
    clamped there, and a cloud that floats clear of the surface reads as one lying flat at an offset), and the
    offset and tilt are penalised by the calibration prior and the seed's own `seed_offset_m`, `seed_tilt_rad`.
    Free space: the contact's free-space points, moved by the cloud's offset, may not lie inside the object (a seed
    that slides a contact along a face, away from the edge the pad saw, puts the object where the pad felt
    nothing). Uses `verify_points` points and `verify_free_points` free-space points per contact.
    """
    T_object_world = invert_transform(np.asarray(T_world_object, dtype=np.float64).reshape(-1, 4, 4))
    offset_std = np.hypot(max(prior.translation_m, 1e-5) / _MEAN_NORM_3D, config.seed_offset_m)
    tilt_std = np.hypot(max(prior.rotation_rad, 1e-4) * _ANGLE_TO_AXIS_STD, config.seed_tilt_rad)
    score = np.zeros(len(T_object_world))
    for contact in thinned(contacts, config.verify_points, config.verify_free_points):
        points = contact.points_sensor
        centred = points[:, :2] - points[:, :2].mean(axis=0)
        design = np.column_stack([np.ones(len(points)), centred])
        if KERNELS is not None:  # pose by pose, no (K, M) temporaries
            KERNELS.offset_scores(
                *field.kernel_arguments(),
                T_object_world @ contact.T_world_sensor,
                np.ascontiguousarray(points, dtype=np.float64),
                np.ascontiguousarray(contact.free_sensor, dtype=np.float64),
                design,
                np.linalg.pinv(design),
                config.fit_tau_m,
                config.max_distance_m,
                config.verify_capture_truncated,
                config.surface_noise_m,
                offset_std,
                tilt_std,
                config.verify_free_noise_m,
                config.free_tau_m,
                score,
            )
            continue
        q = transform_batch(T_object_world @ contact.T_world_sensor, np.vstack([points, contact.free_sensor]))
        distance, _ = field.distance(q, with_gradient=False)
        distance, free_distance = distance[:, : len(points)], distance[:, len(points) :]
        plane = distance @ np.linalg.pinv(design).T  # (K, 3): offset, tilt x, tilt y
        residual = np.minimum(np.abs(distance - plane @ design.T), config.fit_tau_m)
        if config.verify_capture_truncated:
            residual[np.abs(distance) >= config.max_distance_m] = config.fit_tau_m
        spread = np.sqrt(np.mean(residual**2, axis=1))
        score -= 0.5 * (
            (spread / config.surface_noise_m) ** 2
            + (plane[:, 0] / offset_std) ** 2
            + np.sum(plane[:, 1:] ** 2, axis=1) / tilt_std**2
        )
        if free_distance.shape[1]:  # the free space moved with the cloud's offset (a tilt fitted over the small
            # contact is not trusted across the pad)
            depth = np.clip(plane[:, :1] - free_distance, 0.0, config.free_tau_m)
            score -= 0.5 * np.mean(depth**2, axis=1) / config.verify_free_noise_m**2
    return score


def refine_hypotheses(
    field: SurfaceField,
    contacts: list[ContactPoints],
    T_world_object: np.ndarray,
    prior: CalibrationPrior,
    config: RefineConfig,
    corrections_start: np.ndarray | None = None,
) -> Refined:
    """Refine K object poses (K, 4, 4) jointly with a correction per sensor (see the module docstring), each
    correction starting from `corrections_start` (K, 2, 6) twists where given (e.g. what an earlier refinement of
    the same sensors found), else from none.

    A contact with `depth_scale_sigma` > 0 also gets a depth scale s = exp(u), u ~ N(0, depth_scale_sigma): its
    points (x, y, z) are read as (x, y, s z), heights scaled along the sensor's normal about the pad plane (an image
    reconstruction's depth is known only up to such a factor). Without such contacts the system and its results
    are exactly those of the 18 parameters alone."""
    poses = np.array(T_world_object, dtype=np.float64).reshape(-1, 4, 4)
    start_inverse = invert_transform(poses)
    count = len(poses)
    scaled = [c for c, contact in enumerate(contacts) if contact.depth_scale_sigma > 0]
    size = 18 + len(scaled)
    corrections = np.tile(np.eye(4), (count, 2, 1, 1))  # E per side
    information = _prior_information(contacts, prior, config)
    calibration = prior.information()
    scale_information = np.diag(information)[18:]
    log_scale = np.zeros((count, len(contacts)))
    deviation = np.zeros((count, size))  # twists from the start and of the corrections, accumulated to first order
    if corrections_start is not None:
        corrections = se3_exp(np.asarray(corrections_start, dtype=np.float64).reshape(count, 2, 6))
        deviation[:, 6:18] = np.asarray(corrections_start).reshape(count, 12)
    if KERNELS is not None:  # every iteration in one compiled call (the same steps, no per-iteration numpy calls)
        packed = _packed(contacts)
        points, starts, _, _, T_world_sensor, sensor = packed
        rows = np.full(len(contacts), -1)  # each contact's depth scale's row in the system (-1: none)
        rows[scaled] = 18 + np.arange(len(scaled))
        iterations = KERNELS.refine_loop(
            *field.kernel_arguments(),
            points,
            starts,
            T_world_sensor,
            sensor,
            rows,
            information,
            poses,
            corrections,
            deviation,
            log_scale,
            config.iterations,
            config.step_tolerance,
            config.max_distance_m,
            config.surface_noise_m,
            1.0 / config.surface_noise_m**2,
        )
        if iterations < 0:
            raise np.linalg.LinAlgError("Singular matrix")
        field.count_gradient_reads(iterations * len(contacts))
    else:
        for _ in range(config.iterations):
            hessian = np.broadcast_to(information, (count, size, size)).copy()
            gradient = deviation @ information
            depth_scale = np.exp(log_scale) if scaled else None
            _add_normal_equations(field, contacts, poses, corrections, config, hessian, gradient, depth_scale)
            step = -np.linalg.solve(hessian, gradient[:, :, None])[:, :, 0]
            deviation += step
            updates = se3_exp(step[:, :18].reshape(count, 3, 6))
            poses = poses @ updates[:, 0]
            corrections = corrections @ updates[:, 1:]
            log_scale[:, scaled] += step[:, 18:]
            if np.abs(step).max() < config.step_tolerance:
                break
    # both corrections and the offset from the start at once (one call)
    twists = se3_log(np.concatenate([corrections, (start_inverse @ poses)[:, None]], axis=1))
    correction_twists, start_offset = np.ascontiguousarray(twists[:, :2]), np.ascontiguousarray(twists[:, 2])
    depth_scale = np.exp(log_scale)
    if KERNELS is not None:
        fit = _compiled_fit(field, contacts, poses, corrections, depth_scale if scaled else None, config, packed)
    else:
        fit = evaluate_fit(field, contacts, poses, correction_twists, config, depth_scale if scaled else None)
    correction_cost = np.einsum("ksi,i,ksi->k", correction_twists, calibration, correction_twists)
    if scaled:
        correction_cost = correction_cost + log_scale[:, scaled] ** 2 @ scale_information
    return Refined(poses, correction_twists, *fit, correction_cost, start_offset, depth_scale)


def _prior_information(contacts: list[ContactPoints], prior: CalibrationPrior, config: RefineConfig) -> np.ndarray:
    """(18 + S, 18 + S) the refinement's prior information: the starting pose (weak), each sensor's correction
    (the calibration prior), the log depth scale of each of the S contacts with `depth_scale_sigma` > 0."""
    scaled = [contact.depth_scale_sigma for contact in contacts if contact.depth_scale_sigma > 0]
    calibration = prior.information()
    pose = [1.0 / config.prior_rotation_rad**2] * 3 + [1.0 / config.prior_translation_m**2] * 3
    return np.diag(np.concatenate([pose, calibration, calibration, 1.0 / np.square(scaled)]))


def pose_covariance(
    field: SurfaceField,
    contacts: list[ContactPoints],
    refined: Refined,
    index: int,
    prior: CalibrationPrior,
    config: RefineConfig,
) -> np.ndarray:
    """(6, 6) covariance of refined pose `index`'s twist (rotation vector, translation; object frame): the inverse
    of the refinement's Gauss-Newton information there, the sensor corrections and depth scales marginalised. Large
    along what the clouds leave free (a cylinder's axis, a flat face's plane), held there only by the weak prior on
    the starting pose."""
    information = _prior_information(contacts, prior, config)
    hessian = information[None].copy()
    gradient = np.zeros((1, len(information)))
    corrections = se3_exp(refined.corrections[index][None])
    _add_normal_equations(
        field,
        contacts,
        refined.T_world_object[index][None],
        corrections,
        config,
        hessian,
        gradient,
        refined.depth_scale[index][None] if len(information) > 18 else None,
    )
    return np.linalg.inv(hessian[0])[:6, :6]


def _scaled_heights(points_sensor: np.ndarray, depth_scale: np.ndarray) -> np.ndarray:
    """(K, M, 3) the points (M, 3) with their heights (z, about the pad plane) scaled by each of K factors."""
    points = np.broadcast_to(points_sensor, (len(depth_scale),) + points_sensor.shape).copy()
    points[..., 2] *= depth_scale[:, None]
    return points


def _add_normal_equations(
    field: SurfaceField,
    contacts: list[ContactPoints],
    poses: np.ndarray,
    corrections: np.ndarray,
    config: RefineConfig,
    hessian: np.ndarray,
    gradient: np.ndarray,
    depth_scale: np.ndarray | None = None,
) -> None:
    """Add the clouds' robustly weighted Gauss-Newton system into `hessian` (K, 18 + S, 18 + S) and `gradient`
    (K, 18 + S): the object pose's twist, then each sensor's correction, at K poses (K, 4, 4) and corrections
    (K, 2, 4, 4); then the log depth scale of each of the S contacts with `depth_scale_sigma` > 0, in order, at
    `depth_scale` (K, C) (None: there are none)."""
    T_object_world = invert_transform(poses)
    weight_scale = 1.0 / config.surface_noise_m**2
    scale_row = 18
    for c, contact in enumerate(contacts):
        s = contact.sensor
        A = T_object_world @ contact.T_world_sensor @ corrections[:, s]  # object <- sensor
        factor = depth_scale[:, c] if depth_scale is not None and contact.depth_scale_sigma > 0 else None
        if KERNELS is not None:  # the same sums and products in one compiled pass, no (K, M, 6) temporaries
            field.count_gradient_reads(1)
            KERNELS.add_normal_equations(
                *field.kernel_arguments(),
                A,
                np.ascontiguousarray(contact.points_sensor, dtype=np.float64),
                np.ones(len(A)) if factor is None else np.ascontiguousarray(factor, dtype=np.float64),
                config.max_distance_m,
                config.surface_noise_m,
                weight_scale,
                6 + 6 * s,
                -1 if factor is None else scale_row,
                hessian,
                gradient,
            )
            if factor is not None:
                scale_row += 1
            continue
        points = contact.points_sensor if factor is None else _scaled_heights(contact.points_sensor, factor)
        q = transform_batch(A, points)
        r, n = field.distance(q)
        assert n is not None
        magnitude = np.abs(r)
        use = magnitude < config.max_distance_m
        w = huber_weights(magnitude, use, config.surface_noise_m) * weight_scale
        # The residuals of one contact depend on the object pose and on its sensor's correction only. Their
        # rows for the object pose are a = (n x q, -n); for the correction (p x m, m), with m = R^T n the
        # normal in the sensor frame (A = [R | t]), which is M a, M = [[-R^T, R^T [t]x], [0, -R^T]] (the
        # adjoint): so only the 6 x 6 normal equations B = a^T W a are summed over points, and the 12 x 12
        # block is [[B, B M^T], [M B, M B M^T]].
        J = np.empty(q.shape[:2] + (6,))
        cross_into(n, q, J[..., 0:3])
        np.negative(n, out=J[..., 3:6])
        weighted = np.swapaxes(J * w[..., None], 1, 2)
        block = weighted @ J
        g = (weighted @ r[..., None])[..., 0]
        rotation_t = np.swapaxes(A[:, :3, :3], 1, 2)
        adjoint = np.zeros((len(A), 6, 6))
        adjoint[:, :3, :3] = -rotation_t
        adjoint[:, :3, 3:] = rotation_t @ skew(A[:, :3, 3])
        adjoint[:, 3:, 3:] = -rotation_t
        coupled = adjoint @ block  # M B
        side = slice(6 + 6 * s, 12 + 6 * s)  # this sensor's correction
        hessian[:, :6, :6] += block
        hessian[:, :6, side] += np.swapaxes(coupled, 1, 2)
        hessian[:, side, :6] += coupled
        hessian[:, side, side] += coupled @ np.swapaxes(adjoint, 1, 2)
        gradient[:, :6] += g
        gradient[:, side] += (adjoint @ g[:, :, None])[..., 0]
        if factor is not None:
            # d r / d log s = n . (R e_z) s z: the normal in the sensor frame (m = R^T n) along z, times the height
            along = np.einsum("kmi,ki->km", n, A[:, :3, 2]) * points[..., 2]
            row = (weighted @ along[..., None])[..., 0]  # a^T W j
            hessian[:, :6, scale_row] += row
            hessian[:, scale_row, :6] += row
            moved = (adjoint @ row[..., None])[..., 0]
            hessian[:, side, scale_row] += moved
            hessian[:, scale_row, side] += moved
            hessian[:, scale_row, scale_row] += np.sum(w * along**2, axis=1)
            gradient[:, scale_row] += np.sum(w * along * r, axis=1)
            scale_row += 1
