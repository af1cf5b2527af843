"""The pose stage: contact pair -> localize both contacts -> pose hypotheses -> pose result (SPEC "Pose result").

1. Localize each contact (`yoto/localize/`): a few ranked candidates on the model, with beliefs.
2. Seeds: the closed-form pose (normal-aware SVD, paper Sec. 3.4) of every left x right candidate pair whose
   geometry fits the sensors' (separation and the three angles between d, nL, nR); and, unless the localizers
   already agree on one clear answer, the joint two-contact search (`search.py`): every pair of surface
   locations whose local shape and key fit, which covers flat faces, cylinders and edges where a localizer's few
   candidates cannot.
3. Verification: each seed is scored by how well both tactile clouds lie on the surface, allowing each cloud
   an offset and a tilt (what a sensor's calibration error does to it); the best distinct seeds are refined
   jointly with a correction per sensor (`refine.py`) and scored by their residuals, free space and the size of
   the corrections under the calibration prior.
4. Hypotheses (`hypotheses.py`): the refined poses grouped into distinct ones modulo the object's symmetries,
   with probabilities; `ambiguous` when several keep a meaningful share.
5. Confidence (`confidence.py`): the calibrated probability that the first hypothesis is within 5 mm and 5 deg.
6. Where to touch next (`next_touch.py`), when ambiguous.

`PAPER` (each contact's top candidate, SVD, nothing else) reproduces the paper's pose stage exactly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import (
    POSE_RESULT_SUFFIX,
    SIDES,
    WELL_CONDITIONED,
    ContactEstimate,
    ContactPair,
    TactileContact,
    WorldContact,
    contact_in_world,
)
from yoto.errors import DegenerateGeometryError, YotoError
from yoto.geometry import invert_transform, rotate_vectors, se3_exp, se3_log, transform_points
from yoto.localize.base import ContactLocalizer, localize_cloud
from yoto.localize.helper import LocalizerProcess
from yoto.objects.model import ObjectModel
from yoto.objects.symmetry import Symmetry
from yoto.pose.confidence import ConfidenceModel, confidence_features, featureless, load_confidence_model
from yoto.pose.executor import LOCAL, LocalExecutor, SplitExecutor, joined
from yoto.pose.field import FieldConfig, SurfaceField, surface_field
from yoto.pose.hypotheses import (
    Hypotheses,
    HypothesisConfig,
    family_mean,
    family_poses,
    group_hypotheses,
    is_ambiguous,
    log_likelihoods,
    neighbour_poses,
    reported,
)
from yoto.pose.next_touch import NextTouch, NextTouchConfig, suggest_next_touch
from yoto.pose.refine import (
    CalibrationPrior,
    ContactPoints,
    RefineConfig,
    Refined,
    contact_points,
    pose_covariance,
    refine_hypotheses,
    thinned,
)
from yoto.pose.search import LocalShape, SearchConfig, contact_shape, search_poses
from yoto.pose.solver import PoseSolution, solve_pose, solve_poses
from yoto.registration import one_blas_thread


@dataclass(frozen=True)
class ImageBudget:
    """The search and screening of a pair whose contacts were reconstructed from GelSight images
    (docs/journal/sensor.md, "The pose stage's budget for image contacts"). A reconstructed contact's shape is off
    where a clean cloud's is not (box edges and rims: 46-110 um after a plane and a depth scale, against 23 um
    typical), so the truth's location pairs often lie in the sets the clean budget thins, and its seeds rank low by
    the cheap score: more location pairs, more seeds screened, on more points with more iterations; and a sharper fit
    noise in the hypotheses' likelihood. Settings already larger (the fit noise: smaller) are kept."""

    pair_budget: int = 10_000_000  # SearchConfig.pair_budget (clean: 4 M)
    screened: int = 2000  # PoseConfig.screened (clean: 400)
    screen_points: int = 48  # RefineConfig.screen_points (clean: 24)
    screen_iterations: int = 5  # RefineConfig.screen_iterations (clean: 3)
    fit_noise_m: float = 2e-5  # HypothesisConfig.fit_noise_m (clean: 30 um): the fit's evidence weighs more
    # against the sensor corrections. Through images a right pose needs larger corrections than through clean
    # clouds (a reconstructed contact's tilt, level and depth scale are off, and the corrections absorb them): in
    # most image pairs lost by ranking the truth fits the clouds better than the chosen pose and loses on its
    # corrections (docs/journal/sensor.md, stop 14). A setting already smaller is kept.


