"""Sensor calibration from ball presses: ground-truth gradients of the spherical cap, model fits, the file.

Procedure (`calibrate`):
1. Check that the background belongs to the presses (same sensor, same lighting) and find each press's
   colour disc (presses.find_contact_circle, "edge" mode: the rim of the visibly coloured region).
2. The colour disc's rim lies outside the true contact circle (the gel bends back to flat beyond it, and the
   optics blur), so a first colour -> gradient model is fitted only on pixels well inside the disc, labelled
   with the gradients of a sphere of the ball's radius centred on the disc.
3. Self-calibration: with that model, each press's centre is refined by fitting the sphere's gradient field
   to the predicted gradients, and its contact radius is re-found as the ring where the predicted slope
   magnitude peaks (the contact edge: inside, the sphere's slope grows with radius; outside, the gel's slope
   decays). The model is refitted on the refined circles; this repeats `refine_iterations` times.
4. The inverse model (gradient -> colour change) for the optical simulator is fitted on the final circles,
   and the sensor noise is measured on pixels far from every press.

Ground truth of a press with the ball's centre above pixel (cx, cy), ball radius R and contact radius a
(all in pixels), r the distance from (cx, cy): inside the contact circle the gel follows the sphere,
    z(r) = -(sqrt(R^2 - r^2) - sqrt(R^2 - a^2)),   dz/dx = (x - cx) / sqrt(R^2 - r^2),  same for y,
and the gradients do not depend on a. Pixels far outside every press are labelled flat (zero gradient).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError
from yoto.io import load_npz, save_npz_atomic
from yoto.sensor.models import (
    GradientModel,
    GradientModelConfig,
    ImageModel,
    ImageModelConfig,
    fit_gradient_model,
    fit_image_model,
    load_gradient_model,
    normalised_xy,
)
from yoto.sensor.presses import (
    CircleConfig,
    ContactCircle,
    NoCircleError,
    check_image,
    find_contact_circle,
    ring_circle,
)
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec

log = logging.getLogger("yoto")

FORMAT_NAME = "yoto-sensor-calibration"
FORMAT_VERSION = 1


# ---------------------------------------------------------------------------------------------------------
# Ground truth of a ball press


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


# ---------------------------------------------------------------------------------------------------------
# Colour change as the models see it


def model_colour_change(image: np.ndarray, background_i16: np.ndarray, smooth: bool) -> np.ndarray:
    """int16 (rows, cols, 3) colour change, optionally smoothed by a 3x3 binomial filter (edges replicated).

    Integer arithmetic throughout so calibration and reconstruction see bit-identical inputs.
    """
    diff = image.astype(np.int16)
    diff -= background_i16
    if not smooth:
        return diff
    across = diff * 2
    across[:, 1:] += diff[:, :-1]
    across[:, :-1] += diff[:, 1:]
    across[:, 0] += diff[:, 0]
    across[:, -1] += diff[:, -1]
    out = across * 2
    out[1:] += across[:-1]
    out[:-1] += across[1:]
    out[0] += across[0]
    out[-1] += across[-1]
    out += 8
    out >>= 4
    return out


# ---------------------------------------------------------------------------------------------------------
# Configuration and the calibration object


@dataclass(frozen=True)
class MaskConfig:
    """Which pixels of a reconstruction belong to the contact."""

    colour_threshold: float = 15.0  # RGB distance (0-255) by which a contact's pixels change colour
    relative_depth: float = 0.5  # contact pixels are this fraction of the deepest depth or deeper
    min_depth_m: float = 5e-5  # ... and at least this deep (metres); shallower frames have no contact
    min_area_px: int = 40  # fewer changed or contact pixels than this: no contact (explicit empty result)


@dataclass(frozen=True)
class CalibrationConfig:
    """How a sensor is calibrated from ball presses."""

    circle: CircleConfig = field(default_factory=CircleConfig)  # colour-disc detection
    gradient_model: GradientModelConfig = field(default_factory=GradientModelConfig)  # colour -> gradient
    image_model: ImageModelConfig = field(default_factory=ImageModelConfig)  # gradient -> colour
    mask: MaskConfig = field(default_factory=MaskConfig)  # contact mask written into the calibration
    smooth: bool = True  # 3x3 binomial smoothing of the colour change before the model (also at reconstruction)
    first_fit_fraction: float = 0.7  # the first fit uses pixels within this fraction of the colour-disc radius
    inside_fraction: float = 0.9  # later fits use pixels within this fraction of the refined contact radius
    flat_margin: float = 2.2  # pixels beyond this multiple of the radius (of every press) are labelled flat
    flat_stride: int = 21  # use every n-th flat pixel (raster order) of each press
    flat_weight: float = 1.0  # least-squares weight of a flat pixel relative to a contact pixel
    refine_iterations: int = 2  # centre/radius refinements on the model's predicted gradients
    min_presses: int = 4  # fewer usable presses than this is an error
    max_background_change: float = 10.0  # median colour change of a press against the background (0-255)
    saturation_level: int = 255  # a channel at or above this level is saturated


@dataclass(frozen=True)
class PressResult:
    """What calibration found in one press image."""

    name: str  # file name or index of the press
    used: bool  # the press entered the fit
    reason: str  # why not, or "" when used
    disc: ContactCircle | None = None  # the colour disc found on the raw colour change
    contact_x_px: float = float("nan")  # refined contact circle: centre column
    contact_y_px: float = float("nan")  # refined contact circle: centre row
    contact_radius_px: float = float("nan")  # refined contact circle: radius
    gradient_rmse: float = float("nan")  # RMS error of the fitted gradients inside the contact (training)

    def to_json(self) -> dict[str, Any]:
        out = {
            k: getattr(self, k)
            for k in (
                "name",
                "used",
                "reason",
                "contact_x_px",
                "contact_y_px",
                "contact_radius_px",
                "gradient_rmse",
            )
        }
        out["disc"] = None if self.disc is None else asdict(self.disc)
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in out.items()}


@dataclass
class SensorCalibration:
    """Everything reconstruction and the optical simulator need for one sensor."""

    spec: GelSightSpec  # sensor name, image size, scale
    background: np.ndarray  # (rows, cols, 3) uint8: the no-contact image the models are relative to
    gradient_model: GradientModel  # colour change -> surface gradient
    image_model: ImageModel  # surface gradient -> colour change (optical simulator)
    mask: MaskConfig  # contact-mask thresholds
    smooth: bool  # whether the colour change is smoothed before the gradient model
    noise_std: np.ndarray  # (3,) per-channel sensor noise (0-255 levels), measured on flat pixels
    render_blur_px: float  # Gaussian blur (pixels) the optical simulator applies to its colour change
    meta: dict[str, Any] = field(default_factory=dict)  # provenance: presses, circles, fit statistics

    def __post_init__(self) -> None:
        self.background_i16 = self.background.astype(np.int16)

    @property
    def background_sha256(self) -> str:
        return background_hash(self.background)

    def save(self, path: str | Path) -> Path:
        """Write the calibration as one npz file (atomic)."""
        meta = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "sensor": {
                "name": self.spec.name,
                "width_px": self.spec.width_px,
                "height_px": self.spec.height_px,
                "mm_per_px": self.spec.mm_per_px,
            },
            "background_sha256": self.background_sha256,
            "model": {
                "type": "polynomial-lut",
                "gradient": asdict(self.gradient_model.config),
                "image": asdict(self.image_model.config),
                "image_max_gradient": self.image_model.max_gradient,
            },
            "mask": asdict(self.mask),
            "smooth": self.smooth,
            "noise_std": [float(v) for v in self.noise_std],
            "render_blur_px": self.render_blur_px,
            **{
                k: v
                for k, v in self.meta.items()
                if k
                not in (
                    "format",
                    "version",
                    "sensor",
                    "background_sha256",
                    "model",
                    "mask",
                    "smooth",
                    "noise_std",
                    "render_blur_px",
                )
            },
        }
        arrays = {
            "background": self.background,
            **self.gradient_model.arrays("gradient_"),
            **self.image_model.arrays("image_"),
        }
        return save_npz_atomic(path, arrays, meta)


def with_background(
    calibration: SensorCalibration,
    background: np.ndarray,
    path: str | Path | None = None,
    max_change: float = 10.0,
) -> SensorCalibration:
    """The calibration with a fresh background image of the same sensor (lighting drifts over a day).

    Raises InputError when the new background is not of this sensor: wrong size, or its colours differ from
    the calibrated background by more than `max_change` levels (median over pixels, largest channel).
    """
    check_image(background, calibration.spec, path, "background")
    level = background_change(background, calibration.background)
    if level > max_change:
        raise InputError(
            f"background differs from the calibration's background by {level:.0f} levels (median; limit "
            f"{max_change:.0f}): it is from another sensor, or the lighting changed too much; recalibrate",
            path,
        )
    meta = {**calibration.meta, "background_replaced_from": str(path) if path else "array"}
    return SensorCalibration(
        calibration.spec,
        np.ascontiguousarray(background),
        calibration.gradient_model,
        calibration.image_model,
        calibration.mask,
        calibration.smooth,
        calibration.noise_std,
        calibration.render_blur_px,
        meta,
    )


def background_hash(background: np.ndarray) -> str:
    """SHA-256 of a background image's pixels (uint8, row-major RGB)."""
    return hashlib.sha256(np.ascontiguousarray(background, dtype=np.uint8).tobytes()).hexdigest()


