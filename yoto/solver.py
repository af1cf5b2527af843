"""Pose from two localized contacts: the normal-aware SVD solver (paper Sec. 3.4).

Object side: each contact's location `p_object` and outward normal `n_object` on the model (from a
localizer). World side: each contact's location `p_world` and outward surface normal `n_world`, measured
by the sensor (its tactile cloud mapped by `T_world_sensor`). With d the unit vector from the left to the
right contact, the rotation solves Procrustes on Q_world = [d_w, nL_w, nR_w] vs Q_object = [d_o, nL_o, nR_o];
the translation aligns the two contact points on average.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from yoto.contacts import TactileContact
from yoto.errors import DegenerateGeometryError
from yoto.geometry import make_transform, normalize, procrustes_rotation, rotate_vectors, transform_points
from yoto.pointcloud import covariance_eigh

MIN_CONTACT_SEPARATION_M = 0.002  # closer contacts leave the contact-to-contact direction undefined
WELL_CONDITIONED = 0.15  # sigma_2 / sigma_1 of Q_object below this: rotation about one axis is weakly fixed
LOCAL_FIT_RADIUS_M = 0.002  # radius of the surface patch fitted at the contact centre of a tactile cloud
LOCAL_FIT_MIN_POINTS = 12
LINE_POINTS = 8  # points averaged where the centroid's normal line meets the cloud


@dataclass
class ContactEstimate:
    """One contact located on the object model (object frame), with what the localizer knows of it."""

    p_object: np.ndarray  # (3,) contact location
    n_object: np.ndarray  # (3,) outward unit normal there (kNN-aggregated from the parent cloud)
    block: int = -1  # block index, -1 if the localizer has no blocks
    score: float = 0.0  # the localizer's own ranking score (higher is better); comparable within a method
    probability: float = 1.0  # the localizer's belief in this candidate, in [0, 1]
    details: dict = field(default_factory=dict)  # method-specific extras for result files


@dataclass
class WorldContact:
    """One contact as the sensor measured it: location and outward object normal, sensor and world frames."""

    p_sensor: np.ndarray
    n_sensor: np.ndarray
    p_world: np.ndarray
    n_world: np.ndarray


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


def contact_in_sensor(points_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contact centre and outward object normal of a tactile cloud, in the sensor frame.

    The normal is that of a plane fitted to the points around the centroid, signed to point out of the
    object, i.e. toward the sensor (-z). The centre is where the line through the centroid along that
    normal meets the cloud (the surface point nearest the centroid, which is how ground-truth contact
    locations are defined); it is read off the few points closest to the line, so curvature adds no bias.
    """
    centroid = points_sensor.mean(axis=0)
    offsets = points_sensor - centroid
    # Plain distances beat building a KD-tree for one query on a dense (~20k-point) tactile cloud.
    nearest = points_sensor[np.argmin(np.einsum("ij,ij->i", offsets, offsets))]
    squared = np.einsum("ij,ij->i", points_sensor - nearest, points_sensor - nearest)
    neighbours = np.flatnonzero(squared <= LOCAL_FIT_RADIUS_M**2)
    if len(neighbours) < LOCAL_FIT_MIN_POINTS:
        neighbours = np.argsort(squared)[:LOCAL_FIT_MIN_POINTS]
    _, _, eigenvectors = covariance_eigh(points_sensor[neighbours])
    normal = eigenvectors[:, 0] if eigenvectors[2, 0] <= 0 else -eigenvectors[:, 0]
    along = offsets @ normal
    off_line = np.linalg.norm(offsets - along[:, None] * normal, axis=1)
    closest_to_line = np.argpartition(off_line, min(LINE_POINTS, len(off_line) - 1))[:LINE_POINTS]
    return centroid + along[closest_to_line].mean() * normal, normal


def contact_in_world(contact: TactileContact) -> WorldContact:
    p_sensor, n_sensor = contact_in_sensor(contact.points_sensor)
    return WorldContact(
        p_sensor=p_sensor,
        n_sensor=n_sensor,
        p_world=transform_points(contact.T_world_sensor, p_sensor),
        n_world=rotate_vectors(contact.T_world_sensor, n_sensor),
    )


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
    q_object = np.stack([normalize(offset_object), normalize(left.n_object), normalize(right.n_object)], axis=1)
    q_world = np.stack([normalize(offset_world), normalize(left_world.n_world), normalize(right_world.n_world)], axis=1)
    rotation, _ = procrustes_rotation(q_world, q_object)
    translation = 0.5 * (
        (left_world.p_world - rotation @ left.p_object) + (right_world.p_world - rotation @ right.p_object)
    )
    singular_values = np.linalg.svd(q_object, compute_uv=False)
    conditioning = float(singular_values[1] / singular_values[0])
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
