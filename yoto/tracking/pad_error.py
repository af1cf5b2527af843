"""The reconstruction error fixed to a sensor's pad, learnt from its own frames and removed from them before the
closed loop registers them.

A GelSight reconstruction's smooth depth errors (calibration, lighting, integration) belong to the pad: they stay
where they are on the image while the object slides over it. A frame registered on the object is off by them, and
that offset changes as the contact slides onto other parts of the pad (docs/journal/tracking.md, "Why the closed loop
still drifts"): the drift then grows with the path.

**The sliding map** (`_SlidingMap`, default). Each frame the closed loop uses, at rest and while moving, adds the
part of its depth residuals (at its registered pose) that no rigid motion of the contact and no depth scale error
can produce: that part is the pad's error whatever the pose, so neither slip nor the tracker's own error enters the
map (first order; `tests/test_tracking_closed_loop.py` gives frames 0.3 mm off and gets the map learnt at the
truth). A frame tells the error's shape under it, not its offset and tilts there; the frames at other pad
positions and a smooth prior tie them together, so that the map holds how the offset and tilts change across the
pad, which is what would move the registrations. Cells no frame reached stay at 0 (their prior) a few nodes out.

**The rest map** (`rest_map`, off by default; measured worse, docs/journal/tracking.md). While the object rests after
the touch, every frame sees the same patch of the object at the same place on the pad; those frames are registered on
the model one by one as they arrive and the depth difference left between them and the surface, cell by cell, is
the pad's error there, set when the motion starts and continued about a millimetre beyond the cells it saw. The
rest registration comes first because the rigid part of the misfit (the touch's pose error) is no error of the pad.
It holds a depth scale error as scale x the rest's profile, wrong once the contact slides.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import linalg, ndimage, sparse

from yoto.geometry import invert_transform, pose_from_twist, transform_points, twist_of_pose
from yoto.objects.model import ObjectModel
from yoto.registration import (
    GaussNewtonConfig,
    plane_distances,
    point_to_plane_gauss_newton,
    point_to_plane_jacobian,
)

CONTINUATION_FADE = 0.1  # beyond the known cells, the continued error fades where their smoothed weight is below this
MIN_SLIDING_POINTS = 12  # a frame with fewer usable points teaches the sliding map nothing (7 shapes are projected out)


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
    rest_map: bool = False  # a map of the rest's cells learnt from the frames at rest, set when the motion starts,
    # under the sliding map (which then learns from the moving frames only); without it (measured better) the
    # sliding map learns from every frame, at rest too
    online: bool = True  # the sliding map (`_SlidingMap`): the error learnt from every frame, wherever the contact is
    node_m: float = 0.001  # that map's nodes on the pad (bilinear between them)
    magnitude_m: float = 3e-5  # 1-sigma prior of the error at a node (a gel's smooth error, 0.02-0.03 mm)
    correlation_m: float = 0.002  # its smoothness: second differences over a node spacing of about
    # magnitude x (node / correlation)^2
    rest_node_m: float = 3e-5  # with the rest map: 1-sigma prior at nodes on its known cells (removed there)
    reach_nodes: int = 3  # the map extends this many nodes beyond those the frames reached, fading to 0
    frame_points: float = 100.0  # each frame's residuals count as this many independent points of ...
    frame_noise_m: float = 3e-5  # ... this error
    explain_scale: bool = True  # project a depth scale error's shape out of the frames as well


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
        self.sliding = _SlidingMap(config) if config.online else None  # the error learnt from every frame used

    def _cell_index(self, points_sensor: np.ndarray) -> np.ndarray:
        """Flat cell index of each point, -1 off the map."""
        c = self.config
        ij = np.floor((points_sensor[:, :2] + c.extent_m) / c.cell_m).astype(np.int64)
        inside = ((ij >= 0) & (ij < self.cells)).all(axis=1)
        return np.where(inside, ij[:, 1] * self.cells + ij[:, 0], -1)

    def correct(self, points_sensor: np.ndarray) -> np.ndarray:
        """The points with the learnt error of their cells removed (the rest's map, and the sliding one on top)."""
        index = self._cell_index(points_sensor)
        corrected = points_sensor.copy()
        corrected[:, 2] -= np.where(index >= 0, self.error_m[np.maximum(index, 0)], 0.0)
        if self.sliding is not None:
            corrected[:, 2] -= self.sliding.value(points_sensor)
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
        if self.sliding is not None:
            self.sliding.set_rest(known, self.cells, self.config.cell_m)
        return True

    def learn_frame(
        self, model: ObjectModel, points_sensor: np.ndarray, T_object_sensor: np.ndarray, reach_m: float
    ) -> None:
        """Teach the sliding map one frame the closed loop used: `points_sensor` as registered (`correct` applied),
        `T_object_sensor` the registration's pose of the sensor (any pose near the truth: rigid offsets are
        projected out)."""
        if self.sliding is None:
            return
        c = self.config
        points_object = transform_points(T_object_sensor, points_sensor)
        distance, matched, _, normals = plane_distances(model, points_object, reach_m)
        facing = normals @ T_object_sensor[:3, 2]
        use = matched & (np.abs(facing) >= c.min_facing)
        safe = np.where(use, facing, 1.0)
        residual = distance / safe + self.sliding.value(points_sensor)
        use &= np.abs(residual) <= c.max_residual_m
        if use.sum() < MIN_SLIDING_POINTS:
            return
        slope = point_to_plane_jacobian(points_object[use], normals[use]) / safe[use, None]
        if c.explain_scale:  # a depth scale error follows the contact, not the pad: its shape (the depth) goes too
            slope = np.hstack([slope, points_sensor[use, 2:3]])
        self.sliding.add_frame(residual[use], slope, points_sensor[use])


class _SlidingMap:
    """The pad's error wherever the contact goes, learnt from every frame from what the pose cannot explain.

    A frame's depth residuals at its registered pose are the pad's error there plus whatever the pose is off
    by. A rigid motion of the contact (slip, the tracker's own error) moves them by the point-to-plane Jacobian
    times a twist, six shapes over the patch (an offset and two tilts on a flat contact, and what the surface's
    curvature adds), and a depth scale error (it follows the contact, not the pad) by the depth itself; the part of
    the residuals that none of those explains, their projection orthogonal to them, is the pad's error alone,
    whatever the pose. Each frame adds that projection's normal equations for the map's nodes (`node_m` apart,
    bilinear between them); the nodes have a smooth prior (a magnitude and second differences) and, on the cells
    the rest map knows, a tighter one at 0. What one frame cannot see (the error's offset and tilts under it) the
    frames at other pad positions and the smoothness tie to their neighbours: as the contact slides, the error's
    curvature under it tells how its offset and tilts change, which is what moves the registrations. Slip cannot
    enter: it is rigid, and projected out of every frame.
    """

    def __init__(self, config: PadErrorConfig):
        self.config = config
        self.per_axis = int(round(2 * config.extent_m / config.node_m)) + 1
        size = self.per_axis * self.per_axis
        self.information = np.zeros((size, size))  # the frames' normal equations over the nodes ...
        self.evidence = np.zeros(size)
        self.touched = np.zeros(size, dtype=bool)  # ... and which nodes the frames reached
        self.values = np.zeros(size)  # the map's current estimate (0 off the active nodes)
        self.prior = _smooth_prior(self.per_axis, config)
        self.rest_nodes = np.zeros(size, dtype=bool)
        self._active: tuple[int, np.ndarray, np.ndarray] | None = None  # (nodes reached, active nodes, their prior)

    def set_rest(self, rest_known: np.ndarray, rest_cells: int, rest_cell_m: float) -> None:
        """Mark the nodes lying on the rest map's known cells: the error there is already removed."""
        c = self.config
        coordinates = -c.extent_m + c.node_m * np.arange(self.per_axis)
        cell = np.clip(np.floor((coordinates + c.extent_m) / rest_cell_m).astype(np.int64), 0, rest_cells - 1)
        self.rest_nodes = rest_known.reshape(rest_cells, rest_cells)[np.ix_(cell, cell)].ravel()
        self._active = None

    def _bilinear(self, points_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's four nodes (n, 4) and weights (n, 4); points off the map get weight 0."""
        c = self.config
        u = (points_sensor[:, :2] + c.extent_m) / c.node_m
        base = np.clip(np.floor(u).astype(np.int64), 0, self.per_axis - 2)
        i, j = base[:, 0], base[:, 1]
        row = j * self.per_axis + i
        nodes = np.stack([row, row + 1, row + self.per_axis, row + self.per_axis + 1], axis=1)
        fx, fy = (u - base).T
        inside = np.all((u >= 0) & (u <= self.per_axis - 1), axis=1)
        weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1) * inside[:, None]
        return nodes, weights

    def value(self, points_sensor: np.ndarray) -> np.ndarray:
        nodes, weights = self._bilinear(points_sensor)
        return (self.values[nodes] * weights).sum(axis=1)

    def add_frame(self, residual_m: np.ndarray, slope: np.ndarray, points_sensor: np.ndarray) -> None:
        """Add one frame: its points' depth residuals (with this map's values added back: the residuals of
        the frame as the rest map alone corrected it) and the shapes a rigid motion (and a depth scale) give them."""
        c = self.config
        nodes, weights = self._bilinear(points_sensor)
        local, inverse = np.unique(nodes, return_inverse=True)
        design = np.zeros((len(points_sensor), len(local)))
        np.add.at(design, (np.repeat(np.arange(len(points_sensor)), 4), inverse.reshape(-1)), weights.reshape(-1))
        basis, singular, _ = np.linalg.svd(slope, full_matrices=False)
        basis = basis[:, singular > 1e-9 * max(float(singular[0]), 1e-300)]
        design -= basis @ (basis.T @ design)
        residual = residual_m - basis @ (basis.T @ residual_m)
        scale = c.frame_points / len(points_sensor) / c.frame_noise_m**2
        self.information[np.ix_(local, local)] += scale * design.T @ design
        self.evidence[local] += scale * design.T @ residual
        self.touched[local] = True
        self._solve()

    def _solve(self) -> None:
        """The map's values on the nodes the frames reached and `reach_nodes` around them (0 beyond)."""
        c = self.config
        reached = int(self.touched.sum())
        if self._active is None or self._active[0] != reached:  # new nodes reached: a new active set
            shape = (self.per_axis, self.per_axis)
            index = np.flatnonzero(ndimage.binary_dilation(self.touched.reshape(shape), iterations=c.reach_nodes))
            prior = self.prior[index][:, index].toarray()
            prior[np.diag_indices(len(index))] += np.where(self.rest_nodes[index], c.rest_node_m**-2, 0.0)
            self._active = (reached, index, prior)
        _, index, prior = self._active
        system = self.information[np.ix_(index, index)] + prior
        self.values = np.zeros_like(self.values)
        self.values[index] = linalg.solve(system, self.evidence[index], assume_a="pos", check_finite=False)


@functools.lru_cache(maxsize=4)
def _smooth_prior(per_axis: int, config: PadErrorConfig) -> sparse.csr_matrix:
    """The map's prior precision over its nodes: each node's magnitude, and second differences along x and y."""
    size = per_axis * per_axis
    grid = np.arange(size).reshape(per_axis, per_axis)
    blocks = []
    for centre, before, after in (
        (grid[:, 1:-1], grid[:, :-2], grid[:, 2:]),
        (grid[1:-1, :], grid[:-2, :], grid[2:, :]),
    ):
        k = np.arange(centre.size)
        rows = np.concatenate([k, k, k])
        columns = np.concatenate([centre.ravel(), before.ravel(), after.ravel()])
        values = np.concatenate([np.full(k.size, -2.0), np.ones(k.size), np.ones(k.size)])
        blocks.append(sparse.csr_matrix((values, (rows, columns)), shape=(centre.size, size)))
    second = sparse.vstack(blocks).tocsr()
    curvature_m = config.magnitude_m * (config.node_m / config.correlation_m) ** 2
    return (sparse.identity(size, format="csr") / config.magnitude_m**2 + second.T @ second / curvature_m**2).tocsr()
