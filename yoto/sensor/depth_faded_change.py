"""A pressed gel's colour change faded in with the depth, read as slope, estimated from one frame's own gradients.

Real gel changes colour where it is pressed even at zero slope (docs/journal/sensor.md, stops 16-17); faded in with
the depth and read as slope, it adds to the read gradients an error that grows with the depth, d(x, y) c, with d the
depth (mm) and c (slope per mm, x and y) roughly constant over one contact. Its integral leans the contact's deep
part (stop 20). A surface's gradients are curl-free; d c is not (its curl is c_y dd/dx - c_x dd/dy), so part of it is
left in the Poisson solve's residual (read gradients minus the solved height's gradients), which reconstruction
otherwise drops. `estimate_change` fits c to that residual as the non-integrable part of d c (both through the same
solve, so the box's edge conditions are the solve's own), with d the first solve's depth; `remove_change` takes d c
off the read gradients and solves again.

Measured in stop 21 (docs/journal/sensor.md): the residual of object contacts through the table renderer is
dominated by the colour -> gradient model's other errors, which give c of the same size with the change switched
off and through the fitted renderer (no change): the correction makes both worse, so reconstruction does not use it.
"""

from __future__ import annotations

import numpy as np

from yoto.sensor.reconstruction import integrate_box, poisson_integrate

# The largest |c| (slope per mm of depth) taken off: the table renderer's change alone reads as 0.01-0.05 per mm.
MAX_SLOPE_PER_MM = 0.05
# c is taken off only where d c explains at least this share of the residual's energy.
MIN_EXPLAINED = 0.25


def non_integrable(gx: np.ndarray, gy: np.ndarray, free: tuple[bool, bool, bool, bool]) -> tuple[np.ndarray, ...]:
    """(gx, gy) minus the gradients of their Poisson solve with the edges `free` (pixel units, one box)."""
    z = poisson_integrate(gx, gy, 1.0, free)
    zy, zx = np.gradient(z)
    return gx - zx, gy - zy


def estimate_change(
    gx: np.ndarray, gy: np.ndarray, height_m: np.ndarray, box: tuple[int, int, int, int]
) -> tuple[np.ndarray, float]:
    """c (slope per mm of depth, (x, y)) whose d c best explains the residual of the solve in `box`, and the share
    of the residual's energy it explains (0 where there is no residual)."""
    row0, row1, col0, col1 = box
    rows, cols = height_m.shape
    free = (row0 == 0, row1 == rows, col0 == 0, col1 == cols)
    inside = (slice(row0, row1), slice(col0, col1))
    depth_mm = (-1e3 * height_m[inside]).astype(np.float32)
    zero = np.zeros_like(depth_mm)
    residual = np.concatenate([part.ravel() for part in non_integrable(gx[inside], gy[inside], free)])
    design = np.stack(
        [
            np.concatenate([part.ravel() for part in non_integrable(depth_mm, zero, free)]),
            np.concatenate([part.ravel() for part in non_integrable(zero, depth_mm, free)]),
        ],
        axis=1,
    ).astype(np.float64)
    energy = float(residual @ residual)
    if energy <= 0.0:
        return np.zeros(2), 0.0
    c, *_ = np.linalg.lstsq(design, residual.astype(np.float64), rcond=None)
    left = residual - design @ c
    return c, 1.0 - float(left @ left) / energy


def remove_change(
    gx: np.ndarray,
    gy: np.ndarray,
    height_m: np.ndarray,
    box: tuple[int, int, int, int],
    blocks: np.ndarray,
    pixel_size_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The height map re-solved with d c taken off the read gradients (guarded: c applied only where it explains
    MIN_EXPLAINED of the residual, its size limited to MAX_SLOPE_PER_MM), and c (zero where not applied)."""
    c, explained = estimate_change(gx, gy, height_m, box)
    if explained < MIN_EXPLAINED:
        return height_m, np.zeros(2)
    c = c * min(1.0, MAX_SLOPE_PER_MM / max(float(np.hypot(c[0], c[1])), 1e-12))
    depth_mm = -1e3 * height_m
    corrected_x = (gx - np.float32(c[0]) * depth_mm).astype(np.float32)
    corrected_y = (gy - np.float32(c[1]) * depth_mm).astype(np.float32)
    return integrate_box(corrected_x, corrected_y, box, blocks, pixel_size_m), c
