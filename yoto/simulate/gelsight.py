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
3. Gel. The penetration `I = max(0, -z_obj)` is what the object pushes into the undeformed gel volume. The
   elastomer also sinks in around the contact; we model that by Gaussian spreading of the penetration,
   `S = gain * G_sigma * I`, and take the gel depth as `D = max(I, S)`: the gel is at least as deep as
   the object pushes it (it cannot penetrate the object) and sinks in smoothly beside it. The height map
   is `-D`. The contact mask is where the gel touches the object (`I >= S`) and the penetration exceeds a
   small threshold.
4. Reachability. The sensor body (gel block, housing, probe) must not collide with the object; the chosen
   target point must lie inside the contact (deep concavities: the surrounding surface reaches the pad
   first); the contact must be large enough; a narrow contact crossing the whole pad (an edge thinner than
   the pad) is rejected.
5. Ground truth. The object-frame surface point nearest the centroid of the noise-free contact patch
   (nearest point on the mesh surface, not on a point cloud).

Reconstruction noise (`reconstruct_points`) turns the noise-free height map into what a GelSight
reconstruction pipeline would output: a depth scale error, a smooth low-frequency bias field, per-pixel
noise, and a contact mask re-thresholded on the noisy heights.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh
from scipy import ndimage

from yoto.errors import InputError, YotoError
from yoto.geometry import (
    invert_transform,
    make_transform,
    normalize,
    rotation_about_axis,
    rotation_between,
    transform_points,
)
from yoto.raycast import MeshRaycaster
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec

SIMULATOR_VERSION = 1
TOUCH_TOLERANCE_M = 1e-7  # the gel counts as touching the object where it is within this of the surface

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


