"""The pose stage: contact pair -> localize both contacts -> SVD solve -> pose result (SPEC: "Pose result").

Localizers return a few ranked candidates per contact. Two true contacts must agree with the sensors on
their separation and on the angle between their normals, so the pair of candidates is chosen jointly:
the one that maximises the localizers' beliefs times that geometric consistency. With a single candidate
per side this reduces to the paper's independent choice.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import POSE_RESULT_SUFFIX, SIDES, ContactPair
from yoto.errors import DegenerateGeometryError
from yoto.geometry import rotate_vectors, transform_points
from yoto.localize.base import ContactLocalizer
from yoto.objects.model import ObjectModel
from yoto.solver import WELL_CONDITIONED, ContactEstimate, PoseSolution, WorldContact, contact_in_world, solve_pose

# Scales of the geometric consistency check: how far two true contacts typically disagree with the sensors.
SEPARATION_SCALE_M = 0.004
NORMAL_ANGLE_SCALE_RAD = np.radians(12.0)


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
    confidence: float  # in [0, 1]: belief of the localizers x consistency x conditioning
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
            "warnings": self.solution.warnings,
            "latency_ms": self.latency_ms,
        }


def geometric_consistency(solution: PoseSolution) -> float:
    """1 when the contacts' separation and normal angle match the sensors', falling off as they disagree."""
    return float(
        np.exp(-0.5 * (solution.separation_error_m / SEPARATION_SCALE_M) ** 2)
        * np.exp(-0.5 * (solution.normal_angle_error_rad / NORMAL_ANGLE_SCALE_RAD) ** 2)
    )


def choose_candidates(
    candidates: dict[str, list[ContactEstimate]], world: dict[str, WorldContact]
) -> tuple[ContactEstimate, ContactEstimate, PoseSolution, float]:
    """The candidate pair with the highest belief x consistency, its pose and its consistency."""
    best = None
    for left, right in itertools.product(candidates["left"], candidates["right"]):
        try:
            solution = solve_pose(left, right, world["left"], world["right"])
        except DegenerateGeometryError:
            continue
        consistency = geometric_consistency(solution)
        score = left.probability * right.probability * consistency
        if best is None or score > best[0]:
            best = (score, left, right, solution, consistency)
    if best is None:
        # Every combination collapsed; solve the top pair to raise its error for the caller.
        solve_pose(candidates["left"][0], candidates["right"][0], world["left"], world["right"])
        raise DegenerateGeometryError("no pair of contact candidates gives a solvable pose")
    return best[1], best[2], best[3], best[4]


def estimate_pose(
    pair: ContactPair, model: ObjectModel, localizer: ContactLocalizer, joint_selection: bool = True
) -> PoseEstimate:
    """Localize both contacts of `pair` on `model` and solve T_world_object."""
    start = time.perf_counter()
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
        found = localizer.localize(contact.points_sensor, model, truth)
        latency[f"localize_{side}"] = 1000.0 * (time.perf_counter() - tick)
        candidates[side] = found if joint_selection else found[:1]
        world[side] = contact_in_world(contact)
    tick = time.perf_counter()
    left, right, solution, consistency = choose_candidates(candidates, world)
    latency["solve"] = 1000.0 * (time.perf_counter() - tick)
    latency["total"] = 1000.0 * (time.perf_counter() - start)
    conditioning_factor = min(1.0, solution.conditioning / WELL_CONDITIONED)
    return PoseEstimate(
        object_name=model.name,
        method=localizer.name,
        T_world_object=solution.T_world_object,
        T_world_mesh=solution.T_world_object @ model.T_object_mesh,
        contacts={"left": left, "right": right},
        candidates=candidates,
        world=world,
        solution=solution,
        consistency=consistency,
        confidence=float(left.probability * right.probability * consistency * conditioning_factor),
        latency_ms=latency,
    )


def pose_result_path(pair_path: Path, out_dir: str | Path | None) -> Path:
    name = pair_path.name.removesuffix(".json") + POSE_RESULT_SUFFIX
    return (Path(out_dir) if out_dir else pair_path.parent) / name
