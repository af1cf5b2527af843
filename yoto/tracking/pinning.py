"""How well contacts pin each direction of the object's pose, and where a new contact would pin the weakest:
`Pinning` (the spread a reconstruction's smooth error gives a registration, direction by direction; `touch_pinning`
for the touch's two contacts) and `Retouch` (`retouch`: the surface patch that sees a direction most).

Frames: twists (rad, m) and points in the canonical `object` frame, rotation about the centroid; directions in
observable units (`frame_registration.observable_unit`); `Retouch.in_frame` maps the advice to another frame (the
mesh file's).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from yoto.contacts import SIDES, ContactPair
from yoto.geometry import invert_transform, transform_points
from yoto.objects.model import ObjectModel
from yoto.registration import SurfaceCloud
from yoto.tracking.config import CorrectionConfig
from yoto.tracking.frame_registration import contact_information, contact_samples, observable_unit


@dataclass(frozen=True)
class Pinning:
    """How well the contacts' geometry pins each direction of the object's pose: the spread a reconstruction's
    smooth error (`CorrectionConfig.bias_points` points of `bias_noise_m` per contact) gives a registration along
    the eigen-directions of the contacts' shared information. A frame's error of that kind is fixed to the pad and
    changes as the contact slides, so along a direction it moves the fit by more than the drift target no
    registration can hold the object to the target, whatever the filter does: the slip there is not observable
    from contact geometry."""

    directions: np.ndarray  # (6, 6) rows: orthonormal directions in observable units (`observable_unit`), weakest
    # first
    spread: np.ndarray  # (6,) 1-sigma of the fit's offset along each direction, observable units
    unit: np.ndarray  # (6,) the observable unit (rad, m)

    @classmethod
    def of(cls, shared: np.ndarray, unit: np.ndarray) -> Pinning:
        """From the contacts' shared-error information (6, 6; rad, m), summed over the contacts."""
        values, vectors = np.linalg.eigh(shared * np.outer(unit, unit))
        spread = 1.0 / np.sqrt(np.maximum(values, 1e-12))
        return cls(vectors.T, spread, unit)

    def twist(self, index: int) -> np.ndarray:
        """(6,) direction `index` as a twist (rad, m) of unit size in observable units."""
        return self.directions[index] * self.unit

    def split(self, twist: np.ndarray, weak_above: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """A twist (rad, m) as (pinned part, weakly pinned part): its components along the directions whose spread is
        at most / more than `weak_above` observable units (orthogonal in those units)."""
        weak = self.directions[self.spread > weak_above]
        along = (weak.T @ (weak @ (twist / self.unit))) * self.unit
        return twist - along, along

    def describe(self, index: int = 0) -> str:
        """Direction `index` (default the weakest) in words: its turn and shift per observable unit, and its spread."""
        twist = self.twist(index)
        turn, shift = np.degrees(twist[:3]), 1e3 * twist[3:]
        return (
            f"turn ({turn[0]:+.2f}, {turn[1]:+.2f}, {turn[2]:+.2f}) deg with shift ({shift[0]:+.2f}, {shift[1]:+.2f}, "
            f"{shift[2]:+.2f}) mm (object frame, about the centroid), pinned to {self.spread[index]:.2f} of that"
        )


@dataclass(frozen=True)
class Retouch:
    """Where on the object a contact would see one direction of the pose (`retouch`): a contact pins a direction by
    how far that motion moves the surface under it along the surface's normal (sliding along itself, the surface
    shows nothing)."""

    point: np.ndarray  # (3,) the surface sample whose patch sees the direction most (the surface's frame: the
    # canonical object frame for a model; `in_frame` maps it)
    normal: np.ndarray  # (3,) its outward normal: a sensor would press there along -normal
    seen_m: float  # root mean square over that patch of the surface's motion along its normal per observable unit
    seen_at_contacts_m: float  # the same over the touch's contact points: information grows with its square

    def in_frame(self, T_frame_surface: np.ndarray) -> Retouch:
        """The same advice with its point and normal mapped by `T_frame_surface` (e.g. `T_mesh_object`)."""
        point = transform_points(T_frame_surface, self.point[None])[0]
        return dataclasses.replace(self, point=point, normal=T_frame_surface[:3, :3] @ self.normal)

    def describe(self) -> str:
        """In words (millimetres)."""
        point, normal = 1e3 * self.point, self.normal
        return (
            f"a contact at ({point[0]:+.1f}, {point[1]:+.1f}, {point[2]:+.1f}) mm, surface normal ({normal[0]:+.2f}, "
            f"{normal[1]:+.2f}, {normal[2]:+.2f}), would see it move the surface {1e3 * self.seen_m:.3f} mm along "
            f"its normal per unit, the touch's contacts {1e3 * self.seen_at_contacts_m:.3f} mm"
        )


def retouch(
    surface: SurfaceCloud,
    twist: np.ndarray,
    contacts_object: np.ndarray,
    patch_points: int = 64,
    candidates: int = 3000,
) -> Retouch:
    """Where a contact would pin the direction `twist` (rad, m; object frame about its origin, e.g.
    `Pinning.twist(0)`, the weakest): each surface sample moves by w x p + v under it, and a contact there sees the
    part along the surface's normal. Over patches of `patch_points` nearest samples (about a contact's size on a
    model's parent cloud) around `candidates` evenly taken samples, the patch where that motion's root mean square
    is largest, against the same over `contacts_object` (the touch's contact points, object frame). On a surface of
    revolution spun about its axis, or a cylinder slid along it, no patch sees the motion: no re-touch pins it."""
    points = np.asarray(surface.points_object, dtype=np.float64)
    normals = np.asarray(surface.normals_object, dtype=np.float64)

    def seen(where: np.ndarray, normal: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", normal, np.cross(twist[:3], where) + twist[3:])

    along = seen(points, normals)
    picked = np.arange(0, len(points), max(1, len(points) // candidates))
    tree = surface.kdtree if isinstance(surface.kdtree, cKDTree) else cKDTree(points)  # a model's, built already
    _, patches = tree.query(points[picked], k=min(patch_points, len(points)))
    patch_rms = np.sqrt(np.mean(along[patches.reshape(len(picked), -1)] ** 2, axis=1))
    best = picked[int(np.argmax(patch_rms))]
    _, nearest = tree.query(np.asarray(contacts_object, dtype=np.float64))
    return Retouch(
        points[best],
        normals[best],
        float(patch_rms.max()),
        float(np.sqrt(np.mean(seen(points[nearest], normals[nearest]) ** 2))),
    )


def touch_pinning(
    model: ObjectModel, pair: ContactPair, T_world_object: np.ndarray, config: CorrectionConfig = CorrectionConfig()
) -> Pinning:
    """How well the touch's two contacts pin the object at `T_world_object` (canonical frame): their clouds sampled
    as the closed loop samples its frames (`contact_samples`), placed on the object through the pair's sensor
    poses, their shared-error information checked against the surface."""
    points = {
        side: transform_points(
            invert_transform(T_world_object) @ pair.contact(side).T_world_sensor,
            contact_samples(pair.contact(side).points_sensor, config),
        )
        for side in SIDES
    }
    shared = np.sum([bias for _, bias in contact_information(model, points, config).values()], axis=0)
    return Pinning.of(shared, observable_unit(config))
