"""Sensor calibration from ball presses: the colour -> gradient and gradient -> colour models, fitted.

Procedure (`calibrate`):
1. Check that the background belongs to the presses (same sensor, same lighting) and find each press's
   colour disc (presses.find_contact_circle, "edge" mode: the rim of the visibly coloured region).
2. The colour disc's rim lies outside the true contact circle (the gel bends back to flat beyond it, and the
   optics blur), so a first colour -> gradient model is fitted only on pixels well inside the disc, labelled
   with the gradients of a sphere of the ball's radius centred on the disc (`sphere.sphere_gradients`).
3. Self-calibration: with that model, each press's centre is refined by fitting the sphere's gradient field
   to the predicted gradients, and its contact radius is re-found as the ring where the predicted slope
   magnitude peaks (the contact edge: inside, the sphere's slope grows with radius; outside, the gel's slope
   decays). The model is refitted on the refined circles; this repeats `refine_iterations` times.
4. The inverse model (gradient -> colour change) for the optical simulator is fitted on the final circles,
   and the sensor noise is measured on pixels far from every press.

Pixels far outside every press are labelled flat (zero gradient). The result is a `calibration.SensorCalibration`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError
from yoto.sensor.calibration import MaskConfig, SensorCalibration, background_change
from yoto.sensor.models import (
    GradientModel,
    GradientModelConfig,
    ImageModel,
    ImageModelConfig,
    fit_gradient_model,
    fit_image_model,
    gradient_design,
    image_design,
    model_colour_change,
    monomial_exponents,
    monomials,
    normalised_xy,
    solve_ridge,
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
from yoto.sensor.sphere import refine_centre, sphere_gradients

SELECTION_STRIDE = 4  # the model-shape choices score every 4th sample
DEFAULT_RENDER_BLUR_PX = 2.0  # the optical simulator's blur of its colour change (pixels): a default, not fitted
RENDER_MARGIN_PX = 12  # round_trip_gain renders presses this far beyond the pixels it reads (4 blur sigmas + smoothing)


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
    position_degrees: tuple[int, ...] = (2, 3, 4)  # candidate position degrees of the final colour -> gradient
    # model (bias and gains); the one with the lowest press-wise cross-validated gradient error is used
    image_shapes: tuple[tuple[int, int], ...] = ((2, 1), (4, 2), (4, 4))  # candidate (position degree, gain degree) of
    # the gradient -> colour model, chosen by cross-validated colour error
    selection_folds: int = 4  # folds (by press) of those choices
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
    discs: dict[int, ContactCircle] = {}  # press index -> its colour disc, for the usable presses
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
        discs[i] = disc
    if len(mismatched) > len(presses) / 2:
        raise InputError(
            f"the background does not match the press images: {len(mismatched)}/{len(presses)} presses "
            "differ "
            f"from it almost everywhere (median change {np.median(mismatched):.0f} levels, limit "
            f"{config.max_background_change:.0f}); use a background taken with the same sensor and lighting",
            background_path,
        )
    usable = list(discs)
    if len(usable) < config.min_presses:
        reasons = "; ".join(f"{r.name}: {r.reason}" for r in results if not r.used)[:2000]
        raise InputError(f"only {len(usable)} usable presses (need {config.min_presses}). {reasons}")

    changes = {i: model_colour_change(images[i], background_i16, config.smooth) for i in usable}
    circles = {i: (disc.centre_x_px, disc.centre_y_px, disc.radius_px) for i, disc in discs.items()}
    model = _fit_round(changes, circles, ball_radius_px, config.first_fit_fraction, config, spec)
    fraction = config.first_fit_fraction
    for _ in range(config.refine_iterations):
        circles = _refine_circles(model, changes, circles, ball_radius_px, fraction, config)
        fraction = config.inside_fraction
        model = _fit_round(changes, circles, ball_radius_px, fraction, config, spec)

    # The final model's shape by held-out error on these presses (more presses afford more position terms).
    model_config, gradient_errors = _choose_gradient_model(changes, circles, ball_radius_px, fraction, config, spec)
    if model_config != config.gradient_model:
        model = _fit_round(
            changes, circles, ball_radius_px, fraction, replace(config, gradient_model=model_config), spec
        )

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
    image_config, colour_errors = _choose_image_model(raw, circles, ball_radius_px, fraction, config, spec)
    image_model = _fit_image(raw, circles, ball_radius_px, fraction, replace(config, image_model=image_config), spec)
    noise_std = _noise_level(raw, circles)
    ungained = SensorCalibration(
        spec, background.copy(), model, image_model, config.mask, config.smooth, noise_std, DEFAULT_RENDER_BLUR_PX
    )
    gain, read_before, read_after = round_trip_gain(ungained, changes, circles, ball_radius_px, fraction)

    seconds = time.perf_counter() - start
    report = CalibrationReport(results, seconds, float(np.median(list(rmse.values()))))
    meta = {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "ball_diameter_mm": ball_diameter_m * 1e3,
        "config": _config_json(config),
        "presses": [p.to_json() for p in results],
        "training_gradient_rmse": report.gradient_rmse,
        "held_out_gradient_rmse_by_position_degree": {str(k): v for k, v in gradient_errors.items()},
        "held_out_colour_rmse_by_image_shape": {f"{k[0]},{k[1]}": v for k, v in colour_errors.items()},
        # median over presses of the slope the gradient model reads on the rendered press / on the real one
        "rendered_press_read": {"before_gain": read_before, "after_gain": read_after},
    }
    return replace(ungained, image_model=replace(image_model, gain=gain), meta=meta), report


def round_trip_gain(
    calibration: SensorCalibration,
    changes: dict[int, np.ndarray],
    circles: dict[int, tuple[float, float, float]],
    ball_radius_px: float,
    fraction: float,
    iterations: int = 1,
) -> tuple[np.ndarray, float, float]:
    """The optical simulator's gain over the pad (`ImageModel.gain`) that makes the gradient model read each press,
    rendered from its Hertz height map, as it reads the real press.

    The image model is fitted on the presses' colours against their sphere gradients, and those labels carry the
    circle fits' errors: a least-squares fit of colour on noisy gradients comes out attenuated, by an amount that
    varies over the pad (the 44 example presses: rendered / real read 0.984 median, 0.945 for the 6 presses in
    the pad's middle ninth; with the gain 1.000 and 0.974). Only pixels inside the contact are compared: beyond
    it the true gel shape is not known (Hertz assumes a half-space). The gain is a polynomial in the pixel
    position of the image model's position degree, fitted by least squares on the slope the gradient model reads
    along each press's true gradient direction (real slope * current gain ~ new gain * rendered slope), refitted
    `iterations` times as the gradient model is not linear in colour. Returns the gain and the median over
    presses of the rendered / real read before and after it.
    """
    from yoto.sensor.optical import render_image
    from yoto.sensor.sphere import press_height_map

    spec = calibration.spec
    shape = (spec.height_px, spec.width_px)
    x, y = normalised_xy(*shape)
    exponents = monomial_exponents(2, calibration.image_model.config.position_degree)
    presses = []
    for i, change in changes.items():
        cx, cy, a = circles[i]
        tx, ty, r = sphere_gradients(cx, cy, ball_radius_px, shape)
        slope = np.hypot(tx, ty)
        inside = (r < fraction * a) & (slope > 0.05)
        if np.count_nonzero(inside) < 20:
            continue
        gx, gy = calibration.gradient_model.predict(change)
        along = np.stack([tx[inside], ty[inside]], 1) / slope[inside, None]
        real = gx[inside] * along[:, 0] + gy[inside] * along[:, 1]
        height = press_height_map(cx, cy, a, ball_radius_px * spec.pixel_size_m, spec)
        near = r < fraction * a + RENDER_MARGIN_PX
        presses.append((inside, along, real, height, near, monomials(np.stack([x[inside], y[inside]], 1), exponents)))
    gain = np.zeros(len(exponents))
    gain[0] = 1.0
    ratios: list[float] = []
    for iteration in range(iterations + 1):
        gained = replace(calibration, image_model=replace(calibration.image_model, gain=gain))
        design, target, ratio = [], [], []
        for inside, along, real, height, near, basis in presses:
            image = render_image(height, gained, region=near)
            rendered = model_colour_change(image, gained.background_i16, gained.smooth)
            gx, gy = calibration.gradient_model.predict(rendered)
            read = gx[inside] * along[:, 0] + gy[inside] * along[:, 1]
            ratio.append(float(np.median(read / real)))
            design.append(read[:, None] * basis)
            target.append(real * (basis @ gain))
        ratios.append(float(np.median(ratio)))
        if iteration < iterations:
            gain = np.linalg.lstsq(np.vstack(design), np.concatenate(target), rcond=None)[0]
    return gain, ratios[0], ratios[-1]


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


def _held_out_rmse(samples: dict[int, tuple[np.ndarray, ...]], design: Any, ridge: float, folds: int) -> float:
    """Press-wise k-fold RMS error of a linear model: press -> (features input, positions, targets, weights, scored).

    `design(inputs, positions)` builds the features; each fold is fitted on the other presses' samples and scored
    on its own presses' `scored` samples.
    """
    stride = SELECTION_STRIDE  # neighbouring pixels are nearly the same sample: every few is as good and faster
    samples = {k: tuple(v[::stride] for v in value) for k, value in samples.items()}
    presses = sorted(samples)
    squared, count = 0.0, 0
    for fold in range(folds):
        held = [k for n, k in enumerate(presses) if n % folds == fold]
        train = [samples[k] for k in presses if k not in held]
        if not held or not train:
            continue
        inputs, positions, targets, weights, _ = (np.concatenate(parts) for parts in zip(*train, strict=True))
        coefficients = solve_ridge(design(inputs, positions), targets, weights, ridge)
        for k in held:
            inputs, positions, targets, _, scored = samples[k]
            residual = design(inputs[scored], positions[scored]) @ coefficients - targets[scored]
            squared += float(np.sum(residual * residual))
            count += int(scored.sum())
    return float(np.sqrt(squared / max(count, 1)))


def _choose_gradient_model(
    changes, circles, ball_radius_px, fraction, config: CalibrationConfig, spec
) -> tuple[GradientModelConfig, dict[int, float]]:
    """The colour -> gradient model's position degree with the lowest held-out gradient error inside the contacts."""
    samples: dict[int, tuple[np.ndarray, ...]] = {}
    for i in changes:
        colours, positions, gradients, weights = _training_samples(
            {i: changes[i]}, {i: circles[i]}, ball_radius_px, fraction, config, spec
        )
        samples[i] = (colours, positions, gradients, weights, np.any(gradients != 0, axis=1))
    errors = {}
    for degree in config.position_degrees:
        candidate = replace(config.gradient_model, position_degree=degree)
        errors[degree] = _held_out_rmse(
            samples, lambda c, p, m=candidate: gradient_design(c, p, m), candidate.ridge, config.selection_folds
        )
    best = min(errors, key=errors.__getitem__)
    return replace(config.gradient_model, position_degree=best), errors


def _image_samples(raw, circles, ball_radius_px, fraction, spec) -> dict[int, tuple[np.ndarray, ...]]:
    """Per press: gradients, positions and drift-free colour changes of its contact pixels (`_fit_image`)."""
    shape = (spec.height_px, spec.width_px)
    x, y = normalised_xy(*shape)
    out: dict[int, tuple[np.ndarray, ...]] = {}
    for i, change in raw.items():
        cx, cy, a = circles[i]
        gx, gy, r = sphere_gradients(cx, cy, ball_radius_px, shape)
        inside = r < fraction * a
        drift = np.median(change[r > 3 * a], axis=0)
        colours = change[inside].astype(np.float64) - drift
        out[i] = (
            np.stack([gx[inside], gy[inside]], 1),
            np.stack([x[inside], y[inside]], 1),
            colours,
            np.ones(len(colours)),
            np.ones(len(colours), dtype=bool),
        )
    return out


def _choose_image_model(
    raw, circles, ball_radius_px, fraction, config: CalibrationConfig, spec
) -> tuple[ImageModelConfig, dict[tuple[int, int], float]]:
    """The gradient -> colour model's (position degree, gain degree) with the lowest held-out colour error."""
    samples = _image_samples(raw, circles, ball_radius_px, fraction, spec)
    errors = {}
    for position_degree, gain_degree in config.image_shapes:
        candidate = replace(config.image_model, position_degree=position_degree, gain_degree=gain_degree)
        errors[(position_degree, gain_degree)] = _held_out_rmse(
            samples, lambda g, p, m=candidate: image_design(g, p, m), candidate.ridge, config.selection_folds
        )
    position_degree, gain_degree = min(errors, key=errors.__getitem__)
    return replace(config.image_model, position_degree=position_degree, gain_degree=gain_degree), errors


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
    samples = _image_samples(raw, circles, ball_radius_px, fraction, spec).values()
    gradients, positions, colours, weights, _ = (np.concatenate(parts) for parts in zip(*samples, strict=True))
    return fit_image_model(gradients, positions, colours, weights, config.image_model)


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
