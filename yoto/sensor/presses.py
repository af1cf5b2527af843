"""Ball presses: load GelSight images and find each press's contact circle without a human in the loop.

A ball pressed into the gel tilts the gel surface most steeply at the edge of the contact circle: inside,
the surface follows the sphere, whose slope r / sqrt(R^2 - r^2) grows with the distance r from the centre;
outside, the gel bends back to flat and its slope decays. The colour change against the background image
tracks the slope, so the contact circle is the ring where the colour change peaks. We find it by casting
rays from a rough centre, taking the radius of the largest change along each ray, and fitting a circle to
those edge points robustly (RANSAC, then a geometric least-squares refinement), which also handles presses
cut by the image border. `ring_circle` works on any scalar "slope-like" map, so calibration can later
refine the circles on the model's predicted slope magnitude instead of the raw colour change.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


# ---------------------------------------------------------------------------------------------------------
# Images


COLOUR_IMAGE_MODES = ("RGB", "RGBA", "P")  # Pillow modes of an 8-bit colour frame (a GelSight camera's)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_HEADER_BYTES = 26  # the signature and the IHDR chunk up to its colour type byte
PNG_GREY_TYPES = (0, 4)  # the PNG header's colour types of grey and grey + alpha


def is_grey_png(head: bytes) -> bool:
    """Whether `head` (a file's or message's first PNG_HEADER_BYTES bytes, or more) starts a PNG whose header says
    grey or grey + alpha. Pillow opens a 16-bit grey + alpha PNG as colour (mode RGBA), so its mode cannot tell."""
    return (
        len(head) >= PNG_HEADER_BYTES
        and head.startswith(PNG_SIGNATURE)
        and head[12:16] == b"IHDR"
        and head[25] in PNG_GREY_TYPES
    )


def load_image(path: str | Path, spec: GelSightSpec = GELSIGHT_MINI) -> np.ndarray:
    """Read an image file as (rows, cols, 3) uint8 RGB and check it has the sensor's size.

    Pillow decodes PNGs in true RGB order (an image written by OpenCV's imwrite from a BGR array is stored
    as RGB, so it reads back correctly here). 16-bit and greyscale files are rejected: a GelSight camera
    gives 8-bit colour.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError("image file not found", path)
    with open(path, "rb") as file:
        if is_grey_png(file.read(PNG_HEADER_BYTES)):
            raise InputError(
                "expected an 8-bit colour image, got a greyscale PNG (a depth map is no GelSight frame)", path
            )
    try:
        with Image.open(path) as handle:
            if handle.mode not in COLOUR_IMAGE_MODES:
                raise InputError(f"expected an 8-bit colour image, got Pillow mode '{handle.mode}'", path)
            image = np.asarray(handle.convert("RGB"))
    except (UnidentifiedImageError, OSError) as exc:
        raise InputError(f"not a readable image ({exc})", path) from exc
    check_image(image, spec, path)
    return image


def check_image(
    image: np.ndarray, spec: GelSightSpec = GELSIGHT_MINI, path: str | Path | None = None, what: str = "image"
) -> np.ndarray:
    """Raise InputError unless `image` is a (rows, cols, 3) uint8 array of the sensor's size."""
    image = np.asarray(image)
    expected = (spec.height_px, spec.width_px, 3)
    if image.shape != expected:
        raise InputError(
            f"{what} is {_shape_text(image.shape)} but the {spec.name} gives "
            f"{spec.width_px}x{spec.height_px} RGB "
            f"(shape {expected}); resize it or use a calibration for this sensor",
            path,
        )
    if image.dtype != np.uint8:
        raise InputError(f"{what} must be uint8 RGB, got dtype {image.dtype}", path)
    return image


def _shape_text(shape: tuple[int, ...]) -> str:
    if len(shape) == 3:
        return f"{shape[1]}x{shape[0]} with {shape[2]} channels"
    if len(shape) == 2:
        return f"{shape[1]}x{shape[0]} greyscale"
    return f"an array of shape {shape}"


