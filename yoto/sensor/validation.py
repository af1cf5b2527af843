"""Validation on real ball presses: k-fold calibration, reconstruction of held-out presses, sphere fits.

For each fold the sensor is calibrated on the other presses only. Each held-out press is then treated like
any user frame: its contact circle is found automatically (colour disc, then centre and edge refined on the
fold model's predicted gradients, no labels), the frame is reconstructed, and a sphere is fitted by least
squares to the reconstructed surface inside the found contact circle. The fitted radius is compared with
the ball's. The height profile inside the circle is compared with the Hertz press of the found circle
(`calibration.press_height_map`: indentation a^2 / R, of which the cap itself is half): its RMS error after
removing the mean offset (the shape error) and that offset (the depth error) are reported.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from yoto.sensor.ball_calibration import CalibrationConfig, calibrate
from yoto.sensor.calibration import SensorCalibration
from yoto.sensor.models import model_colour_change
from yoto.sensor.presses import CircleConfig, NoCircleError, find_contact_circle, ring_circle
from yoto.sensor.reconstruction import Reconstruction, reconstruct
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec
from yoto.sensor.sphere import press_height_map, refine_centre

log = logging.getLogger("yoto")


@dataclass(frozen=True)
class PressValidation:
    """One held-out press."""

    name: str
    fold: int
    found: bool  # a contact circle was found
    reason: str  # why not
    centre_x_px: float = float("nan")  # found contact circle, column
    centre_y_px: float = float("nan")  # found contact circle, row
    radius_px: float = float("nan")  # found contact circle radius
    fitted_radius_mm: float = float("nan")  # sphere fitted to the reconstructed cap
    sphere_centre_mm: tuple[float, float, float] = (float("nan"),) * 3  # fitted sphere centre, sensor frame
    profile_rmse_mm: float = float("nan")  # RMS height error vs the Hertz press inside the circle, offset removed
    offset_mm: float = float("nan")  # mean (reconstructed - Hertz press) height inside the circle
    depth_mm: float = float("nan")  # deepest reconstructed point
    mask_iou: float = float("nan")  # intersection over union of the contact mask and the found circle

    def radius_error(self, true_radius_mm: float) -> float:
        return self.fitted_radius_mm / true_radius_mm - 1.0


@dataclass
class ValidationResult:
    presses: list[PressValidation]  # one per press, in input order
    ball_radius_mm: float
    folds: int
    calibrations: list[SensorCalibration] = field(default_factory=list)  # per fold, calibrated without it

    def fitted(self) -> np.ndarray:
        return np.array([p.fitted_radius_mm for p in self.presses if p.found and np.isfinite(p.fitted_radius_mm)])

    @property
    def median_radius_mm(self) -> float:
        return float(np.median(self.fitted())) if len(self.fitted()) else float("nan")

    @property
    def median_error(self) -> float:
        return self.median_radius_mm / self.ball_radius_mm - 1.0

    def fold_medians(self) -> list[tuple[int, int, float]]:
        """(fold, presses, median fitted radius in mm) per fold."""
        out = []
        for fold in range(self.folds):
            radii = [p.fitted_radius_mm for p in self.presses if p.fold == fold and p.found]
            out.append((fold, len(radii), float(np.median(radii)) if radii else float("nan")))
        return out

    def table(self) -> str:
        """Markdown table, one row per press, then the summary."""
        lines = [
            f"| press | fold | circle x, y, r (px) | fitted R (mm) | error vs {self.ball_radius_mm:.3f} | "
            "profile RMSE (mm) | offset (mm) | depth (mm) | mask IoU |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for p in self.presses:
            if not p.found:
                lines.append(f"| {p.name} | {p.fold} | not found: {p.reason} | | | | | | |")
                continue
            lines.append(
                f"| {p.name} | {p.fold} | {p.centre_x_px:.1f}, {p.centre_y_px:.1f}, {p.radius_px:.1f} | "
                f"{p.fitted_radius_mm:.3f} | {p.radius_error(self.ball_radius_mm):+.1%} | "
                f"{p.profile_rmse_mm:.3f} | "
                f"{p.offset_mm:+.3f} | {p.depth_mm:.3f} | {p.mask_iou:.2f} |"
            )
        return "\n".join(lines) + "\n\n" + self.summary()

    def summary(self) -> str:
        found = [p for p in self.presses if p.found]
        radii = self.fitted()
        errors = np.abs(radii / self.ball_radius_mm - 1.0)
        per_fold = ", ".join(f"fold {f}: {m:.3f} mm (n={n})" for f, n, m in self.fold_medians())
        return (
            f"held-out presses: {len(found)}/{len(self.presses)} circles found; fitted sphere radius median "
            f"{self.median_radius_mm:.3f} mm vs {self.ball_radius_mm:.3f} mm ({self.median_error:+.1%}), "
            f"IQR {np.percentile(radii, 25):.3f}-{np.percentile(radii, 75):.3f} mm, median |error| "
            f"{np.median(errors):.1%}; profile RMSE median "
            f"{np.median([p.profile_rmse_mm for p in found]):.3f} mm; "
            f"mask IoU median {np.median([p.mask_iou for p in found]):.2f}\nper fold: {per_fold}"
        )


def find_press_circle(
    image: np.ndarray,
    calibration: SensorCalibration,
    ball_radius_px: float,
    circle_config: CircleConfig | None = None,
    iterations: int = 2,
    fit_fraction: float = 0.9,
) -> tuple[float, float, float]:
    """Contact circle (x, y, radius in pixels) of a ball press, found with a calibration's gradient model.

    Colour disc first, then the centre refined on the predicted gradients and the edge re-found where the
    predicted slope peaks (as in calibration). Raises NoCircleError when there is no press.
    """
    circle_config = circle_config or CircleConfig()
    disc = find_contact_circle(image, calibration.background, circle_config)
    change = model_colour_change(image, calibration.background_i16, calibration.smooth)
    gx, gy = calibration.gradient_model.predict(change)
    cx, cy, a = disc.centre_x_px, disc.centre_y_px, disc.radius_px
    peak_config = replace(circle_config, mode="peak", min_radius_px=3.0)
    fraction = 0.7
    for _ in range(iterations):
        cx, cy = refine_centre(gx, gy, (cx, cy), fraction * a, ball_radius_px)
        try:
            ring = ring_circle(np.hypot(gx, gy), peak_config, initial=(cx, cy))
            if np.hypot(ring.centre_x_px - cx, ring.centre_y_px - cy) < 0.3 * a:
                a = min(ring.radius_px, 0.95 * ball_radius_px)
        except NoCircleError:
            pass
        fraction = fit_fraction
    return cx, cy, a


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (centre, radius) through (N, 3) points: algebraic fit, then geometric."""
    points = np.asarray(points, dtype=np.float64)
    origin = points.mean(axis=0)
    p = points - origin
    design = np.hstack([2 * p, np.ones((len(p), 1))])
    solution, *_ = np.linalg.lstsq(design, (p * p).sum(axis=1), rcond=None)
    centre = solution[:3]
    radius = float(np.sqrt(solution[3] + centre @ centre))
    for _ in range(20):  # Gauss-Newton on point-to-sphere distances
        diff = p - centre
        dist = np.linalg.norm(diff, axis=1)
        residual = dist - radius
        jacobian = np.hstack([-diff / dist[:, None], -np.ones((len(p), 1))])
        delta, *_ = np.linalg.lstsq(jacobian, -residual, rcond=None)
        centre = centre + delta[:3]
        radius += float(delta[3])
        if np.abs(delta).max() < 1e-12:
            break
    return centre + origin, radius


