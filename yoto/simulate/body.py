"""The rigid body of a GelSight Mini and its mount, and whether it collides with the object.

Frames: `sensor` is the GelSight frame of the SPEC (origin at the centre of the undeformed gel, z out of the gel
toward the object); `object` is the frame of the mesh the rays are cast on. The body is a few axis-aligned boxes
in the sensor frame (`SensorBody`); it collides with the object when the object's surface crosses any of the
rays that sweep those boxes on a grid (`BodySweep`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.geometry import make_transform
from yoto.raycast import MeshRaycaster
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec

BODY_PARTS = ("housing", "probe")  # the parts `SensorBody.boxes` returns, in order (after the gel block, if any)


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
class BodySweep:
    """Rays crossing each box of the sensor body along x, y and z on a grid, sensor frame."""

    origins: np.ndarray  # (R, 3) where each ray enters its box
    directions: np.ndarray  # (R, 3) unit directions (a box axis)
    lengths: np.ndarray  # (R,) the box's extent along the ray
    part: np.ndarray  # (R,) index into BODY_PARTS of the box each ray sweeps

    @classmethod
    def of(cls, boxes: list[tuple[np.ndarray, np.ndarray]], spacing_m: float) -> BodySweep:
        """Rays every `spacing_m` across each (centre, half extents) box."""
        origins, directions, lengths, part = [], [], [], []
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
                part.append(np.full(gu.size, box))
        return cls(np.vstack(origins), np.vstack(directions), np.concatenate(lengths), np.concatenate(part))

    def collision(self, raycaster: MeshRaycaster, T_object_sensor: np.ndarray) -> str | None:
        """Which part of the body (a name in BODY_PARTS) the object's surface crosses at this pose, or None.

        A surface crossing any ray is a collision: only features smaller than the ray spacing in every direction
        could slip through.
        """
        rays = np.empty((len(self.origins), 6), dtype=np.float32)
        rays[:, :3] = transform_points_elementwise(T_object_sensor, self.origins)
        rays[:, 3:] = transform_points_elementwise(
            make_transform(T_object_sensor[:3, :3], np.zeros(3)), self.directions
        )
        crossing = raycaster.cast_rays(rays).t_hit < self.lengths
        if crossing.any():
            return BODY_PARTS[int(self.part[np.argmax(crossing)])]
        return None


def transform_points_elementwise(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`geometry.transform_points` for large (N, 3) arrays without a BLAS call: numpy's threaded matmul can
    stall for tens of milliseconds on a busy machine, elementwise products do not."""
    rotation, translation = transform[:3, :3], transform[:3, 3]
    result = np.empty_like(points, dtype=np.float64)
    for axis in range(3):
        row = rotation[axis]
        result[:, axis] = points[:, 0] * row[0] + points[:, 1] * row[1] + points[:, 2] * row[2] + translation[axis]
    return result