def list_press_images(folder: str | Path) -> list[Path]:
    """Press images under `folder`: image files directly in it, or one level of sub-folders (k/gelsight.png).

    A folder laid out as the shared example (presses/6.310mm/k/gelsight.png, one sub-folder per ball) holds no
    image within one level: when exactly one of its sub-folders holds presses, those are listed; when several do
    (balls of different diameters must not be mixed), InputError names them. Sorted naturally (2 before 10).
    Raises InputError when the folder holds no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("press folder not found", folder)
    found = _images_within_one_level(folder)
    if not found:
        nested = {sub: _images_within_one_level(sub) for sub in sorted(folder.iterdir()) if sub.is_dir()}
        holding = [sub for sub, images in nested.items() if images]
        if len(holding) > 1:
            names = ", ".join(f"{sub} ({len(nested[sub])} images)" for sub in holding)
            raise InputError(
                f"press folder holds no image files itself, but several of its sub-folders do: {names}; "
                "pass one of them (one ball diameter per calibration)",
                folder,
            )
        if holding:
            found = nested[holding[0]]
    if not found:
        raise InputError("press folder holds no image files (.png, .jpg, ...), in it or two levels down", folder)
    return sorted(found, key=_natural_key)


def _images_within_one_level(folder: Path) -> list[Path]:
    """Image files directly in `folder` and in its immediate sub-folders."""
    found = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    for sub in folder.iterdir():
        if sub.is_dir():
            found += [p for p in sub.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return found


def _natural_key(path: Path) -> list:
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(path))]


def colour_change(image: np.ndarray, background: np.ndarray, sigma_px: float = 0.0) -> np.ndarray:
    """(rows, cols, 3) float32 image minus background, optionally Gaussian-smoothed in the image plane."""
    diff = image.astype(np.float32) - background.astype(np.float32)
    if sigma_px > 0:
        diff = ndimage.gaussian_filter(diff, (sigma_px, sigma_px, 0))
    return diff


# ---------------------------------------------------------------------------------------------------------
# Contact circles


@dataclass(frozen=True)
class CircleConfig:
    """How contact circles are found."""

    smooth_sigma_px: float = 1.5  # Gaussian smoothing of the colour change before searching
    min_peak_change: float = 15.0  # a press must change some pixel's colour by this much (0-255 RGB distance)
    min_radius_px: float = 5.0  # smallest contact radius accepted
    max_radius_px: float = 80.0  # largest contact radius searched
    num_rays: int = 120  # rays cast from the centre estimate
    inlier_px: float = 2.0  # RANSAC inlier distance of an edge point from the circle
    min_coverage: float = 0.4  # fraction of the circle's angles that must hold inlier edge points
    max_residual_px: float = 3.0  # RMS distance of the inlier edge points from the fitted circle
    iterations: int = 3  # re-cast rays from the refined centre this many times
    seed: int = 0  # RANSAC sampling seed
    mode: str = "edge"  # "edge": where the map falls fastest along a ray (the rim of a disc); "peak": its maximum


@dataclass(frozen=True)
class ContactCircle:
    """A press's contact circle in pixel coordinates (column x, row y, both 0-based pixel centres)."""

    centre_x_px: float
    centre_y_px: float
    radius_px: float
    residual_px: float  # RMS distance of the inlier edge points from the circle
    coverage: float  # fraction of the circle's angles supported by inlier edge points
    num_edge_points: int  # inlier edge points used in the final fit
    peak_change: float  # largest value of the map the circle was found on


class NoCircleError(ValueError):
    """No acceptable contact circle in an image; the message says why."""


def find_contact_circle(
    image: np.ndarray, background: np.ndarray, config: CircleConfig = CircleConfig()
) -> ContactCircle:
    """Find the contact circle of a ball press from its colour change against the background.

    Raises NoCircleError (with the reason) when the image holds no press, or no circle fits well enough.
    """
    diff = colour_change(image, background, config.smooth_sigma_px)
    magnitude = np.sqrt((diff * diff).sum(axis=2))
    return ring_circle(magnitude, config, min_peak=config.min_peak_change)


