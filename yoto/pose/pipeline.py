"""The pose stage: contact pair -> localize both contacts -> SVD solve -> pose result (SPEC: "Pose result").

Localizers return a few ranked candidates per contact; the pair of candidates is chosen jointly (with one
candidate per side and `verify`/`refine` off this is exactly the paper's method):
1. consistency: two true contacts agree with the sensors on their separation and on the three angles
   between the contact-to-contact direction and the two normals;
2. verification: under a true pair's SVD pose, both tactile clouds lie on the object's surface;
3. refinement: the chosen pose is sharpened by a joint point-to-plane ICP of both clouds (`refine.py`).
The chosen pair maximises belief x consistency x verification.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import (
    POSE_RESULT_SUFFIX,
    SIDES,
    WELL_CONDITIONED,
    ContactEstimate,
    ContactPair,
    WorldContact,
    contact_in_world,
)
from yoto.errors import DegenerateGeometryError
from yoto.geometry import rotate_vectors, transform_points
from yoto.localize.base import ContactLocalizer
from yoto.objects.model import ObjectModel
from yoto.pose.refine import RefineConfig, SurfaceFit, contact_samples, refine_pose, surface_fit
from yoto.pose.solver import PoseSolution, solve_pose

# Scales of the checks: how far a true pair of contacts typically disagrees with the sensors.
SEPARATION_SCALE_M = 0.004
ANGLE_SCALE_RAD = np.radians(12.0)
SURFACE_SCALE_M = 0.0005


@dataclass(frozen=True)
class PoseConfig:
    """How the pose stage turns ranked contact candidates into a pose."""

    joint_selection: bool = True  # choose the candidate pair jointly (False: each localizer's top candidate)
    verify: bool = True  # check the best hypotheses by how well the tactile clouds lie on the surface
    refine: bool = True  # sharpen the chosen pose by joint point-to-plane ICP of both clouds
    hypotheses_verified: int = 8  # how many hypotheses (best by belief x consistency) are verified
    refine_config: RefineConfig = RefineConfig()


PAPER = PoseConfig(joint_selection=False, verify=False, refine=False)  # the paper's pose stage, exactly


@dataclass
class PoseEstimate:
    """A pose from one contact pair, with everything a user needs to decide whether to act on it."""

    object_name: str
    method: str
    T_world_object: np.ndarray  # (4, 4), YOTO's canonical object frame
    T_world_mesh: np.ndarray  # (4, 4), the mesh file's frame (what users and mocap know)
    contacts: dict[str, ContactEstimate]  # chosen candidate per side
    candidates: dict[str, list[ContactEstimate]]  # every candidate per side, the localizer's order
    world: dict[str, WorldContact]
    solution: PoseSolution
    consistency: float  # in [0, 1]: how well the two contacts agree with the sensors' geometry
    confidence: float  # in [0, 1]: belief of the localizers x consistency x surface fit x conditioning
    surface_fit: SurfaceFit | None = None  # how well both tactile clouds lie on the model under the pose
    refined: bool = False  # whether refinement moved the pose
    latency_ms: dict[str, float] = field(default_factory=dict)

    def to_json(self, model: ObjectModel) -> dict[str, Any]:
        """The SPEC pose result: poses, points and normals in the mesh file's frame."""
        T_mesh_object = model.T_mesh_object
        sides = {}
        for side in SIDES:
            contact = self.contacts[side]
            sides[side] = {
                "p_object": transform_points(T_mesh_object, contact.p_object).tolist(),
                "n_object": rotate_vectors(T_mesh_object, contact.n_object).tolist(),
                "block": int(contact.block),
                "score": float(contact.score),
                "probability": float(contact.probability),
                "p_world_measured": self.world[side].p_world.tolist(),
                **{key: value for key, value in contact.details.items()},
            }
        return {
            "object": self.object_name,
            "method": self.method,
            "frame": "mesh file frame (the frame of the mesh the object model was built from)",
            "T_world_object": self.T_world_mesh.tolist(),
            **sides,
            "confidence": float(self.confidence),
            "consistency": float(self.consistency),
            "conditioning": float(self.solution.conditioning),
            "well_conditioned": bool(self.solution.well_conditioned),
            "separation_error_mm": 1000.0 * self.solution.separation_error_m,
            "normal_angle_error_deg": float(np.degrees(self.solution.normal_angle_error_rad)),
            "surface_rms_mm": None if self.surface_fit is None else 1000.0 * self.surface_fit.rms_m,
            "surface_inlier_fraction": None if self.surface_fit is None else self.surface_fit.inlier_fraction,
            "refined": self.refined,
            "warnings": self.solution.warnings,
            "latency_ms": self.latency_ms,
        }


def geometric_consistency(solution: PoseSolution) -> float:
    """1 when the contacts' separation and the angles between d, nL, nR match the sensors', falling off as
    they disagree."""
    angle_terms = np.sum((solution.direction_angle_errors_rad / ANGLE_SCALE_RAD) ** 2)
    return float(np.exp(-0.5 * (solution.separation_error_m / SEPARATION_SCALE_M) ** 2 - 0.5 * angle_terms))


def surface_agreement(fit: SurfaceFit) -> float:
    """1 when the tactile clouds lie on the surface, falling off with their RMS distance from it."""
    return float(np.exp(-0.5 * (fit.rms_m / SURFACE_SCALE_M) ** 2))


