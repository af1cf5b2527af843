"""The sensor calibration: what reconstruction and the optical simulator need, and its file.

A calibration is made from ball presses by `yoto.sensor.ball_calibration.calibrate`; this module holds the result
(`SensorCalibration`), its npz file (`save`, `load_calibration`; format in docs/formats.md) and the checks that
an image belongs to it (`with_background`, `background_change`).
"""

from __future__ import annotations

import hashlib
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
    load_gradient_model,
)
from yoto.sensor.presses import check_image
from yoto.sensor.spec import GelSightSpec

FORMAT_NAME = "yoto-sensor-calibration"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class MaskConfig:
    """Which pixels of a reconstruction belong to the contact."""

    colour_threshold: float = 15.0  # RGB distance (0-255) by which a contact's pixels change colour
    relative_depth: float = 0.5  # the contact's core (sphere fits): pixels this fraction of the deepest depth or deeper
    min_depth_m: float = 5e-5  # every contact pixel is at least this deep (metres); shallower frames have no contact
    felt_relative_depth: float = 0.05  # the contact (localization): pixels deeper than this fraction of the deepest
    # depth and min_depth_m, connected to the core: the whole region the gel felt, above the reconstruction's noise
    separate_floor_multiple: float = 3.0  # ... and every other region so felt that reaches this many times that
    # noise floor (a second feature of the object pressed apart from the first: a box's edge beside its face)
    min_area_px: int = 40  # fewer changed or contact pixels than this: no contact (explicit empty result)


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


def background_change(image: np.ndarray, background: np.ndarray) -> float:
    """Median over pixels of the largest per-channel colour change (levels).

    Most pixels of a press see no contact, so this is small for a background of the same sensor and
    lighting, and large for anything else.
    """
    change = np.abs(image.astype(np.int16) - background.astype(np.int16)).max(axis=2)
    return float(np.median(change))


def _check_known(settings: dict[str, Any], config_type: type, path: Path) -> None:
    """Refuse settings `config_type` does not have, naming them: a file written by a newer YOTO (or edited)."""
    unknown = sorted(set(settings) - {f.name for f in fields(config_type)})
    if unknown:
        raise InputError(
            f"sensor calibration file has {config_type.__name__} settings this yoto does not know "
            f"({', '.join(unknown)}): was it made by a newer version? Recalibrate with this one's `yoto sensor "
            "calibrate`, or update yoto",
            path,
        )


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
        for settings, config_type in ((model["gradient"], GradientModelConfig), (model["image"], ImageModelConfig)):
            _check_known(settings, config_type, path)
        _check_known(meta["mask"], MaskConfig, path)
        gradient_config = GradientModelConfig(**{"anchored": False, **model["gradient"]})  # older files: not anchored
        image_config = ImageModelConfig(**{"gain_degree": 1, **model["image"]})  # files before gain_degree: 1
        mask = MaskConfig(**meta["mask"])
        background = arrays["background"]
        gradient_model = load_gradient_model(
            arrays, "gradient_", gradient_config, (file_spec.height_px, file_spec.width_px)
        )
        image_gain = arrays["image_gain"] if "image_gain" in arrays else None  # files before the round-trip gain
        image_model = ImageModel(
            arrays["image_coefficients"], float(model["image_max_gradient"]), image_config, image_gain
        )
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
