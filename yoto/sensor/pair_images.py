"""GelSight images as tactile inputs: the image sides of contact-pair files, and single frames to localize.

`ImageSides(calibration)` is what `read_contact_pair(path, images=...)` calls for a side that gives an `image`
(SPEC "Dual contact"): it loads the side's own `calibration` (or the default one) once, swaps in the side's
`background` when it has one, reconstructs the frame and returns the cloud the localizer uses (the whole
contact the gel felt, `Reconstruction.mask`). A frame in which nothing touches the gel raises NoContactError.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from yoto.contacts import TactileImage
from yoto.errors import InputError, NoContactError
from yoto.sensor.calibration import SensorCalibration, load_calibration, with_background
from yoto.sensor.presses import load_image
from yoto.sensor.reconstruction import Reconstruction, reconstruct


class ImageSides:
    """Reconstructs GelSight image sides into tactile clouds, with calibrations and backgrounds loaded once."""

    def __init__(self, calibration: str | Path | SensorCalibration | None = None, background: Path | None = None):
        """`calibration`: the default for sides that name none (a file or a loaded calibration); `background`: the
        default fresh no-contact frame for sides that give none (None: the calibration's)."""
        self.default = calibration
        self.background = background
        self._calibrations: dict[tuple[Path | None, Path | None], SensorCalibration] = {}

    def calibration(self, calibration_path: Path | None, background_path: Path | None) -> SensorCalibration:
        """The calibration for a side: its own file or the default, with its background when it gives one."""
        key = (calibration_path, background_path)
        if key not in self._calibrations:
            if background_path is not None:
                base = self.calibration(calibration_path, None)
                calibration = with_background(base, load_image(background_path, base.spec), background_path)
            elif calibration_path is not None:
                calibration = load_calibration(calibration_path)
            elif self.default is None:
                raise InputError(
                    "a GelSight image needs the sensor's calibration: give one (`--calibration CAL`, from "
                    '`yoto sensor calibrate`) or a "calibration" entry in the pair file\'s side'
                )
            elif isinstance(self.default, SensorCalibration):
                calibration = self.default
            else:
                calibration = load_calibration(self.default)
            self._calibrations[key] = calibration
        return self._calibrations[key]

    def reconstruct(self, side: TactileImage) -> Reconstruction:
        """The side's frame reconstructed with its calibration and background."""
        calibration = self.calibration(side.calibration, side.background or self.background)
        return reconstruct(load_image(side.image, calibration.spec), calibration, source=side.image)

    def __call__(self, side: TactileImage) -> tuple[np.ndarray, float]:
        """The side's tactile cloud (N, 3), sensor frame, metres, and the 1-sigma of the log of its depth scale
        (`Reconstruction.depth_scale_sigma`); NoContactError when the frame shows none."""
        result = self.reconstruct(side)
        if not result.contact:
            raise NoContactError(result.reason, side.image)
        return result.points_sensor, result.depth_scale_sigma