# ------------------------------------------------------------------------------------------------ configs
@dataclass(frozen=True)
class SensorBody:
    """Rigid parts of a GelSight Mini and its mount, as axis-aligned boxes in the sensor frame.

    The Mini's front face is about 32 x 28 mm and its body about 25 mm deep behind the gel; the gel
    (sensed area 20.3 x 15.2 mm) stands proud of the housing face. We take 2.0 mm: with a 1.5 mm recess,
    every 1.5 mm press into a flat face would graze the housing, which a real Mini does not.
    """

    housing_size_m: tuple[float, float] = (0.032, 0.028)  # housing face, along sensor x and y
    housing_depth_m: float = 0.025  # housing extent behind its face, along -z
    gel_protrusion_m: float = 0.002  # the housing face lies this far behind the undeformed gel (z = -this)
    probe_size_m: tuple[float, float] = (0.020, 0.020)  # cross-section of the rigid probe behind the housing
    probe_length_m: float = 0.060  # probe length behind the housing (0: no probe)

    def boxes(self, spec: GelSightSpec = GELSIGHT_MINI, with_gel: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
        """(centre, half extents) of each body box in the sensor frame; the gel block only if `with_gel`."""
        pad_x, pad_y = spec.pad_size_m
        front = -self.gel_protrusion_m
        boxes = []
        if with_gel:
            boxes.append((np.array([0.0, 0.0, front / 2]), np.array([pad_x / 2, pad_y / 2, self.gel_protrusion_m / 2])))
        housing_half = np.array([self.housing_size_m[0] / 2, self.housing_size_m[1] / 2, self.housing_depth_m / 2])
        boxes.append((np.array([0.0, 0.0, front - self.housing_depth_m / 2]), housing_half))
        if self.probe_length_m > 0:
            probe_half = np.array([self.probe_size_m[0] / 2, self.probe_size_m[1] / 2, self.probe_length_m / 2])
            back = front - self.housing_depth_m
            boxes.append((np.array([0.0, 0.0, back - self.probe_length_m / 2]), probe_half))
        return boxes


@dataclass(frozen=True)
class GelModel:
    """How the elastomer deforms around an indenter (see the module docstring, step 3)."""

    spread_sigma_m: float = 0.0004  # Gaussian sink-in length of the gel around a contact (0: no spreading)
    spread_gain: float = 1.0  # weight of the spread indentation (1: a flat, wide press keeps its depth)
    contact_threshold_m: float = 5e-5  # penetration below this is not counted as contact (noise floor)


@dataclass(frozen=True)
class ReconstructionNoise:
    """Errors of a GelSight height-map reconstruction (photometric stereo + Poisson integration).

    The defaults are a judgement, not a fit to data: depth errors of a few hundredths of a millimetre
    (per pixel and low-frequency, RMS about 0.03 mm together) and a few percent of depth scale error from the
    gradient calibration, the size GelSight-class reconstructions of ball presses show. For realism beyond
    this, plug an image renderer and the real reconstruction into `simulate_contact(reconstruct=...)`.
    """

    pixel_std_m: float = 1.5e-5  # white per-pixel height noise
    bias_std_m: float = 2e-5  # smooth low-frequency bias field (integration drift), standard deviation
    bias_length_m: float = 0.003  # correlation length of the bias field
    scale_std: float = 0.03  # relative depth scale error, drawn once per press
    mask_threshold_m: float = 6e-5  # the noisy reconstruction's contact threshold on gel depth
    mask_margin_px: int = 8  # noisy contact pixels count only within this distance of the true contact

    @classmethod
    def none(cls) -> ReconstructionNoise:
        """No reconstruction error: the tactile cloud is the noise-free contact patch."""
        return cls(pixel_std_m=0.0, bias_std_m=0.0, scale_std=0.0, mask_threshold_m=0.0, mask_margin_px=0)

    @property
    def is_noise_free(self) -> bool:
        return self.pixel_std_m == 0 and self.bias_std_m == 0 and self.scale_std == 0


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
    points_sensor: np.ndarray | None = None  # (N, 3) reconstructed tactile cloud, sensor frame; None if rejected
    noise: dict[str, float] = field(default_factory=dict)  # the reconstruction errors drawn for this press

    @property
    def accepted(self) -> bool:
        return self.press.accepted and self.points_sensor is not None

    @property
    def rejection(self) -> str | None:
        return self.press.rejection


# ------------------------------------------------------------------------------------------------ simulator
class PressSimulator:
    """Presses a GelSight into one mesh. Builds the ray-casting scene once; a press then takes tens of ms."""

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
        self._collision_rays_sensor = _box_sweep_rays(config.body.boxes(spec), config.collision_ray_spacing_m)
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
        helper = normalize(rng.normal(size=3))
        tilt_axis = np.cross(inward, helper)
        if np.linalg.norm(tilt_axis) < 1e-9:
            tilt_axis = np.cross(inward, np.eye(3)[np.argmin(np.abs(inward))])
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

        Rays sweep each body box along x, y and z every `collision_ray_spacing_m`; a surface crossing any
        of them is a collision (only features smaller than the spacing in every direction could slip through).
        """
        origins, directions, lengths, box_index = self._collision_rays_sensor
        rays = np.empty((len(origins), 6), dtype=np.float32)
        rays[:, :3] = _transform_points_elementwise(T_object_sensor, origins)
        rays[:, 3:] = _transform_points_elementwise(make_transform(T_object_sensor[:3, :3], np.zeros(3)), directions)
        crossing = self.raycaster.cast_rays(rays).t_hit < lengths
        if crossing.any():
            return ("housing", "probe")[int(box_index[np.argmax(crossing)])]
        return None


# ------------------------------------------------------------------------------------------------ gel model
def gel_surface(
    object_z_m: np.ndarray, gel: GelModel, spec: GelSightSpec = GELSIGHT_MINI
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free gel height map, contact mask and penetration from the object's height over the pad.

    `object_z_m` is the object surface z in the sensor frame (+inf where there is no surface). Returns
    (height_map_m, contact_mask, penetration_m), each (H, W).
    """
    penetration = np.where(np.isfinite(object_z_m), np.maximum(-object_z_m, 0.0), 0.0)
    spread = np.zeros_like(penetration)
    rows, columns = np.flatnonzero(penetration.any(axis=1)), np.flatnonzero(penetration.any(axis=0))
    if gel.spread_sigma_m > 0 and len(rows):
        # Filter only the window around the indentation (the kernel is truncated at 4 sigma anyway);
        # 'nearest' at the image border: the gel and the object continue a little beyond the sensed area.
        sigma_px = gel.spread_sigma_m / spec.pixel_size_m
        margin = int(np.ceil(4 * sigma_px)) + 1
        window = (
            slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
            slice(max(columns.min() - margin, 0), columns.max() + margin + 1),
        )
        spread[window] = gel.spread_gain * ndimage.gaussian_filter(penetration[window], sigma_px, mode="nearest")
    depth = np.maximum(penetration, spread)
    # Touching: the gel lies on the object. The tolerance covers the float32 ray casting (~0.03 um at 0.3 m),
    # which would otherwise make a flat press, where penetration and spread are equal, flicker.
    touching = (penetration >= spread - TOUCH_TOLERANCE_M) & (penetration > gel.contact_threshold_m)
    return -depth, touching, penetration


# ------------------------------------------------------------------------------------------------ noise
def reconstruct_points(
    height_map_m: np.ndarray,
    contact_mask: np.ndarray,
    noise: ReconstructionNoise,
    rng: np.random.Generator,
    spec: GelSightSpec = GELSIGHT_MINI,
) -> tuple[np.ndarray, dict[str, float]]:
    """The tactile cloud a reconstruction would output for a noise-free height map.

    Applies a depth scale error (once per press), a smooth bias field (random Fourier features of a
    Gaussian-covariance field with correlation length `bias_length_m`) and white per-pixel noise, then
    thresholds the noisy gel depth at `mask_threshold_m` within `mask_margin_px` of the true contact.
    Without noise it returns the contact patch unchanged. Returns (points_sensor, drawn errors).
    """
    if noise.is_noise_free:
        return spec.height_map_to_points(height_map_m, contact_mask), {"scale_error": 0.0}
    scale_error = float(rng.normal() * noise.scale_std)
    noisy = height_map_m * (1.0 + scale_error)
    if noise.bias_std_m > 0:
        noisy = noisy + bias_field(noise.bias_std_m, noise.bias_length_m, rng, spec)
    if noise.pixel_std_m > 0:
        noisy = noisy + rng.normal(scale=noise.pixel_std_m, size=noisy.shape)
    region = contact_mask
    if noise.mask_margin_px > 0:
        region = ndimage.maximum_filter(contact_mask, size=2 * noise.mask_margin_px + 1)
    mask = region & (-noisy > noise.mask_threshold_m)
    return spec.height_map_to_points(noisy, mask), {"scale_error": scale_error}


def bias_field(
    std_m: float, length_m: float, rng: np.random.Generator, spec: GelSightSpec = GELSIGHT_MINI, features: int = 16
) -> np.ndarray:
    """A smooth zero-mean random field over the image, (H, W) metres, with standard deviation about `std_m`.

    Sum of `features` cosines with wave vectors drawn from N(0, 1/length^2): in expectation a stationary
    Gaussian process with covariance exp(-r^2 / (2 length^2)).
    """
    columns, rows = _pixel_axes(spec)
    wave = rng.normal(scale=1.0 / length_m, size=(features, 2))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=features)
    # cos(kx x + ky y + p) = cos(ky y) cos(kx x + p) - sin(ky y) sin(kx x + p): one matrix product.
    along_rows = np.hstack([np.cos(np.outer(rows, wave[:, 1])), -np.sin(np.outer(rows, wave[:, 1]))])
    along_columns = np.vstack(
        [np.cos(np.outer(wave[:, 0], columns) + phase[:, None]), np.sin(np.outer(wave[:, 0], columns) + phase[:, None])]
    )
    field_ = np.einsum("rk,kc->rc", along_rows, along_columns)  # no BLAS: see _transform_points_elementwise
    return std_m * np.sqrt(2.0 / features) * field_


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
        contact.points_sensor = None
        return contact
    contact.points_sensor = points
    if reconstruct is not None:
        # SPEC: the true contact is the surface point nearest the centroid of the contact patch, and the patch
        # is what the sensor reports. A reconstruction's mask can differ from the gel's true contact (a tilted
        # flat press keeps only its deeper half), so the truth follows the observed cloud.
        centroid_object = transform_points(press.T_object_sensor, points.mean(axis=0))
        press.details["p_object_of_true_contact"] = press.p_object.tolist()
        press.p_object = simulator.closest_surface_points(centroid_object[None])[0]
    return contact


