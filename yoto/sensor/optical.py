"""Optical simulator: a gel height map -> a realistic GelSight image, the inverse of reconstruction.

The image is the calibration's real background plus the colour change its inverse model predicts from the
surface gradients at each pixel, blurred like the real optics, plus (optionally) sensor noise of the
measured level. A contact simulator that produces gel height maps can so emit images and run them through
`reconstruct`, and the reconstruction's own errors reach the pose figures.

The blur was chosen by rendering Hertz ball presses (`calibration.press_height_map`) at the circles found
in real held-out presses and comparing with those images (docs/sensor.md).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.calibration import SensorCalibration


def height_gradients(height_map_m: np.ndarray, pixel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(dz/dx, dz/dy) of a height map by central differences (one-sided at the border), dimensionless."""
    gy, gx = np.gradient(np.asarray(height_map_m, dtype=np.float64), pixel_size_m)
    return np.asarray(gx), np.asarray(gy)


def render_image(
    height_map_m: np.ndarray,
    calibration: SensorCalibration,
    rng: np.random.Generator | None = None,
    *,
    blur_px: float | None = None,
) -> np.ndarray:
    """Render the (rows, cols, 3) uint8 RGB image the sensor would show for a gel height map.

    height_map_m: (rows, cols) gel-surface z in metres (SPEC sensor frame: <= 0 where pressed), rows and
        columns as in `GelSightSpec.height_map_to_points`.
    rng: draw per-pixel Gaussian sensor noise of the calibration's measured level; None renders noise-free.
    blur_px: Gaussian blur of the colour change (pixels); None uses the calibration's measured value.
    """
    spec = calibration.spec
    height_map_m = np.asarray(height_map_m)
    if height_map_m.shape != (spec.height_px, spec.width_px):
        raise InputError(
            f"height map has shape {height_map_m.shape}, but the {spec.name} calibration renders "
            f"({spec.height_px}, {spec.width_px})"
        )
    if not np.isfinite(height_map_m).all():
        raise InputError(f"height map has {int((~np.isfinite(height_map_m)).sum())} NaN or infinite values")
    if height_map_m.max() > 1e-3 or height_map_m.min() < -0.01:
        raise InputError(
            f"height map spans {height_map_m.min() * 1e3:.2f} to {height_map_m.max() * 1e3:.2f} mm: heights "
            "must be metres, <= 0 where the gel is pressed (did you pass millimetres?)"
        )
    gx, gy = height_gradients(height_map_m, spec.pixel_size_m)
    change = calibration.image_model.predict(gx, gy)
    sigma = calibration.render_blur_px if blur_px is None else blur_px
    if sigma > 0:
        change = ndimage.gaussian_filter(change, (sigma, sigma, 0), mode="nearest")
    image = change + calibration.background.astype(np.float32)
    if rng is not None:
        image += rng.normal(size=image.shape).astype(np.float32) * calibration.noise_std.astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def image_path_reconstructor(calibration: SensorCalibration, sensor_noise: bool = True):
    """A height map -> tactile cloud function that goes through a rendered GelSight image and its reconstruction.

    Plug it into the contact simulator (`PairSimulator(..., reconstruct=...)`) so contacts carry the real
    reconstruction's errors. The sensor noise of each image is seeded from the height map itself, so a
    contact's cloud does not depend on the order contacts are simulated in.
    """
    import hashlib

    from yoto.sensor.reconstruction import reconstruct

    def height_map_to_points(height_map_m: np.ndarray) -> np.ndarray:
        rng = None
        if sensor_noise:
            digest = hashlib.sha256(np.ascontiguousarray(height_map_m, dtype=np.float64).tobytes()).digest()
            rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
        return reconstruct(render_image(height_map_m, calibration, rng), calibration).points_sensor

    return height_map_to_points
