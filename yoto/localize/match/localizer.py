"""The matched-filter localizer: coarse and fine filter passes, per-candidate ICP, ranking."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, replace

import numpy as np

from yoto.contacts import ContactEstimate, validate_tactile_points
from yoto.errors import DegenerateGeometryError
from yoto.geometry import so3_exp
from yoto.localize.match.anchors import AnchorMaps, anchor_maps
from yoto.localize.match.config import MatchConfig
from yoto.localize.match.contact import ContactImage, contact_image, contact_maps
from yoto.localize.match.kernels import KERNELS
from yoto.localize.match.lookup import ParentSurface, one_openmp_thread, parent_surface
from yoto.localize.match.rings import contact_rings, ring_distances
from yoto.localize.match.scores import best_plane_costs, free_space_penalty, free_space_violation, plane_costs
from yoto.localize.ranking import rank_registrations
from yoto.objects.model import ObjectModel
from yoto.registration import GaussNewtonConfig, one_blas_thread, point_to_plane_gauss_newton, truncated_plane_fit

Z_AXIS = np.array([0.0, 0.0, 1.0])
MIN_CONTACT_CELLS = 3  # fewer covered cells leave nothing to match


@dataclass
class FilterHypotheses:
    """The matched filter's shortlist for one contact, best first, after non-maximum suppression."""

    image: ContactImage  # the contact's height image
    anchors: np.ndarray  # (K,) anchor index of each hypothesis
    rolls: np.ndarray  # (K,) roll index (of `MatchConfig.rolls`)
    filter_cost: np.ndarray  # (K,) mean squared height difference (plus free-space penalty), m^2
    poses: np.ndarray  # (K, 4, 4) T_object_sensor of each hypothesis


