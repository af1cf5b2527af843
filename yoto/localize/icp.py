"""The geometry-only baseline: multi-start point-to-plane ICP of the tactile cloud onto the parent cloud.

Paper Sec. 4 and App. D compare YOTO with "multi-start point-to-plane ICP with 30 starts" (Open3D). The paper
does not say how the starts are drawn or how the registrations are ranked; this module decides, and says so:

Starts (normal-aware, geometry only). The tactile cloud's contact centre c_sensor and outward normal
n_sensor come from `contact_in_sensor`. A start picks a random parent point q (uniform over the surface, as
the parent cloud is area-uniform), rotates n_sensor onto q's parent normal, spins the patch by a random
angle about that normal, and puts c_sensor on q. Every start therefore already touches the surface from
outside; ICP only has to slide and spin the patch. Random rotations in SO(3) would waste most of the 30
starts on poses where the sensor faces into the object.

Registration. Open3D's legacy `registration_icp` with `TransformationEstimationPointToPlane` (the source
is the voxel-downsampled tactile cloud in the sensor frame, the target the parent cloud with its normals in
the object frame; the result is T_object_sensor). The legacy call builds a KD-tree on its target every
time, so each start registers against the parent points within a ball around its start location (the
patch's radius plus `crop_margin_m`), cut from a full cloud cached per model. The ball is also a trust
region: a start cannot wander off to a place another start covers. (The tensor API, `o3d.t...icp`, was two to
three times slower here on CPU and returned the identity, a failed solve, on flat patches.)

Point-to-plane ICP is singular on flat and cylindrical patches: motion along the surface costs nothing, and
Open3D's solver then steps to poses metres away. A run whose result fits worse than its start keeps its
start (`Registration.refined` is False). `estimation="generalized"` swaps in Open3D's generalized
(plane-to-plane) ICP, which stays well-posed there, for comparison; the paper's objective is the default.

Score. Open3D's own `fitness` and `inlier_rmse` are point-to-point, so on a parent cloud of spacing s every
registration, right or wrong, reports an RMSE near s / 2: they cannot rank starts. Each registration is
instead scored against the full parent cloud by a truncated point-to-plane residual: a tactile point is an
inlier when its nearest parent point is within tau (`inlier_distance_m`) and the two normals agree; its
residual is its point-to-plane distance, capped at tau; an outlier counts tau. The truncated RMS residual
r = sqrt(mean(residual^2)) combines fit and coverage in one number (fitness * rmse^2 + (1 - fitness) * tau^2
under the square root). `score = 1 - r / tau` lies in [0, 1], 1 for a perfect fit.

Belief. Distinct registrations get beliefs from their residuals exactly as the matched filter's candidates do
(`yoto.localize.ranking`): T = 0.1 mm, a few times the 0.02-0.03 mm residual of a right fit of a simulated cloud
with 0.03 mm noise (real GelSight residuals are not measured yet), a "none of these" residual of 0.3 mm. Set both
(`IcpConfig.belief`) to your sensor's residual scale.

Convergence. Open3D stops a run when fitness and inlier RMSE change by less than `convergence_tolerance`
between iterations; the comparison is absolute (despite the names `relative_*`), and the RMSE is in metres.
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from yoto.contacts import ContactEstimate, contact_in_sensor, validate_tactile_points
from yoto.errors import DegenerateGeometryError, InputError, require_open3d
from yoto.geometry import make_transform, rotate_vectors, rotation_about_axis, rotation_between, transform_points
from yoto.localize.ranking import BeliefConfig, rank_registrations
from yoto.objects.model import ObjectModel
from yoto.patches.canonical import prepare_tactile_cloud
from yoto.registration import truncated_plane_fit

MIN_SOURCE_POINTS = 10  # fewer down-sampled tactile points leave point-to-plane ICP underdetermined or noise-fitted
ESTIMATIONS = ("point_to_plane", "generalized")
COVARIANCE_NEIGHBOURS = 20  # k of the local covariances generalized ICP needs (Open3D's usual choice)


@dataclass(frozen=True)
class IcpConfig:
    """Multi-start point-to-plane ICP (paper Sec. 4: 30 starts, Open3D)."""

    num_starts: int = 30  # ICP runs per contact (paper: 30)
    estimation: str = "point_to_plane"  # the paper's objective; or "generalized" (Open3D's plane-to-plane ICP)
    max_iterations: int = 30  # ICP iterations per start
    convergence_tolerance: float = 1e-6  # stop when fitness and inlier RMSE (metres!) change less than this per step
    max_correspondence_m: float = 0.003  # ICP pairs points no further apart than this
    crop_margin_m: float = 0.005  # each start registers to the parent points within patch radius + this
    voxel_spacing_m: float | None = None  # tactile-cloud voxel size; None: the model's point spacing
    inlier_distance_m: float | None = None  # tau of the score; None: twice the voxel spacing, at least 1 mm
    belief: BeliefConfig = BeliefConfig(num_candidates=5)  # distinct registrations and their beliefs
    normal_neighbours: int = 20  # k of the kNN-aggregated model normal at a candidate
    seed: int = 0  # start sampling seed (mixed with a hash of the tactile cloud)

    def __post_init__(self):
        if self.num_starts < 1 or self.max_iterations < 1:
            raise InputError("num_starts and max_iterations must be at least 1")
        if self.estimation not in ESTIMATIONS:
            raise InputError(f"unknown ICP estimation {self.estimation!r} (use one of {', '.join(ESTIMATIONS)})")
        if self.max_correspondence_m <= 0 or self.crop_margin_m < 0:
            raise InputError("max_correspondence_m must be positive, crop_margin_m non-negative")


@dataclass
class Registration:
    """One ICP run: where it ended and how well the tactile cloud fits there."""

    T_object_sensor: np.ndarray  # (4, 4) registered pose of the sensor in the object frame
    T_object_sensor_start: np.ndarray  # (4, 4) where it started
    residual_m: float  # truncated RMS point-to-plane residual over all tactile points
    fitness: float  # fraction of tactile points with an inlier correspondence
    inlier_rmse_m: float  # RMS point-to-plane distance over the inliers (0 when there are none)
    score: float  # 1 - residual / tau, in [0, 1]
    refined: bool  # False when ICP ended worse than it started (it diverged) and the start was kept


_TARGETS: dict[str, Any] = {}  # model fingerprint -> open3d.geometry.PointCloud with normals, object frame
_TARGETS_LOCK = threading.Lock()
_TARGET_CACHE_SIZE = 8


def _target(model: ObjectModel, covariances: bool = False):
    """The cached Open3D parent cloud of a model (keyed by its fingerprint), with covariances if asked."""
    o3d = require_open3d("the ICP baseline")
    key = model.fingerprint
    with _TARGETS_LOCK:
        cloud = _TARGETS.get(key)
        if cloud is None:
            cloud = o3d.geometry.PointCloud(
                o3d.utility.Vector3dVector(np.ascontiguousarray(model.points_object, dtype=np.float64))
            )
            cloud.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(model.normals_object, dtype=np.float64))
            if len(_TARGETS) >= _TARGET_CACHE_SIZE:
                _TARGETS.pop(next(iter(_TARGETS)))
            _TARGETS[key] = cloud
        if covariances and not cloud.has_covariances():
            cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(COVARIANCE_NEIGHBOURS))
    return cloud


def clear_cache() -> None:
    """Forget the cached Open3D parent clouds (they are rebuilt on the next call)."""
    with _TARGETS_LOCK:
        _TARGETS.clear()


def sample_starts(
    model: ObjectModel,
    c_sensor: np.ndarray,
    n_sensor: np.ndarray,
    count: int,
    rng: np.random.Generator,
    allowed: np.ndarray | None = None,
) -> np.ndarray:
    """(count, 4, 4) starting T_object_sensor: contact centre on a random parent point, normals aligned.

    Each start maps the tactile contact centre `c_sensor` onto a random parent point q and its outward
    normal `n_sensor` onto q's parent normal, with a uniformly random spin about that normal. `allowed`
    restricts q to these parent-point indices (default: the whole surface).
    """
    pool = np.arange(len(model.points_object)) if allowed is None else np.asarray(allowed)
    if len(pool) == 0:
        raise InputError("no parent points to start ICP from")
    indices = pool[rng.integers(len(pool), size=count)]
    spins = rng.uniform(0.0, 2.0 * np.pi, size=count)
    starts = np.empty((count, 4, 4))
    for i, (index, spin) in enumerate(zip(indices, spins, strict=True)):
        q_object = model.points_object[index].astype(np.float64)
        n_object = model.normals_object[index].astype(np.float64)
        rotation = rotation_about_axis(n_object, spin) @ rotation_between(n_sensor, n_object)
        starts[i] = make_transform(rotation, q_object - rotation @ c_sensor)
    return starts


def registration_residual(
    points_sensor: np.ndarray,
    normals_sensor: np.ndarray,
    T_object_sensor: np.ndarray,
    model: ObjectModel,
    tau_m: float,
) -> tuple[float, float, float]:
    """Truncated RMS point-to-plane residual, fitness and inlier RMSE of a registered tactile cloud.

    See the module docstring; all three are measured against the full parent cloud, so they rank
    registrations from different starts on the same footing.
    """
    fit = truncated_plane_fit(
        model,
        transform_points(T_object_sensor, points_sensor)[None],
        tau_m,
        facing_surface=rotate_vectors(T_object_sensor, normals_sensor)[None],
    )
    return float(fit.rms_m[0]), float(fit.inlier_fraction[0]), float(fit.inlier_rms_m[0])


def _input_seed(points_sensor: np.ndarray) -> int:
    """A stable integer from the tactile cloud's bytes: different contacts get different starts."""
    digest = hashlib.blake2b(np.ascontiguousarray(points_sensor, dtype=np.float64).tobytes(), digest_size=8)
    return int.from_bytes(digest.digest(), "little")


