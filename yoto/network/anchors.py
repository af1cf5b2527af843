"""Anchors: places on the object surface every few millimetres, with the height map a press at each would see.

The `cpu` network's candidates (instead of the paper's 54 blocks): one parent point per `anchor_spacing_m` voxel,
with a smoothed outward normal, a tangent frame (u, v, -n) and the surface's height along -n at the polar cells
around it (yoto.network.polar), cast on the mesh. Built once per object model and network config (seconds) and
kept in a small in-memory cache keyed by the model's fingerprint.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from yoto.geometry import tangent_basis
from yoto.network.polar import PolarGrid, press_maps
from yoto.network.presets import AnchorNetConfig
from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel
from yoto.pointcloud import voxel_downsample
from yoto.raycast import MeshRaycaster

RAYS_PER_BATCH = 1_000_000


@dataclass
class AnchorSet:
    """Anchors of one object model and the surface around each, on the polar cells of `grid`."""

    points_object: np.ndarray  # (A, 3) anchor locations (parent points), object frame
    normals_object: np.ndarray  # (A, 3) outward unit normals
    u_object: np.ndarray  # (A, 3) tangent axis u; (u, v, -n) is right-handed (the frame of a sensor pressing -n)
    v_object: np.ndarray  # (A, 3) tangent axis v
    heights_m: np.ndarray  # (A, R, T) float32 surface height into the object along -n at each cell centre (0: none)
    valid: np.ndarray  # (A, R, T) bool: there is surface within reach at the cell centre
    grid: PolarGrid
    seconds: float  # time to build

    def __len__(self) -> int:
        return len(self.points_object)

    def network_inputs(self, config: AnchorNetConfig) -> np.ndarray:
        """(A, 2, R, T) float32: what a press `config.press_depth_m` deep at each anchor would show the network."""
        return press_maps(self.heights_m, self.valid, config.press_depth_m, config.height_unit_m)

    def frames(self, index: np.ndarray) -> np.ndarray:
        """(K, 3, 3) columns u, v, -n of the anchors `index`: their map frames in the object frame."""
        return np.stack([self.u_object[index], self.v_object[index], -self.normals_object[index]], axis=2)


def surface_heights(
    raycaster: MeshRaycaster,
    points: np.ndarray,
    normals: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    cells: np.ndarray,
    start_m: float,
    reach_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(A, C) heights of the surface along -n at in-plane offsets `cells` (C, 2) of each frame, and validity.

    A ray starts `start_m` in front of the tangent plane and travels along -n; its first hit is the surface a sensor
    pressed there would meet. A back-face hit means the ray started inside the object (the surface rises above the
    start): height -start_m. No hit, or one deeper than `reach_m`: no surface.
    """
    heights = np.zeros((len(points), len(cells)), dtype=np.float32)
    valid = np.zeros((len(points), len(cells)), dtype=bool)
    chunk = max(1, RAYS_PER_BATCH // len(cells))
    for first in range(0, len(points), chunk):
        last = min(first + chunk, len(points))
        origins = (
            points[first:last, None]
            + cells[None, :, 0, None] * u[first:last, None]
            + cells[None, :, 1, None] * v[first:last, None]
            + start_m * normals[first:last, None]
        ).reshape(-1, 3)
        directions = np.broadcast_to(-normals[first:last, None], (last - first, len(cells), 3)).reshape(-1, 3)
        hits = raycaster.cast(origins, directions)
        h = np.where(hits.back_face, -start_m, hits.t_hit - start_m)
        ok = hits.hit & (h <= reach_m)
        heights[first:last] = np.where(ok, h, 0.0).reshape(last - first, len(cells))
        valid[first:last] = ok.reshape(last - first, len(cells))
    return heights, valid


def make_anchor_set(model: ObjectModel, config: AnchorNetConfig) -> AnchorSet:
    """The anchors of `model` and their surface height maps. Deterministic for a model and config."""
    start = time.perf_counter()
    parent = model.points_object.astype(np.float64)
    (voxel_centres,) = voxel_downsample(parent, config.anchor_spacing_m)
    _, nearest = model.kdtree.query(voxel_centres)
    points = parent[np.unique(nearest)]
    normals = model.aggregated_normal(points, config.anchor_normal_neighbours)
    u, v = tangent_basis(-normals)
    grid = PolarGrid.of(config)
    heights, valid = surface_heights(
        model.raycaster, points, normals, u, v, grid.centres.reshape(-1, 2), config.ray_start_m, config.ray_reach_m
    )
    shape = (len(points), grid.rings, grid.angles)
    return AnchorSet(
        points, normals, u, v, heights.reshape(shape), valid.reshape(shape), grid, time.perf_counter() - start
    )


_CACHE: ModelCache[AnchorNetConfig, AnchorSet] = ModelCache(make_anchor_set, size=8)


def anchor_set(model: ObjectModel, config: AnchorNetConfig) -> AnchorSet:
    """The cached anchors of a model (keyed by its fingerprint and the network config)."""
    return _CACHE.get(model, config)
