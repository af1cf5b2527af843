"""The matched-filter localizer: coarse and fine filter passes, per-candidate ICP, ranking."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.contacts import ContactEstimate, validate_tactile_points
from yoto.errors import DegenerateGeometryError
from yoto.geometry import make_transform, rotation_about_axis
from yoto.localize.match.anchors import AnchorMaps, anchor_maps
from yoto.localize.match.config import MatchConfig
from yoto.localize.match.contact import ContactImage, contact_image, contact_maps
from yoto.localize.match.scores import free_space_penalty, free_space_violation, plane_costs
from yoto.localize.ranking import rank_registrations
from yoto.objects.model import ObjectModel
from yoto.registration import point_to_plane_gauss_newton, truncated_plane_fit

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

    def __init__(self, config: MatchConfig = MatchConfig()):
        self.config = config

    def prepare_object(self, model: ObjectModel) -> AnchorMaps:
        return anchor_maps(model, self.config.anchors)

    def hypotheses(self, points_sensor: np.ndarray, model: ObjectModel) -> FilterHypotheses:
        """The matched filter's shortlist: anchors, rolls, costs and poses (best first, NMS applied)."""
        config = self.config
        anchors = anchor_maps(model, config.anchors)
        grid = anchors.grid
        image = contact_image(points_sensor, grid.radius_m, config)
        # Coarse stage: every anchor, half the cells, fewer rolls, offset only.
        coarse = grid.coarse
        contact = contact_maps(image, grid.centres[coarse], config.coarse_rolls, config)
        if contact.mask.sum(axis=1).max() < MIN_CONTACT_CELLS:
            raise DegenerateGeometryError(
                f"the tactile contact covers fewer than {MIN_CONTACT_CELLS} height-map cells "
                f"({config.anchors.cell_m * 1000:.2f} mm apart): too small to match (is the cloud in metres?)"
            )
        valid_coarse, height_coarse = anchors.coarse_columns
        cost, _ = plane_costs(
            contact.mask,
            contact.heights,
            valid_coarse,
            height_coarse,
            height_coarse * height_coarse,
            grid.centres[coarse],
            False,
            config.air_penalty_m,
        )
        best = cost.min(axis=0)
        count = min(config.shortlist, len(best))
        shortlist = np.argpartition(best, count - 1)[:count] if count < len(best) else np.arange(len(best))
        shortlist = np.sort(shortlist)
        # Fine stage: the shortlist, every cell, every roll, offset and tilt, free space.
        contact = contact_maps(image, grid.centres, config.rolls, config)
        cost, beta = plane_costs(
            contact.mask,
            contact.heights,
            anchors.valid_columns[:, shortlist],
            anchors.height_columns[:, shortlist],
            anchors.height2_columns[:, shortlist],
            grid.centres,
            config.remove_tilt,
            config.air_penalty_m,
        )
        best_roll = np.argmin(cost, axis=0)
        columns = np.arange(len(shortlist))
        score = cost[best_roll, columns].astype(np.float64)
        beta = beta[:, best_roll, columns]
        if config.free_space:
            penalty = free_space_penalty(contact, anchors, shortlist, best_roll, beta, config)
            score = score + penalty / np.maximum(contact.mask.sum(axis=1)[best_roll], 1.0)
        suppressed = np.zeros(len(best), dtype=bool)
        kept: list[int] = []
        for i in np.argsort(score, kind="stable"):
            a = shortlist[i]
            if suppressed[a]:
                continue
            kept.append(int(i))
            suppressed[anchors.neighbours[a]] = True
            if len(kept) >= config.refine_candidates:
                break
        poses = np.array(
            [self._pose(image, anchors, shortlist[i], contact.rolls_rad[best_roll[i]], beta[:, i]) for i in kept]
        )
        return FilterHypotheses(image, shortlist[kept], best_roll[kept], score[kept], poses)

    @staticmethod
    def _pose(image: ContactImage, anchors: AnchorMaps, a: int, roll: float, beta: np.ndarray) -> np.ndarray:
        """T_object_sensor of a hypothesis: contact local -> (tilt, roll) -> anchor local -> object."""
        frame_anchor = np.stack([anchors.u_object[a], anchors.v_object[a], -anchors.normals_object[a]], axis=1)
        spin = rotation_about_axis(Z_AXIS, roll)
        tilt = np.array([-beta[2], beta[1], 0.0], dtype=np.float64)
        angle = float(np.linalg.norm(tilt))
        if angle > 1e-9:
            spin = rotation_about_axis(tilt, angle) @ spin
        rotation = frame_anchor @ spin @ image.basis_sensor.T
        origin = anchors.points_object[a] + float(beta[0]) * anchors.normals_object[a]
        return make_transform(rotation, origin - rotation @ image.centre_sensor)

    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        config = self.config
        points_sensor = validate_tactile_points(points_sensor, None)
        found = self.hypotheses(points_sensor, model)
        image = found.image
        local = image.points_local()
        if len(local) > config.icp_points:
            local = local[np.linspace(0, len(local) - 1, config.icp_points).astype(np.int64)]
        samples = image.to_sensor(local)
        poses = found.poses
        if config.refine:
            poses = point_to_plane_gauss_newton(
                model, samples, poses, config.icp, pivot_source=image.centre_sensor, facing_source=image.normal_sensor
            )
        residual = truncated_plane_fit(
            model,
            np.matmul(samples, np.transpose(poses[:, :3, :3], (0, 2, 1))) + poses[:, None, :3, 3],
            config.residual_tau_m,
            # search further than tau: a point on the surface can lie a point spacing from the nearest parent point
            reach_m=config.residual_tau_m + 3.0 * model.point_spacing_m,
            facing_surface=(poses[:, :3, :3] @ image.normal_sensor)[:, None, :],
        ).rms_m
        violation = free_space_violation(model, image, poses, config) if config.free_space else np.zeros(len(poses))
        total = np.sqrt(residual**2 + violation)
        centres = np.einsum("kij,j->ki", poses[:, :3, :3], image.centre_sensor) + poses[:, :3, 3]
        p_all = model.nearest_surface_point(centres)
        ranking = rank_registrations(p_all, total, config.belief)
        out = []
        for i, probability in zip(ranking.indices, ranking.probabilities, strict=True):
            p = p_all[i]
            out.append(
                ContactEstimate(
                    p_object=p,
                    n_object=model.aggregated_normal(p, config.normal_neighbours),
                    block=int(model.block_of_points(p)[0]),
                    score=float(1.0 - min(total[i], config.residual_tau_m) / config.residual_tau_m),
                    probability=float(probability),
                    details={
                        "match_anchor": int(found.anchors[i]),
                        "match_roll_deg": float(np.degrees(2.0 * np.pi * found.rolls[i] / config.rolls)),
                        "match_filter_rms_mm": 1000.0 * float(np.sqrt(max(found.filter_cost[i], 0.0))),
                        "match_residual_mm": 1000.0 * float(residual[i]),
                        "match_free_space_mm": 1000.0 * float(np.sqrt(violation[i])),
                        "match_T_object_sensor": poses[i].tolist(),
                    },
                )
            )
        return out
