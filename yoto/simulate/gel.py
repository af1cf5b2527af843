"""The simulated gel: how the elastomer deforms around an indenter, and what a reconstruction makes of it.

The gel (step 3 of `press.PressSimulator.press`). The penetration `I = max(0, -z_obj)` is what the object pushes
into the undeformed gel volume (`z_obj`: the object's surface z in the sensor frame). The elastomer also sinks in
around the contact; we model that by Gaussian spreading of the penetration, `S = gain * G_sigma * I`, and take the
gel depth as `D = max(I, S)`: the gel is at least as deep as the object pushes it (it cannot penetrate the object)
and sinks in smoothly beside it. The height map is `-D`. The contact mask is where the gel touches the object
(`I >= S`) and the penetration exceeds a small threshold.

Reconstruction noise (`reconstruct_points`) turns the noise-free height map into what a GelSight reconstruction
pipeline would output: a depth scale error, a smooth low-frequency bias field, per-pixel noise, and a contact mask
re-thresholded on the noisy heights.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec

TOUCH_TOLERANCE_M = 1e-7  # the gel counts as touching the object where it is within this of the surface


@dataclass(frozen=True)
class GelModel:
    """How the elastomer deforms around an indenter (see the module docstring)."""

    spread_sigma_m: float = 0.0004  # Gaussian sink-in length of the gel around a contact (0: no spreading)
    spread_gain: float = 1.0  # weight of the spread indentation (1: a flat, wide press keeps its depth)
    contact_threshold_m: float = 5e-5  # penetration below this is not counted as contact (noise floor)


@dataclass(frozen=True)
class ReconstructionNoise:
    """Errors of a GelSight height-map reconstruction (photometric stereo + Poisson integration).

    The defaults are a judgement, not a fit to data: depth errors of a few hundredths of a millimetre
    (per pixel and low-frequency, RMS about 0.03 mm together) and a few percent of depth scale error from the
    gradient calibration, the size GelSight-class reconstructions of ball presses show. For realism beyond
    this, plug an image renderer and the real reconstruction into `press.simulate_contact(reconstruct=...)`.
    """

    pixel_std_m: float = 1.5e-5  # white per-pixel height noise
    bias_std_m: float = 2e-5  # smooth low-frequency bias field (integration drift), standard deviation
    bias_length_m: float = 0.003  # correlation length of the bias field
    scale_std: float = 0.03  # relative depth scale error, drawn once per press
    mask_threshold_m: float = 6e-5  # the noisy reconstruction's contact threshold on gel depth
    mask_margin_px: int = 8  # noisy contact pixels count only within this distance of the true contact
    not_applied: tuple[str, ...] = ()  # of "scale", "bias", "pixel": drawn as usual but not applied, so every later
    # draw stays what it was (a controlled comparison; a standard deviation of 0 draws nothing and shifts them)

    def applied(self, part: str) -> float:
        """1.0 where the error `part` ("scale", "bias", "pixel") is applied, 0.0 where it is drawn only."""
        return 0.0 if part in self.not_applied else 1.0

    @classmethod
    def none(cls) -> ReconstructionNoise:
        """No reconstruction error: the tactile cloud is the noise-free contact patch."""
        return cls(pixel_std_m=0.0, bias_std_m=0.0, scale_std=0.0, mask_threshold_m=0.0, mask_margin_px=0)

    @property
    def is_noise_free(self) -> bool:
        return self.pixel_std_m == 0 and self.bias_std_m == 0 and self.scale_std == 0


def gel_surface(
    object_z_m: np.ndarray, gel: GelModel, spec: GelSightSpec = GELSIGHT_MINI
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free gel height map, contact mask and penetration from the object's height over the pad.

    `object_z_m` is the object surface z in the sensor frame (+inf where there is no surface). Returns
    (height_map_m, contact_mask, penetration_m), each (H, W).
    """
    penetration = np.where(np.isfinite(object_z_m), np.maximum(-object_z_m, 0.0), 0.0)
    spread = np.zeros_like(penetration)
    rows, columns = np.flatnonzero(penetration.any(axis=1)), np.flatnonzero(penetration.any(axis=0))
    if gel.spread_sigma_m > 0 and len(rows):
        # Filter only the window around the indentation (the kernel is truncated at 4 sigma anyway);
        # 'nearest' at the image border: the gel and the object continue a little beyond the sensed area.
        sigma_px = gel.spread_sigma_m / spec.pixel_size_m
        margin = int(np.ceil(4 * sigma_px)) + 1
        window = (
            slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
            slice(max(columns.min() - margin, 0), columns.max() + margin + 1),
        )
        spread[window] = gel.spread_gain * ndimage.gaussian_filter(penetration[window], sigma_px, mode="nearest")
    depth = np.maximum(penetration, spread)
    # Touching: the gel lies on the object. The tolerance covers the float32 ray casting (~0.03 um at 0.3 m),
    # which would otherwise make a flat press, where penetration and spread are equal, flicker.
    touching = (penetration >= spread - TOUCH_TOLERANCE_M) & (penetration > gel.contact_threshold_m)
    return -depth, touching, penetration