def evaluate_press(
    image: np.ndarray,
    calibration: SensorCalibration,
    ball_radius_m: float,
    name: str,
    fold: int,
    fit_fraction: float = 0.9,
) -> tuple[PressValidation, Reconstruction | None]:
    """Find the circle, reconstruct, fit a sphere inside the circle, compare with the Hertz press."""
    spec = calibration.spec
    ball_radius_px = ball_radius_m / spec.pixel_size_m
    try:
        cx, cy, a = find_press_circle(image, calibration, ball_radius_px)
    except NoCircleError as exc:
        return PressValidation(name, fold, False, str(exc)), None
    recon = reconstruct(image, calibration)
    rows, cols = recon.height_map_m.shape
    r = np.hypot(np.arange(cols)[None, :] - cx, np.arange(rows)[:, None] - cy)
    inside = r < fit_fraction * a
    x, y = spec.pixel_xy_sensor()
    points = np.stack([x[inside], y[inside], recon.height_map_m[inside].astype(np.float64)], axis=1)
    centre, radius = fit_sphere(points)
    ideal = press_height_map(cx, cy, a, ball_radius_m, spec)
    error = (recon.height_map_m - ideal)[inside]
    offset = float(error.mean())
    disc = r < a
    union = np.count_nonzero(disc | recon.core_mask)
    iou = np.count_nonzero(disc & recon.core_mask) / union if union else 0.0
    result = PressValidation(
        name,
        fold,
        True,
        "",
        cx,
        cy,
        a,
        radius * 1e3,
        (float(centre[0]) * 1e3, float(centre[1]) * 1e3, float(centre[2]) * 1e3),
        float(np.sqrt(np.mean((error - offset) ** 2))) * 1e3,
        offset * 1e3,
        recon.max_depth_m * 1e3,
        float(iou),
    )
    return result, recon


