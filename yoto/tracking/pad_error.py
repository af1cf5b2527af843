"""The reconstruction error fixed to a sensor's pad, learnt while the object rests in the gel, removed from the frames
taken while it slides.

A GelSight reconstruction's smooth depth errors (calibration, lighting, integration) belong to the pad: they stay
where they are on the image while the object slides over it. A frame registered on the object is off by them, and
that offset changes as the contact slides (docs/tracking.md, "Why the closed loop still drifts"). While the object
rests after the touch, every frame sees the same patch of the object at the same place on the pad. Those frames,
this sensor's alone, are registered on the model from the pose the tracker holds; the depth difference left
between them and the model's surface, cell by cell over the pad (sensor x, y), is the pad's error there. Frames
taken later have it subtracted, cell by cell, before the closed loop registers them; beyond the cells the rest saw
it is continued from them for about a millimetre and faded out.

Why the rest frames are registered first: the rigid part of what they disagree with the model by (the touch's
pose error, a tilt of the error field) is not an error of the pad. Kept in the depth map, it would be right only
where the contact was: a pose error of a few tenths of a millimetre along a curved surface turns, once the contact
has slid by millimetres, into depth errors several times the pad's own (measured: the map taken at the tracker's
pose without that registration drifts more than no map at all).

It cannot absorb slip: the map is set at rest and never changed once the sensors move. Slip moves the contact
over the pad; the map stays where the error is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from yoto.geometry import transform_points
from yoto.objects.model import ObjectModel
from yoto.registration import GaussNewtonConfig, plane_distances, point_to_plane_gauss_newton

CONTINUATION_FADE = 0.1  # beyond the known cells, the continued error fades where their smoothed weight is below this


@dataclass(frozen=True)
class PadErrorConfig:
    """How each sensor's pad-fixed reconstruction error is learnt and removed (closed loop)."""

    enabled: bool = True  # subtract each pad's learnt error from its frames before registering them
    cell_m: float = 0.0005  # the map's cells on the pad (sensor x and y), finer than the error's smoothness
    extent_m: float = 0.02  # the map covers |x|, |y| up to this (a GelSight Mini pad is about 18 x 14 mm)
    rest_m: float = 0.001  # the object counts as at rest until a sensor has moved this far from its pose at the
    # touch (rotation at the closed loop's turn radius); then the map is set
    rest_fit_rotation_rad: float = float(np.radians(1.0))  # the rest frames' registration may turn the contact by
    rest_fit_translation_m: float = 0.001  # about this and move it by this (its priors)
    min_rest_frames: int = 3  # fewer frames at rest than this: no map for that sensor
    min_cell_samples: int = 2  # a cell is known once this many residuals fell in it
    min_facing: float = 0.5  # residuals only where the surface faces the sensor (|normal . sensor z| at least
    # this): a depth error on a steep flank moves the point mostly along the surface, which says little about it
    max_residual_m: float = 0.0003  # a larger residual is a bad correspondence, not a reconstruction error
    continuation_m: float = 0.001  # beyond the cells the rest saw, the error is continued from them (a Gaussian of
    # this width) and fades out about twice as far: no step in the corrected surface where the known cells end


class PadError:
    """One sensor's learnt depth error (metres along the sensor's z) per cell of its pad."""

    def __init__(self, config: PadErrorConfig):
        self.config = config
        self.cells = int(np.ceil(2 * config.extent_m / config.cell_m))
        self.sums = np.zeros(self.cells * self.cells)
        self.counts = np.zeros(self.cells * self.cells, dtype=np.int64)
        self.rest_samples: list[np.ndarray] = []  # the frames at rest (sensor frame), until the map is set
        self.error_m = np.zeros(self.cells * self.cells)  # the error removed in each cell (0: unknown, far away)

    def _cell_index(self, points_sensor: np.ndarray) -> np.ndarray:
        """Flat cell index of each point, -1 off the map."""
        c = self.config
        ij = np.floor((points_sensor[:, :2] + c.extent_m) / c.cell_m).astype(np.int64)
        inside = ((ij >= 0) & (ij < self.cells)).all(axis=1)
        return np.where(inside, ij[:, 1] * self.cells + ij[:, 0], -1)

    def correct(self, points_sensor: np.ndarray) -> np.ndarray:
        """The points with the learnt error of their cells removed."""
        index = self._cell_index(points_sensor)
        corrected = points_sensor.copy()
        corrected[:, 2] -= np.where(index >= 0, self.error_m[np.maximum(index, 0)], 0.0)
        return corrected

    def _set_error(self) -> None:
        """The error per cell: the mean residual where known; beyond, continued from the known cells nearby
        (normalized Gaussian smoothing) and faded out where they are far."""
        c = self.config
        known = self.counts >= c.min_cell_samples
        mean = np.where(known, self.sums / np.maximum(self.counts, 1), 0.0)
        shape = (self.cells, self.cells)
        sigma = c.continuation_m / c.cell_m
        weight = ndimage.gaussian_filter(known.astype(np.float64).reshape(shape), sigma, mode="constant").ravel()
        spread = ndimage.gaussian_filter(mean.reshape(shape), sigma, mode="constant").ravel()
        faded = spread / np.maximum(weight, 1e-12) * np.minimum(weight / CONTINUATION_FADE, 1.0)
        self.error_m = np.where(known, mean, np.where(weight > 1e-6, faded, 0.0))

    def settle(self, model: ObjectModel, T_object_sensor: np.ndarray, solver: GaussNewtonConfig) -> bool:
        """Set the map from the frames at rest, the sensor at `T_object_sensor` on the object (the pose the tracker
        holds): register them on the model (this contact alone), and keep the depth residuals left as the pad's
        error. Returns whether a map was set (enough frames at rest)."""
        rest, self.rest_samples = self.rest_samples, []
        if len(rest) < self.config.min_rest_frames:
            return False
        stacked = np.vstack(rest)
        fix = point_to_plane_gauss_newton(model, transform_points(T_object_sensor, stacked), np.eye(4)[None], solver)
        self._add(model, stacked, fix[0] @ T_object_sensor)
        self._set_error()
        return True

    def _add(self, model: ObjectModel, points_sensor: np.ndarray, T_object_sensor: np.ndarray) -> None:
        """Add each point's depth residual against the model's surface to its cell."""
        c = self.config
        distance, matched, _, normals = plane_distances(
            model, transform_points(T_object_sensor, points_sensor), 2 * c.max_residual_m
        )
        facing = normals @ T_object_sensor[:3, 2]
        use = matched & (np.abs(facing) >= c.min_facing)
        residual = np.where(use, distance / np.where(use, facing, 1.0), 0.0)
        index = self._cell_index(points_sensor)
        use &= (index >= 0) & (np.abs(residual) <= c.max_residual_m)
        np.add.at(self.sums, index[use], residual[use])
        np.add.at(self.counts, index[use], 1)