@dataclass(frozen=True)
class PoseConfig:
    """How the pose stage turns ranked contact candidates into pose hypotheses."""

    calibration: CalibrationPrior = CalibrationPrior()  # expected error of each reported sensor pose
    joint_selection: bool = True  # seed from every candidate pair (False: each localizer's top candidate only)
    verify: bool = True  # verify and refine the seeds with the tactile clouds (False: the best seed's SVD pose)
    search: str = "auto"  # joint two-contact search: "auto" (unless the localizers clearly agree), "always", "never"
    decisive_probability: float = 0.99  # "auto" skips the search when, among the candidate seeds, one hypothesis
    # holds this probability, ...
    decisive_log_likelihood: float = -10.0  # ... explains the contacts this well (hypotheses.log_likelihoods) ...
    decisive_featured: int = 1  # ... and at least this many of the two contacts have features of their own
    search_unless_log_likelihood: float = -6.0  # "auto" searches anyway when the candidates' most likely hypothesis
    # explains the contacts worse than this (a right pose from the candidates fits at -1 to -10, but a banana's
    # pose 8 mm along it at -7.9 against its truth's -3.3, and the candidates' single hypothesis then holds all of the
    # probability: docs/journal/pose.md, stop 13)
    screened: int = 400  # seeds (the best by a cheap score) that get a short refinement (150 kept the truth's seed
    # on the pose benchmark's searches but lost right and confident poses on the trust benchmark's mugs:
    # docs/journal/pose.md)
    seeds_refined: int = 40  # distinct hypotheses (the most likely after the short refinement) refined in full
    full_from_screen_corrections: bool = True  # the full refinement starts each pose's sensor corrections where
    # its short refinement left them (False: from none; from none a pose near the truth can stop in another
    # basin of the corrections and score far below it: docs/journal/pose.md, stop 13)
    candidates_screened: int = 24  # the same two numbers when only the localizers' candidate pairs are verified
    candidates_refined: int = 6
    neighbours_refined: int = 36  # the neighbours of the most likely hypotheses (hypotheses.neighbour_poses) are
    # screened by the short refinement, and the best of this many distinct ones refined in full (0: all in full)
    family_screened: int = 100  # poses along the weakest directions of the most likely hypotheses
    # (hypotheses.family_poses): the best by the cheap score get the short refinement, ...
    family_refined: int = 36  # ... the best of this many distinct ones the full one ...
    family_passes: int = 2  # ... this many times (each pass starts where the last stopped: along a family the weak
    # prior on the starting pose holds a single pass short of the best fit)
    neighbours_if_decisive: bool = True  # refine them even when the most likely hypothesis is decisive by itself
    # (decisive_probability and decisive_log_likelihood; False saves ~10 ms there, see docs/journal/pose.md)
    family_if_decisive: bool = False  # run the family step even when, after the search, the most likely hypothesis
    # is decisive (decisive_probability and decisive_log_likelihood; skipping it saves ~35 ms there,
    # docs/journal/pose.md)
    rescue_log_likelihood: float = -14.0  # when, after the search and the family step, the most likely hypothesis
    # still explains the contacts worse than this (hypotheses.log_likelihoods: right poses mostly -2 to -12), the
    # search's seeds that the first pass did not screen are verified too (`_rescue`): ...
    rescue_screened: int = 1600  # ... the best this many by the cheap score (the first pass's) get the short
    # refinement, on this many points per contact (half the first pass's refine_config.screen_points) ...
    rescue_screen_points: int = 12
    rescue_refined: int = 40  # ... and the best of this many distinct ones the full one (docs/journal/pose.md, stop 11)
    rescue_probability: float = 0.5  # the rescue also runs where the most likely hypothesis, however well it fits,
    # holds less than this probability: where several poses explain the contacts about as well (a can turned about
    # its axis, a box slid along a face), the truth's seeds can rank below the first pass's screen
    # (docs/journal/pose.md, stop 13; 0: only for the fit)
    seed_distinct_m: float = 0.005  # seeds in one cell of this size (object centroid) ...
    seed_distinct_rad: float = float(np.radians(5.0))  # ... and of this (rotation vector) are screened as one
    search_config: SearchConfig = SearchConfig()
    refine_config: RefineConfig = RefineConfig()
    field_config: FieldConfig = FieldConfig()
    hypotheses: HypothesisConfig = HypothesisConfig()
    next_touch: NextTouchConfig = NextTouchConfig()
    suggest_next_touch: bool = True  # compute next_touch when the pose is ambiguous
    confidence_model: str | None = None  # confidence parameters file (None: the ones shipped with YOTO)
    image_budget: ImageBudget | None = ImageBudget()  # pairs reconstructed from images search and screen wider
    # (`for_pair`; None: as clean clouds)

    def for_pair(self, pair: ContactPair) -> PoseConfig:
        """This config for `pair`: with the search and screening raised (the fit noise lowered) to `image_budget`
        when a side was reconstructed from a GelSight image (its depth scale is uncertain: `depth_scale_sigma` > 0),
        else itself. Clean clouds keep the defaults, their speed and poses; applying it twice changes nothing."""
        budget = self.image_budget
        if budget is None or not any(pair.contact(side).depth_scale_sigma > 0.0 for side in SIDES):
            return self
        search, refine, hypotheses = self.search_config, self.refine_config, self.hypotheses
        return replace(
            self,
            search_config=replace(search, pair_budget=max(search.pair_budget, budget.pair_budget)),
            screened=max(self.screened, budget.screened),
            refine_config=replace(
                refine,
                screen_points=max(refine.screen_points, budget.screen_points),
                screen_iterations=max(refine.screen_iterations, budget.screen_iterations),
            ),
            hypotheses=replace(hypotheses, fit_noise_m=min(hypotheses.fit_noise_m, budget.fit_noise_m)),
        )


PAPER = PoseConfig(joint_selection=False, verify=False, search="never", suggest_next_touch=False)


