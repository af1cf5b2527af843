"""A tactile cloud as a height image in the contact's own tangent frame: what the matched filter and the `cpu`
network both read a contact from.

The frame: origin at the contact centre, x and y tangent (x as close to the sensor's x as it gets), z into the
object (-normal). Pixels hold the mean height of their points; single empty pixels inside the contact are filled
from their neighbours (sparse clouds from other programs must not punch holes that the rim erosion would widen).
Where numba is installed (`yoto.jit`) the binning and the mask's closing, erosion and dilation run compiled (the same
masks and sums; the local frame's product in another order: heights within ~1e-17 m of numpy's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from yoto.contacts import contact_in_sensor
from yoto.errors import DegenerateGeometryError
from yoto.geometry import tangent_basis
from yoto.jit import ENABLED, jit

X_AXIS = np.array([1.0, 0.0, 0.0])


SPACING_NEIGHBOURS = 16  # the spacing is read off the distance to this many neighbours


def tactile_spacing_m(local: np.ndarray, samples: int = 512) -> float:
    """The cloud's own resolution: the side of the square each tactile point stands for (1 / sqrt(density)), measured
    on the `samples` points nearest the contact centre, their neighbours found among the 4 x `samples` nearest.

    The density is read off the disc reaching each point's `SPACING_NEIGHBOURS`-th neighbour (the median of
    pi r^2 / (k - 1/2)): a grid's pitch within 1%, and a randomly decimated cloud's (where the nearest neighbour lies
    at about half the spacing, and pixels of 1.5 x that distance are mostly empty) within 2%.
    """
    near = _central_points(local, samples)
    k = min(SPACING_NEIGHBOURS, len(near) - 1)
    distances, _ = cKDTree(near).query(near[:samples], k=k + 1)
    return float(np.sqrt(np.pi * np.median(distances[:, k] ** 2) / (k - 0.5)))


def _central_points(local: np.ndarray, samples: int) -> np.ndarray:
    """(<= 4 samples, 2) in-plane coordinates of the 4 x `samples` points nearest the contact centre, nearest first."""
    radial = local[:, 0] ** 2 + local[:, 1] ** 2
    near = np.argpartition(radial, min(4 * samples, len(local)) - 1)[: 4 * samples]
    return local[near[np.argsort(radial[near])], :2]


def tactile_spacing_at_most(local: np.ndarray, spacing_m: float, samples: int = 512) -> bool:
    """True when `tactile_spacing_m(local, samples)` is at most `spacing_m`, without a k-d tree: when more than half
    of the measured points share a square cell of diagonal `spacing_m` with another point, a grid's pitch is at most
    the cell's side, and random points hold ln 2 or more per cell (a spacing of at most 0.85 `spacing_m`).
    (False: not known.)"""
    near = _central_points(local, samples)
    cells = np.floor(near / (spacing_m / np.sqrt(2.0))).astype(np.int64)
    cells -= cells.min(axis=0)
    _, inverse, counts = np.unique(
        cells[:, 0] * (cells[:, 1].max() + 1) + cells[:, 1], return_inverse=True, return_counts=True
    )
    measured = min(samples, len(near))
    return int(np.count_nonzero(counts[inverse[:measured]] > 1)) > measured // 2


@dataclass
class TactileHeightImage:
    """The tactile cloud as a height image in its local frame (x, y tangent; height into the object)."""

    centre_sensor: np.ndarray  # (3,) contact centre
    normal_sensor: np.ndarray  # (3,) outward normal
    basis_sensor: np.ndarray  # (3, 3) columns u, v, z' (= -normal) of the local frame
    heights: np.ndarray  # (S, S) mean height per pixel
    filled: np.ndarray  # (S, S) pixels holding points
    mask: np.ndarray  # (S, S) pixels trusted as object surface (filled, rim eroded)
    pixel_m: float
    half_m: float  # the image spans [-half, half] in x and y

    def sample(self, x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear heights at local (x, y) and whether all four pixels are in `mask`."""
        x0, y0, fx, fy = self._corner(x, y)
        wx = np.clip(fx - x0, 0.0, 1.0)
        wy = np.clip(fy - y0, 0.0, 1.0)
        corners = (
            (x0, y0, (1 - wx) * (1 - wy)),
            (x0 + 1, y0, wx * (1 - wy)),
            (x0, y0 + 1, (1 - wx) * wy),
            (x0 + 1, y0 + 1, wx * wy),
        )
        heights = np.zeros(np.shape(wx))
        for i, j, w in corners:
            heights += self.heights[i, j] * w
        return heights, self._all_corners(mask, x0, y0)

    def covered(self, x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Whether all four pixels around local (x, y) are in `mask` (`sample`'s second answer, without heights)."""
        x0, y0, _, _ = self._corner(x, y)
        return self._all_corners(mask, x0, y0)

    def _corner(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The low corner pixel (row, column) of the bilinear cell of each local (x, y), and (x, y) in pixels."""
        side = len(self.heights)
        fx = (x + self.half_m) / self.pixel_m - 0.5
        fy = (y + self.half_m) / self.pixel_m - 0.5
        x0 = np.clip(np.floor(fx).astype(np.int64), 0, side - 2)
        y0 = np.clip(np.floor(fy).astype(np.int64), 0, side - 2)
        return x0, y0, fx, fy

    @staticmethod
    def _all_corners(mask: np.ndarray, x0: np.ndarray, y0: np.ndarray) -> np.ndarray:
        return mask[x0, y0] & mask[x0 + 1, y0] & mask[x0, y0 + 1] & mask[x0 + 1, y0 + 1]

    def pixel_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pixel (row, column) nearest each local (x, y), clipped to the image."""
        side = len(self.heights)
        i = np.clip(np.rint((x + self.half_m) / self.pixel_m - 0.5).astype(np.int64), 0, side - 1)
        j = np.clip(np.rint((y + self.half_m) / self.pixel_m - 0.5).astype(np.int64), 0, side - 1)
        return i, j


def tactile_height_image(
    points_sensor: np.ndarray, radius_m: float, pixel_m: float, erode_px: int
) -> TactileHeightImage:
    """The height image of a tactile cloud (N, 3; sensor frame, metres) over a disc of `radius_m` (plus two pixels).

    Pixels are `pixel_m`, or 1.5 x the cloud's own point spacing when it is sparser; the mask is the filled pixels
    with the rim eroded by `erode_px` (at the rim the gel, not the object, shapes the surface).
    """
    centre, normal = contact_in_sensor(points_sensor)
    u, v = tangent_basis(-normal, reference=X_AXIS)
    basis = np.stack([u, v, -normal], axis=1)
    if ENABLED:
        local = np.empty((len(points_sensor), 3))
        _to_local(points_sensor, centre, basis, local)
    else:
        local = (points_sensor - centre) @ basis
    # A dense cloud (the usual case) is told from a sparse one without measuring its spacing.
    pixel = pixel_m if tactile_spacing_at_most(local, pixel_m / 1.5) else max(pixel_m, 1.5 * tactile_spacing_m(local))
    half = radius_m + 2.0 * pixel
    side = int(np.ceil(2.0 * half / pixel))
    sums: np.ndarray
    counts: np.ndarray
    if ENABLED:
        sums, counts = np.zeros((side, side)), np.zeros((side, side))
        any_inside = _bin_heights(local, half, pixel, sums, counts)
    else:
        ix = np.floor((local[:, 0] + half) / pixel).astype(np.int64)
        iy = np.floor((local[:, 1] + half) / pixel).astype(np.int64)
        inside = (ix >= 0) & (ix < side) & (iy >= 0) & (iy < side)
        any_inside = bool(inside.any())
        if any_inside:
            key = ix[inside] * side + iy[inside]
            sums = np.bincount(key, weights=local[inside, 2], minlength=side * side).reshape(side, side)
            counts = np.bincount(key, minlength=side * side).reshape(side, side).astype(np.float64)
    if not any_inside:
        raise DegenerateGeometryError("the tactile cloud has no points around its contact centre")
    filled = counts > 0
    holes = binary_erosion(binary_dilation(filled, 1), 1) & ~filled  # a closing
    if holes.any():  # a hole's height: the mean of the points in its 3 x 3 neighbourhood
        sums = np.where(holes, ndimage.uniform_filter(sums, 3, mode="constant"), sums)
        counts = np.where(holes, ndimage.uniform_filter(counts, 3, mode="constant"), counts)
        filled = filled | holes
    heights = np.where(filled, sums / np.maximum(counts, 1e-12), 0.0)
    mask = binary_erosion(filled, erode_px) if erode_px > 0 else filled
    return TactileHeightImage(centre, normal, basis, heights, filled, mask, pixel, half)


def binary_dilation(mask: np.ndarray, iterations: int) -> np.ndarray:
    """`scipy.ndimage.binary_dilation(mask, iterations=iterations)` (4-neighbour cross), compiled where numba is."""
    if not ENABLED:
        return ndimage.binary_dilation(mask, iterations=iterations)
    out = np.array(mask, dtype=bool)
    for _ in range(iterations):
        out = _cross_morphology(out, True)
    return out


def binary_erosion(mask: np.ndarray, iterations: int) -> np.ndarray:
    """`scipy.ndimage.binary_erosion(mask, iterations=iterations)` (4-neighbour cross, nothing beyond the border),
    compiled where numba is."""
    if not ENABLED:
        return ndimage.binary_erosion(mask, iterations=iterations)
    out = np.array(mask, dtype=bool)
    for _ in range(iterations):
        out = _cross_morphology(out, False)
    return out


@jit
def _cross_morphology(mask, dilate):
    """One step of a binary dilation (any of the pixel and its 4 neighbours set) or erosion (all set, pixels beyond
    the border unset) of a 2-D boolean image."""
    rows, columns = mask.shape
    out = np.empty_like(mask)
    for i in range(rows):
        for j in range(columns):
            centre = mask[i, j]
            up = mask[i - 1, j] if i > 0 else False
            down = mask[i + 1, j] if i + 1 < rows else False
            left = mask[i, j - 1] if j > 0 else False
            right = mask[i, j + 1] if j + 1 < columns else False
            if dilate:
                out[i, j] = centre or up or down or left or right
            else:
                out[i, j] = centre and up and down and left and right
    return out


@jit
def _to_local(points, centre, basis, out):
    """out = (points - centre) @ basis for (N, 3) points."""
    for n in range(points.shape[0]):
        x, y, z = points[n, 0] - centre[0], points[n, 1] - centre[1], points[n, 2] - centre[2]
        for j in range(3):
            out[n, j] = x * basis[0, j] + y * basis[1, j] + z * basis[2, j]


@jit
def _bin_heights(local, half, pixel, sums, counts):
    """Add each local point's height to its pixel of the (S, S) `sums` and count it in `counts`, in point order (the
    sums `np.bincount` makes); whether any point fell in the image."""
    side = sums.shape[0]
    any_inside = False
    for n in range(local.shape[0]):
        i = np.floor((local[n, 0] + half) / pixel)
        j = np.floor((local[n, 1] + half) / pixel)
        if i >= 0 and i < side and j >= 0 and j < side:
            sums[int(i), int(j)] += local[n, 2]
            counts[int(i), int(j)] += 1.0
            any_inside = True
    return any_inside
