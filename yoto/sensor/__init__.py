"""GelSight sensor: image geometry, calibration from ball presses, image <-> height map <-> point cloud.

Public API (imported lazily, so `from yoto.sensor.spec import GELSIGHT_MINI` stays light):
    calibrate(background, presses, ball_diameter_m) -> (SensorCalibration, CalibrationReport)
    load_calibration(path) -> SensorCalibration
    reconstruct(image_rgb_uint8, calibration) -> Reconstruction (height_map_m, mask, points_sensor, contact)
    render_image(height_map_m, calibration, rng=None) -> (rows, cols, 3) uint8
    press_height_map(centre_x_px, centre_y_px, contact_radius_px, ball_radius_m) -> height map (metres)
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "GELSIGHT_MINI": "yoto.sensor.spec",
    "GelSightSpec": "yoto.sensor.spec",
    "CalibrationConfig": "yoto.sensor.ball_calibration",
    "calibrate": "yoto.sensor.ball_calibration",
    "SensorCalibration": "yoto.sensor.calibration",
    "load_calibration": "yoto.sensor.calibration",
    "with_background": "yoto.sensor.calibration",
    "press_height_map": "yoto.sensor.sphere",
    "Reconstruction": "yoto.sensor.reconstruction",
    "reconstruct": "yoto.sensor.reconstruction",
    "render_image": "yoto.sensor.optical",
    "image_path_reconstructor": "yoto.sensor.optical",
    "ImageSides": "yoto.sensor.pair_images",
    "ShadingSensor": "yoto.sensor.shading",
    "find_contact_circle": "yoto.sensor.presses",
    "load_image": "yoto.sensor.presses",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'yoto.sensor' has no attribute '{name}'")
