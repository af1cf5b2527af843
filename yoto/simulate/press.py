"""Pressing a simulated GelSight Mini into a mesh: height map, contact mask, tactile cloud, ground truth.

This is the contact simulator that stands in for real contacts in tests and benchmarks (SPEC: "The
GelSight Mini and its simulated contacts"). It is deliberately unrelated to the virtual-patch sampler
used for training: a patch here is what a flat elastomer pad sees when it is pushed into the mesh, not a
ball of parent points.

Frames: `object` is the frame of the mesh given to `PressSimulator` (for an ObjectModel, YOTO's canonical
frame, `model.mesh_object`); `sensor` is the GelSight frame of the SPEC (origin at the centre of the
undeformed gel, x along image columns, y along rows, z out of the gel toward the object, gel at z = 0).

The press, step by step (`PressSimulator.press`):
1. Rays. One ray per image pixel (320 x 240 at 0.0634 mm), starting far behind the gel (outside the object)
   and travelling along the sensor's +z. The first hit gives the object surface height `z_obj(x, y)`.
   A hit on a back face (ray and face normal pointing the same way) near the gel means an open mesh or a
   wall thinner than the ray spacing: the press is rejected.
2. Depth. The sensor is moved along its z so that the deepest point of the object over the pad lies exactly
   `depth_m` behind the undeformed gel: a press stops at a depth measured at its deepest point.
3. Gel. The gel sinks in where the object pushes it and smoothly around it (`gel.gel_surface`); the contact
   mask is where it touches the object.
4. Reachability. The sensor body (housing, probe: `body.SensorBody`) must not collide with the object; the
   chosen target point must lie inside the contact (deep concavities: the surrounding surface reaches the pad
   first); the contact must be large enough; a narrow contact crossing the whole pad (an edge thinner than
   the pad) is rejected.
5. Ground truth. The object-frame surface point nearest the centroid of the noise-free contact patch
   (nearest point on the mesh surface, not on a point cloud).

An accepted press becomes a tactile cloud through the reconstruction noise model (`gel.reconstruct_points`)
or a caller's reconstruction (`simulate_contact(reconstruct=...)`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from yoto.errors import InputError, YotoError
from yoto.geometry import (
    invert_transform,
    make_transform,
    normalize,
    rotation_about_axis,
    rotation_between,
    tangent_basis,
    transform_points,
)
from yoto.raycast import MeshRaycaster
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec
from yoto.simulate.body import BodySweep, SensorBody
from yoto.simulate.gel import GelModel, ReconstructionNoise, gel_surface, reconstruct_points

SIMULATOR_VERSION = 1

# Why a press was rejected. Keys are stable identifiers (they appear in statistics and files).
REJECTION_REASONS = {
    "no_contact": "nothing under the pad: the rays miss the object",
    "no_normal": "the model has no defined normal at the chosen point (a sheet thinner than the normal estimate)",
    "back_face": "rays hit back faces near the gel (open mesh, or a wall thinner than a pixel)",
    "target_occluded": "another part of the object lies in front of the chosen point (a deep concavity or overhang)",
    "target_not_in_contact": "the press stops before reaching the chosen point (a concavity at the pad's scale, "
    "or a tilted press on a flat face)",
    "small_contact": "the contact covers too few pixels (a sharp corner or a small feature)",
    "thin_edge": "a narrow contact crossing the whole pad (an edge or ridge thinner than the pad can resolve)",
    "border": "the contact covers too much of the pad border",
    "housing_collision": "the sensor body (housing or the probe behind it) would collide with the object",
    "reconstruction_failed": "the reconstruction returned too few points",
}


# ------------------------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class PressConfig:
    """Everything that defines one simulated press and whether it is accepted."""

    spec: GelSightSpec = GELSIGHT_MINI
    body: SensorBody = SensorBody()
    gel: GelModel = GelModel()
    noise: ReconstructionNoise = ReconstructionNoise()
    depth_range_m: tuple[float, float] = (0.0005, 0.0015)  # indentation depth, uniform (SPEC: 0.5-1.5 mm)
    max_tilt_deg: float = 10.0  # approach direction: reversed surface normal tilted by up to this (uniform on the cap)
    max_offset_m: float = 0.0015  # the pad centre lands up to this far from the target (uniform on a disc)
    min_contact_pixels: int = 500  # fewer contact pixels are rejected (about 2 mm^2)
    min_crossing_width_m: float = 0.0025  # a contact crossing the pad narrower than this is a thin edge
    max_border_fraction: float = 1.0  # reject contacts covering more of the pad border than this (1: never;
    # measured: contacts touching the border are no harder for the solver, see docs/simulation.md)
    back_face_clearance_m: float = 0.002  # back faces hit closer than this in front of the gel reject the press
    target_tolerance_m: float = 1e-4  # the target counts as seen if the ray through it first hits within this
    collision_ray_spacing_m: float = 0.001  # spacing of the rays that sweep the body boxes for collisions


# ------------------------------------------------------------------------------------------------ results
@dataclass
class Press:
    """One press of the sensor into the object, noise-free, and whether the sensor could have made it."""

    T_object_sensor: np.ndarray  # (4, 4) final sensor pose: the gel's undeformed surface is z = 0 of this frame
    depth_m: float  # deepest penetration of the object into the undeformed gel
    object_z_m: np.ndarray  # (H, W) first-hit object surface z in the sensor frame; +inf where no surface
    height_map_m: np.ndarray  # (H, W) noise-free gel surface z (<= 0), metres
    contact_mask: np.ndarray  # (H, W) bool, where the gel touches the object
    p_object: np.ndarray | None = None  # (3,) ground-truth contact location (object frame), None if rejected
    rejection: str | None = None  # key of REJECTION_REASONS, None if accepted
    details: dict[str, Any] = field(default_factory=dict)  # measured quantities behind the decision

    @property
    def accepted(self) -> bool:
        return self.rejection is None

    @property
    def contact_pixels(self) -> int:
        return int(self.contact_mask.sum())

    def contact_points_sensor(self, spec: GelSightSpec = GELSIGHT_MINI) -> np.ndarray:
        """The noise-free contact patch: (N, 3) sensor-frame points of the gel where it touches the object."""
        return spec.height_map_to_points(self.height_map_m, self.contact_mask)

    @property
    def p_sensor(self) -> np.ndarray | None:
        """The ground-truth contact location in the sensor frame."""
        if self.p_object is None:
            return None
        return transform_points(invert_transform(self.T_object_sensor), self.p_object)


@dataclass
class SimulatedContact:
    """An attempted contact: the approach that was drawn, the press, and (if accepted) the tactile cloud."""

    target_object: np.ndarray  # (3,) the surface point the sensor was aimed at
    approach: dict[str, float]  # tilt_deg, roll_deg, offset_mm, depth_mm
    press: Press
    # (N, 3) reconstructed tactile cloud, sensor frame; empty until an accepted press is reconstructed
    points_sensor: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    noise: dict[str, float] = field(default_factory=dict)  # the reconstruction errors drawn for this press

    @property
    def accepted(self) -> bool:
        return self.press.accepted and len(self.points_sensor) > 0

    @property
    def rejection(self) -> str | None:
        return self.press.rejection

    @property
    def p_object(self) -> np.ndarray:
        """The ground-truth contact location (object frame) of an accepted press."""
        if self.press.p_object is None:
            raise ValueError(f"a rejected press ({self.rejection}) has no ground-truth contact location")
        return self.press.p_object


# ------------------------------------------------------------------------------------------------ simulator
class PressSimulator:
    """Presses a GelSight into one mesh. Ray casting is set up once; a press then takes tens of ms."""

    def __init__(
        self,
        mesh_object: trimesh.Trimesh,
        config: PressConfig = PressConfig(),
        raycaster: MeshRaycaster | None = None,
    ):
        """`raycaster`: ray casting on `mesh_object` when one exists already (`ObjectModel.raycaster`)."""
        vertices = np.asarray(mesh_object.vertices, dtype=np.float64)
        if len(mesh_object.faces) == 0:
            raise InputError("cannot press a sensor into a mesh without faces")
        self.config = config
        self.mesh = mesh_object
        self.raycaster = raycaster or MeshRaycaster(vertices, mesh_object.faces, "the GelSight contact simulator")
        self.bounds_centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        self.bounds_radius = float(np.linalg.norm(vertices - self.bounds_centre, axis=1).max())
        spec = config.spec
        x, y = spec.pixel_xy_sensor()
        self._pixel_x, self._pixel_y = x.ravel(), y.ravel()  # every pixel, row-major
        self._coarse_x, self._coarse_y = x[::8, ::8].ravel(), y[::8, ::8].ravel()  # every 8th row and column
        self._border = _border_ring_indices(spec.height_px, spec.width_px)
        self._body_sweep = BodySweep.of(config.body.boxes(spec), config.collision_ray_spacing_m)
        self._face_area_cdf = np.cumsum(mesh_object.area_faces) / mesh_object.area

    # ------------------------------------------------------------------------------------------ sampling
    def sample_surface(self, rng: np.random.Generator, count: int = 1) -> np.ndarray:
        """`count` points drawn uniformly (by area) from the mesh surface, object frame, (count, 3)."""
        faces = np.searchsorted(self._face_area_cdf, rng.random(count) * self._face_area_cdf[-1], side="right")
        faces = np.minimum(faces, len(self._face_area_cdf) - 1)
        u, v = rng.random(count), rng.random(count)
        outside = u + v > 1.0  # fold the unit square onto the triangle
        u[outside], v[outside] = 1.0 - u[outside], 1.0 - v[outside]
        corners = self.mesh.triangles[faces]
        return (
            corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])
        )

    def draw_approach(
        self, p_object: np.ndarray, n_object: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, float, dict[str, float]]:
        """A random pre-press sensor pose aimed at `p_object` against the outward normal, and a depth.

        The sensor's z is the reversed normal tilted by an angle uniform on the spherical cap of half-angle
        `max_tilt_deg`, with a uniformly random roll about z; the pad centre is offset from the target by up
        to `max_offset_m`. Returns the pose (origin on the target's side of the gel plane), the depth and
        the drawn parameters.
        """
        config = self.config
        inward = -normalize(np.asarray(n_object, dtype=np.float64))
        cos_tilt = rng.uniform(np.cos(np.radians(config.max_tilt_deg)), 1.0)
        tilt = float(np.arccos(np.clip(cos_tilt, -1.0, 1.0)))
        # A random axis perpendicular to the approach. `geometry.tangent_basis(inward, reference=helper)[1]` is the
        # same axis up to rounding, but the last bits of every simulated pose would change: the bare cross product
        # keeps simulated pairs bit-identical across versions.
        helper = normalize(rng.normal(size=3))
        tilt_axis = np.cross(inward, helper)
        if np.linalg.norm(tilt_axis) < 1e-9:  # the draw is parallel to the approach: any perpendicular will do
            tilt_axis = tangent_basis(inward)[0]
        z_axis = rotation_about_axis(tilt_axis, tilt) @ inward
        roll = float(rng.uniform(0.0, 2.0 * np.pi))
        rotation = rotation_between(np.array([0.0, 0.0, 1.0]), z_axis) @ rotation_about_axis(
            np.array([0, 0, 1.0]), roll
        )
        offset_radius = config.max_offset_m * np.sqrt(rng.random())
        offset_angle = rng.uniform(0.0, 2.0 * np.pi)
        offset_sensor = offset_radius * np.array([np.cos(offset_angle), np.sin(offset_angle), 0.0])
        origin = np.asarray(p_object, dtype=np.float64) - rotation @ offset_sensor
        depth = float(rng.uniform(*config.depth_range_m))
        parameters = {
            "tilt_deg": float(np.degrees(tilt)),
            "roll_deg": float(np.degrees(roll)),
            "offset_mm": float(offset_radius * 1e3),
            "depth_mm": depth * 1e3,
        }
        return make_transform(rotation, origin), depth, parameters

    # ------------------------------------------------------------------------------------------ the press
    def _cast(
        self, T_object_sensor: np.ndarray, x_sensor: np.ndarray, y_sensor: np.ndarray, start_z: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rays along the sensor's +z from (x, y, start_z): hit z, sensor frame (+inf: miss), and back-face flags."""
        rotation = T_object_sensor[:3, :3]
        direction = rotation[:, 2]
        start = T_object_sensor[:3, 3] + start_z * direction
        rays = np.empty((len(x_sensor), 6), dtype=np.float32)
        for axis in range(3):  # column by column from 1-D arrays: ten times faster than (N, 3) broadcasting
            rays[:, axis] = x_sensor * rotation[axis, 0] + y_sensor * rotation[axis, 1] + start[axis]
            rays[:, 3 + axis] = direction[axis]
        hits = self.raycaster.cast_rays(rays)
        return start_z + hits.t_hit, hits.back_face

    def press(
        self, T_object_sensor_start: np.ndarray, depth_m: float, target_object: np.ndarray | None = None
    ) -> Press:
        """Press the sensor along its z from a starting pose until the object is `depth_m` deep in the gel.

        `T_object_sensor_start` fixes the sensor's orientation and its pad position; only its position along
        its own z changes. `target_object`, if given, is the surface point the press must touch (concavity
        check). Returns a Press; `rejection` says why the sensor could not have made it, if it could not.
        """
        config, spec = self.config, self.config.spec
        shape = (spec.height_px, spec.width_px)
        T_start = np.asarray(T_object_sensor_start, dtype=np.float64)
        # Start the rays behind every part of the object: further back than the object's bounding sphere.
        centre_sensor = transform_points(invert_transform(T_start), self.bounds_centre)
        start_z = float(centre_sensor[2] - self.bounds_radius - 0.01)

        empty = np.full(shape, np.inf)

        def rejected(reason: str, T: np.ndarray, object_z: np.ndarray, **details: Any) -> Press:
            return Press(T, depth_m, object_z, np.zeros(shape), np.zeros(shape, bool), None, reason, details)

        target_sensor = None
        if target_object is not None:
            # Cheap first: a coarse grid and the ray through the target. The coarse minimum is never below the
            # true one, so a target already too shallow against it is too shallow against the full grid.
            target_sensor = transform_points(invert_transform(T_start), np.asarray(target_object, dtype=np.float64))
            coarse_x = np.append(self._coarse_x, target_sensor[0])
            coarse_z, _ = self._cast(T_start, coarse_x, np.append(self._coarse_y, target_sensor[1]), start_z)
            target_hit_z = float(coarse_z[-1])
            if not (np.isfinite(target_hit_z) and target_hit_z > target_sensor[2] - config.target_tolerance_m):
                return rejected("target_occluded", T_start, empty)
            coarse_min = float(np.min(coarse_z[np.isfinite(coarse_z)]))
            if target_sensor[2] - coarse_min >= depth_m - config.gel.contact_threshold_m:
                return rejected("target_not_in_contact", T_start, empty, coarse=True)

        z_start, back = self._cast(T_start, self._pixel_x, self._pixel_y, start_z)
        z_start, back = z_start.reshape(shape), back.reshape(shape)
        hit = np.isfinite(z_start)
        if not hit.any():
            return rejected("no_contact", T_start, empty)

        # Move the sensor along its z so that the deepest object point is depth_m behind the gel.
        shift = float(z_start[hit].min() + depth_m)
        T_final = T_start @ make_transform(np.eye(3), np.array([0.0, 0.0, shift]))
        object_z = z_start - shift  # +inf stays +inf

        near_back = back & (object_z < config.back_face_clearance_m)
        if near_back.any():
            return rejected("back_face", T_final, object_z, back_face_pixels=int(near_back.sum()))

        height_map, contact_mask, penetration = gel_surface(object_z, config.gel, spec)
        details: dict[str, Any] = {"contact_pixels": int(contact_mask.sum())}

        if target_sensor is not None:
            target_z = float(target_sensor[2] - shift)
            column = int(round(target_sensor[0] / spec.pixel_size_m + (spec.width_px - 1) / 2))
            row = int(round(target_sensor[1] / spec.pixel_size_m + (spec.height_px - 1) / 2))
            on_pad = 0 <= row < shape[0] and 0 <= column < shape[1]
            details["target_depth_mm"] = -target_z * 1e3
            if not (on_pad and -target_z > config.gel.contact_threshold_m and contact_mask[row, column]):
                return rejected("target_not_in_contact", T_final, object_z, **details)

        if details["contact_pixels"] < config.min_contact_pixels:
            return rejected("small_contact", T_final, object_z, **details)

        border = contact_mask.ravel()[self._border]
        details["border_fraction"] = float(border.mean())
        details["border_runs"] = _count_runs_circular(border)
        width = _contact_width_m(contact_mask, spec)
        details["contact_width_mm"] = width * 1e3
        if details["border_runs"] >= 2 and width < config.min_crossing_width_m:
            return rejected("thin_edge", T_final, object_z, **details)
        if details["border_fraction"] > config.max_border_fraction:
            return rejected("border", T_final, object_z, **details)

        collision = self.body_collision(T_final)
        if collision is not None:
            details["collision"] = collision
            return rejected("housing_collision", T_final, object_z, **details)

        # Ground truth: the mesh surface point nearest the centroid of the noise-free contact patch.
        patch = spec.height_map_to_points(height_map, contact_mask)
        centroid_object = transform_points(T_final, patch.mean(axis=0))
        p_object = self.closest_surface_points(centroid_object[None])[0]
        details["max_penetration_mm"] = float(penetration.max() * 1e3)
        return Press(T_final, float(depth_m), object_z, height_map, contact_mask, p_object, None, details)

    # ------------------------------------------------------------------------------------------ queries
    def closest_surface_points(self, points_object: np.ndarray) -> np.ndarray:
        """Nearest points on the mesh surface (object frame) to (M, 3) query points."""
        return self.raycaster.closest_points(points_object)

    def body_collision(self, T_object_sensor: np.ndarray) -> str | None:
        """Which part of the sensor body collides with the object at this pose ("housing", "probe"), or None.

        Rays sweep each body box along x, y and z every `collision_ray_spacing_m` (`body.BodySweep`).
        """
        return self._body_sweep.collision(self.raycaster, T_object_sensor)


# ------------------------------------------------------------------------------------------------ one contact
def simulate_contact(
    simulator: PressSimulator,
    p_object: np.ndarray,
    n_object: np.ndarray,
    rng: np.random.Generator,
    noise_rng: np.random.Generator | None = None,
    reconstruct: Callable[[np.ndarray], np.ndarray] | None = None,
) -> SimulatedContact:
    """Aim the sensor at a surface point, press, and (if accepted) reconstruct the tactile cloud.

    `p_object`, `n_object`: target point and outward normal (object frame). `rng` draws the approach;
    `noise_rng` (default: `rng`) the reconstruction errors, drawn only for accepted presses. `reconstruct`,
    if given, replaces the noise model: it receives the noise-free height map ((H, W) metres, gel surface
    z <= 0) and returns the (N, 3) sensor-frame cloud, e.g. a GelSight image renderer followed by the
    image-to-cloud reconstruction.
    """
    contact = press_contact(simulator, p_object, n_object, rng)
    if contact.press.accepted:
        finish_contact(simulator, contact, noise_rng or rng, reconstruct)
    return contact


def press_contact(
    simulator: PressSimulator, p_object: np.ndarray, n_object: np.ndarray, rng: np.random.Generator
) -> SimulatedContact:
    """Draw an approach toward a surface point and press (noise-free; no tactile cloud yet)."""
    n_object = np.asarray(n_object, dtype=np.float64)
    if not (np.all(np.isfinite(n_object)) and np.linalg.norm(n_object) > 1e-6):
        # The model's normal cancelled out (both sides of a sheet thinner than its neighbourhood): no approach.
        spec = simulator.config.spec
        shape = (spec.height_px, spec.width_px)
        press = Press(np.eye(4), 0.0, np.full(shape, np.inf), np.zeros(shape), np.zeros(shape, bool), None, "no_normal")
        return SimulatedContact(target_object=np.asarray(p_object, dtype=np.float64), approach={}, press=press)
    T_start, depth, approach = simulator.draw_approach(p_object, n_object, rng)
    press = simulator.press(T_start, depth, target_object=p_object)
    return SimulatedContact(target_object=np.asarray(p_object, dtype=np.float64), approach=approach, press=press)


def finish_contact(
    simulator: PressSimulator,
    contact: SimulatedContact,
    noise_rng: np.random.Generator,
    reconstruct: Callable[[np.ndarray], np.ndarray] | None = None,
) -> SimulatedContact:
    """Turn an accepted press into its tactile cloud (noise model, or the `reconstruct` hook), in place."""
    from yoto.contacts import MIN_TACTILE_POINTS

    press = contact.press
    if reconstruct is not None:
        try:
            points = np.asarray(reconstruct(press.height_map_m), dtype=np.float64).reshape(-1, 3)
        except YotoError as exc:  # the reconstruction refused the frame: a contact the sensor cannot report
            press.details["reconstruction_error"] = str(exc)
            points = np.empty((0, 3))
        contact.noise = {"reconstruct": 1.0}
    else:
        points, contact.noise = reconstruct_points(
            press.height_map_m, press.contact_mask, simulator.config.noise, noise_rng, simulator.config.spec
        )
    if len(points) < MIN_TACTILE_POINTS or not np.all(np.isfinite(points)):
        press.rejection = "reconstruction_failed"
        press.details["reconstructed_points"] = len(points)
        contact.points_sensor = np.empty((0, 3))
        return contact
    contact.points_sensor = points
    if reconstruct is not None:
        # SPEC: the true contact is the surface point nearest the centroid of the contact patch, and the patch
        # is what the sensor reports. A reconstruction's mask can differ from the gel's true contact (a tilted
        # flat press keeps only its deeper half), so the truth follows the observed cloud.
        centroid_object = transform_points(press.T_object_sensor, points.mean(axis=0))
        press.details["p_object_of_true_contact"] = contact.p_object.tolist()
        press.p_object = simulator.closest_surface_points(centroid_object[None])[0]
    return contact


# ------------------------------------------------------------------------------------------------ helpers
def _border_ring_indices(rows: int, cols: int) -> np.ndarray:
    """Flat indices of the image's outermost pixels, in order around the ring (clockwise from top-left)."""
    top = [(0, c) for c in range(cols)]
    right = [(r, cols - 1) for r in range(1, rows)]
    bottom = [(rows - 1, c) for c in range(cols - 2, -1, -1)]
    left = [(r, 0) for r in range(rows - 2, 0, -1)]
    ring = np.array(top + right + bottom + left)
    return ring[:, 0] * cols + ring[:, 1]


def _count_runs_circular(flags: np.ndarray) -> int:
    """Number of separate runs of True in a circular boolean sequence."""
    if flags.all():
        return 1
    return int(np.count_nonzero(flags & ~np.roll(flags, 1)))


def _contact_width_m(mask: np.ndarray, spec: GelSightSpec) -> float:
    """Mean width of a contact: its area over its length along its principal axis."""
    rows, cols = np.nonzero(mask)
    if len(rows) < 3:
        return 0.0
    u, v = cols - cols.mean(), rows - rows.mean()
    uv = float((u * v).sum())  # elementwise sums, not a BLAS dot (body.transform_points_elementwise)
    covariance = np.array([[float((u * u).sum()), uv], [uv, float((v * v).sum())]])
    _, vectors = np.linalg.eigh(covariance)
    along = u * vectors[0, -1] + v * vectors[1, -1]
    length_px = np.ptp(along) + 1.0
    return float(len(rows) / length_px * spec.pixel_size_m)
