"""The `cpu` YOTO localizer: learned descriptors shortlist anchors, a roll search and ICP place the contact.

Per contact (docs/network.md):
1. coarse (learned): the tactile cloud's polar height map (yoto.network.polar) -> roll-invariant descriptor
   (yoto.network.descriptor) -> cosine score against every anchor of the object (descriptors cached per object
   model) -> the best `shortlist` anchors;
2. fine (geometric): the contact's height map fitted to each shortlisted anchor's surface at every roll, with an
   offset-and-tilt plane removed (`roll_plane_search`, one FFT product per moment); the best fits at distinct
   anchors become sensor poses on the object;
3. verification: each pose is refined by point-to-plane ICP of the tactile points (yoto.registration) and ranked
   by its truncated residual; beliefs from the residuals (yoto.localize.ranking), as the other geometric
   localizers, so the pose stage weighs every method's candidates alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from yoto.contacts import ContactEstimate, validate_tactile_points
from yoto.errors import DegenerateGeometryError
from yoto.geometry import so3_exp
from yoto.localize.network import is_trained_object
from yoto.localize.ranking import BeliefConfig, rank_registrations
from yoto.network.anchors import AnchorSet, anchor_set
from yoto.network.checkpoint import LocalizerCheckpoint
from yoto.network.descriptor import DescriptorNet
from yoto.network.polar import (
    ContactPolarMap,
    PolarGrid,
    contact_polar_map,
    free_space_penalty,
    roll_plane_search,
)
from yoto.network.presets import AnchorNetConfig
from yoto.objects.model import ObjectModel
from yoto.registration import CANDIDATE_REFINEMENT, GaussNewtonConfig, point_to_plane_gauss_newton, truncated_plane_fit

MIN_COVERED_CELLS = 8  # a contact covering fewer polar cells leaves nothing to match


@dataclass(frozen=True)
class DescriptorLocalizerConfig:
    """How the `cpu` localizer turns descriptor scores into ranked contact candidates."""

    shortlist: int = 512  # anchors, best by descriptor score, that the roll search fits
    refine_candidates: int = 16  # best fits at distinct anchors that ICP refines
    nms_radius_m: float = 0.004  # fits at anchors closer than this to a better one are the same place
    air_penalty_m: float = 0.0005  # roll search: a contact cell with no anchor surface costs like this height error
    free_space: bool = True  # fits whose surface would push into the gel where the sensor saw nothing pay for it
    free_space_cap_m: float = 0.005  # ... each such cell at most this deep
    fine_stage: bool = True  # fit the shortlisted anchors (False, an ablation: the best anchors by score alone)
    refine: bool = True  # refine the fits by ICP and rank them by its residual (False, an ablation: by the fit)
    icp_points: int = 300  # tactile points used by the per-candidate ICP
    icp: GaussNewtonConfig = CANDIDATE_REFINEMENT  # the per-candidate point-to-plane ICP, its start as a weak prior
    residual_tau_m: float = 0.0005  # truncation of the ranking residual
    belief: BeliefConfig = BeliefConfig()  # distinct candidates and their beliefs from the ranking residuals ...
    score_weight: float = 0.0  # ... times exp(weight x the network's logit) (0: the residuals alone)
    normal_neighbours: int = 20  # k of the aggregated model normal reported with a candidate

    def __post_init__(self):
        if self.shortlist < 1 or self.refine_candidates < 1 or self.icp_points < 3:
            raise ValueError("shortlist and refine_candidates must be at least 1, icp_points at least 3")


@dataclass
class _ObjectCache:
    anchors: AnchorSet
    descriptors: torch.Tensor  # (A, D)
    neighbours: list[np.ndarray]  # per anchor, the anchors within the NMS radius
    trained: bool


class DescriptorLocalizer:
    """Locates a tactile contact with the anchor-descriptor network; implements yoto.localize.ContactLocalizer."""

    name = "yoto"
    needs_ground_truth = False

    def __init__(
        self,
        net: DescriptorNet,
        checkpoint: LocalizerCheckpoint | None = None,
        config: DescriptorLocalizerConfig = DescriptorLocalizerConfig(),
        source: str | Path | None = None,
    ):
        self.net = net.eval()
        self.network: AnchorNetConfig = net.config
        self.grid = PolarGrid.of(self.network)
        self.config = config
        self.trained_objects = list(checkpoint.objects) if checkpoint is not None else []
        self.source = source
        self._cache: dict[str, _ObjectCache] = {}

    # ------------------------------------------------------------------------------------------- objects
    def prepare_object(self, model: ObjectModel) -> _ObjectCache:
        """Anchors and their descriptors, once per object model (fingerprint)."""
        cached = self._cache.get(model.fingerprint)
        if cached is not None:
            return cached
        anchors = anchor_set(model, self.network)
        trained = is_trained_object(
            model, self.trained_objects, "its anchors are described by the shared network", len(anchors.points_object)
        )
        descriptors = self.net.encode_many(torch.from_numpy(anchors.network_inputs(self.network)))
        neighbours = cKDTree(anchors.points_object).query_ball_point(anchors.points_object, self.config.nms_radius_m)
        cached = _ObjectCache(anchors, descriptors, [np.asarray(n, dtype=np.int64) for n in neighbours], trained)
        self._cache[model.fingerprint] = cached
        return cached

    # ------------------------------------------------------------------------------------------ localize
    def contact_map(self, points_sensor: np.ndarray) -> ContactPolarMap:
        """The contact's polar height map, as the network and the roll search read it."""
        network = self.network
        contact = contact_polar_map(points_sensor, self.grid, network.contact_pixel_m, network.contact_erode_px)
        if contact.covered.sum() < MIN_COVERED_CELLS:
            raise DegenerateGeometryError(
                f"the tactile contact covers {int(contact.covered.sum())} polar cells (fewer than "
                f"{MIN_COVERED_CELLS}): too small to match (is the cloud in metres?)"
            )
        return contact

    def scores(self, contact: ContactPolarMap, model: ObjectModel) -> np.ndarray:
        """(A,) cosine similarity of the contact's descriptor to every anchor's."""
        cache = self.prepare_object(model)
        with torch.inference_mode():
            descriptor = self.net(torch.from_numpy(contact.network_input(self.network.height_unit_m))[None])
        return (cache.descriptors @ descriptor[0]).numpy()

    def shortlist(self, contact: ContactPolarMap, model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
        """The `shortlist` anchors with the best descriptor scores (best first), and every anchor's score."""
        scores = self.scores(contact, model)
        count = min(self.config.shortlist, len(scores))
        best = np.argpartition(-scores, count - 1)[:count] if count < len(scores) else np.arange(len(scores))
        return best[np.argsort(-scores[best], kind="stable")], scores

    def distinct(self, cost: np.ndarray, anchors: np.ndarray, cache: _ObjectCache) -> np.ndarray:
        """Indices into `anchors` of the best `refine_candidates` by `cost`, none near a better one (NMS radius)."""
        suppressed = np.zeros(len(cache.anchors), dtype=bool)
        kept: list[int] = []
        for i in np.argsort(cost, kind="stable"):
            if suppressed[anchors[i]]:
                continue
            kept.append(int(i))
            suppressed[cache.neighbours[anchors[i]]] = True
            if len(kept) >= self.config.refine_candidates:
                break
        return np.asarray(kept, dtype=np.int64)

    def hypotheses(self, points_sensor: np.ndarray, model: ObjectModel) -> tuple[ContactPolarMap, np.ndarray, dict]:
        """The contact's map, the (K, 4, 4) T_object_sensor of the best fits at distinct anchors (best first), and
        per hypothesis its anchor, descriptor score and fit RMS (with the free-space penalty)."""
        config = self.config
        cache = self.prepare_object(model)
        contact = self.contact_map(points_sensor)
        shortlist, scores = self.shortlist(contact, model)
        anchors = cache.anchors
        heights, valid = anchors.heights_m[shortlist], anchors.valid[shortlist]
        fit = roll_plane_search(contact, self.grid, heights, valid, config.air_penalty_m)
        cost = fit.cost_m2
        if config.free_space:
            cost = cost + free_space_penalty(contact, self.grid, heights, valid, fit, config.free_space_cap_m)
        chosen = self.distinct(cost, shortlist, cache)
        index = shortlist[chosen]
        roll = fit.shift[chosen] * (2.0 * np.pi / self.grid.angles)
        plane = fit.plane[:, chosen]
        spin = so3_exp(roll[:, None] * np.array([0.0, 0.0, 1.0]))
        tilt = so3_exp(np.stack([-plane[2], plane[1], np.zeros(len(chosen))], axis=1))  # in the contact's frame
        rotation = anchors.frames(index) @ spin @ tilt @ contact.basis_sensor.T
        poses = np.zeros((len(chosen), 4, 4))
        poses[:, :3, :3] = rotation
        origins = anchors.points_object[index] + plane[0][:, None] * anchors.normals_object[index]
        poses[:, :3, 3] = origins - rotation @ contact.centre_sensor
        poses[:, 3, 3] = 1.0
        details = {"anchor": index, "score": scores[index], "fit_rms_m": np.sqrt(np.maximum(cost[chosen], 0.0))}
        return contact, poses, details

    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        """Candidate contacts on `model` (object frame), best first, with beliefs."""
        config = self.config
        points_sensor = validate_tactile_points(points_sensor, None)
        if not config.fine_stage:
            return self._coarse_candidates(points_sensor, model)
        contact, poses, details = self.hypotheses(points_sensor, model)
        residual = details["fit_rms_m"]
        if config.refine:
            radial = np.linalg.norm((points_sensor - contact.centre_sensor) @ contact.basis_sensor[:, :2], axis=1)
            inside = points_sensor[radial <= self.grid.radius_m]
            samples = inside[np.linspace(0, len(inside) - 1, min(len(inside), config.icp_points)).astype(np.int64)]
            pivot, facing = contact.centre_sensor, contact.normal_sensor
            poses = point_to_plane_gauss_newton(
                model, samples, poses, config.icp, pivot_source=pivot, facing_source=facing
            )
            residual = truncated_plane_fit(
                model,
                np.matmul(samples, np.transpose(poses[:, :3, :3], (0, 2, 1))) + poses[:, None, :3, 3],
                config.residual_tau_m,
                reach_m=config.residual_tau_m + 3.0 * model.point_spacing_m,
                facing_surface=(poses[:, :3, :3] @ contact.normal_sensor)[:, None, :],
            ).rms_m
        centres = np.einsum("kij,j->ki", poses[:, :3, :3], contact.centre_sensor) + poses[:, :3, 3]
        p_all = model.nearest_surface_point(centres)
        ranked = residual
        if config.score_weight > 0:
            # exp(-r'^2 / 2T^2) = exp(-r^2 / 2T^2) exp(w (logit - best logit)): the network's score as a prior
            logits = float(self.net.temperature.detach()) * details["score"]
            temperature = config.belief.temperature_m
            ranked = np.sqrt(residual**2 + 2.0 * temperature**2 * config.score_weight * (logits.max() - logits))
        ranking = rank_registrations(p_all, ranked, config.belief)
        return self._estimates(
            model,
            p_all,
            ranking.indices,
            ranking.probabilities,
            [
                {
                    "anchor": int(details["anchor"][i]),
                    "descriptor_score": round(float(details["score"][i]), 4),
                    "fit_rms_mm": round(1000.0 * float(details["fit_rms_m"][i]), 4),
                    "residual_mm": round(1000.0 * float(residual[i]), 4),
                    "T_object_sensor": poses[i].tolist(),
                }
                for i in ranking.indices
            ],
            1.0 - np.minimum(residual, config.residual_tau_m) / config.residual_tau_m,
        )

    def _coarse_candidates(self, points_sensor: np.ndarray, model: ObjectModel) -> list[ContactEstimate]:
        """The coarse stage alone (an ablation): the best distinct anchors by descriptor score, at their places,
        beliefs a softmax of the network's logits over them."""
        cache = self.prepare_object(model)
        contact = self.contact_map(points_sensor)
        shortlist, scores = self.shortlist(contact, model)
        chosen = shortlist[self.distinct(-scores[shortlist], shortlist, cache)][: self.config.belief.num_candidates]
        logits = float(self.net.temperature.detach()) * scores[chosen]
        beliefs = np.exp(logits - logits.max())
        details = [{"anchor": int(a), "descriptor_score": round(float(scores[a]), 4)} for a in chosen]
        points = cache.anchors.points_object
        return self._estimates(model, points, list(chosen), beliefs / beliefs.sum(), details, np.zeros(len(points)))

    def _estimates(
        self,
        model: ObjectModel,
        p_all: np.ndarray,
        indices: list[int],
        probabilities: np.ndarray,
        details: list[dict],
        score: np.ndarray,
    ) -> list[ContactEstimate]:
        chosen = np.asarray(indices, dtype=np.int64)
        normals = model.aggregated_normal(p_all[chosen], self.config.normal_neighbours)
        blocks = model.block_of_points(p_all[chosen])
        trained = self.prepare_object(model).trained
        return [
            ContactEstimate(
                p_object=p_all[i],
                n_object=normals[j],
                block=int(blocks[j]),
                score=float(score[i]),
                probability=float(probability),
                details={**details[j], "trained_object": trained},
            )
            for j, (i, probability) in enumerate(zip(chosen, probabilities, strict=True))
        ]
