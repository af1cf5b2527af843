"""GelSight images as tactile inputs: the image sides of contact-pair files, and single frames to localize.

`ImageSides(calibration)` is what `read_contact_pair(path, images=...)` calls for a side that gives an `image`
(SPEC "Dual contact"): it loads the side's own `calibration` (or the default one) once, swaps in the side's
`background` when it has one, reconstructs the frame and returns the cloud the localizer uses (the whole
contact the gel felt, `Reconstruction.mask`). A frame in which nothing touches the gel raises NoContactError.

`in_rgb_order` is what every reader of GelSight frames (these sides, `yoto localize`, `yoto sensor reconstruct`,
`yoto track`'s frames) passes a frame through before reconstructing it: SPEC's frames are RGB, and a frame written
in BGR order (OpenCV's `imwrite` given an RGB array, a bag's `rgb8` tag on BGR data) is told from the calibration's
background and read in RGB order, with a warning naming the file.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from yoto.contacts import TactileImage
from yoto.errors import InputError, NoContactError
from yoto.sensor.calibration import SensorCalibration, load_calibration, with_background
from yoto.sensor.presses import load_image
from yoto.sensor.reconstruction import (
    MAX_BACKGROUND_CHANGE,
    MAX_UNTOUCHED_CHANGE,
    Reconstruction,
    block_change,
    reconstruct,
)

log = logging.getLogger("yoto")


def shows_background(frame: np.ndarray, background: np.ndarray) -> tuple[bool, float]:
    """Whether a frame shows `background` where it is untouched (reconstruction's test: the median 8x8 block changed
    by at most MAX_BACKGROUND_CHANGE levels, or the least-changed tenth by at most MAX_UNTOUCHED_CHANGE), and that
    median change."""
    blocks = block_change(frame, background.astype(np.int16))
    least, median = (float(v) for v in np.percentile(blocks, [10.0, 50.0]))
    return median <= MAX_BACKGROUND_CHANGE or least <= MAX_UNTOUCHED_CHANGE, median


def in_rgb_order(
    frame: np.ndarray, background: np.ndarray, source: str | Path | None = None, warn: bool = True
) -> np.ndarray:
    """The (rows, cols, 3) frame in RGB order, told by the sensor's background (`background`, RGB).

    A GelSight's LEDs light its gel in distinct colours, so a frame whose red and blue are swapped differs from its
    background almost everywhere (the 44 real GelSight Mini presses of the shared data: median 8x8 block change
    24-29 levels swapped, 0.8-1.3 as written). A frame that does not show the background in its own order but does
    with red and blue swapped was written in BGR order: it is returned swapped back, with a warning naming `source`
    (when `warn`). Anything else is returned as it is (reconstruction refuses a frame of another sensor or lighting).
    """
    if frame.shape != background.shape or frame.shape[-1] != 3:
        return frame  # the size check that follows names the problem
    shows, median = shows_background(frame, background)
    if shows:
        return frame
    swapped = np.ascontiguousarray(frame[:, :, ::-1])
    shows_swapped, median_swapped = shows_background(swapped, background)
    if not shows_swapped:
        return frame
    if not warn:
        return swapped
    log.warning(
        "%s: the frame's colour channels are in BGR order (it matches the calibration's background with red and blue "
        "swapped: median change %.0f levels, against %.0f as written; written by OpenCV from an RGB array?): read "
        "as RGB",
        source if source is not None else "GelSight frame",
        median_swapped,
        median,
    )
    return swapped


def read_frame(path: str | Path, calibration: SensorCalibration) -> np.ndarray:
    """A GelSight image file as (rows, cols, 3) uint8 RGB for `calibration`: colour, the calibration's size, red and
    blue swapped back when it was written in BGR order (`in_rgb_order`)."""
    return in_rgb_order(load_image(path, calibration.spec), calibration.background, path)


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
                calibration = with_background(base, read_frame(background_path, base), background_path)
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
        return reconstruct(read_frame(side.image, calibration), calibration, source=side.image)

    def __call__(self, side: TactileImage) -> tuple[np.ndarray, float]:
        """The side's tactile cloud (N, 3), sensor frame, metres, and the 1-sigma of the log of its depth scale
        (`Reconstruction.depth_scale_sigma`); NoContactError when the frame shows none."""
        result = self.reconstruct(side)
        if not result.contact:
            raise NoContactError(result.reason, side.image)
        return result.points_sensor, result.depth_scale_sigma
