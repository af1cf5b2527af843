"""Optical simulator: a gel height map -> a realistic GelSight image, the inverse of reconstruction.

The image is the calibration's real background plus the colour change its inverse model predicts from the
surface gradients at each pixel, blurred like the real optics, plus (optionally) sensor noise of the
measured level. A contact simulator that produces gel height maps can so emit images and run them through
`reconstruct`, and the reconstruction's own errors reach the pose figures.

The blur was chosen by rendering Hertz ball presses (`calibration.press_height_map`) at the circles found
in real held-out presses and comparing with those images (docs/sensor.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from yoto.errors import InputError
from yoto.sensor.calibration import SensorCalibration

if TYPE_CHECKING:
    from yoto.sensor.reconstruction import Reconstruction

log = logging.getLogger("yoto")


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
    region: np.ndarray | None = None,
) -> np.ndarray:
    """Render the (rows, cols, 3) uint8 RGB image the sensor would show for a gel height map.

    height_map_m: (rows, cols) gel-surface z in metres (SPEC sensor frame: <= 0 where pressed), rows and
        columns as in `GelSightSpec.height_map_to_points`.
    rng: draw per-pixel Gaussian sensor noise of the calibration's measured level; None renders noise-free.
    blur_px: Gaussian blur of the colour change (pixels); None uses the calibration's measured value.
    region: (rows, cols) bool: draw the colour change only there (flat gel elsewhere), which is faster where
        only part of a frame is needed (a press's contact, `ball_calibration.round_trip_gain`).
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
    if region is not None:
        gx, gy = np.where(region, gx, 0.0), np.where(region, gy, 0.0)
    change = calibration.image_model.predict(gx, gy)
    sigma = calibration.render_blur_px if blur_px is None else blur_px
    if sigma > 0:
        change = ndimage.gaussian_filter(change, (sigma, sigma, 0), mode="nearest")
    image = change + calibration.background.astype(np.float32)
    if rng is not None:
        image += rng.normal(size=image.shape).astype(np.float32) * calibration.noise_std.astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class OpticsVariation:
    """How far each rendered image strays from the calibration's own optics (drawn per image, uniformly)."""

    lighting: float = 0.0  # each channel's colour change is scaled by up to exp(+-lighting) (LEDs, another unit)
    noise: float = 0.0  # the sensor noise is scaled by up to exp(+-noise)
    blur_px: float = 0.0  # the optical blur differs by up to this many pixels (never below zero)
    gel_sigma_m: float = 0.0  # the gel smooths the indenter's shape by a Gaussian of up to this sigma (metres)

    @classmethod
    def of(cls, amount: float) -> OpticsVariation:
        """A variation of size `amount` (0: none; 1: LEDs +-15%, noise x/÷2, blur +-1 px, gel up to 0.1 mm)."""
        return cls(lighting=0.15 * amount, noise=0.7 * amount, blur_px=1.0 * amount, gel_sigma_m=1e-4 * amount)

    @property
    def none(self) -> bool:
        return self == OpticsVariation()


def render_varied(
    height_map_m: np.ndarray, calibration: SensorCalibration, rng: np.random.Generator, variation: OpticsVariation
) -> np.ndarray:
    """`render_image` with lighting, noise, blur and gel response drawn from `variation` around the calibration's."""
    spec = calibration.spec
    gains = np.exp(rng.uniform(-variation.lighting, variation.lighting, 3))
    noise = float(np.exp(rng.uniform(-variation.noise, variation.noise)))
    blur = max(0.0, calibration.render_blur_px + float(rng.uniform(-variation.blur_px, variation.blur_px)))
    sigma_px = float(rng.uniform(0.0, variation.gel_sigma_m)) / spec.pixel_size_m
    if sigma_px > 0:
        height_map_m = ndimage.gaussian_filter(np.asarray(height_map_m, dtype=np.float64), sigma_px, mode="nearest")
    change = render_image(height_map_m, calibration, blur_px=blur).astype(np.float32) - calibration.background
    image = calibration.background + change * gains.astype(np.float32)
    image += rng.normal(size=image.shape).astype(np.float32) * (noise * calibration.noise_std).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


Renderer = Callable[[np.ndarray, "np.random.Generator | None"], np.ndarray]


class ImagePath:
    """A height map -> tactile cloud function that goes through a rendered GelSight image and its reconstruction
    (`image_path_reconstructor`); `reconstruction(height_map_m)` gives the whole reconstruction (None: refused)."""

    def __init__(
        self, calibration: SensorCalibration, sensor_noise: bool, render: Renderer | None, variation: OpticsVariation
    ):
        self.calibration = calibration
        self.sensor_noise = sensor_noise
        self.render = render
        self.variation = variation

    def image(self, height_map_m: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The GelSight image of a gel height map, its noise (and variation) drawn from `rng`, else seeded from the
        height map (the same press gives the same image; a sequence of frames at rest needs an `rng` of its own)."""
        import hashlib

        if self.variation.none and not self.sensor_noise:  # a noise-free image of the sensor as calibrated
            rng = None
        elif rng is None:
            digest = hashlib.sha256(np.ascontiguousarray(height_map_m, dtype=np.float64).tobytes()).digest()
            rng = np.random.default_rng(int.from_bytes(digest[:8], "little"))
        if self.render is not None:
            return self.render(height_map_m, rng if self.sensor_noise else None)
        if rng is not None and not self.variation.none:
            return render_varied(height_map_m, self.calibration, rng, self.variation)
        return render_image(height_map_m, self.calibration, rng)

    def reconstruction(self, height_map_m: np.ndarray) -> Reconstruction | None:
        """The reconstruction of the height map's image; None where the reconstruction refuses the frame."""
        from yoto.sensor.reconstruction import reconstruct

        try:
            return reconstruct(self.image(height_map_m), self.calibration)
        except InputError as exc:
            log.warning("a rendered frame was refused, its contact gives no cloud: %s", exc)
            return None

    def __call__(self, height_map_m: np.ndarray) -> np.ndarray:
        result = self.reconstruction(height_map_m)
        return np.zeros((0, 3)) if result is None else result.points_sensor


def image_path_reconstructor(
    calibration: SensorCalibration,
    sensor_noise: bool = True,
    render: Renderer | None = None,
    variation: OpticsVariation = OpticsVariation(),
) -> ImagePath:
    """A height map -> tactile cloud function that goes through a rendered GelSight image and its reconstruction.

    Plug it into the contact simulator (`PairSimulator(..., reconstruct=...)`) so contacts carry the real
    reconstruction's errors. Images come from the calibration's own optical model (`render_image`, varied per
    image by `variation`), or from `render(height_map_m, rng)`, another optical model (e.g.
    `ShadingSensor.render`, calibrated into `calibration` from its own ball presses). The sensor noise of each
    image is seeded from the height map itself, so a contact's cloud does not depend on the order contacts are
    simulated in. A frame in which the reconstruction finds no contact gives an empty cloud, and so does a frame
    it refuses (InputError, e.g. a contact covering nearly the whole pad reads as another sensor's background):
    a lab's pipeline would get no cloud from it either, and the benchmark counts the contact as failed.
    """
    return ImagePath(calibration, sensor_noise, render, variation)


def image_route(source: str, variation: float = 0.0) -> ImagePath:
    """The height map -> image -> reconstructed cloud function a benchmark names by `source`.

    `source`: a calibration file (images from its own fitted optical model), or `shading[:SEED]`: images from the
    second optical model (`shading.ShadingSensor`: the nominal sensor for seed 0, else one varied by the seed),
    reconstructed with a calibration made from 44 ball presses it renders, as a lab calibrates a new sensor, or
    `table:FOLDER`: images from the third (`table.TableSensor`, a lookup table read off the real ball presses in
    FOLDER, laid out as ../shared/data/gelsight_mini), reconstructed with the calibration `yoto sensor calibrate`
    makes from the same presses.
    `variation` (0: none, 1: large) varies lighting, noise, blur and gel response per image around that sensor.
    """
    if source == "shading" or source.startswith("shading:"):
        from yoto.sensor.shading import ShadingSensor, calibrate_shading_sensor

        seed = int(source.partition(":")[2] or 0)
        rng = np.random.default_rng(seed)
        sensor = ShadingSensor() if seed == 0 else ShadingSensor().varied(rng, 1.0)
        calibration = calibrate_shading_sensor(sensor, rng)

        def render(height_map_m: np.ndarray, image_rng: np.random.Generator | None) -> np.ndarray:
            varied = sensor.varied(image_rng, variation) if variation > 0 and image_rng is not None else sensor
            return varied.render(height_map_m, image_rng)

        return image_path_reconstructor(calibration, render=render)
    if source.startswith("table:"):
        from yoto.sensor.table import table_sensor_and_calibration

        if variation > 0:
            raise InputError("the table renderer (table:FOLDER) renders one sensor's optics; it takes no variation")
        table_sensor, table_calibration = table_sensor_and_calibration(str(Path(source.partition(":")[2]).resolve()))
        return image_path_reconstructor(table_calibration, render=table_sensor.render)
    from yoto.sensor.calibration import load_calibration

    return image_path_reconstructor(load_calibration(source), variation=OpticsVariation.of(variation))
