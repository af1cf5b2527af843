"""Pose from two localized contacts: the normal-aware SVD solver (paper Sec. 3.4).

Object side: each contact's location `p_object` and outward normal `n_object` on the model (from a
localizer). World side: each contact's location `p_world` and outward surface normal `n_world`, measured
by the sensor (its tactile cloud mapped by `T_world_sensor`). With d the unit vector from the left to the
right contact, the rotation solves Procrustes on Q_world = [d_w, nL_w, nR_w] vs Q_object = [d_o, nL_o, nR_o];
the translation aligns the two contact points on average.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.contacts import (
    SIDES,
    WELL_CONDITIONED,
    ContactEstimate,
    ContactPair,
    WorldContact,
    contact_in_world,
    dual_contact_conditioning,
    dual_contact_directions,
)
from yoto.errors import DegenerateGeometryError, InputError
from yoto.geometry import (
    invert_transform,
    make_transform,
    normalize,
    procrustes_rotation,
    rotation_angle_rad,
    transform_points,
)
from yoto.objects.model import ObjectModel

MIN_CONTACT_SEPARATION_M = 0.002  # closer contacts leave the contact-to-contact direction undefined


@dataclass
class PoseSolution:
    """The solver's pose and how far to trust its geometry."""

    T_world_object: np.ndarray  # (4, 4), object = YOTO's canonical frame
    direction_singular_values: np.ndarray  # (3,) singular values of Q_object (unit columns)
    conditioning: float  # sigma_2 / sigma_1 of Q_object: 0 means rotation about one axis is free
    well_conditioned: bool
    separation_error_m: float  # | |pR_w - pL_w| - |pR_o - pL_o| |: a wrong localization shows here
    normal_angle_error_rad: float  # |angle(nL_w, nR_w) - angle(nL_o, nR_o)|
    direction_angle_errors_rad: np.ndarray  # (3,) |world - object| of the angles (d, nL), (d, nR), (nL, nR)
    alignment_residual_rad: float  # largest angle between R @ Q_object and Q_world columns

    @property
    def warnings(self) -> list[str]:
        notes = []
        if not self.well_conditioned:
            notes.append(
                f"near-coaxial contacts (conditioning {self.conditioning:.3f} < {WELL_CONDITIONED}): the rotation "
                "about the contact axis is poorly determined; touch again with less opposed sensors"
            )
        return notes


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(normalize(a) @ normalize(b), -1.0, 1.0)))


def solve_pose(
    left: ContactEstimate, right: ContactEstimate, left_world: WorldContact, right_world: WorldContact
) -> PoseSolution:
    """T_world_object from two contacts located on the object and measured in the world.

    Raises DegenerateGeometryError when the contacts coincide (on the object or in the world). Near-coaxial
    contacts (all three directions nearly parallel) return a solution flagged `well_conditioned=False`.
    """
    offset_object = right.p_object - left.p_object
    offset_world = right_world.p_world - left_world.p_world
    for offset, frame in ((offset_object, "on the object"), (offset_world, "in the world")):
        if np.linalg.norm(offset) < MIN_CONTACT_SEPARATION_M:
            raise DegenerateGeometryError(
                f"the two contacts are {np.linalg.norm(offset) * 1000:.2f} mm apart {frame}: the pose needs two "
                "distinct contacts"
            )
    q_object = dual_contact_directions(offset_object, left.n_object, right.n_object)
    q_world = dual_contact_directions(offset_world, left_world.n_world, right_world.n_world)
    rotation, _ = procrustes_rotation(q_world, q_object)
    translation = 0.5 * (
        (left_world.p_world - rotation @ left.p_object) + (right_world.p_world - rotation @ right.p_object)
    )
    conditioning, singular_values = dual_contact_conditioning(offset_object, left.n_object, right.n_object)
    aligned = rotation @ q_object
    pairs = ((0, 1), (0, 2), (1, 2))
    angle_errors = np.array(
        [abs(_angle(q_world[:, i], q_world[:, j]) - _angle(q_object[:, i], q_object[:, j])) for i, j in pairs]
    )
    return PoseSolution(
        T_world_object=make_transform(rotation, translation),
        direction_singular_values=singular_values,
        conditioning=conditioning,
        well_conditioned=conditioning >= WELL_CONDITIONED,
        separation_error_m=float(abs(np.linalg.norm(offset_world) - np.linalg.norm(offset_object))),
        normal_angle_error_rad=float(angle_errors[2]),
        direction_angle_errors_rad=angle_errors,
        alignment_residual_rad=max(_angle(aligned[:, i], q_world[:, i]) for i in range(3)),
    )


def oracle_pose_errors(model: ObjectModel, pair: ContactPair) -> tuple[float, float]:
    """Translation (m) and rotation (rad) error of the solver fed ground-truth contacts and model normals.

    The tactile clouds give the world side (`contact_in_world`); the true contact locations and the model's
    aggregated normals there give the object side. This is the floor of the geometric chain.
    """
    if not pair.has_ground_truth:
        raise InputError("the pair has no ground truth", pair.path)
    T_object_mesh = invert_transform(model.T_mesh_object)
    left, right = (
        ContactEstimate(p_object, model.aggregated_normal(p_object))
        for p_object in (transform_points(T_object_mesh, pair.p_mesh_true[side]) for side in SIDES)
    )
    solution = solve_pose(left, right, contact_in_world(pair.left), contact_in_world(pair.right))
    T_world_object_true = pair.T_world_mesh_true @ model.T_mesh_object
    translation_error = float(np.linalg.norm(solution.T_world_object[:3, 3] - T_world_object_true[:3, 3]))
    return translation_error, rotation_angle_rad(solution.T_world_object, T_world_object_true)