def load_calibration(path: str | Path, spec: GelSightSpec | None = None) -> SensorCalibration:
    """Load a calibration file; with `spec`, also check that it was made for that sensor.

    Raises InputError naming the file for anything that is not a readable calibration of a matching sensor.
    """
    path = Path(path)
    arrays, meta = load_npz(path, "sensor calibration")
    if meta.get("format") != FORMAT_NAME:
        raise InputError(
            f"not a sensor calibration file (its format is '{meta.get('format')}', expected "
            f"'{FORMAT_NAME}'); make one with `yoto sensor calibrate`",
            path,
        )
    if meta.get("version") != FORMAT_VERSION:
        raise InputError(
            f"sensor calibration format version {meta.get('version')} is not supported (this yoto "
            f"reads version {FORMAT_VERSION}); recalibrate with `yoto sensor calibrate`",
            path,
        )
    try:
        sensor = meta["sensor"]
        file_spec = GelSightSpec(
            name=str(sensor["name"]),
            width_px=int(sensor["width_px"]),
            height_px=int(sensor["height_px"]),
            mm_per_px=float(sensor["mm_per_px"]),
        )
        model = meta["model"]
        gradient_config = GradientModelConfig(**model["gradient"])
        image_config = ImageModelConfig(**model["image"])
        mask = MaskConfig(**meta["mask"])
        background = arrays["background"]
        gradient_model = load_gradient_model(
            arrays, "gradient_", gradient_config, (file_spec.height_px, file_spec.width_px)
        )
        image_model = ImageModel(arrays["image_coefficients"], float(model["image_max_gradient"]), image_config)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"sensor calibration file is incomplete or damaged ({type(exc).__name__}: {exc})", path
        ) from exc
    if spec is not None and (spec.name, spec.width_px, spec.height_px) != (
        file_spec.name,
        file_spec.width_px,
        file_spec.height_px,
    ):
        raise InputError(
            f"calibration is for sensor '{file_spec.name}' ({file_spec.width_px}x{file_spec.height_px}"
            f" px) but '{spec.name}' ({spec.width_px}x{spec.height_px} px) was expected",
            path,
        )
    if spec is not None and abs(spec.mm_per_px - file_spec.mm_per_px) > 1e-9:
        raise InputError(
            f"calibration scale is {file_spec.mm_per_px} mm/px but the {spec.name} has {spec.mm_per_px} mm/px",
            path,
        )
    if background.shape != (file_spec.height_px, file_spec.width_px, 3) or background.dtype != np.uint8:
        raise InputError(
            f"calibration background has shape {background.shape} {background.dtype}, expected "
            f"({file_spec.height_px}, {file_spec.width_px}, 3) uint8",
            path,
        )
    if background_hash(background) != meta.get("background_sha256"):
        raise InputError("calibration background does not match its recorded SHA-256 (file damaged)", path)
    return SensorCalibration(
        file_spec,
        background,
        gradient_model,
        image_model,
        mask,
        bool(meta["smooth"]),
        np.asarray(meta["noise_std"], dtype=np.float64),
        float(meta["render_blur_px"]),
        {k: v for k, v in meta.items()},
    )


