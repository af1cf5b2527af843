"""Settings of the matched filter: what shapes the anchor maps (built once per object) and what each query uses."""

from __future__ import annotations

from dataclasses import dataclass, replace

from yoto.errors import InputError
from yoto.localize.ranking import BeliefConfig
from yoto.registration import CANDIDATE_REFINEMENT, GaussNewtonConfig
from yoto.sensor.spec import GELSIGHT_MINI


@dataclass(frozen=True)
class AnchorConfig:
    """What the anchor maps of an object are made of; the anchor cache is keyed on this alone."""

    anchor_spacing_m: float = 0.002  # anchors: one parent point per voxel of this size
    anchor_normal_neighbours: int = 50  # k of an anchor's aggregated normal (smooth, stable)
    map_radius_m: float = 0.0105  # height maps cover the disc of this radius around the contact / anchor
    cell_m: float = 0.0015  # height-map cell size
    ray_start_m: float = 0.005  # anchor rays start this far in front of the tangent plane
    ray_reach_m: float = 0.005  # surface further than this behind the tangent plane counts as absent
    nms_radius_m: float = 0.004  # matched-filter candidates closer than this are one (anchor neighbourhoods)
    ring_step_m: float = 0.00075  # coarse stage: height samples on rings this far apart, out to map_radius_m ...
    ring_angles: int = 24  # ... with this many samples per ring ...
    ring_harmonics: int = 6  # ... described by their mean and the magnitudes of angular harmonics 2 to this

    def __post_init__(self):
        if self.cell_m <= 0 or self.map_radius_m <= self.cell_m or self.anchor_spacing_m <= 0:
            raise InputError("cell_m and anchor_spacing_m must be positive and map_radius_m larger than a cell")
        if not 0 < self.ring_step_m <= self.map_radius_m:
            raise InputError("ring_step_m must lie in (0, map_radius_m]")
        if not 2 <= self.ring_harmonics <= self.ring_angles // 2:
            raise InputError("ring_harmonics must lie between 2 and ring_angles / 2")


@dataclass(frozen=True)
class MatchConfig:
    """The matched-filter localizer: its anchor maps, and how one contact is matched, refined and ranked."""

    anchors: AnchorConfig = AnchorConfig()
    rolls: int = 36  # sensor roll angles tried by the fine stage (360 / rolls degrees apart)
    shortlist: int = 600  # anchors (best by the coarse stage) scored by the fine stage
    ring_coverage: float = 0.75  # coarse stage: a ring counts when the contact covers this share of its samples
    min_rings: int = 2  # fewer covered rings: the coarse stage falls back to an offset-only filter of every anchor
    coarse_rolls: int = 24  # ... on half the cells at this many rolls
    air_penalty_m: float = 0.0005  # a contact cell with no anchor surface costs like this height error
    remove_tilt: bool = True  # fit and remove a plane (offset + tilt) instead of a constant offset
    contact_pixel_m: float = 0.0002  # pixel of the contact's local height image
    contact_erode_px: int = 1  # the contact image's mask is eroded by this many pixels (the rim is gel, not object)
    free_margin_m: float = 0.0001  # free space: the object may reach this far past the gel plane unseen ...
    free_margin_quantile: float = 0.02  # ... or as deep as the cloud's shallowest points (this quantile of depth)
    free_clearance_m: float = 0.0005  # free space: cells this close to the contact are not judged
    pad_size_m: tuple[float, float] = GELSIGHT_MINI.pad_size_m  # sensed area of the gel (x, y extents)
    refine_candidates: int = 20  # best matched-filter candidates refined by ICP
    icp_points: int = 60  # tactile points used by the per-candidate ICP
    icp: GaussNewtonConfig = replace(CANDIDATE_REFINEMENT, iterations=3)  # the per-candidate point-to-plane ICP, on
    # few points and few iterations (the best are polished below), its start as a weak prior
    icp_keep: int | None = None  # after its first iteration the ICP goes on with only this many candidates, those then
    # fitting best (None: all; 10 saves ~1.5 ms per contact but cost confidence, docs/journal/localization.md)
    polish_candidates: int = 3  # the best distinct candidates after ICP are refined again ...
    polish_points: int = 300  # ... on this many tactile points ...
    polish_iterations: int = 4  # ... for this many more iterations (2: faster, see icp_keep)
    residual_tau_m: float = 0.0005  # truncation of the ranking residual
    belief: BeliefConfig = BeliefConfig()  # distinct candidates and their beliefs from the ranking residuals
    normal_neighbours: int = 20  # k of the aggregated model normal reported with a candidate
    free_space: bool = True  # penalise poses that push the object into the gel where the sensor saw nothing
    refine: bool = True  # refine the candidates by ICP (False: matched-filter poses only)
    image_depth_scales: tuple[float, ...] = (1.0, 1.1, 1.2)  # a contact reconstructed from an image (its
    # `depth_scale_sigma` > 0) is matched with its heights times each of these and the candidates ranked together:
    # reconstructions read curved faces shallow (docs/journal/localization.md, stop 23); (1.0,): as a clean cloud

    def __post_init__(self):
        if (
            self.rolls < 1
            or self.coarse_rolls < 1
            or self.refine_candidates < 1
            or (self.icp_keep is not None and self.icp_keep < 1)
        ):
            raise InputError("rolls, coarse_rolls, refine_candidates and icp_keep must be at least 1")
        if not self.image_depth_scales or min(self.image_depth_scales) <= 0:
            raise InputError(f"image_depth_scales must be positive factors, got {self.image_depth_scales!r}")