@dataclass
class PoseEstimate:
    """A pose from one contact pair, with everything a user needs to decide whether to act on it."""

    object_name: str
    method: str
    T_world_object: np.ndarray  # (4, 4), YOTO's canonical object frame
    T_world_mesh: np.ndarray  # (4, 4), the mesh file's frame (what users and mocap know)
    contacts: dict[str, ContactEstimate]  # where each contact lies on the object under the pose
    candidates: dict[str, list[ContactEstimate]]  # every candidate per side, the localizer's order
    world: dict[str, WorldContact]
    solution: PoseSolution  # the closed-form solve at the chosen contacts (conditioning, residual angles)
    hypotheses: Hypotheses  # distinct poses (canonical frame), most probable first; the first is T_world_object
    ambiguous: bool
    confidence: float  # calibrated probability that T_world_object is within 5 mm and 5 deg of the truth
    features: dict[str, float] = field(default_factory=dict)  # what the confidence was computed from
    fit_rms_m: tuple[float, float] = (float("nan"), float("nan"))  # each cloud's residual after its correction
    depth_scale: tuple[float, float] = (1.0, 1.0)  # each cloud's depth scale as refined (1: its heights taken as exact)
    corrections: np.ndarray | None = None  # (2, 6) each sensor's correction twist (rotation vector, translation)
    hypothesis_corrections: np.ndarray | None = None  # (H, 2, 6) the same under each hypothesis
    most_likely: tuple[np.ndarray, np.ndarray] | None = None  # the most likely refined pose (4, 4) and its
    # corrections (2, 6) before the family mean: along a free family the mean sits between poses, and a re-touch
    # that fixes the family must still start from one the family holds
    next_touch: NextTouch | None = None
    searched: bool = False  # whether the joint two-contact search ran
    latency_ms: dict[str, float] = field(default_factory=dict)

    def hypotheses_mesh(self, model: ObjectModel) -> np.ndarray:
        """(H, 4, 4) the hypotheses in the mesh file's frame."""
        return self.hypotheses.T_world_object @ model.T_object_mesh

    def to_json(self, model: ObjectModel) -> dict[str, Any]:
        """The SPEC pose result: poses, points and normals in the mesh file's frame."""
        T_mesh_object = model.T_mesh_object
        sides = {}
        for s, side in enumerate(SIDES):
            contact = self.contacts[side]
            sides[side] = {
                "p_object": transform_points(T_mesh_object, contact.p_object).tolist(),
                "n_object": rotate_vectors(T_mesh_object, contact.n_object).tolist(),
                "block": int(contact.block),
                "score": float(contact.score),
                "probability": float(contact.probability),
                "p_world_measured": self.world[side].p_world.tolist(),
                "surface_rms_mm": 1000.0 * float(self.fit_rms_m[s]),
                "depth_scale": float(self.depth_scale[s]),  # the factor its heights were read by (1: as given)
                "sensor_correction": None
                if self.corrections is None
                else {
                    "rotation_deg": float(np.degrees(np.linalg.norm(self.corrections[s, :3]))),
                    "translation_mm": 1000.0 * float(np.linalg.norm(self.corrections[s, 3:])),
                },
                **{key: value for key, value in contact.details.items()},
            }
        hypotheses_mesh = self.hypotheses_mesh(model)
        return {
            "object": self.object_name,
            "method": self.method,
            "frame": "mesh file frame (the frame of the mesh the object model was built from)",
            "T_world_object": self.T_world_mesh.tolist(),
            **sides,
            "confidence": float(self.confidence),
            "hypotheses": [
                {"T_world_object": T.tolist(), "probability": float(p)}
                for T, p in zip(hypotheses_mesh, self.hypotheses.probability)
            ],
            "ambiguous": bool(self.ambiguous),
            "next_touch": None if self.next_touch is None else self.next_touch.to_json(model),
            "symmetry": model.symmetry.describe(),
            "conditioning": float(self.solution.conditioning),
            "well_conditioned": bool(self.solution.well_conditioned),
            "separation_error_mm": 1000.0 * self.solution.separation_error_m,
            "normal_angle_error_deg": float(np.degrees(self.solution.normal_angle_error_rad)),
            "confidence_features": {key: float(value) for key, value in self.features.items()},
            "searched": self.searched,
            "warnings": self.solution.warnings,
            "latency_ms": self.latency_ms,
        }


def localize_contacts(
    pair: ContactPair, model: ObjectModel, localizer: ContactLocalizer, helper: LocalizerProcess | None = None
) -> tuple[dict[str, list[ContactEstimate]], dict[str, WorldContact], dict[str, float]]:
    """Each contact's ranked candidates on the model, its world-side measurement, and the localizer's time (ms).

    With `helper` (a `LocalizerProcess` holding a copy of the localizer), the right contact is localized in the
    helper process while this one localizes the left: a robot waits for both contacts at once, not for each in
    turn. Each side's time is then measured where it ran, and `localize_pair` is the time of both (with their
    world-side measurements).
    """

    def truth(side: str) -> np.ndarray | None:
        if not localizer.needs_ground_truth:
            return None
        if side not in pair.p_mesh_true:
            raise DegenerateGeometryError(f"{pair.path}: the oracle needs ground_truth.{side}_p_object")
        return transform_points(model.T_object_mesh, pair.p_mesh_true[side])

    start = time.perf_counter()
    remote = None if helper is None else helper.submit(pair.right, model, truth("right"))
    candidates, world, latency = {}, {}, {}
    for side in SIDES if remote is None else ("left",):
        tick = time.perf_counter()
        contact = pair.contact(side)
        candidates[side] = localize_cloud(
            localizer, contact.points_sensor, model, truth(side), contact.depth_scale_sigma
        )
        latency[f"localize_{side}"] = 1000.0 * (time.perf_counter() - tick)
        world[side] = contact_in_world(pair.contact(side))
    if remote is not None:
        candidates["right"], world["right"], latency["localize_right"] = remote.result()
    latency["localize_pair"] = 1000.0 * (time.perf_counter() - start)
    return candidates, world, latency


def _seeds(
    model: ObjectModel,
    world: dict[str, WorldContact],
    shapes: dict[str, LocalShape],
    candidates: dict[str, list[ContactEstimate]],
    config: PoseConfig,
    search: bool,
    run: LocalExecutor = LOCAL,
) -> np.ndarray:
    """(K, 4, 4) closed-form poses of the candidate pairs whose key fits (and, with `search`, of the search's
    matches); the localizers' top pair is always among them, fitting or not, so there is a pose to verify. Of the
    matches in one pose cell only the one whose key fits best is kept. `run` tests the search's location pairs and
    poses its matches."""
    matches = search_poses(
        model, world, shapes, candidates, config.search_config, search, run.key_matches, run.closed_form
    )
    best = _best_per_cell(matches.translations, matches.rotation_vectors, -matches.mismatch, config)
    matches_T = matches.subset(best).T_world_object
    left, right = candidates["left"][0], candidates["right"][0]
    top = solve_poses(
        left.p_object[None],
        left.n_object[None],
        right.p_object[None],
        right.n_object[None],
        world["left"],
        world["right"],
    )
    return np.concatenate([top.T_world_object, matches_T])