# ---------------------------------------------------------------------------------------------------------
# Calibration


@dataclass
class CalibrationReport:
    """Per-press results and the fit's statistics."""

    presses: list[PressResult]
    seconds: float
    gradient_rmse: float  # median over used presses of the training RMS gradient error inside the contact

    def summary(self) -> str:
        used = [p for p in self.presses if p.used]
        radii = np.array([p.contact_radius_px for p in used])
        return (
            f"{len(used)}/{len(self.presses)} presses used, contact radius median {np.median(radii):.1f} px, "
            f"training gradient RMSE median {self.gradient_rmse:.3f}, {self.seconds:.1f} s"
        )


def background_change(image: np.ndarray, background: np.ndarray) -> float:
    """Median over pixels of the largest per-channel colour change (levels).

    Most pixels of a press see no contact, so this is small for a background of the same sensor and
    lighting, and large for anything else.
    """
    change = np.abs(image.astype(np.int16) - background.astype(np.int16)).max(axis=2)
    return float(np.median(change))


def calibrate(
    background: np.ndarray,
    presses: Sequence[np.ndarray],
    ball_diameter_m: float,
    config: CalibrationConfig = CalibrationConfig(),
    spec: GelSightSpec = GELSIGHT_MINI,
    names: Sequence[str] | None = None,
    background_path: str | Path | None = None,
) -> tuple[SensorCalibration, CalibrationReport]:
    """Calibrate a sensor from a background image and ball-press images (all (rows, cols, 3) uint8 RGB).

    Presses whose contact circle cannot be found are left out (their reason is in the report). Raises
    InputError for a background that does not belong to the presses, or too few usable presses.
    """
    start = time.perf_counter()
    check_image(background, spec, background_path, "background")
    names = [str(i) for i in range(len(presses))] if names is None else list(names)
    if not 0 < ball_diameter_m < 0.05:
        raise InputError(f"ball diameter {ball_diameter_m * 1e3:.3f} mm is not plausible (expected 1-50 mm)")
    ball_radius_px = ball_diameter_m / 2 / spec.pixel_size_m
    background_i16 = background.astype(np.int16)

    results: list[PressResult] = []
    usable: list[int] = []
    images: list[np.ndarray] = []
    mismatched = []
    for i, (name, image) in enumerate(zip(names, presses, strict=True)):
        check_image(image, spec, name, "press image")
        images.append(image)
        level = background_change(image, background)
        if level > config.max_background_change:
            mismatched.append(level)
            results.append(
                PressResult(
                    name,
                    False,
                    f"the image differs from the background almost everywhere "
                    f"(median change {level:.0f} levels): another sensor or lighting?",
                )
            )
            continue
        saturated = float((image >= config.saturation_level).any(axis=2).mean())
        if saturated > 0.001:
            results.append(PressResult(name, False, f"{saturated:.1%} of the pixels are saturated"))
            continue
        try:
            disc = find_contact_circle(image, background, config.circle)
        except NoCircleError as exc:
            results.append(PressResult(name, False, str(exc)))
            continue
        if disc.radius_px >= 0.95 * ball_radius_px:
            results.append(
                PressResult(
                    name,
                    False,
                    f"contact radius {disc.radius_px:.1f} px is not smaller than "
                    f"the ball's radius {ball_radius_px:.1f} px: wrong ball diameter?",
                    disc,
                )
            )
            continue
        results.append(PressResult(name, True, "", disc))
        usable.append(i)
    if len(mismatched) > len(presses) / 2:
        raise InputError(
            f"the background does not match the press images: {len(mismatched)}/{len(presses)} presses "
            "differ "
            f"from it almost everywhere (median change {np.median(mismatched):.0f} levels, limit "
            f"{config.max_background_change:.0f}); use a background taken with the same sensor and lighting",
            background_path,
        )
    if len(usable) < config.min_presses:
        reasons = "; ".join(f"{r.name}: {r.reason}" for r in results if not r.used)[:2000]
        raise InputError(f"only {len(usable)} usable presses (need {config.min_presses}). {reasons}")

    changes = {i: model_colour_change(images[i], background_i16, config.smooth) for i in usable}
    circles = {i: (results[i].disc.centre_x_px, results[i].disc.centre_y_px, results[i].disc.radius_px) for i in usable}
    model = _fit_round(changes, circles, ball_radius_px, config.first_fit_fraction, config, spec)
    fraction = config.first_fit_fraction
    for _ in range(config.refine_iterations):
        circles = _refine_circles(model, changes, circles, ball_radius_px, fraction, config)
        fraction = config.inside_fraction
        model = _fit_round(changes, circles, ball_radius_px, fraction, config, spec)

    # Final report per press, the inverse model, the noise level.
    raw = {i: images[i].astype(np.int16) - background_i16 for i in usable}
    rmse = {}
    for i in usable:
        gx, gy = model.predict(changes[i])
        cx, cy, a = circles[i]
        tx, ty, r = sphere_gradients(cx, cy, ball_radius_px, gx.shape)
        inside = r < fraction * a
        rmse[i] = float(np.sqrt(np.mean((gx - tx)[inside] ** 2 + (gy - ty)[inside] ** 2)))
        results[i] = PressResult(results[i].name, True, "", results[i].disc, cx, cy, a, rmse[i])
    image_model = _fit_image(raw, circles, ball_radius_px, fraction, config, spec)
    noise_std = _noise_level(raw, circles)

    seconds = time.perf_counter() - start
    report = CalibrationReport(results, seconds, float(np.median(list(rmse.values()))))
    meta = {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "ball_diameter_mm": ball_diameter_m * 1e3,
        "config": _config_json(config),
        "presses": [p.to_json() for p in results],
        "training_gradient_rmse": report.gradient_rmse,
    }
    calibration = SensorCalibration(
        spec,
        background.copy(),
        model,
        image_model,
        config.mask,
        config.smooth,
        noise_std,
        DEFAULT_RENDER_BLUR_PX,
        meta,
    )
    return calibration, report


