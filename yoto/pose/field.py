"""A signed distance field of the object surface: point-to-surface residuals for thousands of poses at once.

The pose stage asks one question many times: under this pose hypothesis, how far does each tactile point lie
from the object's surface, and along which normal? A KD-tree over the parent cloud answers it in microseconds
per point; this grid answers it by trilinear interpolation in tens of nanoseconds, which is what lets the
joint two-contact search verify hundreds of poses per pair.

Values: the signed distance (object frame, metres, negative inside) to the model's mesh at grid nodes within
`band_m` of the surface (Open3D's closest-point queries); beyond the band the value is clamped to +-band. The
gradient of the interpolant is the outward normal. Built once per object model and cached in memory (keyed by
the model's fingerprint and the config), like the matched filter's anchor maps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel
from yoto.pose.kernels import KERNELS


@dataclass(frozen=True)
class FieldConfig:
    """The grid of the surface distance field."""

    cell_m: float = 0.0005  # grid spacing (coarser for large objects, see max_nodes): at 1 mm, trilinear reads at
    # a thin wall's surface (a mug's) were 25-90 um off the mesh, several times a right pose's 30 um residual
    max_nodes: int = 12_000_000  # the cell grows until the grid holds at most this many nodes (48 MB of float32)
    band_m: float = 0.004  # distances are computed within this band of the surface and clamped beyond it


@dataclass
class SurfaceField:
    """Signed distance to the object surface on a regular grid (object frame)."""

    origin: np.ndarray  # (3,) position of node (0, 0, 0)
    cell_m: float
    values: np.ndarray  # (nx, ny, nz) float32 signed distance, metres, clamped to +-band_m
    band_m: float
    seconds: float  # time to build

    def __post_init__(self):
        nx, ny, nz = self.values.shape
        self._flat = np.ascontiguousarray(self.values.reshape(-1), dtype=np.float32)
        self._strides = (ny * nz, nz)
        self._last_cell = np.array([nx - 2, ny - 2, nz - 2], dtype=np.uint64)  # cells, not nodes: a cell has 8 corners
        # flat offsets of the 8 corners of a cell, in the order (dx, dy, dz) = 000, 001, 010, 011, 100, ...
        self._corners = np.array([dx * ny * nz + dy * nz + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])

    def distance(self, points_object: np.ndarray, with_gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Signed distance (...,) and, if asked, outward unit normal (..., 3) at (..., 3) object-frame points.

        Points outside the grid read +band_m with a zero normal (never a match). The interpolation runs in float32
        (grid units: a position error of 1e-5 cells, far below the field's own error), the results are float64.
        """
        shape = points_object.shape[:-1]
        points = np.ascontiguousarray(points_object, dtype=np.float64).reshape(-1, 3)
        if KERNELS is not None:  # the same arithmetic compiled, point by point (bitwise the same results)
            distance = np.empty(len(points))
            normal = np.empty((len(points) if with_gradient else 0, 3))
            KERNELS.field_read(*self.kernel_arguments(), points, distance, normal, with_gradient)
            return distance.reshape(shape), (normal.reshape(shape + (3,)) if with_gradient else None)
        return self._distance_numpy(points, shape, with_gradient)

    def kernel_arguments(self) -> tuple:
        """The grid as `yoto.pose.kernels` reads it: flat values, shape, origin, 1 / cell, band."""
        nx, ny, nz = self.values.shape
        return self._flat, nx, ny, nz, np.asarray(self.origin, dtype=np.float64), 1.0 / self.cell_m, self.band_m

    def count_gradient_reads(self, count: int) -> None:
        """Told of `count` compiled reads with gradients outside `distance` (the refinement's kernels, one per
        contact and Gauss-Newton iteration), which `executor` counts; nothing here."""

    def _distance_numpy(
        self, points: np.ndarray, shape: tuple[int, ...], with_gradient: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """`distance` in numpy (without numba): (N, 3) points, the results shaped `shape`."""
        # (3, N) and (8, N) layouts: every row below is a contiguous run of N numbers.
        grid = np.empty((3, len(points)), dtype=np.float32)
        for axis in range(3):  # each coordinate straight into its float32 row (no (N, 3) temporaries)
            np.multiply(points[:, axis] - self.origin[axis], 1.0 / self.cell_m, out=grid[axis], casting="unsafe")
        base = np.floor(grid)
        fx, fy, fz = grid - base
        i, j, k = base.astype(np.int64)
        inside = (i.view(np.uint64) <= self._last_cell[0]) & (j.view(np.uint64) <= self._last_cell[1])
        inside &= k.view(np.uint64) <= self._last_cell[2]  # a negative index wraps to a huge unsigned one
        flat = i * self._strides[0] + j * self._strides[1] + k
        # (8, N); "clip" keeps the reads of points outside the grid in bounds (their values are masked below)
        c = np.take(self._flat, self._corners[:, None] + flat, mode="clip")
        # Interpolate along z (corner index = 4 dx + 2 dy + dz), then y, then x.
        step_z = c[1::2] - c[0::2]  # (4, N): the cell's four z-edges, (dx, dy) = 00, 01, 10, 11
        along_z = c[0::2] + fz * step_z
        step_y = along_z[1::2] - along_z[0::2]  # (2, N) over dx
        along_y = along_z[0::2] + fy * step_y
        gx = along_y[1] - along_y[0]
        distance = np.where(inside, (along_y[0] + fx * gx).astype(np.float64), self.band_m)
        if not with_gradient:
            return distance.reshape(shape), None
        gy = step_y[0] + fx * (step_y[1] - step_y[0])
        dz = step_z[0::2] + fy * (step_z[1::2] - step_z[0::2])  # (2, N) over dx
        gz = dz[0] + fx * (dz[1] - dz[0])
        norm = np.sqrt(gx * gx + gy * gy + gz * gz)
        scale = np.where(inside & (norm > 1e-12), 1.0 / np.maximum(norm, 1e-12), 0.0)
        normal = np.empty((len(scale), 3))
        normal[:, 0], normal[:, 1], normal[:, 2] = gx * scale, gy * scale, gz * scale
        return distance.reshape(shape), normal.reshape(shape + (3,))


def build_surface_field(model: ObjectModel, config: FieldConfig = FieldConfig()) -> SurfaceField:
    """The signed distance field of a model's parent cloud (see the module docstring)."""
    start = time.perf_counter()
    points = model.points_object.astype(np.float64)
    low = points.min(axis=0) - config.band_m - 2 * config.cell_m
    high = points.max(axis=0) + config.band_m + 2 * config.cell_m
    cell = config.cell_m
    while np.prod(np.ceil((high - low) / cell) + 1) > config.max_nodes:
        cell *= 1.1
    shape = tuple(int(n) for n in np.ceil((high - low) / cell) + 1)
    # Nodes within the band: the Euclidean distance transform of the grid cells holding parent points. Only they
    # are computed exactly; the others keep +-band, signed by the nearest node of a grid `coarse` times coarser.
    occupied = np.zeros(shape, dtype=bool)
    index = np.clip(np.rint((points - low) / cell).astype(np.int64), 0, np.array(shape) - 1)
    occupied[index[:, 0], index[:, 1], index[:, 2]] = True
    near = np.argwhere(ndimage.distance_transform_edt(~occupied) * cell <= config.band_m + cell)
    coarse = 4
    axes = [low[i] + cell * np.arange(0, shape[i], coarse) for i in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = (_signed_distance(model, nodes) < 0.0).reshape([len(a) for a in axes])
    # Each fine node takes the sign of its nearest coarse node.
    nearest = [np.minimum(np.rint(np.arange(n) / coarse).astype(np.int64), len(a) - 1) for n, a in zip(shape, axes)]
    sign = np.where(inside[np.ix_(*nearest)], -1.0, 1.0)
    values = (sign * config.band_m).astype(np.float32)
    distance = _signed_distance(model, low + cell * near)
    values[near[:, 0], near[:, 1], near[:, 2]] = np.clip(distance, -config.band_m, config.band_m)
    return SurfaceField(low, float(cell), values, config.band_m, time.perf_counter() - start)


def _signed_distance(model: ObjectModel, nodes: np.ndarray) -> np.ndarray:
    """Signed distance of (N, 3) nodes to the mesh: the distance to the closest surface point, negative where the
    node lies behind that point's triangle (a local test, so an open mesh is fine away from its holes)."""
    distance = np.empty(len(nodes))
    chunk = 500_000
    for first in range(0, len(nodes), chunk):
        part = nodes[first : first + chunk]
        closest, normals = model.raycaster.closest_points_and_normals(part)
        offset = part - closest
        behind = np.einsum("ij,ij->i", offset, normals) < 0.0
        distance[first : first + chunk] = np.where(behind, -1.0, 1.0) * np.linalg.norm(offset, axis=1)
    return distance


_CACHE: ModelCache[FieldConfig, SurfaceField] = ModelCache(build_surface_field, size=4)


def surface_field(model: ObjectModel, config: FieldConfig = FieldConfig()) -> SurfaceField:
    """The cached surface distance field of a model (built on first use)."""
    return _CACHE.get(model, config)