def validate(
    background: np.ndarray,
    presses: Sequence[np.ndarray],
    ball_diameter_m: float,
    folds: int = 4,
    config: CalibrationConfig | None = None,
    spec: GelSightSpec = GELSIGHT_MINI,
    names: Sequence[str] | None = None,
    figure: str | Path | None = None,
) -> ValidationResult:
    """k-fold validation on ball presses: calibrate on k-1 folds, reconstruct and measure the held-out fold.

    Press i is in fold i % folds. With `figure`, writes a PNG for the held-out press with the median error.
    """
    config = config or CalibrationConfig()
    names = [str(i) for i in range(len(presses))] if names is None else list(names)
    if not 2 <= folds <= len(presses):
        raise ValueError(f"folds must be in [2, {len(presses)}], got {folds}")
    fold_of = np.arange(len(presses)) % folds
    results: dict[int, PressValidation] = {}  # press index -> its validation
    kept: dict[int, tuple[np.ndarray, Reconstruction, SensorCalibration]] = {}
    calibrations = []
    for fold in range(folds):
        train = [i for i in range(len(presses)) if fold_of[i] != fold]
        calibration, report = calibrate(
            background, [presses[i] for i in train], ball_diameter_m, config, spec, [names[i] for i in train]
        )
        log.info("fold %d: calibrated on %s", fold, report.summary())
        calibrations.append(calibration)
        held_out = [i for i in range(len(presses)) if fold_of[i] == fold]
        for i in held_out:
            result, recon = evaluate_press(presses[i], calibration, ball_diameter_m / 2, names[i], fold)
            results[i] = result
            if recon is not None:
                kept[i] = (presses[i], recon, calibration)
    validation = ValidationResult([results[i] for i in sorted(results)], ball_diameter_m / 2 * 1e3, folds, calibrations)
    if figure is not None and kept:
        errors = {i: abs(results[i].radius_error(validation.ball_radius_mm)) for i in kept}
        median = float(np.median(list(errors.values())))
        chosen = min(errors, key=lambda i: abs(errors[i] - median))
        image, recon, calibration = kept[chosen]
        write_validation_figure(figure, image, recon, results[chosen], ball_diameter_m / 2, spec)
    return validation