def _best_per_cell(
    translations: np.ndarray, rotation_vectors: np.ndarray, score: np.ndarray, config: PoseConfig
) -> np.ndarray:
    """Indices of the best-scoring pose in each cell of a pose grid (translation and rotation vector quantised at
    the seed distinctness): thousands of near-duplicate seeds become fewer."""
    translation = np.floor(translations / config.seed_distinct_m)
    rotation = np.floor(rotation_vectors / config.seed_distinct_rad)
    order = np.argsort(-score, kind="stable")
    cells = np.hstack([translation, rotation])[order].astype(np.int64)
    cells -= cells.min(axis=0, initial=0)
    key = np.zeros(len(cells), dtype=np.int64)  # one integer per cell: a 1-D unique is far faster than rows'
    for column, span in zip(cells.T, cells.max(axis=0, initial=0) + 1):
        key = key * span + column
    _, first = np.unique(key, return_index=True)
    return order[np.sort(first)]


def _verify_and_refine(
    field: SurfaceField,
    contacts: list[ContactPoints],
    seeds: np.ndarray,
    symmetry: Symmetry,
    config: PoseConfig,
    screened: int,
    refined: int,
    neighbours: bool = False,
    run: LocalExecutor = LOCAL,
    score: np.ndarray | None = None,
) -> Refined:
    """Screen the seeds and refine the best distinct ones.

    A cheap score (each cloud may sit off the surface by an offset and a tilt) ranks the seeds; the best
    `screened` get a short refinement on a few points; the best pose of each of the `refined`
    most likely distinct hypotheses among those is refined in full; with `neighbours`, the neighbours of the most
    likely of them (`hypotheses.neighbour_poses`) are screened the same way (most land back on a hypothesis
    already found), and the best of `neighbours_refined` distinct ones refined in full. `run` computes the batches
    (`executor.SplitExecutor`: half of each in a helper process). `score`: the seeds' cheap scores, when known.
    """
    refine = config.refine_config
    if score is None:
        score = run.offsets(field, contacts, seeds, config.calibration, refine)
    chosen = np.argsort(-score, kind="stable")[:screened]
    short = replace(refine, iterations=refine.screen_iterations)
    screening = thinned(contacts, refine.screen_points, refine.screen_free_points)
    first = run.refine(field, screening, seeds[chosen], config.calibration, short)
    best = _best_distinct(first, symmetry, config.hypotheses, refined)
    full = run.refine(
        field, contacts, first.T_world_object[best], config.calibration, refine, _started(first, best, config)
    )
    if not neighbours or not config.hypotheses.neighbours_of:
        return full
    grouped = group_hypotheses(full, symmetry, config.hypotheses)
    if not config.neighbours_if_decisive and _clear_first(grouped, config):
        return full
    top = grouped.member[: config.hypotheses.neighbours_of]
    near = neighbour_poses(full.T_world_object[top], config.hypotheses)
    start = None
    if config.neighbours_refined:
        first = run.refine(field, screening, near, config.calibration, short)
        best = _best_distinct(first, symmetry, config.hypotheses, config.neighbours_refined)
        near, start = first.T_world_object[best], _started(first, best, config)
    more = run.refine(field, contacts, near, config.calibration, refine, start)
    return joined(full, more)


def _started(screened: Refined, chosen: np.ndarray, config: PoseConfig) -> np.ndarray | None:
    """Where the full refinement of the `chosen` short-refined poses starts their sensor corrections: where the
    short refinement left them (`full_from_screen_corrections`), else from none."""
    return screened.corrections[chosen] if config.full_from_screen_corrections else None


def _fill_family(
    field: SurfaceField,
    contacts: list[ContactPoints],
    refined: Refined,
    hypotheses: Hypotheses,
    symmetry: Symmetry,
    config: PoseConfig,
    run: LocalExecutor = LOCAL,
) -> tuple[Refined, Hypotheses]:
    """The refined poses and their hypotheses, with poses along the weakest directions of the most likely
    hypotheses (`hypotheses.family_poses`) refined as well: where the two contacts leave a family of poses (a mug
    turned about its axis, a box slid along its faces), the truth can lie far along it from every hypothesis the
    seeds led to. The family's poses are scored cheaply, the best screened by the short refinement, and the best
    distinct ones refined in full."""
    family = family_poses(field, contacts, hypotheses, config.hypotheses, config.refine_config.max_distance_m)
    if not len(family):
        return refined, hypotheses
    more = _verify_and_refine(
        field, contacts, family, symmetry, config, config.family_screened, config.family_refined, run=run
    )
    for _ in range(config.family_passes - 1):  # each pass starts where the last stopped
        more = run.refine(field, contacts, more.T_world_object, config.calibration, config.refine_config)
    refined = joined(refined, more)
    return refined, group_hypotheses(refined, symmetry, config.hypotheses)