DEFAULT_RENDER_BLUR_PX = 2.0


def _config_json(config: CalibrationConfig) -> dict[str, Any]:
    return {
        f.name: (
            asdict(getattr(config, f.name))
            if hasattr(getattr(config, f.name), "__dataclass_fields__")
            else getattr(config, f.name)
        )
        for f in fields(config)
    }


def _training_samples(
    changes: dict[int, np.ndarray],
    circles: dict[int, tuple[float, float, float]],
    ball_radius_px: float,
    fraction: float,
    config: CalibrationConfig,
    spec: GelSightSpec,
) -> tuple[np.ndarray, ...]:
    """Colour changes, positions, target gradients and weights of contact pixels and sparse flat pixels."""
    shape = (spec.height_px, spec.width_px)
    x, y = normalised_xy(*shape)
    stride = (np.arange(shape[0] * shape[1]).reshape(shape) % config.flat_stride) == 0
    out: dict[str, list[np.ndarray]] = {"c": [], "p": [], "g": [], "w": []}
    for i, change in changes.items():
        cx, cy, a = circles[i]
        gx, gy, r = sphere_gradients(cx, cy, ball_radius_px, shape)
        inside = r < fraction * a
        flat = (r > config.flat_margin * a) & stride
        for mask, is_contact in ((inside, True), (flat, False)):
            out["c"].append(change[mask].astype(np.float64))
            out["p"].append(np.stack([x[mask], y[mask]], 1))
            out["g"].append(np.stack([gx[mask], gy[mask]], 1) if is_contact else np.zeros((int(mask.sum()), 2)))
            out["w"].append(np.full(int(mask.sum()), 1.0 if is_contact else config.flat_weight))
    return tuple(np.concatenate(v) for v in out.values())