@dataclass
class _Hypothesis:
    left: ContactEstimate
    right: ContactEstimate
    solution: PoseSolution
    consistency: float
    fit: SurfaceFit | None = None

    @property
    def score(self) -> float:
        agreement = 1.0 if self.fit is None else surface_agreement(self.fit)
        return self.left.probability * self.right.probability * self.consistency * agreement


def choose_hypothesis(
    candidates: dict[str, list[ContactEstimate]],
    world: dict[str, WorldContact],
    model: ObjectModel,
    points_world: np.ndarray | None,
    config: PoseConfig,
) -> _Hypothesis:
    """The best candidate pair by belief x consistency (x surface agreement when `points_world` is given)."""
    hypotheses = []
    for left, right in itertools.product(candidates["left"], candidates["right"]):
        try:
            solution = solve_pose(left, right, world["left"], world["right"])
        except DegenerateGeometryError:
            continue
        hypotheses.append(_Hypothesis(left, right, solution, geometric_consistency(solution)))
    if not hypotheses:
        # Every combination collapsed; solve the top pair to raise its error for the caller.
        solve_pose(candidates["left"][0], candidates["right"][0], world["left"], world["right"])
        raise DegenerateGeometryError("no pair of contact candidates gives a solvable pose")
    hypotheses.sort(key=lambda h: h.score, reverse=True)
    if points_world is None:
        return hypotheses[0]
    shortlist = hypotheses[: config.hypotheses_verified]
    for hypothesis in shortlist:
        hypothesis.fit = surface_fit(model, hypothesis.solution.T_world_object, points_world, config.refine_config)
    return max(shortlist, key=lambda h: h.score)


def localize_contacts(
    pair: ContactPair, model: ObjectModel, localizer: ContactLocalizer
) -> tuple[dict[str, list[ContactEstimate]], dict[str, WorldContact], dict[str, float]]:
    """Each contact's ranked candidates on the model, its world-side measurement, and the localizer's time (ms)."""
    latency: dict[str, float] = {}
    candidates: dict[str, list[ContactEstimate]] = {}
    world: dict[str, WorldContact] = {}
    for side in SIDES:
        contact = pair.contact(side)
        truth = None
        if localizer.needs_ground_truth:
            if side not in pair.p_mesh_true:
                raise DegenerateGeometryError(f"{pair.path}: the oracle needs ground_truth.{side}_p_object")
            truth = transform_points(model.T_object_mesh, pair.p_mesh_true[side])
        tick = time.perf_counter()
        candidates[side] = localizer.localize(contact.points_sensor, model, truth)
        latency[f"localize_{side}"] = 1000.0 * (time.perf_counter() - tick)
        world[side] = contact_in_world(contact)
    return candidates, world, latency


def pose_from_candidates(
    pair: ContactPair,
    model: ObjectModel,
    candidates: dict[str, list[ContactEstimate]],
    world: dict[str, WorldContact],
    config: PoseConfig = PoseConfig(),
    method: str = "",
) -> PoseEstimate:
    """The pose stage proper: choose, verify and refine from localized candidates. `latency_ms["solve"]` is set."""
    tick = time.perf_counter()
    if not config.joint_selection:
        candidates = {side: found[:1] for side, found in candidates.items()}
    points_world = None
    if config.verify or config.refine:
        points_world = np.vstack(
            [
                contact_samples(
                    pair.contact(side).points_sensor,
                    pair.contact(side).T_world_sensor,
                    model.point_spacing_m,
                    config.refine_config,
                )
                for side in SIDES
            ]
        )
    best = choose_hypothesis(candidates, world, model, points_world if config.verify else None, config)
    T_world_object, fit, refined = best.solution.T_world_object, best.fit, False
    if config.refine and points_world is not None:
        T_world_object, fit = refine_pose(model, T_world_object, points_world, config.refine_config)
        refined = T_world_object is not best.solution.T_world_object
    conditioning_factor = min(1.0, best.solution.conditioning / WELL_CONDITIONED)
    agreement = 1.0 if fit is None else surface_agreement(fit)
    return PoseEstimate(
        object_name=model.name,
        method=method,
        T_world_object=T_world_object,
        T_world_mesh=T_world_object @ model.T_object_mesh,
        contacts={"left": best.left, "right": best.right},
        candidates=candidates,
        world=world,
        solution=best.solution,
        consistency=best.consistency,
        confidence=float(
            best.left.probability * best.right.probability * best.consistency * agreement * conditioning_factor
        ),
        surface_fit=fit,
        refined=refined,
        latency_ms={"solve": 1000.0 * (time.perf_counter() - tick)},
    )


def estimate_pose(
    pair: ContactPair, model: ObjectModel, localizer: ContactLocalizer, config: PoseConfig = PoseConfig()
) -> PoseEstimate:
    """Localize both contacts of `pair` on `model` and solve T_world_object."""
    start = time.perf_counter()
    candidates, world, latency = localize_contacts(pair, model, localizer)
    estimate = pose_from_candidates(pair, model, candidates, world, config, localizer.name)
    estimate.latency_ms = {**latency, **estimate.latency_ms, "total": 1000.0 * (time.perf_counter() - start)}
    return estimate


def pose_result_path(pair_path: Path, out_dir: str | Path | None) -> Path:
    name = pair_path.name.removesuffix(".json") + POSE_RESULT_SUFFIX
    return (Path(out_dir) if out_dir else pair_path.parent) / name