def _rescue(
    field: SurfaceField,
    contacts: list[ContactPoints],
    seeds: np.ndarray,
    score: np.ndarray,
    refined: Refined,
    symmetry: Symmetry,
    config: PoseConfig,
    run: LocalExecutor = LOCAL,
) -> tuple[Refined, Hypotheses]:
    """The refined poses and their hypotheses, with more of the search's `seeds` verified: of those the first pass
    did not screen (all but the best `screened` by the cheap `score`, the first pass's), the best `rescue_screened`
    get the short refinement (on `rescue_screen_points` per contact) and the best of `rescue_refined` distinct ones
    the full one (with their neighbours, as the first pass); then the family step on the joined pool. For a pair
    that nothing found so far explains well: the cheap score can rank the seeds near the truth below the screened
    ones (their clouds touch a rounded edge or a rim imperfectly until refined), and the few screened near it can
    stop short of it (docs/journal/pose.md, stop 11)."""
    unscreened = np.sort(np.argsort(-score, kind="stable")[config.screened :])
    screening = replace(config.refine_config, screen_points=config.rescue_screen_points)
    more = _verify_and_refine(
        field,
        contacts,
        seeds[unscreened],
        symmetry,
        replace(config, refine_config=screening),
        config.rescue_screened,
        config.rescue_refined,
        True,
        run,
        score[unscreened],
    )
    refined = joined(refined, more)
    hypotheses = group_hypotheses(refined, symmetry, config.hypotheses)
    if len(hypotheses) > 1:
        refined, hypotheses = _fill_family(field, contacts, refined, hypotheses, symmetry, config, run)
    return refined, hypotheses


def _best_distinct(refined: Refined, symmetry: Symmetry, config: HypothesisConfig, count: int) -> np.ndarray:
    """Indices of the best pose of each of the `count` most likely distinct hypotheses (`group_hypotheses`).

    Grouping visits the poses from the most likely down, and whether a pose founds a hypothesis depends only on
    the poses before it: the first `count` founders among the most likely few poses are the first `count` of all.
    So the grouping runs on the most likely 4 x `count` poses first, and on all only when they hold fewer.
    """
    order = np.argsort(-log_likelihoods(refined, config), kind="stable")
    subset = order[: 4 * count]
    members = subset[group_hypotheses(refined.subset(subset), symmetry, config).member[:count]]
    if len(members) < count and len(subset) < len(order):
        members = group_hypotheses(refined, symmetry, config).member[:count]
    return members


def _contact_under_pose(
    model: ObjectModel,
    T_world_object: np.ndarray,
    world: WorldContact,
    correction: np.ndarray | None,
    T_world_sensor: np.ndarray,
    candidates: list[ContactEstimate],
) -> ContactEstimate:
    """Where the measured contact lies on the object under a pose: the nearest surface point to the contact centre,
    with the localizer's candidate there (block, belief) when one lies within 3 mm."""
    T_world_sensor_corrected = T_world_sensor if correction is None else T_world_sensor @ se3_exp(correction)
    centre_object = transform_points(invert_transform(T_world_object) @ T_world_sensor_corrected, world.p_sensor)
    p_object = model.nearest_surface_point(centre_object)
    near = [c for c in candidates if np.linalg.norm(c.p_object - p_object) < 0.003]
    if near:
        best = max(near, key=lambda c: c.probability)
        return ContactEstimate(
            p_object, model.aggregated_normal(p_object), best.block, best.score, best.probability, best.details
        )
    return ContactEstimate(
        p_object, model.aggregated_normal(p_object), int(model.block_of_points(p_object)[0]), 0.0, 0.0
    )


def pose_from_candidates(
    pair: ContactPair,
    model: ObjectModel,
    candidates: dict[str, list[ContactEstimate]],
    world: dict[str, WorldContact],
    config: PoseConfig = PoseConfig(),
    method: str = "",
    confidence_model: ConfidenceModel | None = None,
    helper: LocalizerProcess | None = None,
) -> PoseEstimate:
    """The pose stage proper, from localized candidates. `latency_ms` holds `pose` (this stage's own time) and
    `next_touch` when one was computed. BLAS runs on one thread (`registration.one_blas_thread`). With `helper`
    (a `LocalizerProcess`), half of each large batch of poses is scored and refined there (`executor`): the same
    numbers, bitwise, on two cores. A pair reconstructed from images runs with `config.for_pair(pair)`."""
    config = config.for_pair(pair)
    run = LOCAL if helper is None else SplitExecutor(helper, model, config.field_config)
    with one_blas_thread():
        estimate = _pose_from_candidates(pair, model, candidates, world, config, method, confidence_model, run)
    if isinstance(run, SplitExecutor):  # what the second core did (executor.SplitExecutor's counts)
        counts = {"pose_split": run.split, "pose_split_redone": run.redone, "pose_split_slow": run.slow}
        estimate.latency_ms.update(pose_helper_extra_cpu=run.helper_extra_cpu_ms, **counts)
    return estimate