def reconstruct_points(
    height_map_m: np.ndarray,
    contact_mask: np.ndarray,
    noise: ReconstructionNoise,
    rng: np.random.Generator,
    spec: GelSightSpec = GELSIGHT_MINI,
) -> tuple[np.ndarray, dict[str, float]]:
    """The tactile cloud a reconstruction would output for a noise-free height map.

    Applies a depth scale error (once per press), a smooth bias field (random Fourier features of a
    Gaussian-covariance field with correlation length `bias_length_m`) and white per-pixel noise, then
    thresholds the noisy gel depth at `mask_threshold_m` within `mask_margin_px` of the true contact.
    Without noise it returns the contact patch unchanged. Returns (points_sensor, drawn errors).
    """
    if noise.is_noise_free:
        return spec.height_map_to_points(height_map_m, contact_mask), {"scale_error": 0.0}
    scale_error, bias = calibration_errors(noise, rng, spec)
    noisy = height_map_m * (1.0 + scale_error) + bias
    if noise.pixel_std_m > 0:
        noisy = noisy + rng.normal(scale=noise.pixel_std_m, size=noisy.shape) * noise.applied("pixel")
    region = contact_mask
    if noise.mask_margin_px > 0:
        region = ndimage.maximum_filter(contact_mask, size=2 * noise.mask_margin_px + 1)
    mask = region & (-noisy > noise.mask_threshold_m)
    return spec.height_map_to_points(noisy, mask), {"scale_error": scale_error}


def calibration_errors(
    noise: ReconstructionNoise, rng: np.random.Generator, spec: GelSightSpec = GELSIGHT_MINI
) -> tuple[float, np.ndarray | float]:
    """The errors a reconstruction's calibration and lighting put on a whole frame, drawn in this order: the depth
    scale error (relative) and the smooth bias field ((H, W) metres; 0.0 without one), each 0 where `not_applied`."""
    scale_error = float(rng.normal() * noise.scale_std) * noise.applied("scale")
    if noise.bias_std_m <= 0:
        return scale_error, 0.0
    return scale_error, bias_field(noise.bias_std_m, noise.bias_length_m, rng, spec) * noise.applied("bias")


def bias_field(
    std_m: float, length_m: float, rng: np.random.Generator, spec: GelSightSpec = GELSIGHT_MINI, features: int = 16
) -> np.ndarray:
    """A smooth zero-mean random field over the image, (H, W) metres, with standard deviation about `std_m`.

    Sum of `features` cosines with wave vectors drawn from N(0, 1/length^2): in expectation a stationary
    Gaussian process with covariance exp(-r^2 / (2 length^2)).
    """
    columns, rows = _pixel_axes(spec)
    wave = rng.normal(scale=1.0 / length_m, size=(features, 2))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=features)
    # cos(kx x + ky y + p) = cos(ky y) cos(kx x + p) - sin(ky y) sin(kx x + p): one matrix product.
    along_rows = np.hstack([np.cos(np.outer(rows, wave[:, 1])), -np.sin(np.outer(rows, wave[:, 1]))])
    along_columns = np.vstack(
        [np.cos(np.outer(wave[:, 0], columns) + phase[:, None]), np.sin(np.outer(wave[:, 0], columns) + phase[:, None])]
    )
    field_ = np.einsum("rk,kc->rc", along_rows, along_columns)  # not BLAS: threaded matmul can stall
    return std_m * np.sqrt(2.0 / features) * field_


@functools.lru_cache(maxsize=8)
def _pixel_axes(spec: GelSightSpec) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame x of each image column and y of each image row (metres), as in `spec.pixel_xy_sensor`."""
    x, y = spec.pixel_xy_sensor()
    return x[0].copy(), y[:, 0].copy()