def ring_circle(
    ring_map: np.ndarray,
    config: CircleConfig = CircleConfig(),
    min_peak: float = 0.0,
    initial: tuple[float, float] | None = None,
) -> ContactCircle:
    """Fit the circle along which a non-negative map peaks radially (the contact edge of a press).

    `initial` (x, y) seeds the centre; otherwise the weighted centroid of the map's largest strong blob.
    """
    ring_map = np.asarray(ring_map, dtype=np.float32)
    peak = float(ring_map.max())
    if not np.isfinite(peak) or peak < min_peak:
        raise NoCircleError(f"no contact: the largest change is {peak:.1f}, below {min_peak:.1f}")
    if initial is None:
        initial = _blob_centre(ring_map, 0.4 * peak)
    centre = np.asarray(initial, dtype=np.float64)
    rng = np.random.default_rng(config.seed)
    circle = None
    for _ in range(config.iterations):
        points, strengths = _ray_peaks(ring_map, centre, config)
        if len(points) < 8:
            raise NoCircleError(f"only {len(points)} rays found a contact edge inside the image")
        circle, inliers = _ransac_circle(points, config.inlier_px, rng)
        if circle is None:
            raise NoCircleError("the contact edge points do not lie on a circle")
        circle = _refine_circle(points[inliers], circle)
        centre = circle[:2]
    if circle is None:
        raise ValueError(f"CircleConfig.iterations must be at least 1, got {config.iterations}")
    cx, cy, radius = circle
    distances = np.hypot(points[:, 0] - cx, points[:, 1] - cy) - radius
    inliers = np.abs(distances) < config.inlier_px
    residual = float(np.sqrt(np.mean(distances[inliers] ** 2))) if inliers.any() else np.inf
    angles = np.arctan2(points[inliers, 1] - cy, points[inliers, 0] - cx)
    bins = np.unique(np.floor((angles + np.pi) / (2 * np.pi) * 36).astype(int) % 36)
    coverage = len(bins) / 36.0
    if not config.min_radius_px <= radius <= config.max_radius_px:
        raise NoCircleError(
            f"circle radius {radius:.1f} px is outside [{config.min_radius_px}, {config.max_radius_px}] px"
        )
    if coverage < config.min_coverage:
        raise NoCircleError(f"the edge points cover only {coverage:.0%} of the circle (need {config.min_coverage:.0%})")
    if residual > config.max_residual_px:
        raise NoCircleError(
            f"edge points scatter {residual:.1f} px RMS about the circle (limit {config.max_residual_px} px)"
        )
    return ContactCircle(float(cx), float(cy), float(radius), residual, coverage, int(inliers.sum()), peak)


def _blob_centre(ring_map: np.ndarray, threshold: float) -> tuple[float, float]:
    """Weighted centroid of the largest connected region where the map exceeds `threshold`."""
    strong = ring_map > threshold
    labels, count = ndimage.label(strong)
    if count > 1:
        sizes = ndimage.sum(strong, labels, np.arange(1, count + 1))
        strong = labels == (int(np.argmax(sizes)) + 1)
    strong = ndimage.binary_fill_holes(strong)
    rows, cols = np.nonzero(strong)
    weights = ring_map[rows, cols]
    return float(np.average(cols, weights=weights)), float(np.average(rows, weights=weights))


