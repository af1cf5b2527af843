"""Anchors on the object surface and the height map a sensor pressed at each would see (once per object model)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from yoto.geometry import tangent_basis
from yoto.localize.match.config import AnchorConfig
from yoto.localize.match.rings import RingDescriptors, RingGrid
from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel
from yoto.pointcloud import voxel_downsample
from yoto.raycast import MeshRaycaster


@dataclass(frozen=True)
class MapGrid:
    """Cells of a height map: squares of `cell_m` whose centres lie within a disc of `radius_m`."""

    cell_m: float
    radius_m: float

    @cached_property
    def centres(self) -> np.ndarray:
        """(C, 2) cell centres (x, y), row by row."""
        side = 2 * int(np.ceil(self.radius_m / self.cell_m))
        coords = (np.arange(side) + 0.5 - side / 2.0) * self.cell_m
        cx, cy = np.meshgrid(coords, coords, indexing="ij")
        inside = cx**2 + cy**2 <= self.radius_m**2
        return np.stack([cx[inside], cy[inside]], axis=1)

    @property
    def size(self) -> int:
        return len(self.centres)

    @cached_property
    def coarse(self) -> np.ndarray:
        """(C,) bool: the checkerboard half of the cells (a lattice sqrt(2) cells apart), for the coarse stage."""
        side = 2 * int(np.ceil(self.radius_m / self.cell_m))
        index = np.rint(self.centres / self.cell_m + side / 2.0 - 0.5).astype(np.int64)
        return (index.sum(axis=1) % 2) == 0


# ------------------------------------------------------------------------------------------------ anchors
@dataclass
class AnchorMaps:
    """Anchors on the object surface and the height map a sensor pressed at each would see."""

    points_object: np.ndarray  # (A, 3) anchor locations (parent points)
    normals_object: np.ndarray  # (A, 3) outward unit normals
    u_object: np.ndarray  # (A, 3) tangent axis u
    v_object: np.ndarray  # (A, 3) tangent axis v; (u, v, -n) is right-handed
    heights: np.ndarray  # (A, C) float32 surface height into the object along -n at each cell centre (0: invalid)
    valid: np.ndarray  # (A, C) float32 1 where the anchor has surface at the cell centre
    grid: MapGrid
    rings: RingDescriptors  # each anchor's height map on rings, described independently of roll (coarse stage)
    neighbours: list[np.ndarray]  # per anchor, the anchors within the NMS radius
    kdtree: cKDTree  # over the anchors
    area_m2: float  # surface area each anchor stands for (the free-space test samples the surface at the anchors)
    seconds: float  # time to build


def cast_height_maps(
    raycaster: MeshRaycaster,
    anchors: np.ndarray,
    normals: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    centres: np.ndarray,
    config: AnchorConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(A, C) surface heights at (C, 2) positions (u, v) of each anchor frame, by casting rays along -n onto the mesh.

    A ray starts `ray_start_m` in front of the tangent plane. Its first hit is the surface a sensor pressed
    along -n would meet; a back-face hit means the ray started inside the object (the surface rises above the
    start): height -ray_start_m. No hit, or a hit deeper than `ray_reach_m`: no surface (invalid).
    """
    size = len(centres)
    heights = np.zeros((len(anchors), size), dtype=np.float32)
    valid = np.zeros((len(anchors), size), dtype=np.float32)
    chunk = max(1, 1_000_000 // size)
    for first in range(0, len(anchors), chunk):
        last = min(first + chunk, len(anchors))
        count = (last - first) * size
        origins = (
            anchors[first:last, None, :]
            + centres[None, :, 0, None] * u[first:last, None, :]
            + centres[None, :, 1, None] * v[first:last, None, :]
            + config.ray_start_m * normals[first:last, None, :]
        ).reshape(count, 3)
        directions = np.broadcast_to(-normals[first:last, None, :], (last - first, size, 3)).reshape(count, 3)
        hits = raycaster.cast(origins, directions)
        h = np.where(hits.back_face, -config.ray_start_m, hits.t_hit - config.ray_start_m)
        ok = hits.hit & (h <= config.ray_reach_m)
        heights[first:last] = np.where(ok, h, 0.0).reshape(last - first, size)
        valid[first:last] = ok.reshape(last - first, size)
    return heights, valid


def build_anchor_maps(model: ObjectModel, config: AnchorConfig) -> AnchorMaps:
    """Anchors every `anchor_spacing_m` on the parent cloud with their height maps and ring descriptors (once per
    object model)."""
    start = time.perf_counter()
    points = model.points_object.astype(np.float64)
    (centres,) = voxel_downsample(points, config.anchor_spacing_m)
    _, nearest = model.kdtree.query(centres)
    anchors = points[np.unique(nearest)]
    normals = model.aggregated_normal(anchors, config.anchor_normal_neighbours)
    u, v = tangent_basis(-normals)  # (u, v, -n) right-handed: the frame of a sensor pressing along -n
    grid = MapGrid(config.cell_m, config.map_radius_m)
    heights, valid = cast_height_maps(model.raycaster, anchors, normals, u, v, grid.centres, config)
    ring_grid = RingGrid(config.ring_step_m, config.map_radius_m, config.ring_angles, config.ring_harmonics)
    ring_heights, ring_valid = cast_height_maps(model.raycaster, anchors, normals, u, v, ring_grid.centres, config)
    # Where the anchor has no surface within reach, describe the ring as if it lay at the reach: a contact that
    # touched there does not match it.
    rings = RingDescriptors.from_samples(ring_grid, np.where(ring_valid > 0, ring_heights, config.ray_reach_m))
    kdtree = cKDTree(anchors)
    neighbours = [np.asarray(n, dtype=np.int64) for n in kdtree.query_ball_point(anchors, config.nms_radius_m)]
    area = float(model.meta["surface_area_m2"]) / len(anchors)
    return AnchorMaps(
        anchors, normals, u, v, heights, valid, grid, rings, neighbours, kdtree, area, time.perf_counter() - start
    )


_CACHE: ModelCache[AnchorConfig, AnchorMaps] = ModelCache(build_anchor_maps, size=4)


def anchor_maps(model: ObjectModel, config: AnchorConfig) -> AnchorMaps:
    """The cached anchor maps of a model, keyed by its fingerprint and the anchor settings only (per-query
    settings such as the number of candidates do not rebuild them)."""
    return _CACHE.get(model, config)


def clear_cache() -> None:
    """Forget every cached anchor map (they are rebuilt on the next query)."""
    _CACHE.clear()