def _pose_from_candidates(
    pair: ContactPair,
    model: ObjectModel,
    candidates: dict[str, list[ContactEstimate]],
    world: dict[str, WorldContact],
    config: PoseConfig,
    method: str,
    confidence_model: ConfidenceModel | None,
    run: LocalExecutor,
) -> PoseEstimate:
    tick = time.perf_counter()
    if not config.joint_selection:
        candidates = {side: found[:1] for side, found in candidates.items()}
    if not config.verify:
        return _closed_form_estimate(pair, model, candidates, world, config, method, tick)
    field = surface_field(model, config.field_config)
    contacts = _pair_clouds(pair, model, config)
    shapes = _contact_shapes(pair, world, config)
    searched = config.search == "always"
    refined = None
    # The candidates' pass, unless "auto" searches whatever it finds: `_decisive` needs `decisive_featured` contacts
    # with features of their own, and without them the pass would be thrown away.
    if config.search != "auto" or _featured(shapes) >= config.decisive_featured:
        seeds = _seeds(model, world, shapes, candidates, config, searched, run)
        if len(seeds):
            screened, kept = (
                (config.screened, config.seeds_refined)
                if searched
                else (config.candidates_screened, config.candidates_refined)
            )
            score = run.offsets(field, contacts, seeds, config.calibration, config.refine_config)
            refined = _verify_and_refine(
                field, contacts, seeds, model.symmetry, config, screened, kept, searched, run, score
            )
    hypotheses = None if refined is None else group_hypotheses(refined, model.symmetry, config.hypotheses)
    if config.search == "auto" and not _decisive(hypotheses, shapes, config):
        searched = True
        seeds = _seeds(model, world, shapes, candidates, config, True, run)
        if len(seeds):
            score = run.offsets(field, contacts, seeds, config.calibration, config.refine_config)
            refined = _verify_and_refine(
                field, contacts, seeds, model.symmetry, config, config.screened, config.seeds_refined, True, run, score
            )
            hypotheses = group_hypotheses(refined, model.symmetry, config.hypotheses)
    if (
        searched
        and refined is not None
        and hypotheses is not None
        and len(hypotheses) > 1
        and (config.family_if_decisive or not _clear_first(hypotheses, config))
    ):
        refined, hypotheses = _fill_family(field, contacts, refined, hypotheses, model.symmetry, config, run)
    if (
        searched
        and len(seeds)
        and refined is not None
        and hypotheses is not None
        and len(hypotheses)
        and (
            hypotheses.log_likelihood[0] < config.rescue_log_likelihood
            or hypotheses.probability[0] < config.rescue_probability
        )
    ):
        refined, hypotheses = _rescue(field, contacts, seeds, score, refined, model.symmetry, config, run)
    if refined is None or hypotheses is None or not len(hypotheses):
        return _closed_form_estimate(pair, model, candidates, world, config, method, tick)
    estimate = _estimate(
        pair, model, candidates, world, shapes, refined, hypotheses, searched, config, method, field, contacts
    )
    estimate.confidence = (confidence_model or load_confidence_model(config.confidence_model)).predict(
        estimate.features
    )
    estimate.latency_ms["pose"] = 1000.0 * (time.perf_counter() - tick)
    if estimate.ambiguous and config.suggest_next_touch:
        tock = time.perf_counter()
        estimate.next_touch = suggest_next_touch(model, estimate.hypotheses, pair, config.next_touch)
        estimate.latency_ms["next_touch"] = 1000.0 * (time.perf_counter() - tock)
    return estimate


def _pair_clouds(pair: ContactPair, model: ObjectModel, config: PoseConfig) -> list[ContactPoints]:
    """The two tactile clouds as the refinement reads them."""
    return [
        contact_points(
            pair.contact(side).points_sensor,
            pair.contact(side).T_world_sensor,
            s,
            model.point_spacing_m,
            config.refine_config,
            pair.contact(side).depth_scale_sigma,
        )
        for s, side in enumerate(SIDES)
    ]


def refined_log_likelihood(
    pair: ContactPair,
    model: ObjectModel,
    T_world_object: np.ndarray,
    config: PoseConfig = PoseConfig(),
    corrections: np.ndarray | None = None,
) -> float:
    """How well a given pose explains the pair once refined from there (`family_passes` times, as the family step
    refines its poses; the hypotheses' log-likelihood, `hypotheses.log_likelihoods`), the sensor corrections
    starting from `corrections` (2, 6) twists where given (a simulation's true ones), else from none. For
    diagnosis: the true pose's against the first hypothesis's tells a truth the verification never reached (the
    truth explains the contacts better) from one the score ranks below a wrong pose (it explains them worse: the
    model and the contacts disagree there). From the truth with no corrections, a refinement can stop in another
    basin (a mug's pair: -191 against -8.6 from its true corrections), so a simulation passes them in."""
    field = surface_field(model, config.field_config)
    contacts = _pair_clouds(pair, model, config)
    poses = T_world_object[None]
    start = None if corrections is None else np.asarray(corrections, dtype=np.float64)[None]
    with one_blas_thread():  # as the pose stage refines (sums in one order)
        for _ in range(max(config.family_passes, 1)):  # the family step refines at least once
            refined = refine_hypotheses(field, contacts, poses, config.calibration, config.refine_config, start)
            poses, start = refined.T_world_object, refined.corrections
    return float(log_likelihoods(refined, config.hypotheses)[0])


def true_corrections(pair: ContactPair, T_world_sensor_true: dict[str, np.ndarray]) -> np.ndarray:
    """(2, 6) the sensor corrections (twists, `refine.refine_hypotheses`' convention E: T_reported E = T_true) that
    bring each reported sensor pose of a simulated pair onto its true one."""
    return np.stack(
        [se3_log(invert_transform(pair.contact(side).T_world_sensor) @ T_world_sensor_true[side]) for side in SIDES]
    )