def _ray_peaks(ring_map: np.ndarray, centre: np.ndarray, config: CircleConfig) -> tuple[np.ndarray, np.ndarray]:
    """Edge points: along each ray from `centre`, the radius where the map peaks (sub-pixel)."""
    rows, cols = ring_map.shape
    angles = np.linspace(0.0, 2 * np.pi, config.num_rays, endpoint=False)
    step = 0.5
    radii = np.arange(1.0, config.max_radius_px + 6.0, step)
    xs = centre[0] + np.cos(angles)[:, None] * radii
    ys = centre[1] + np.sin(angles)[:, None] * radii
    inside = (xs >= 0) & (xs <= cols - 1) & (ys >= 0) & (ys <= rows - 1)
    profiles = ndimage.map_coordinates(ring_map, [ys, xs], order=1, mode="nearest")
    if config.mode == "edge":
        profiles = -np.gradient(profiles, step, axis=1)
    profiles[~inside] = -1e30
    best = np.argmax(profiles, axis=1)
    index = np.arange(len(angles))
    height = profiles[index, best]
    # A peak counts when it is an interior maximum, the ray stays in the image a few pixels past it (else the
    # "peak" may be the image border cutting a rising profile) and it is not weak against the strongest rays.
    margin = int(round(4.0 / step))
    past = np.minimum(best + margin, len(radii) - 1)
    valid = (best > 0) & (best < len(radii) - 1) & inside[index, past]
    valid &= height >= 0.3 * (np.percentile(height[valid], 90) if valid.any() else 0.0)
    best_c = np.clip(best, 1, len(radii) - 2)
    left, mid, right = profiles[index, best_c - 1], profiles[index, best_c], profiles[index, best_c + 1]
    curvature = left - 2 * mid + right
    offset = np.where(curvature < 0, 0.5 * (left - right) / np.where(curvature < 0, curvature, -1.0), 0.0)
    radius = radii[best_c] + np.clip(offset, -0.5, 0.5) * step
    points = np.stack([centre[0] + np.cos(angles) * radius, centre[1] + np.sin(angles) * radius], axis=1)
    return points[valid], height[valid]


def _circle_algebraic(points: np.ndarray) -> np.ndarray | None:
    """Kasa circle (cx, cy, r) through points by linear least squares; None if degenerate."""
    x, y = points[:, 0], points[:, 1]
    design = np.stack([x, y, np.ones_like(x)], axis=1)
    solution, _, rank, _ = np.linalg.lstsq(design, x * x + y * y, rcond=None)
    if rank < 3:
        return None
    cx, cy = solution[0] / 2, solution[1] / 2
    squared = solution[2] + cx * cx + cy * cy
    return None if squared <= 0 else np.array([cx, cy, np.sqrt(squared)])


def _ransac_circle(
    points: np.ndarray, inlier_px: float, rng: np.random.Generator, trials: int = 200
) -> tuple[np.ndarray | None, np.ndarray]:
    """Circle through the most points (within `inlier_px`), from circles through random point triples."""
    triples = rng.random((trials, len(points))).argpartition(3, axis=1)[:, :3]
    sample = points[triples]  # (trials, 3, 2)
    design = np.concatenate([sample, np.ones((trials, 3, 1))], axis=2)
    rhs = (sample**2).sum(axis=2)
    good = np.abs(np.linalg.det(design)) > 1e-6
    if not good.any():
        return None, np.zeros(len(points), bool)
    solution = np.linalg.solve(design[good], rhs[good][..., None])[..., 0]
    cx, cy = solution[:, 0] / 2, solution[:, 1] / 2
    squared = solution[:, 2] + cx * cx + cy * cy
    radius = np.sqrt(np.maximum(squared, 0.0))
    distance = np.abs(np.hypot(points[None, :, 0] - cx[:, None], points[None, :, 1] - cy[:, None]) - radius[:, None])
    inliers = distance < inlier_px
    counts = np.where(squared > 0, inliers.sum(axis=1), 0)
    best = int(np.argmax(counts))
    if counts[best] < 3:
        return None, inliers[best]
    refit = _circle_algebraic(points[inliers[best]])
    fallback = np.array([cx[best], cy[best], radius[best]])
    return (fallback if refit is None else refit), inliers[best]


def _refine_circle(points: np.ndarray, circle: np.ndarray, steps: int = 10) -> np.ndarray:
    """Geometric least squares (Gauss-Newton on point-to-circle distances) from an initial circle."""
    circle = circle.astype(np.float64).copy()
    for _ in range(steps):
        dx, dy = points[:, 0] - circle[0], points[:, 1] - circle[1]
        dist = np.maximum(np.hypot(dx, dy), 1e-9)
        residual = dist - circle[2]
        jacobian = np.stack([-dx / dist, -dy / dist, -np.ones_like(dist)], axis=1)
        delta, *_ = np.linalg.lstsq(jacobian, -residual, rcond=None)
        circle += delta
        if np.abs(delta).max() < 1e-4:
            break
    return circle
