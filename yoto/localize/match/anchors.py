"""Anchors on the object surface and the height map a sensor pressed at each would see (once per object model)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from yoto.localize.match.config import AnchorConfig
from yoto.localize.match.rings import RingDescriptors, RingGrid
from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel


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


def build_anchor_maps(model: ObjectModel, config: AnchorConfig) -> AnchorMaps:
    """Anchors every `anchor_spacing_m` on the parent cloud with their height maps and ring descriptors (once per
    object model)."""
    start = time.perf_counter()
    anchors, normals, u, v = model.anchor_frames(config.anchor_spacing_m, config.anchor_normal_neighbours)
    reach = (config.ray_start_m, config.ray_reach_m)
    grid = MapGrid(config.cell_m, config.map_radius_m)
    heights, valid_cells = model.raycaster.height_maps(anchors, normals, u, v, grid.centres, *reach)
    valid = valid_cells.astype(np.float32)  # used as weights
    ring_grid = RingGrid(config.ring_step_m, config.map_radius_m, config.ring_angles, config.ring_harmonics)
    ring_heights, ring_valid = model.raycaster.height_maps(anchors, normals, u, v, ring_grid.centres, *reach)
    # Where the anchor has no surface within reach, describe the ring as if it lay at the reach: a contact that
    # touched there does not match it.
    rings = RingDescriptors.from_samples(ring_grid, np.where(ring_valid, ring_heights, config.ray_reach_m))
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
