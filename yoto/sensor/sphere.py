"""The ground truth of a ball press: the gel surface and its gradients under a sphere of known radius.

With the ball's centre above pixel (cx, cy), ball radius R and contact radius a (all in pixels), r the distance
from (cx, cy): inside the contact circle the gel follows the sphere,
    z(r) = -(sqrt(R^2 - r^2) - sqrt(R^2 - a^2)),   dz/dx = (x - cx) / sqrt(R^2 - r^2),  same for y,
and the gradients do not depend on a. Outside, the gel returns to flat (`press_height_map`: Hertz).
"""

from __future__ import annotations

import numpy as np

from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec


def sphere_gradients(
    centre_x_px: float, centre_y_px: float, ball_radius_px: float, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradients (dz/dx, dz/dy) of a sphere of radius `ball_radius_px` pressed at (cx, cy), and r (pixels).

    Dimensionless (metres per metre), each (rows, cols) float64; valid inside the contact circle, where the
    gel follows the ball. Outside the ball's footprint (r >= R) the values are clamped, not meaningful.
    """
    rows, cols = shape
    dx = np.arange(cols)[None, :] - centre_x_px
    dy = np.arange(rows)[:, None] - centre_y_px
    r2 = dx * dx + dy * dy
    s = np.sqrt(np.maximum(ball_radius_px**2 - r2, 1e-6))
    return np.broadcast_to(dx / s, shape).copy(), np.broadcast_to(dy / s, shape).copy(), np.sqrt(r2)


def press_height_map(
    centre_x_px: float,
    centre_y_px: float,
    contact_radius_px: float,
    ball_radius_m: float,
    spec: GelSightSpec = GELSIGHT_MINI,
) -> np.ndarray:
    """Gel surface (metres, <= 0) of a ball pressed into an elastic half-space (Hertz), contact radius a.

    Hertz: with d = a^2 / R, the gel at the contact edge is pressed d / 2 deep, and outside the contact the
    surface displacement -(d / pi) [(2 - r^2/a^2) asin(a/r) + sqrt(r^2/a^2 - 1)] returns it to flat (it is
    -d/2 at the edge). Inside, the gel follows the sphere exactly, so the deepest point is
    (R - sqrt(R^2 - a^2)) + d / 2 deep (about d for a << R).
    """
    pixel = spec.pixel_size_m
    a = contact_radius_px * pixel
    if not 0 < a < ball_radius_m:
        raise ValueError(f"contact radius {a * 1e3:.3f} mm must lie in (0, {ball_radius_m * 1e3:.3f}) mm")
    depth = a * a / ball_radius_m
    dx = (np.arange(spec.width_px)[None, :] - centre_x_px) * pixel
    dy = (np.arange(spec.height_px)[:, None] - centre_y_px) * pixel
    r = np.hypot(dx, dy)
    inside = r < a
    sphere = -(np.sqrt(np.maximum(ball_radius_m**2 - r * r, 0.0)) - np.sqrt(ball_radius_m**2 - a * a)) - depth / 2
    ratio = np.maximum(r / a, 1.0)
    outside = -(depth / np.pi) * ((2 - ratio**2) * np.arcsin(1 / ratio) + np.sqrt(ratio**2 - 1))
    return np.where(inside, sphere, outside)


def refine_centre(
    gx: np.ndarray,
    gy: np.ndarray,
    centre_xy: tuple[float, float],
    fit_radius_px: float,
    ball_radius_px: float,
    steps: int = 8,
) -> tuple[float, float]:
    """Centre (x, y) whose sphere gradient field best fits the given gradients within `fit_radius_px`.

    Gauss-Newton on the two centre coordinates; the ball radius is known.
    """
    cx, cy = float(centre_xy[0]), float(centre_xy[1])
    rows, cols = gx.shape
    ys, xs = np.mgrid[:rows, :cols]
    for _ in range(steps):
        dx, dy = xs - cx, ys - cy
        r2 = dx * dx + dy * dy
        inside = r2 < min(fit_radius_px, 0.95 * ball_radius_px) ** 2
        if inside.sum() < 10:
            break
        dx, dy = dx[inside], dy[inside]
        s = np.sqrt(ball_radius_px**2 - r2[inside])
        s3 = s**3
        residual = np.concatenate([gx[inside] - dx / s, gy[inside] - dy / s])
        # d(dx/s)/dcx = -1/s - dx^2/s^3, d(dx/s)/dcy = -dx dy/s^3, and symmetrically for dy/s.
        jxy = -dx * dy / s3
        jacobian = np.concatenate(
            [np.stack([-1 / s - dx * dx / s3, jxy], 1), np.stack([jxy, -1 / s - dy * dy / s3], 1)]
        )
        delta, *_ = np.linalg.lstsq(jacobian, residual, rcond=None)
        cx, cy = cx + float(delta[0]), cy + float(delta[1])
        if np.hypot(*delta) < 1e-3:
            break
    return cx, cy
