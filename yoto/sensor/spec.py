"""The GelSight Mini's image grid and its mapping to the sensor frame (SPEC: "Sensor frame").

Sensor frame: origin at the centre of the undeformed gel surface, x along image columns, y along image
rows, z out of the gel toward the object. The undeformed gel is the plane z = 0; a pressed gel has
z < 0. A height map is a (rows, cols) array of the gel surface's z in metres, row r and column c
sampling the sensor-frame point ((c - (cols-1)/2) * pixel, (r - (rows-1)/2) * pixel).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GelSightSpec:
    """Image geometry of one GelSight model."""

    name: str = "gelsight_mini"
    width_px: int = 320  # image columns (sensor x)
    height_px: int = 240  # image rows (sensor y)
    mm_per_px: float = 0.0634  # gel-surface size of one pixel

    @property
    def pixel_size_m(self) -> float:
        return self.mm_per_px * 1e-3

    @property
    def pad_size_m(self) -> tuple[float, float]:
        """Sensed area (x extent, y extent) in metres: about 20.3 x 15.2 mm for the Mini."""
        return self.width_px * self.pixel_size_m, self.height_px * self.pixel_size_m

    def pixel_xy_sensor(self) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame x and y (metres) of every pixel centre, each of shape (height_px, width_px). Read-only."""
        return _pixel_grid(self.width_px, self.height_px, self.pixel_size_m)

    def height_map_to_points(self, height_map_m: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Sensor-frame (N, 3) points of the masked pixels of a height map, row-major order."""
        if height_map_m.shape != (self.height_px, self.width_px) or mask.shape != height_map_m.shape:
            raise ValueError(
                f"height map {height_map_m.shape} and mask {mask.shape} must be ({self.height_px}, {self.width_px})"
            )
        x, y = self.pixel_xy_sensor()
        return np.stack([x[mask], y[mask], height_map_m[mask]], axis=1)


GELSIGHT_MINI = GelSightSpec()


@functools.lru_cache(maxsize=8)
def _pixel_grid(width_px: int, height_px: int, pixel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    cols = (np.arange(width_px) - (width_px - 1) / 2.0) * pixel_size_m
    rows = (np.arange(height_px) - (height_px - 1) / 2.0) * pixel_size_m
    x, y = np.meshgrid(cols, rows)
    x.flags.writeable = False
    y.flags.writeable = False
    return x, y