# ------------------------------------------------------------------------------------------------ helpers
def _transform_points_elementwise(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`geometry.transform_points` for large (N, 3) arrays without a BLAS call: numpy's threaded matmul can
    stall for tens of milliseconds on a busy machine, elementwise products do not."""
    rotation, translation = transform[:3, :3], transform[:3, 3]
    result = np.empty_like(points, dtype=np.float64)
    for axis in range(3):
        row = rotation[axis]
        result[:, axis] = points[:, 0] * row[0] + points[:, 1] * row[1] + points[:, 2] * row[2] + translation[axis]
    return result


@functools.lru_cache(maxsize=8)
def _pixel_axes(spec: GelSightSpec) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame x of each image column and y of each image row (metres), as in `spec.pixel_xy_sensor`."""
    x, y = spec.pixel_xy_sensor()
    return x[0].copy(), y[:, 0].copy()


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
    uv = float((u * v).sum())  # elementwise sums, not BLAS dot (see _transform_points_elementwise)
    covariance = np.array([[float((u * u).sum()), uv], [uv, float((v * v).sum())]])
    _, vectors = np.linalg.eigh(covariance)
    along = u * vectors[0, -1] + v * vectors[1, -1]
    length_px = np.ptp(along) + 1.0
    return float(len(rows) / length_px * spec.pixel_size_m)


def _box_sweep_rays(
    boxes: list[tuple[np.ndarray, np.ndarray]], spacing_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rays crossing each box along x, y and z on a grid (sensor frame): origins, directions, lengths, box index."""
    origins, directions, lengths, index = [], [], [], []
    for box, (centre, half) in enumerate(boxes):
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            nu = max(2, int(np.ceil(2 * half[u] / spacing_m)) + 1)
            nv = max(2, int(np.ceil(2 * half[v] / spacing_m)) + 1)
            gu, gv = np.meshgrid(np.linspace(-half[u], half[u], nu), np.linspace(-half[v], half[v], nv))
            start = np.zeros((gu.size, 3))
            start[:, u], start[:, v], start[:, axis] = gu.ravel(), gv.ravel(), -half[axis]
            origins.append(start + centre)
            direction = np.zeros(3)
            direction[axis] = 1.0
            directions.append(np.tile(direction, (gu.size, 1)))
            lengths.append(np.full(gu.size, 2 * half[axis]))
            index.append(np.full(gu.size, box))
    return np.vstack(origins), np.vstack(directions), np.concatenate(lengths), np.concatenate(index)
