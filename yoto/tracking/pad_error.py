"""The reconstruction error fixed to a sensor's pad, learnt while the object rests in the gel, removed from the frames
taken while it slides.

A GelSight reconstruction's smooth depth errors (calibration, lighting, integration) belong to the pad: they stay
where they are on the image while the object slides over it. A frame registered on the object is off by them, and
that offset changes as the contact slides (docs/tracking.md, "Why the closed loop still drifts"). While the object
rests after the touch, every frame sees the same patch of the object at the same place on the pad. Those frames,
this sensor's alone, are registered on the model from the pose the tracker holds, one by one as they arrive (a
live loop cannot stop for all of them when the motion starts); the depth difference left between them and the
model's surface, cell by cell over the pad (sensor x, y), is the pad's error there. Frames
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

from yoto.geometry import invert_transform, pose_from_twist, transform_points, twist_of_pose
from yoto.objects.model import ObjectModel
from yoto.registration import (
    GaussNewtonConfig,
    plane_distances,
    point_to_plane_gauss_newton,
    point_to_plane_jacobian,
)

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
        size = self.cells * self.cells
        self.counts = np.zeros(size, dtype=np.int64)
        self.residual_sums = np.zeros(size)  # each rest point's depth residual, taken back to the reference pose
        self.residual_slopes = np.zeros((size, 6))  # how those residuals change with the fit's twist
        self.rest_frames = 0
        self.T_reference: np.ndarray | None = None  # T_object_sensor of the first rest frame: the fit's origin
        self.fit_information = np.zeros((6, 6))  # the rest frames' Gauss-Newton information about the fit ...
        self.fit_evidence = np.zeros(6)  # ... and the information-weighted twists each frame fitted
        self.error_m = np.zeros(size)  # the error removed in each cell (0: unknown, far away)

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

    def _continued(self, known: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Per cell: `values` where known; beyond, continued from the known cells nearby (normalized Gaussian
        smoothing) and faded out where they are far: no step in the corrected surface where the known cells end."""
        c = self.config
        shape = (self.cells, self.cells)
        sigma = c.continuation_m / c.cell_m
        weight = ndimage.gaussian_filter(known.astype(np.float64).reshape(shape), sigma, mode="constant").ravel()
        spread = ndimage.gaussian_filter(np.where(known, values, 0.0).reshape(shape), sigma, mode="constant").ravel()
        faded = spread / np.maximum(weight, 1e-12) * np.minimum(weight / CONTINUATION_FADE, 1.0)
        return np.where(known, values, np.where(weight > 1e-6, faded, 0.0))

    def add_rest_frame(
        self, model: ObjectModel, points_sensor: np.ndarray, T_object_sensor: np.ndarray, solver: GaussNewtonConfig
    ) -> None:
        """Register one frame taken at rest on the model (this contact alone, from the fit of the frames so far)
        and add its depth residuals to the cells: the rest's registration is spread over the rest frames as they
        arrive, so the first frame in motion waits for nothing (`settle` only combines). The frames' fits are
        combined in information form about the first frame's pose; each residual keeps its slope with respect to
        that fit, so the map is read at the combined fit in the end (first order)."""
        c = self.config
        if self.T_reference is None:
            self.T_reference = np.asarray(T_object_sensor, dtype=np.float64)
        start = self.rest_fit(solver)
        points_start = transform_points(start, points_sensor)
        fit = point_to_plane_gauss_newton(model, points_start, np.eye(4)[None], solver)[0] @ start
        points_object = transform_points(fit, points_sensor)
        distance, matched, _, normals = plane_distances(model, points_object, solver.max_distance_m)
        jacobian = point_to_plane_jacobian(points_object, normals)
        twist = twist_of_pose(fit @ invert_transform(self.T_reference))
        information = jacobian[matched].T @ jacobian[matched] / solver.surface_noise_m**2
        self.fit_information += information
        self.fit_evidence += information @ twist
        self.rest_frames += 1
        facing = normals @ fit[:3, 2]
        use = matched & (np.abs(facing) >= c.min_facing)
        safe = np.where(use, facing, 1.0)
        residual, slope = distance / safe, jacobian / safe[:, None]
        index = self._cell_index(points_sensor)
        use &= (index >= 0) & (np.abs(residual) <= c.max_residual_m)
        np.add.at(self.counts, index[use], 1)
        np.add.at(self.residual_sums, index[use], residual[use] - slope[use] @ twist)
        np.add.at(self.residual_slopes, index[use], slope[use])

    def _fit_twist(self, solver: GaussNewtonConfig) -> np.ndarray:
        prior = np.diag([solver.prior_rotation_rad**-2] * 3 + [solver.prior_translation_m**-2] * 3)
        return np.linalg.solve(prior + self.fit_information, self.fit_evidence)

    def rest_fit(self, solver: GaussNewtonConfig) -> np.ndarray:
        """The rest frames' combined fit so far, T_object_sensor."""
        assert self.T_reference is not None
        return pose_from_twist(self._fit_twist(solver)) @ self.T_reference

    def settle(self, solver: GaussNewtonConfig) -> bool:
        """Set the map from the rest frames added: each cell's mean residual at the combined fit, continued beyond.
        Returns whether a map was set (enough frames at rest)."""
        if self.rest_frames < self.config.min_rest_frames:
            return False
        twist = self._fit_twist(solver)
        known = self.counts >= self.config.min_cell_samples
        mean = (self.residual_sums + self.residual_slopes @ twist) / np.maximum(self.counts, 1)
        self.error_m = self._continued(known, mean)
        return True
