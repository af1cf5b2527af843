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

from yoto.network.polar import PolarGrid, press_maps
from yoto.network.presets import AnchorNetConfig
from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel


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


def make_anchor_set(model: ObjectModel, config: AnchorNetConfig) -> AnchorSet:
    """The anchors of `model` and their surface height maps. Deterministic for a model and config."""
    start = time.perf_counter()
    points, normals, u, v = model.anchor_frames(config.anchor_spacing_m, config.anchor_normal_neighbours)
    grid = PolarGrid.of(config)
    heights, valid = model.raycaster.height_maps(
        points, normals, u, v, grid.centres.reshape(-1, 2), config.ray_start_m, config.ray_reach_m
    )
    shape = (len(points), grid.rings, grid.angles)
    return AnchorSet(
        points, normals, u, v, heights.reshape(shape), valid.reshape(shape), grid, time.perf_counter() - start
    )


_CACHE: ModelCache[AnchorNetConfig, AnchorSet] = ModelCache(make_anchor_set, size=8)


def anchor_set(model: ObjectModel, config: AnchorNetConfig) -> AnchorSet:
    """The cached anchors of a model (keyed by its fingerprint and the network config)."""
    return _CACHE.get(model, config)