def _fit_round(changes, circles, ball_radius_px, fraction, config, spec) -> GradientModel:
    colours, positions, gradients, weights = _training_samples(changes, circles, ball_radius_px, fraction, config, spec)
    return fit_gradient_model(
        colours, positions, gradients, weights, (spec.height_px, spec.width_px), config.gradient_model
    )


def _refine_circles(
    model: GradientModel, changes, circles, ball_radius_px: float, fraction: float, config: CalibrationConfig
) -> dict[int, tuple[float, float, float]]:
    """Re-centre each press on its predicted gradient field and re-find its contact edge (slope peak)."""
    refined = {}
    peak_config = CircleConfig(**{**asdict(config.circle), "mode": "peak", "min_radius_px": 3.0})
    for i, change in changes.items():
        cx, cy, a = circles[i]
        gx, gy = model.predict(change)
        cx, cy = refine_centre(gx, gy, (cx, cy), fraction * a, ball_radius_px)
        try:
            ring = ring_circle(np.hypot(gx, gy), peak_config, initial=(cx, cy))
            radius = ring.radius_px if np.hypot(ring.centre_x_px - cx, ring.centre_y_px - cy) < 0.3 * a else a
        except NoCircleError:
            radius = a
        refined[i] = (cx, cy, min(radius, 0.95 * ball_radius_px))
    return refined