class MatchLocalizer:
    """Locates a tactile contact by matching its height map against every anchor and roll (no training)."""

    name = "match"
    needs_ground_truth = False
    reads_depth_scale = True  # `localize` takes a reconstructed cloud's depth_scale_sigma (base.localize_cloud)

    def __init__(self, config: MatchConfig = MatchConfig()):
        self.config = config

    def prepare_object(self, model: ObjectModel) -> AnchorMaps:
        parent_surface(model)  # the candidate ICP's k-d tree (tens of milliseconds), built ahead too
        return anchor_maps(model, self.config.anchors)

    def image(self, points_sensor: np.ndarray, model: ObjectModel) -> ContactImage:
        """The contact's height image at this filter's resolution and extent."""
        return contact_image(points_sensor, anchor_maps(model, self.config.anchors).grid.radius_m, self.config)

    def hypotheses(self, image: ContactImage, model: ObjectModel) -> FilterHypotheses:
        """The matched filter's shortlist for a contact image: anchors, rolls, costs and poses (best first, NMS
        applied)."""
        config = self.config
        anchors = anchor_maps(model, config.anchors)
        grid = anchors.grid
        contact = contact_maps(image, grid.centres, config.rolls, config)
        if contact.mask.sum(axis=1).max() < MIN_CONTACT_CELLS:
            raise DegenerateGeometryError(
                f"the tactile contact covers fewer than {MIN_CONTACT_CELLS} height-map cells "
                f"({config.anchors.cell_m * 1000:.2f} mm apart): too small to match (is the cloud in metres?)"
            )
        shortlist = self._shortlist(image, anchors)
        # Fine stage: the shortlist, every cell, every roll, offset and tilt, free space.
        heights = anchors.heights[shortlist]
        best_roll, score, beta = best_plane_costs(
            contact.mask,
            contact.heights,
            anchors.valid[shortlist].T,
            heights.T,
            (heights * heights).T,
            grid.centres,
            config.remove_tilt,
            config.air_penalty_m,
        )
        if config.free_space:
            penalty = free_space_penalty(contact, anchors, shortlist, best_roll, beta, config)
            score = score + penalty / np.maximum(contact.mask.sum(axis=1)[best_roll], 1.0)
        suppressed = np.zeros(len(anchors.points_object), dtype=bool)
        kept: list[int] = []
        for i in np.argsort(score, kind="stable"):
            a = shortlist[i]
            if suppressed[a]:
                continue
            kept.append(int(i))
            suppressed[anchors.neighbours[a]] = True
            if len(kept) >= config.refine_candidates:
                break
        poses = self._poses(image, anchors, shortlist[kept], contact.rolls_rad[best_roll[kept]], beta[:, kept])
        return FilterHypotheses(image, shortlist[kept], best_roll[kept], score[kept], poses)

    def _shortlist(self, image: ContactImage, anchors: AnchorMaps) -> np.ndarray:
        """The anchors the fine stage scores: the `shortlist` best by the roll-free ring distance (rings.py), or,
        when the contact covers fewer than `min_rings` rings (a thin strip, a hole at its centre), by the
        offset-only cost on half the cells at `coarse_rolls` rolls."""
        config = self.config
        count = min(config.shortlist, len(anchors.points_object))
        rings = contact_rings(image, anchors.rings.grid, config.ring_coverage)
        if rings.used.sum() >= config.min_rings:
            distance = ring_distances(anchors.rings, rings)
        else:
            coarse = anchors.grid.coarse
            contact = contact_maps(image, anchors.grid.centres[coarse], config.coarse_rolls, config)
            heights = anchors.heights[:, coarse].T
            cost, _ = plane_costs(
                contact.mask,
                contact.heights,
                anchors.valid[:, coarse].T,
                heights,
                heights * heights,
                anchors.grid.centres[coarse],
                False,
                config.air_penalty_m,
            )
            distance = cost.min(axis=0)
        if count < len(distance):
            return np.sort(np.argpartition(distance, count - 1)[:count])
        return np.arange(len(distance))

    @staticmethod
    def _poses(
        image: ContactImage, anchors: AnchorMaps, index: np.ndarray, roll: np.ndarray, beta: np.ndarray
    ) -> np.ndarray:
        """(K, 4, 4) T_object_sensor of hypotheses: contact local -> (tilt, roll) -> anchor local -> object."""
        frame_anchor = np.stack([anchors.u_object[index], anchors.v_object[index], -anchors.normals_object[index]], 2)
        spin = so3_exp(np.stack([-beta[2], beta[1], np.zeros(len(index))], axis=1)) @ so3_exp(roll[:, None] * Z_AXIS)
        rotation = frame_anchor @ spin @ image.basis_sensor.T
        origin = anchors.points_object[index] + beta[0][:, None] * anchors.normals_object[index]
        poses = np.zeros((len(index), 4, 4))
        poses[:, :3, :3] = rotation
        poses[:, :3, 3] = origin - rotation @ image.centre_sensor
        poses[:, 3, 3] = 1.0
        return poses

    def localize(
        self,
        points_sensor: np.ndarray,
        model: ObjectModel,
        truth_p_object: np.ndarray | None = None,
        depth_scale_sigma: float = 0.0,
    ) -> list[ContactEstimate]:
        """Ranked candidate contacts (`ContactEstimate`, best first) of a tactile cloud on the model.

        A cloud reconstructed from an image (`depth_scale_sigma` > 0, as `TactileContact.depth_scale_sigma`) is
        matched at each of `image_depth_scales` (`localize_scaled`). The filter's matrix products are small: BLAS
        runs them on one thread. (Its threads wait for one another, and on a busy machine a product that takes 2 ms
        alone took 50 ms on two threads.)
        """
        points_sensor = validate_tactile_points(points_sensor, None)
        if self.scales_depth(depth_scale_sigma):
            return self.localize_scaled(points_sensor, model)
        return self.localize_image(self.image(points_sensor, model), model)

    def scales_depth(self, depth_scale_sigma: float) -> bool:
        """Whether a cloud with this `depth_scale_sigma` is matched at several depth scales."""
        return depth_scale_sigma > 0 and self.config.image_depth_scales != (1.0,)

    def localize_image(self, image: ContactImage, model: ObjectModel) -> list[ContactEstimate]:
        """`localize` from the contact's height image (`image`)."""
        with one_blas_thread(), one_openmp_thread():
            return self.refine(self.hypotheses(image, model), model)

    def localize_scaled(
        self, points_sensor: np.ndarray, model: ObjectModel, image: ContactImage | None = None
    ) -> list[ContactEstimate]:
        """`localize` of a cloud whose depth is uncertain: its heights below the pad (-z_sensor) times each of
        `image_depth_scales`, each matched and refined as a cloud of its own, and all their registrations ranked
        together. Each candidate's `T_object_sensor` is that of its scaled cloud (`match_depth_scale`). `image`: the
        cloud's own height image (`self.image`), where the caller made it already, serves its scale 1."""

        def scaled_image(scale: float) -> ContactImage:
            if scale == 1.0 and image is not None:
                return image
            return self.image(scaled_depth(points_sensor, scale), model)

        scales = self.config.image_depth_scales
        with one_blas_thread(), one_openmp_thread():
            fits = [self._fitted(self.hypotheses(scaled_image(scale), model), model) for scale in scales]
        merged = _Fitted(
            *(np.concatenate([getattr(fit, field.name) for fit in fits]) for field in dataclasses.fields(_Fitted))
        )
        scale = np.concatenate([np.full(len(fit.residual), s) for fit, s in zip(fits, scales, strict=True)])
        return self._estimates(merged, model, scale)

    def refine(self, found: FilterHypotheses, model: ObjectModel) -> list[ContactEstimate]:
        """The filter's hypotheses refined by ICP, checked for free space, ranked and given beliefs."""
        return self._estimates(self._fitted(found, model), model)

    def _fitted(self, found: FilterHypotheses, model: ObjectModel) -> _Fitted:
        """The filter's hypotheses refined by ICP, their residuals and free-space violations, and where each puts the
        contact on the surface.

        Every hypothesis is refined on `icp_points` tactile points; the best `polish_candidates` distinct ones
        again on `polish_points` (more points average the noise: a more precise location and residual).
        """
        config = self.config
        image = found.image
        surface = parent_surface(model)
        samples = self._samples(image, config.icp_points)
        poses = found.poses
        if config.refine:
            poses = candidate_icp(surface, samples, poses, config.icp, image, keep_best=config.icp_keep)
        residual, violation = self._fit(model, image, samples, poses)
        ranking = self._rank(model, image, poses, residual, violation)
        if config.refine and config.polish_candidates > 0:
            best = np.asarray(ranking.indices[: config.polish_candidates], dtype=np.int64)
            samples = self._samples(image, config.polish_points)
            polish = replace(config.icp, iterations=config.polish_iterations)
            poses[best] = candidate_icp(surface, samples, poses[best], polish, image)
            residual[best], violation[best] = self._fit(model, image, samples, poses[best])
            ranking = self._rank(model, image, poses, residual, violation)
        return _Fitted(found.anchors, found.rolls, found.filter_cost, poses, residual, violation, ranking.p_object)

    def _estimates(
        self, fit: _Fitted, model: ObjectModel, depth_scale: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        """Ranked distinct candidates with beliefs of refined registrations (with `depth_scale`, each registration's
        depth scale, reported as `match_depth_scale`)."""
        config = self.config
        poses, residual, violation, p_all = fit.poses, fit.residual, fit.violation, fit.p_object
        total = np.sqrt(residual**2 + violation)
        ranking = rank_registrations(p_all, total, config.belief)
        chosen = np.asarray(ranking.indices, dtype=np.int64)
        normals = model.aggregated_normal(p_all[chosen], config.normal_neighbours)
        blocks = model.block_of_points(p_all[chosen])
        out = []
        for j, (i, probability) in enumerate(zip(chosen, ranking.probabilities, strict=True)):
            out.append(
                ContactEstimate(
                    p_object=p_all[i],
                    n_object=normals[j],
                    block=int(blocks[j]),
                    score=float(1.0 - min(total[i], config.residual_tau_m) / config.residual_tau_m),
                    probability=float(probability),
                    details={
                        "match_anchor": int(fit.anchors[i]),
                        "match_roll_deg": float(np.degrees(2.0 * np.pi * fit.rolls[i] / config.rolls)),
                        "match_filter_rms_mm": 1000.0 * float(np.sqrt(max(fit.filter_cost[i], 0.0))),
                        "match_residual_mm": 1000.0 * float(residual[i]),
                        "match_free_space_mm": 1000.0 * float(np.sqrt(violation[i])),
                        "match_T_object_sensor": poses[i].tolist(),
                    },
                )
            )
            if depth_scale is not None:
                out[-1].details["match_depth_scale"] = float(depth_scale[i])
        return out

    @staticmethod
    def _samples(image: ContactImage, count: int) -> np.ndarray:
        """(count, 3) tactile points (sensor frame) spread over the contact's trusted pixels."""
        local = image.points_local()
        if len(local) > count:
            local = local[np.linspace(0, len(local) - 1, count).astype(np.int64)]
        return image.to_sensor(local)

    def _fit(
        self, model: ObjectModel, image: ContactImage, samples: np.ndarray, poses: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(K,) truncated point-to-plane residual of the samples under each pose, and free-space violation."""
        config = self.config
        surface = parent_surface(model)
        # search further than tau: a point on the surface can lie a point spacing from the nearest parent point
        reach = config.residual_tau_m + 3.0 * model.point_spacing_m
        if KERNELS is not None:
            poses = np.ascontiguousarray(poses, dtype=np.float64)
            points = np.empty((len(poses), len(samples), 3))
            KERNELS.transform_active(poses, np.arange(len(poses)), np.ascontiguousarray(samples), points)
            gaps, index = surface.kdtree.query(points.reshape(-1, 3), distance_upper_bound=reach)
            residual = np.empty(len(poses))
            normal = np.ascontiguousarray(image.normal_sensor, dtype=np.float64)
            KERNELS.truncated_rms(
                poses, points, gaps, index, surface.points_object, surface.normals_object, normal,
                config.residual_tau_m, residual,
            )  # fmt: skip
        else:
            residual = truncated_plane_fit(
                surface,
                np.matmul(samples, np.transpose(poses[:, :3, :3], (0, 2, 1))) + poses[:, None, :3, 3],
                config.residual_tau_m,
                reach_m=reach,
                facing_surface=(poses[:, :3, :3] @ image.normal_sensor)[:, None, :],
            ).rms_m
        violation = np.zeros(len(poses))
        if config.free_space:
            violation = free_space_violation(anchor_maps(model, config.anchors), image, poses, config)
        return residual, violation

    def _rank(
        self, model: ObjectModel, image: ContactImage, poses: np.ndarray, residual: np.ndarray, violation: np.ndarray
    ) -> _Ranked:
        """Distinct registrations, best first, with beliefs; contact locations on the surface."""
        centres = np.einsum("kij,j->ki", poses[:, :3, :3], image.centre_sensor) + poses[:, :3, 3]
        p_object = model.nearest_surface_point(centres)
        ranking = rank_registrations(p_object, np.sqrt(residual**2 + violation), self.config.belief)
        return _Ranked(ranking.indices, ranking.probabilities, p_object)


def scaled_depth(points_sensor: np.ndarray, scale: float) -> np.ndarray:
    """The cloud with its heights below the pad plane (-z_sensor) times `scale`."""
    return points_sensor * np.array([1.0, 1.0, scale])


def candidate_icp(
    surface: ParentSurface,
    samples: np.ndarray,
    T_object_sensor: np.ndarray,
    config: GaussNewtonConfig,
    image: ContactImage,
    keep_best: int | None = None,
) -> np.ndarray:
    """(K, 4, 4) the candidates' poses refined by `registration.point_to_plane_gauss_newton` (the contact's centre
    as pivot, its normal as the facing normal); compiled (`kernels.py`) where numba is installed and every pose
    iterates (`keep_best` None), numpy otherwise."""
    if KERNELS is None or keep_best is not None:
        return point_to_plane_gauss_newton(
            surface,
            samples,
            T_object_sensor,
            config,
            pivot_source=image.centre_sensor,
            facing_source=image.normal_sensor,
            keep_best=keep_best,
        )
    poses = np.array(T_object_sensor, dtype=np.float64).reshape(-1, 4, 4)
    start_rotations = np.ascontiguousarray(poses[:, :3, :3])
    pivot = np.ascontiguousarray(image.centre_sensor, dtype=np.float64)
    anchor_start = start_rotations @ pivot + poses[:, :3, 3]
    prior = config.prior_information()
    facing = np.ascontiguousarray(image.normal_sensor, dtype=np.float64)
    samples = np.ascontiguousarray(samples, dtype=np.float64)
    active = np.arange(len(poses))
    for iteration in range(config.iterations):
        points = np.empty((len(active), len(samples), 3))
        KERNELS.transform_active(poses, active, samples, points)
        gaps, index = surface.kdtree.query(points.reshape(-1, 3), distance_upper_bound=config.max_distance_m)
        moving = np.empty(len(active), dtype=bool)
        KERNELS.gauss_newton_step(
            poses,
            active,
            points,
            gaps,
            index,
            surface.points_object,
            surface.normals_object,
            facing,
            pivot,
            start_rotations,
            anchor_start,
            prior,
            config.surface_noise_m,
            iteration == 0,
            iteration < config.translation_only_iterations,
            config.step_tolerance_m,
            config.step_tolerance_rad,
            moving,
        )
        active = active[moving]
        if len(active) == 0:
            break
    return poses


@dataclass
class _Fitted:
    """Refined registrations of one contact (K of each), before ranking."""

    anchors: np.ndarray  # (K,) the filter's anchor of each
    rolls: np.ndarray  # (K,) its roll index
    filter_cost: np.ndarray  # (K,) its filter cost, m^2
    poses: np.ndarray  # (K, 4, 4) T_object_sensor after ICP
    residual: np.ndarray  # (K,) truncated point-to-plane residual, m
    violation: np.ndarray  # (K,) free-space violation, m^2
    p_object: np.ndarray  # (K, 3) the contact's location on the surface


@dataclass
class _Ranked:
    indices: list[int]  # distinct registrations, best first
    probabilities: np.ndarray  # their beliefs
    p_object: np.ndarray  # (K, 3) every registration's contact location