class IcpLocalizer:
    """Multi-start point-to-plane ICP of the tactile cloud onto the parent cloud (the paper's baseline)."""

    name = "icp"
    needs_ground_truth = False

    def __init__(self, config: IcpConfig = IcpConfig()):
        self.config = config

    # ------------------------------------------------------------------------------------------ public API
    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        """Ranked contact candidates (object frame), best first. `truth_p_object` is ignored."""
        points_sensor = self._check_points(points_sensor)
        c_sensor, n_sensor = contact_in_sensor(points_sensor)
        rng = np.random.default_rng([self.config.seed, _input_seed(points_sensor)])
        starts = sample_starts(model, c_sensor, n_sensor, self.config.num_starts, rng)
        return self.localize_from(points_sensor, model, starts, contact=(c_sensor, n_sensor))

    def localize_from(
        self,
        points_sensor: np.ndarray,
        model: ObjectModel,
        starts_T_object_sensor: np.ndarray,
        contact: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> list[ContactEstimate]:
        """Like `localize`, from given starting poses (S, 4, 4) T_object_sensor instead of sampled ones."""
        points_sensor = self._check_points(points_sensor)
        c_sensor, _ = contact if contact is not None else contact_in_sensor(points_sensor)
        registrations = self.register(points_sensor, model, starts_T_object_sensor, c_sensor)
        return self._candidates(registrations, model, c_sensor)

    def register(
        self,
        points_sensor: np.ndarray,
        model: ObjectModel,
        starts_T_object_sensor: np.ndarray,
        c_sensor: np.ndarray | None = None,
    ) -> list[Registration]:
        """Run ICP from every start; registrations in start order, each scored against the full parent cloud."""
        o3d = require_open3d("the ICP baseline")
        registration = o3d.pipelines.registration
        points_sensor = self._check_points(points_sensor)
        if c_sensor is None:
            c_sensor, _ = contact_in_sensor(points_sensor)
        spacing = self._spacing(model)
        tau = self._tau(model)
        source_points, source_normals = prepare_tactile_cloud(points_sensor, spacing)
        if len(source_points) < MIN_SOURCE_POINTS:
            raise DegenerateGeometryError(
                f"the tactile cloud holds only {len(source_points)} points at the model's {spacing * 1000:.2f} mm "
                f"spacing; ICP needs at least {MIN_SOURCE_POINTS} (is the contact too small or the cloud in mm?)"
            )
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source_points))
        generalized = self.config.estimation == "generalized"
        target = _target(model, covariances=generalized)
        crop_radius = float(np.linalg.norm(source_points - c_sensor, axis=1).max()) + self.config.crop_margin_m
        criteria = registration.ICPConvergenceCriteria(
            # Open3D compares absolute changes despite the names; the RMSE is in metres, so 1e-6 is 1 micron.
            relative_fitness=self.config.convergence_tolerance,
            relative_rmse=self.config.convergence_tolerance,
            max_iteration=self.config.max_iterations,
        )
        if generalized:
            source.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(COVARIANCE_NEIGHBOURS))
            estimation, run_icp = (
                registration.TransformationEstimationForGeneralizedICP(),
                registration.registration_generalized_icp,
            )
        else:
            estimation, run_icp = registration.TransformationEstimationPointToPlane(), registration.registration_icp
        results = []
        for start in np.asarray(starts_T_object_sensor, dtype=np.float64).reshape(-1, 4, 4):
            centre_object = transform_points(start, c_sensor)
            members = model.kdtree.query_ball_point(centre_object, crop_radius)  # a list: select_by_index is fast
            at_start = registration_residual(source_points, source_normals, start, model, tau)
            T_object_sensor, (residual, fitness, inlier_rmse), refined = start, at_start, False
            if len(members) >= MIN_SOURCE_POINTS:
                crop = target.select_by_index(members)
                result = run_icp(source, crop, self.config.max_correspondence_m, start, estimation, criteria)
                T_result = np.array(result.transformation)
                if np.isfinite(T_result).all():
                    at_result = registration_residual(source_points, source_normals, T_result, model, tau)
                    # Point-to-plane ICP is singular on flat and cylindrical patches (in-plane motion is free) and
                    # can then run off to metres away; a run that ends worse than it started keeps its start.
                    if at_result[0] <= at_start[0]:
                        T_object_sensor, (residual, fitness, inlier_rmse), refined = T_result, at_result, True
            results.append(
                Registration(
                    T_object_sensor=T_object_sensor,
                    T_object_sensor_start=start,
                    residual_m=residual,
                    fitness=fitness,
                    inlier_rmse_m=inlier_rmse,
                    score=1.0 - residual / tau,
                    refined=refined,
                )
            )
        return results

    # ------------------------------------------------------------------------------------------ internals
    def _spacing(self, model: ObjectModel) -> float:
        return self.config.voxel_spacing_m if self.config.voxel_spacing_m is not None else model.point_spacing_m

    def _tau(self, model: ObjectModel) -> float:
        if self.config.inlier_distance_m is not None:
            return self.config.inlier_distance_m
        return max(0.001, 2.0 * self._spacing(model))

    @staticmethod
    def _check_points(points_sensor: np.ndarray) -> np.ndarray:
        """The tactile cloud as float64 (N, 3), or an InputError saying why it cannot be localized."""
        return validate_tactile_points(points_sensor, None)

    def _candidates(
        self, registrations: list[Registration], model: ObjectModel, c_sensor: np.ndarray
    ) -> list[ContactEstimate]:
        """Deduplicate registrations by contact location, attach beliefs, return the best few."""
        config = self.config
        p_all = np.array(
            [model.nearest_surface_point(transform_points(reg.T_object_sensor, c_sensor)) for reg in registrations]
        )
        ranking = rank_registrations(p_all, np.array([reg.residual_m for reg in registrations]), config.belief)
        candidates = []
        for i, probability in zip(ranking.indices, ranking.probabilities, strict=True):
            reg, p_object = registrations[i], p_all[i]
            candidates.append(
                ContactEstimate(
                    p_object=p_object,
                    n_object=model.aggregated_normal(p_object, config.normal_neighbours),
                    block=int(model.block_of_points(p_object)[0]),
                    score=float(reg.score),
                    probability=float(probability),
                    details={
                        "icp_residual_mm": 1000.0 * reg.residual_m,
                        "icp_fitness": reg.fitness,
                        "icp_inlier_rmse_mm": 1000.0 * reg.inlier_rmse_m,
                        "icp_T_object_sensor": reg.T_object_sensor.tolist(),
                        "icp_refined": reg.refined,
                        "icp_distinct_registrations": ranking.distinct,
                    },
                )
            )
        return candidates