def write_validation_figure(
    path: str | Path,
    image: np.ndarray,
    recon: Reconstruction,
    press: PressValidation,
    ball_radius_m: float,
    spec: GelSightSpec = GELSIGHT_MINI,
) -> Path:
    """Full frame, then (zoomed on the press) image with the found circle, contact mask, height map, and the
    height profile through the centre against the Hertz press and the fitted sphere."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from yoto.io import write_bytes_atomic

    fig = plt.figure(figsize=(11, 6.6))
    grid = fig.add_gridspec(2, 3, height_ratios=[1, 1.1])
    axes = [
        fig.add_subplot(grid[0, 0]),
        fig.add_subplot(grid[0, 1]),
        fig.add_subplot(grid[0, 2]),
        fig.add_subplot(grid[1, 0]),
        fig.add_subplot(grid[1, 1:]),
    ]
    theta = np.linspace(0, 2 * np.pi, 200)
    circle_x = press.centre_x_px + press.radius_px * np.cos(theta)
    circle_y = press.centre_y_px + press.radius_px * np.sin(theta)
    half = 2.2 * press.radius_px
    window = (
        press.centre_x_px - half,
        press.centre_x_px + half,
        press.centre_y_px + half,
        press.centre_y_px - half,
    )
    axes[0].imshow(image)
    axes[0].plot(circle_x, circle_y, "w--", lw=0.8)
    axes[0].set_title(f"held-out press {press.name}", fontsize=9)
    axes[1].imshow(image)
    axes[1].plot(circle_x, circle_y, "w--", lw=1)
    axes[1].set_title("found contact circle", fontsize=9)
    axes[2].imshow(recon.core_mask, cmap="gray")
    axes[2].plot(circle_x, circle_y, "r--", lw=1)
    axes[2].set_title("contact core vs circle", fontsize=9)
    shown = axes[3].imshow(recon.height_map_m * 1e3, cmap="viridis")
    fig.colorbar(shown, ax=axes[3], fraction=0.046, label="z (mm)")
    axes[3].set_title("height map", fontsize=9)
    for ax in axes[1:4]:
        ax.set_xlim(window[0], window[1])
        ax.set_ylim(window[2], window[3])
    for ax in axes[:4]:
        ax.set_xticks([])
        ax.set_yticks([])
    row = int(round(press.centre_y_px))
    x_sensor, y_sensor = spec.pixel_xy_sensor()
    x_mm = x_sensor[row] * 1e3
    centre_x_mm = x_sensor[0, 0] * 1e3 + press.centre_x_px * spec.mm_per_px
    near = np.abs(x_mm - centre_x_mm) < 2.5 * press.radius_px * spec.mm_per_px
    inside = np.abs(x_mm - centre_x_mm) < press.radius_px * spec.mm_per_px
    hertz = press_height_map(press.centre_x_px, press.centre_y_px, press.radius_px, ball_radius_m, spec)
    profile = axes[4]
    profile.plot(x_mm[near], recon.height_map_m[row, near] * 1e3, "C0", lw=2, label="reconstructed")
    profile.plot(
        x_mm[near],
        hertz[row, near] * 1e3,
        "k--",
        lw=1,
        label=f"Hertz press, ball R={ball_radius_m * 1e3:.3f} mm",
    )
    # The fitted sphere's lower half cut by the plane of this row, over the contact.
    sx, sy, sz = press.sphere_centre_mm
    fitted = press.fitted_radius_mm
    y_mm = y_sensor[row, 0] * 1e3
    section = sz - np.sqrt(np.maximum(fitted**2 - (x_mm[inside] - sx) ** 2 - (y_mm - sy) ** 2, 0.0))
    profile.plot(x_mm[inside], section, "C3:", lw=2.5, label=f"fitted sphere R={fitted:.3f} mm")
    profile.axvspan(
        centre_x_mm - press.radius_px * spec.mm_per_px,
        centre_x_mm + press.radius_px * spec.mm_per_px,
        color="0.9",
        zorder=0,
        label="found contact",
    )
    profile.set_xlabel("sensor x through the centre (mm)")
    profile.set_ylabel("z (mm)")
    profile.legend(fontsize=7, loc="lower right")
    profile.set_title("height profile", fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=80)
    plt.close(fig)
    return write_bytes_atomic(path, buffer.getvalue())