def _estimate(
    pair: ContactPair,
    model: ObjectModel,
    candidates: dict[str, list[ContactEstimate]],
    world: dict[str, WorldContact],
    shapes: dict[str, LocalShape],
    refined: Refined,
    hypotheses: Hypotheses,
    searched: bool,
    config: PoseConfig,
    method: str,
    field: SurfaceField,
    contacts: list[ContactPoints],
) -> PoseEstimate:
    """The estimate of the most probable hypothesis (its confidence still to be set): the likelihood-weighted mean
    of the refined poses in its family (`hypotheses.family_mean`), refined once more so that both clouds lie on the
    surface again; the first reported hypothesis is that pose."""
    best = int(hypotheses.member[0])
    mean = refined.subset(np.array([best]))
    if config.hypotheses.mean_reach > 0.0:
        T_mean = family_mean(refined, hypotheses, model.symmetry, config.hypotheses)
        mean = refine_hypotheses(
            field, contacts, T_mean[None], config.calibration, config.refine_config, mean.corrections
        )
    T_world_object = mean.T_world_object[0]
    corrections = mean.corrections[0]
    chosen = {
        side: _contact_under_pose(
            model, T_world_object, world[side], corrections[s], pair.contact(side).T_world_sensor, candidates[side]
        )
        for s, side in enumerate(SIDES)
    }
    solution = solve_pose(chosen["left"], chosen["right"], world["left"], world["right"])
    shown = reported(hypotheses, config.hypotheses)
    shown.T_world_object[0] = T_world_object
    hypothesis_corrections = refined.corrections[shown.member]
    hypothesis_corrections[0] = corrections
    return PoseEstimate(
        object_name=model.name,
        method=method,
        T_world_object=T_world_object,
        T_world_mesh=T_world_object @ model.T_object_mesh,
        contacts=chosen,
        candidates=candidates,
        world=world,
        solution=solution,
        hypotheses=shown,
        ambiguous=is_ambiguous(hypotheses, config.hypotheses),
        confidence=float("nan"),
        features=confidence_features(
            hypotheses,
            refined,
            solution,
            chosen,
            shapes,
            searched,
            model.symmetry,
            pose_covariance(field, contacts, refined, best, config.calibration, config.refine_config),
        ),
        fit_rms_m=(float(mean.fit_rms_m[0, 0]), float(mean.fit_rms_m[0, 1])),
        depth_scale=(float(mean.depth_scale[0, 0]), float(mean.depth_scale[0, 1])),
        corrections=corrections,
        hypothesis_corrections=hypothesis_corrections,
        most_likely=(refined.T_world_object[best], refined.corrections[best]),
        searched=searched,
    )


def fuse_next_touch(
    pair: ContactPair,
    model: ObjectModel,
    estimate: PoseEstimate,
    touch: TactileContact,
    sensor: str,
    config: PoseConfig = PoseConfig(),
    confidence_model: ConfidenceModel | None = None,
    localizer: ContactLocalizer | None = None,
    earlier: tuple[tuple[TactileContact, str], ...] = (),
) -> PoseEstimate:
    """The pose after one more touch: `sensor` moved and pressed again (`touch`: its tactile cloud and reported
    pose) while the other stayed. Every hypothesis of the previous estimate is refined with all the clouds (a
    sensor's contacts share its calibration error) and regrouped. With a `localizer`, the new touch and the contact
    that stayed are also a pair of their own: the seeds of its joint search join the previous hypotheses and all
    are verified with all the clouds, so a truth that the first pair missed can be found. `earlier` holds the
    touches (contact, sensor) fused into `estimate` before this one, in order: a sequence of touches. A pair
    reconstructed from images runs with `config.for_pair(pair)`, as its first estimate did."""
    tick = time.perf_counter()
    config = config.for_pair(pair)
    field = surface_field(model, config.field_config)
    spacing = model.point_spacing_m
    touches = [*((pair.contact(side), side) for side in SIDES), *earlier, (touch, sensor)]
    contacts = [
        contact_points(
            c.points_sensor, c.T_world_sensor, SIDES.index(side), spacing, config.refine_config, c.depth_scale_sigma
        )
        for c, side in touches
    ]
    now = pair
    for contact, side in touches[2:-1]:
        now = _moved(now, contact, side)
    # Every earlier hypothesis is refined in full with all the clouds, its sensor corrections starting where its
    # own refinement left them: a sensor's correction moves its new contact too, often by millimetres far from the
    # first, and from no correction the refinement can settle beside the truth. The second pair's seeds are
    # verified beside them.
    starts, start_corrections = estimate.hypotheses.T_world_object, estimate.hypothesis_corrections
    most_likely = estimate.most_likely  # (with `mean_reach` 0 it is the first hypothesis already)
    if most_likely is not None and start_corrections is not None and not np.array_equal(most_likely[0], starts[0]):
        starts = np.concatenate([starts, most_likely[0][None]])
        start_corrections = np.concatenate([start_corrections, most_likely[1][None]])
    refined = refine_hypotheses(field, contacts, starts, config.calibration, config.refine_config, start_corrections)
    second_seeds = _second_pair_seeds(now, model, touch, sensor, config, localizer) if localizer else None
    if second_seeds is not None and len(second_seeds):
        more = _verify_and_refine(
            field, contacts, second_seeds, model.symmetry, config, config.screened, config.seeds_refined
        )
        refined = joined(refined, more)
    hypotheses = group_hypotheses(refined, model.symmetry, config.hypotheses)
    shapes = _contact_shapes(pair, estimate.world, config)
    fused = _estimate(
        pair,
        model,
        estimate.candidates,
        estimate.world,
        shapes,
        refined,
        hypotheses,
        True,
        config,
        estimate.method,
        field,
        contacts,
    )
    fused.confidence = (confidence_model or load_confidence_model(config.confidence_model)).predict(fused.features)
    fused.latency_ms = {"fuse": 1000.0 * (time.perf_counter() - tick)}
    if fused.ambiguous and config.suggest_next_touch:
        tock = time.perf_counter()
        fused.next_touch = suggest_next_touch(model, fused.hypotheses, _moved(now, touch, sensor), config.next_touch)
        fused.latency_ms["next_touch"] = 1000.0 * (time.perf_counter() - tock)
    return fused


