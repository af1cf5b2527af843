"""GelSight images as tactile inputs: the image sides of contact-pair files, and single frames to localize.

`ImageSides(calibration)` is what `read_contact_pair(path, images=...)` calls for a side that gives an `image`
(SPEC "Dual contact"): it loads the side's own `calibration` (or the default one) once, swaps in the side's
`background` when it has one, reconstructs the frame and returns the cloud the localizer uses (the whole
contact the gel felt, `Reconstruction.mask`). A frame in which nothing touches the gel raises NoContactError.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import ContactPair, TactileImage
from yoto.errors import InputError, NoContactError
from yoto.sensor.calibration import SensorCalibration, load_calibration, with_background
from yoto.sensor.presses import load_image
from yoto.sensor.reconstruction import Reconstruction, reconstruct

# The pose stage's settings for a pair whose contacts come from images (docs/sensor.md "The pose stage's budget
# for image contacts"). A reconstructed contact's shape is off where a clean cloud's is not (box edges and rims:
# 46-110 um after a plane and a depth scale, against 23 um typical), so the truth's location pairs often lie in the
# sets the clean budget thins, and its seeds rank low by the cheap score (858th-6,646th on the cracker box): the
# joint search keeps more location pairs (clean: SearchConfig.pair_budget, 4 M), more seeds get the short
# refinement (PoseConfig.screened, 400), on more points with more iterations (RefineConfig.screen_points 24,
# screen_iterations 3). Clean clouds keep the defaults and their speed.
IMAGE_PAIR_BUDGET = 10_000_000
IMAGE_SCREENED = 2000
IMAGE_SCREEN_POINTS = 48
IMAGE_SCREEN_ITERATIONS = 5


def image_pose_config(config: Any) -> Any:
    """`config` (the pose stage's `PoseConfig`, typed loosely: the sensor stage sits below the pose stage and does
    not import it) for a pair whose contacts were reconstructed from GelSight images: the search's pair budget and
    the screening raised to the image settings above (a setting already larger is kept)."""
    search, refine = config.search_config, config.refine_config
    return replace(
        config,
        search_config=replace(search, pair_budget=max(search.pair_budget, IMAGE_PAIR_BUDGET)),
        screened=max(config.screened, IMAGE_SCREENED),
        refine_config=replace(
            refine,
            screen_points=max(refine.screen_points, IMAGE_SCREEN_POINTS),
            screen_iterations=max(refine.screen_iterations, IMAGE_SCREEN_ITERATIONS),
        ),
    )


def pose_config_for(pair: ContactPair, config: Any) -> Any:
    """`image_pose_config(config)` when a side of `pair` was reconstructed from an image (its depth scale is
    uncertain: `TactileContact.depth_scale_sigma` > 0), else `config` unchanged."""
    reconstructed = any(pair.contact(side).depth_scale_sigma > 0.0 for side in ("left", "right"))
    return image_pose_config(config) if reconstructed else config


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