def _fit_image(raw, circles, ball_radius_px, fraction, config, spec) -> ImageModel:
    """Fit gradient -> colour change on the contact pixels, each press's lighting drift removed.

    The drift (the median colour change of the press's pixels far from the contact: the lighting moved a
    little between the background and the press) is not part of the optics, and the model is anchored to
    render the background exactly where the gel is flat.
    """
    shape = (spec.height_px, spec.width_px)
    x, y = normalised_xy(*shape)
    g, p, c = [], [], []
    for i, change in raw.items():
        cx, cy, a = circles[i]
        gx, gy, r = sphere_gradients(cx, cy, ball_radius_px, shape)
        inside = r < fraction * a
        drift = np.median(change[r > 3 * a], axis=0)
        g.append(np.stack([gx[inside], gy[inside]], 1))
        p.append(np.stack([x[inside], y[inside]], 1))
        c.append(change[inside].astype(np.float64) - drift)
    gradients, positions, colours = np.concatenate(g), np.concatenate(p), np.concatenate(c)
    return fit_image_model(gradients, positions, colours, np.ones(len(colours)), config.image_model)


def _noise_level(raw, circles) -> np.ndarray:
    """Per-channel robust standard deviation of the colour change far from every press."""
    samples = []
    for i, change in raw.items():
        cx, cy, a = circles[i]
        rows, cols = change.shape[:2]
        r = np.hypot(np.arange(cols)[None, :] - cx, np.arange(rows)[:, None] - cy)
        samples.append(change[r > 3 * a].astype(np.float64))
    far = np.concatenate(samples)
    mad = np.median(np.abs(far - np.median(far, axis=0)), axis=0)
    return 1.4826 * mad