def estimate_pose_with_touch(
    pair: ContactPair,
    model: ObjectModel,
    localizer: ContactLocalizer,
    touch: TactileContact,
    sensor: str,
    config: PoseConfig = PoseConfig(),
) -> tuple[PoseEstimate, PoseEstimate]:
    """The pose of `pair`, and the pose after `sensor` moved and pressed again (`touch`, e.g. where the first
    estimate's `next_touch` said) while the other sensor stayed: (first estimate, fused estimate)."""
    if sensor not in SIDES:
        raise YotoError(f"the sensor that touched again must be 'left' or 'right', got {sensor!r}")
    first = estimate_pose(pair, model, localizer, replace(config, suggest_next_touch=False))
    return first, fuse_next_touch(pair, model, first, touch, sensor, config, localizer=localizer)


def _moved(pair: ContactPair, touch: TactileContact, sensor: str) -> ContactPair:
    """The pair of the sensors' latest contacts after `sensor` touched again."""
    left, right = (touch, pair.right) if sensor == "left" else (pair.left, touch)
    return ContactPair(pair.object_name, left, right)


def _second_pair_seeds(
    pair: ContactPair,
    model: ObjectModel,
    touch: TactileContact,
    sensor: str,
    config: PoseConfig,
    localizer: ContactLocalizer,
) -> np.ndarray | None:
    """The closed-form seeds (candidates and joint search) of the pair made by the new touch and the contact that
    stayed, or None when that pair cannot be solved (e.g. its contacts are too close)."""
    second = _moved(pair, touch, sensor)
    try:
        candidates, world, _ = localize_contacts(second, model, localizer)
        return _seeds(model, world, _contact_shapes(second, world, config), candidates, config, search=True)
    except YotoError:
        return None


def _decisive(hypotheses: Hypotheses | None, shapes: dict[str, LocalShape], config: PoseConfig) -> bool:
    """Whether the candidate seeds alone settle the pose (see PoseConfig.decisive_*): measured on simulated pairs of
    nine objects, no pair that passed was wrong."""
    if hypotheses is None or not len(hypotheses):
        return False
    return (
        _clear_first(hypotheses, config)
        and hypotheses.log_likelihood[0] >= config.search_unless_log_likelihood
        and _featured(shapes) >= config.decisive_featured
    )


def _clear_first(hypotheses: Hypotheses, config: PoseConfig) -> bool:
    """Whether the most likely hypothesis holds `decisive_probability` and explains the contacts at least as well
    as `decisive_log_likelihood`."""
    return bool(
        hypotheses.probability[0] >= config.decisive_probability
        and hypotheses.log_likelihood[0] >= config.decisive_log_likelihood
    )


def _contact_shapes(pair: ContactPair, world: dict[str, WorldContact], config: PoseConfig) -> dict[str, LocalShape]:
    """Each contact's local shape (the joint search's key), from its cloud about its measured centre and normal."""
    return {
        side: contact_shape(
            pair.contact(side).points_sensor, world[side].p_sensor, world[side].n_sensor, config.search_config.samples
        )
        for side in SIDES
    }


def _featured(shapes: dict[str, LocalShape]) -> int:
    """How many of the two contacts have features of their own (are not `featureless`)."""
    return sum(not featureless(shapes[side]) for side in SIDES)


def _closed_form_estimate(
    pair: ContactPair,
    model: ObjectModel,
    candidates: dict[str, list[ContactEstimate]],
    world: dict[str, WorldContact],
    config: PoseConfig,
    method: str,
    tick: float,
) -> PoseEstimate:
    """The paper's pose stage: the SVD pose of the best candidate pair (by belief), no verification."""
    best: tuple[float, ContactEstimate, ContactEstimate, PoseSolution] | None = None
    for left in candidates["left"]:
        for right in candidates["right"]:
            try:
                solution = solve_pose(left, right, world["left"], world["right"])
            except DegenerateGeometryError:
                continue
            score = left.probability * right.probability
            if best is None or score > best[0]:
                best = (score, left, right, solution)
    if best is None:
        solve_pose(candidates["left"][0], candidates["right"][0], world["left"], world["right"])  # raises
        raise DegenerateGeometryError("no pair of contact candidates gives a solvable pose")
    _, left, right, solution = best
    T = solution.T_world_object
    conditioning = min(1.0, solution.conditioning / WELL_CONDITIONED)
    hypotheses = Hypotheses(T[None], np.ones(1), np.zeros(1), np.zeros(1, np.int64), np.ones(1, np.int64))
    return PoseEstimate(
        object_name=model.name,
        method=method,
        T_world_object=T,
        T_world_mesh=T @ model.T_object_mesh,
        contacts={"left": left, "right": right},
        candidates=candidates,
        world=world,
        solution=solution,
        hypotheses=hypotheses,
        ambiguous=False,
        confidence=float(left.probability * right.probability * conditioning),
        latency_ms={"pose": 1000.0 * (time.perf_counter() - tick)},
    )


def estimate_pose(
    pair: ContactPair,
    model: ObjectModel,
    localizer: ContactLocalizer,
    config: PoseConfig = PoseConfig(),
    helper: LocalizerProcess | None = None,
) -> PoseEstimate:
    """Localize both contacts of `pair` on `model` and estimate T_world_object with its hypotheses. With `helper`
    (a `LocalizerProcess` holding a copy of `localizer`), the right contact is localized there at the same time,
    and half of the pose stage's large batches are computed there (the same numbers, bitwise)."""
    start = time.perf_counter()
    candidates, world, latency = localize_contacts(pair, model, localizer, helper)
    estimate = pose_from_candidates(pair, model, candidates, world, config, localizer.name, helper=helper)
    estimate.latency_ms = {**latency, **estimate.latency_ms, "total": 1000.0 * (time.perf_counter() - start)}
    return estimate


def pose_result_path(pair_path: Path, out_dir: str | Path | None) -> Path:
    name = pair_path.name.removesuffix(".json") + POSE_RESULT_SUFFIX
    return (Path(out_dir) if out_dir else pair_path.parent) / name
