"""The closed loop's filter: `ClosedLoop` takes tactile instants one by one and corrects the tracked grasps,
each instant's record a `Correction`.

**Closed loop.** Slip moves the object in the gels, and the grasps drift with it. Each new tactile frame is a
measurement of where the object really is: its points, mapped into the object frame through the live sensor pose
and the predicted object pose, must lie on the object's surface. A point-to-plane Gauss-Newton
(`yoto.registration`) started at the prediction, over the surface near the current contact (correspondences within
a few millimetres), gives the correction; frames of both sensors taken at about the same time are registered
together (two contacts fix all six degrees of freedom where one may leave some free). The correction is not
applied blindly: a small Kalman filter on the object-frame error weighs it against the prediction, with
  - the registration's information (its Gauss-Newton normal matrix), so directions a contact cannot see (sliding
    along a flat face, spinning a sphere) keep the prediction; where it is weakest it is checked by re-matching the
    points at a small step (a scanned mesh's tilted planes claim directions its surface leaves free);
  - a measurement bias: a reconstruction's errors are smooth over the patch and the same from frame to frame
    (calibration, lighting), so a registration is off by a bias that repeating the frame does not average away.
    The filter estimates it beside the slip, with the size a contact's shape gives it in each direction (small
    where the contact pins the object, large where it barely does), so only changes the bias cannot explain
    correct the pose;
  - a slip model: slip grows with the sensors' travel at a rate the filter estimates along the way (the paper
    observes drift growing with motion length), plus a random part for elastic, inertial slip. The rate lets the
    evidence of all frames add up, so even a direction a single frame sees poorly is corrected over the path.
Before registering, each sensor's own reconstruction error, fixed to its pad and learnt from its own frames from
what no rigid motion explains (`pad_error.py`), is subtracted from the frame by pad position: as the contact slides
over the pad, that error would otherwise move the registrations as slip does.
A divergence guard watches the result: where the tracked slip leaves what the slip model allows over the travel so
far, the instant's frames are registered from the open-loop pose too; if they fit there as well, they never asked
for the departure (a direction the contacts barely pin, followed by the slip rate: a mug spun about its axis), so
the loop re-anchors on that fit and from then on lets the prediction stand along the departure's direction. It
checks as well when the slip's turn, its shift or the filter's slip rate alone leaves the model (a spin the scanned
mesh's planes claim to pin), and along the directions the two contacts pin weakly it holds the tracked slip within the
slip model's sigma: the frames cannot tell slip there, and the slip rate would carry the pose along (a face's slide).
Both grasps then take the corrected pose. A frame is unusable, and the prediction (open loop) stands, when it has
too few points (contact lost), when too few of its points lie on the surface after registration (a bad fit),
or when it asks for a jump larger than slip can make; when one sensor's frame is unusable, the other's is used
alone.

Frames: YOTO's canonical `object` frame inside (origin at the centroid: corrections rotate about it); tactile
points in their sensor's frame until mapped through the live sensor pose and the grasps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from yoto.contacts import MIN_TACTILE_POINTS, SIDES
from yoto.errors import InputError
from yoto.geometry import invert_transform, pose_from_twist, rotation_angle_rad, skew, transform_points, twist_of_pose
from yoto.objects.model import ObjectModel
from yoto.registration import plane_distances, point_to_plane_jacobian, truncated_plane_fit
from yoto.tracking.config import TrackConfig
from yoto.tracking.frame_registration import (
    contact_information,
    contact_samples,
    frame_indentation_m,
    observable_unit,
    pad_rest_solver,
    predicted_indentation_m,
    register_contacts,
    registration_prior,
    registration_solver,
    without_depth_scale,
)
from yoto.tracking.fusion import SensorPoses, StreamJitter, fuse_holding, sensor_poses
from yoto.tracking.pad_error import PadError
from yoto.tracking.pinning import Pinning
from yoto.tracking.streams import TactileStream, felt_contact
from yoto.tracking.touch import Touch, pose_distance_m
from yoto.trajectory import PoseStream


@dataclass
class Correction:
    """What one tactile instant (a frame of one sensor, or of both at about the same time) did."""

    timestamp_s: float  # the instant's time: its latest frame's
    used: tuple[str, ...]  # sides whose frames corrected the pose
    unusable: dict[str, str]  # side -> why its frame was not used
    correction_m: float = 0.0  # how far the applied correction moved the centroid ...
    correction_rad: float = 0.0  # ... and turned the object
    slip_m: float = 0.0  # the object's total motion in the grasp since the touch, as tracked so far ...
    slip_rad: float = 0.0
    inlier_fraction: float = 0.0  # share of the registered points on the surface after registration
    latency_ms: float = 0.0  # loading, registering and updating, this instant
    guard: str = ""  # the divergence guard's check this instant: "" (none), "kept" (the frames see the departure),
    # "re-anchored" (they fit as well from open loop: the loop moved back onto that fit)
    held: bool = False  # the tracked slip along weakly pinned directions brought back to the slip model's bound
    sigma_rad: float = 0.0  # the filter's 1-sigma of the object's pose after the instant, along its least certain
    sigma_m: float = 0.0  # turn and shift (what it believes; the weakly pinned directions of `TrackResult.pinning`)
    indentation_m: dict[str, float] = field(default_factory=dict)  # side -> how deep its frame read the press


class OpenLoopChange(NamedTuple):
    """A change of the open loop's grasps after the touch (`ClosedLoop.open_changes`): from `time_s` on, `side`
    carries the object with `T_sensor_object`, or (None) it let go and carries it no more."""

    time_s: float
    side: str
    T_sensor_object: np.ndarray | None


class ClosedLoop:
    """The closed loop's state: the grasps, and a Kalman filter on (error, slip rate, measurement bias).

    Error-state filter: the grasps hold the current estimate; the state is the object-frame error of the grasps
    (a twist, rotation about the centroid first), the slip rate per metre of travel, and the registrations' bias,
    6 numbers each. The error's mean is folded into the grasps after every update.
    """

    def __init__(
        self,
        model: ObjectModel,
        touch: Touch,
        streams: dict[str, PoseStream],
        jitter: dict[str, StreamJitter],
        config: TrackConfig,
    ):
        self.model, self.streams, self.jitter, self.config = model, streams, jitter, config
        _ = model.kdtree  # built now, before the first frame, so that no live frame waits for it
        c = config.correction
        self.grasps = dict(touch.T_sensor_object)
        self.open_grasps = dict(touch.T_sensor_object)  # the open loop's grasps (the divergence guard's anchor; the
        # output's open loop follows their changes, `open_changes`)
        self.unit = observable_unit(c)
        self.rate = np.zeros(6)  # slip per metre of travel (rad/m, m/m), object frame
        self.bias = np.zeros(6)  # the registrations' bias (rad, m)
        self.bias_covariance: np.ndarray | None = None  # its size, from the first registered contact's shape
        self.covariance = self._initial_covariance()
        self.solver = registration_solver(c)
        self.rest_solver = pad_rest_solver(c)
        self.last_correction = (0.0, 0.0)  # (metres, radians) of the latest applied correction
        self.last_time = touch.time_s
        self.last_sensors = sensor_poses(streams, np.array([touch.time_s]), config.fusion, jitter)
        self.touch_sensors = self.last_sensors
        self.pads = {side: PadError(c.pad_error) for side in SIDES} if c.pad_error.enabled else {}
        self.moving = False  # a sensor has left its pose at the touch: the pads' errors are set, the rest reads too
        self.rest_reads: dict[str, list[tuple[float, float]]] = {side: [] for side in SIDES}  # per side, at rest:
        # (how deep its frame read the press, the distance between the sensors then) ...
        self.rest_read: dict[str, np.ndarray] = {}  # ... and their median, per side that had any, once moving
        self.touch_press = {  # per side, how deep the object at the touch's pose presses the pad (nan: no surface)
            side: predicted_indentation_m(model, invert_transform(grasp)) for side, grasp in self.grasps.items()
        }
        # per side, the last frame used at rest: its samples (sensor frame), its registered T_object_sensor, and the
        # pad's error removed from them as the bias now holds it (`bias_follows_pads`)
        self.rest_reference: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.travel_m = 0.0  # the sensors' travel since the touch (rotation counted at `turn_radius_m`)
        self.guard_wait = 0  # applied instants the divergence guard still skips ...
        self.guard_next_s = -np.inf  # ... and the time before which it does not check again
        self.pair_shared, self.pair_instants = np.zeros((6, 6)), 0  # the shared-error information summed over the
        # applied two-contact instants, and their count (`TrackResult.pinning`)
        self.unpinned: np.ndarray | None = None  # (K, 6) orthonormal directions (observable units) the guard found
        # the frames leave free: the departures it undid; the prediction stands along them from then on
        self.gone: set[str] = set()  # the sides that let go (`ReleaseWatch.let_go`): their grasps carry nothing ...
        self.lifted: set[str] = set()  # ... and those without contact whose sensor left the object (`lifted_apart_m`):
        # while the other touches, it alone predicts the pose (a side letting go, its sensor withdrawing)
        self.open_changes: list[OpenLoopChange] = []  # the open loop's grasps since the touch, as they changed
        self.tilt_rad: dict[str, float] = {}  # per side whose contacts tilt (`image_contact_tilt_rad`...): sigma

    def _initial_covariance(self) -> np.ndarray:
        """The filter's covariance at the touch: its pose's uncertainty and the slip rate's prior (the bias's is set
        by the first registered contact)."""
        c = self.config.correction
        covariance = np.diag(
            [c.touch_rotation_rad**2] * 3
            + [c.touch_translation_m**2] * 3
            + [c.slip_rate_rotation**2] * 3
            + [c.slip_rate_translation**2] * 3
            + [0.0] * 6
        )
        if self.bias_covariance is not None:
            covariance[12:, 12:] = self.bias_covariance
        return covariance

    def _slip(self) -> np.ndarray:
        """(4, 4) the tracked slip since the touch: the closed loop's object pose in the open loop's (object frame)."""
        return invert_transform(self.open_grasps["left"]) @ self.grasps["left"]

    def _slip_variance(self) -> np.ndarray:
        """(6,) the slip model's variance of the slip since the touch (rad^2, m^2; object frame) over the travel so
        far: a rate drawn from its prior and wandering as it may, the elastic wander, and the touch's own
        uncertainty."""
        c = self.config.correction
        travel, share = self.travel_m, self.travel_m / c.slip_travel_m
        spread = travel**2 + travel**3 / (3.0 * c.slip_travel_m)  # a constant rate and its random walk
        return np.array(
            [c.slip_rate_rotation**2 * spread + c.slip_wander_rotation_rad**2 * share + c.touch_rotation_rad**2] * 3
            + [c.slip_rate_translation**2 * spread + c.slip_wander_translation_m**2 * share + c.touch_translation_m**2]
            * 3
        )

    def _slip_beyond_model(self) -> bool:
        """Whether the tracked slip since the touch (closed loop against open loop, object frame) lies beyond what
        the slip model allows over the travel so far (`_slip_variance`): all six together, or its turn or its shift
        alone (`guard_block_bound`: a departure in one of them, a spin, is not diluted by the other's quiet)."""
        c = self.config.correction
        squared = twist_of_pose(self._slip()) ** 2 / self._slip_variance()
        rate = self.rate**2 / np.repeat([c.slip_rate_rotation**2, c.slip_rate_translation**2], 3)
        blocks = [squared[:3].sum(), squared[3:].sum()] + ([rate[:3].sum(), rate[3:].sum()] if c.guard_rate else [])
        block = c.guard_block_bound > 0.0 and max(blocks) > c.guard_block_bound
        return float(squared.sum()) > c.guard_bound or block

    def _hold_weak(self) -> bool:
        """Hold the tracked slip along the directions the two-contact instants so far pin weakly (their mean shared
        error moves the fit by more than `guard_weak_spread` observable units there, `Pinning`: a face's slide, a
        spin about a body's long axis) within `guard_weak_sigmas` of the slip model (`_slip_variance`): the frames
        cannot tell slip there from their own error, and a departure beyond what slip itself does is the slip rate's
        estimate carrying the pose along. Beyond it, the slip there is brought back to that bound and the slip rate
        along those directions set to zero (observable units). Returns whether it held."""
        c = self.config.correction
        pinning = self.pair_pinning()
        if c.guard_weak_spread <= 0.0 or pinning is None:
            return False
        weak = pinning.directions[pinning.spread > c.guard_weak_spread]  # (K, 6), orthonormal, observable units
        if not len(weak):
            return False
        slip = twist_of_pose(self._slip()) / self.unit
        along = weak @ slip
        covariance = weak @ np.diag(self._slip_variance() / self.unit**2) @ weak.T
        distance = float(np.sqrt(along @ np.linalg.solve(covariance, along)))
        if distance <= c.guard_weak_sigmas:
            return False
        kept = slip - weak.T @ along * (1.0 - c.guard_weak_sigmas / distance)
        change = invert_transform(pose_from_twist(slip * self.unit)) @ pose_from_twist(kept * self.unit)
        self.grasps = {side: grasp @ change for side, grasp in self.grasps.items()}
        rate = self.rate / self.unit
        self.rate = (rate - weak.T @ (weak @ rate)) * self.unit
        return True

    def pair_pinning(self) -> Pinning | None:
        """How the applied two-contact instants so far pin each direction (their mean shared-error information),
        or None before the first."""
        return Pinning.of(self.pair_shared / self.pair_instants, self.unit) if self.pair_instants else None

    def _guard_due(self, instant_s: float) -> bool:
        """Whether the divergence guard checks at this applied instant (at `instant_s`): the tracked slip beyond the
        slip model, the last check `guard_every_s` and `guard_every` applied instants back at least."""
        c = self.config.correction
        if self.guard_wait > 0 or instant_s < self.guard_next_s - 1e-9:
            self.guard_wait = max(self.guard_wait - 1, 0)
            return False
        if not self._slip_beyond_model():
            return False
        self.guard_wait, self.guard_next_s = c.guard_every, instant_s + c.guard_every_s
        return True

    def _guard(
        self,
        instant_s: float,
        sensors: SensorPoses,
        rows: dict[str, int],
        points_sensor: dict[str, np.ndarray],
        fractions: dict[str, float],
    ) -> str:
        """The divergence guard, after an applied update: where the tracked slip has left what the slip model allows,
        register the instant's frames from the open-loop pose as well; if they fit there about as well as at the
        closed loop's registration and stay near it, the evidence never asked for the departure (a direction the
        contacts barely pin, followed by the slip rate): re-anchor the loop on that fit, the slip rate back to its
        prior. A real pivot the frames see fits worse from open loop, or leads that fit away from it, and is kept.
        Returns "" (no check, `_guard_due`), "kept" or "re-anchored"."""
        c = self.config.correction
        if not self._guard_due(instant_s):
            return ""
        predicted = self.fuse(sensors)  # after this instant's update
        open_loop = fuse_holding(sensors, self.open_grasps, self.holding)[0]
        closed, opened, facing = [], [], {}
        for side, points in points_sensor.items():
            row = rows[side]
            T_world_sensor = sensors.T_world_sensor[side][row]
            closed.append(transform_points(invert_transform(predicted[row]) @ T_world_sensor, points))
            T_open_sensor = invert_transform(open_loop[row]) @ T_world_sensor
            opened.append(transform_points(T_open_sensor, points))
            facing[side] = T_open_sensor
        anchor, open_fractions = self._register(dict(zip(points_sensor, opened, strict=True)), facing)
        fit_open = truncated_plane_fit(self.model, transform_points(anchor, np.vstack(opened))[None], c.max_distance_m)
        fit_closed = truncated_plane_fit(self.model, np.vstack(closed)[None], c.max_distance_m)
        worse_inliers = min(open_fractions.values()) < min(fractions.values()) - 0.05
        if worse_inliers or fit_open.rms_m[0] > c.guard_fit_margin * fit_closed.rms_m[0]:
            return "kept"
        # Observable units: the departure (closed loop from open loop) and the fit's shift from open loop. Frames
        # that see a real pivot lead the fit away from open loop (back to the pivot, or anywhere but there).
        shift = twist_of_pose(anchor) / self.unit
        slip = twist_of_pose(self._slip()) / self.unit
        if np.linalg.norm(shift) >= c.guard_support_fraction * np.linalg.norm(slip):
            return "kept"
        # The departure undone is a direction the frames leave free: from now on the prediction stands along it,
        # and the anchor keeps the open loop's pose there (the fit from open loop wandered along it only as far as
        # its prior let it).
        departure = slip + shift
        departure /= max(float(np.linalg.norm(departure)), 1e-12)
        undo = invert_transform(pose_from_twist((shift - (shift @ departure) * departure) * self.unit))
        self.grasps = {side: grasp @ undo for side, grasp in self.open_grasps.items()}
        directions = departure[None] if self.unpinned is None else np.vstack([self.unpinned, departure])
        self.unpinned = np.linalg.qr(directions.T)[0].T[: min(len(directions), 5)]
        self.rate = np.zeros(6)
        self.covariance = self._initial_covariance()
        return "re-anchored"

    @property
    def holding(self) -> set[str]:
        """The sides whose grasps carry the object: those that have not let go and touch (all that have not let go
        where none touches)."""
        held = set(SIDES) - self.gone
        return held - self.lifted or held

    def fuse(self, sensors: SensorPoses, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The tracked T_world_object (K, 4, 4) at the chosen rows of `sensors`, from the sides that hold it."""
        return fuse_holding(sensors, self.grasps, self.holding, rows)[0]

    def let_go(self, side: str, since_s: float) -> None:
        """`side` let go (its first frame without contact at `since_s`): from now on the other side's grasp alone
        carries the object (its own grasp still follows the corrections, unused, until it touches again)."""
        self.gone.add(side)
        self.open_changes.append(OpenLoopChange(since_s, side, None))

    def _apart(self, side: str, sensors: SensorPoses) -> bool:
        """Whether `side`'s grasp puts the object more than `lifted_apart_m` from where the other side's puts it, at
        the instant (the last row of `sensors`; False where either sensor has no pose then)."""
        other = SIDES[1 - SIDES.index(side)]
        if other in self.gone or not (sensors.covered[side][-1] and sensors.covered[other][-1]):
            return False
        here = sensors.T_world_sensor[side][-1] @ self.grasps[side]
        there = sensors.T_world_sensor[other][-1] @ self.grasps[other]
        return bool(pose_distance_m(here, there[None])[0] > self.config.release.lifted_apart_m)

    def _touch_again(self, side: str, row: int, sensors: SensorPoses, stamp: float) -> None:
        """A side that had let go touches again: its grasps (closed and open loop) are the object's pose now, from
        the side that held on, in the side's live sensor pose; what its pad read at rest no longer applies."""
        T_sensor_world = invert_transform(sensors.T_world_sensor[side][row])
        self.grasps[side] = T_sensor_world @ self.fuse(sensors, slice(row, row + 1))[0]
        open_now = fuse_holding(sensors, self.open_grasps, self.holding, slice(row, row + 1))[0][0]
        self.open_grasps[side] = T_sensor_world @ open_now
        self.open_changes.append(OpenLoopChange(stamp, side, self.open_grasps[side]))
        self.gone.discard(side)
        self.touch_press[side] = predicted_indentation_m(self.model, invert_transform(self.grasps[side]))
        self.rest_read.pop(side, None)

    def _apply(self, twist: np.ndarray) -> None:
        """Move the object by `twist` (object frame) in both grasps: T_world_object <- T_world_object @ exp^-1."""
        undo = invert_transform(pose_from_twist(twist))
        self.grasps = {side: grasp @ undo for side, grasp in self.grasps.items()}

    def _predict(self, sensors: SensorPoses, now_s: float) -> None:
        """Slip since the last instant: the rate times the travel, and the covariance grown by the slip model."""
        c = self.config.correction
        travelled, turned = [], []
        for side in [side for side in SIDES if side not in self.gone]:  # a side that let go moves on its own
            before, now = self.last_sensors.T_world_sensor[side][0], sensors.T_world_sensor[side][-1]
            travelled.append(np.linalg.norm(now[:3, 3] - before[:3, 3]))
            turned.append(rotation_angle_rad(before, now))
        travel = float(np.mean(travelled)) + c.turn_radius_m * float(np.mean(turned))
        elapsed = max(now_s - self.last_time, 0.0)
        self.travel_m += travel
        self._apply(self.rate * travel)
        transition = np.eye(18)
        transition[:6, 6:12] = travel * np.eye(6)
        share = travel / c.slip_travel_m
        noise = np.diag(
            [c.slip_wander_rotation_rad**2 * share + c.creep_rotation_rad**2 * elapsed] * 3
            + [c.slip_wander_translation_m**2 * share + c.creep_translation_m**2 * elapsed] * 3
            + [c.slip_rate_rotation**2 * share] * 3
            + [c.slip_rate_translation**2 * share] * 3
            + [0.0] * 6
        )
        if self.bias_covariance is not None:
            noise[12:, 12:] = self.bias_covariance * min(travel / c.bias_travel_m, 1.0)
        self.covariance = transition @ self.covariance @ transition.T + noise
        self.last_time, self.last_sensors = now_s, sensors

    def _information(
        self, points_object: dict[str, np.ndarray], tilts: dict[str, tuple[np.ndarray, float]] | None = None
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each contact's information (`contact_information`), the surface check where more than
        `observable_max_contacts` contacts register together; the `tilts` given (pad axes, sigma) left out."""
        check = len(points_object) > self.config.correction.observable_max_contacts
        return contact_information(self.model, points_object, self.config.correction, check, tilts)

    def _register(
        self, points: dict[str, np.ndarray], sensors: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, dict[str, float]]:
        """The correction T_object_predicted bringing the sides' points (predicted object frame) onto the surface,
        and each side's inlier fraction after it. `sensors`: each side's T_predicted_sensor; its points match only
        surface facing that sensor (the other face of a thin wall, 1 mm behind the contact on a mug, is not theirs)."""
        c = self.config.correction
        move_limit = self.unit * c.contact_tilt_move_units if c.contact_tilt_move_units > 0.0 else None
        correction = register_contacts(self.model, points, sensors, self.solver, self.tilt_rad, move_limit)
        fractions = {}
        for side, side_points in points.items():
            fit = truncated_plane_fit(
                self.model,
                transform_points(correction, side_points)[None],
                c.max_distance_m,
                inlier_m=c.inlier_distance_m,
            )
            fractions[side] = float(fit.inlier_fraction[0])
        return correction, fractions

    def correct(self, instant_s: float, frames: dict[str, tuple[TactileStream, int]]) -> Correction:
        """Predict the slip to this instant, register its frames, fuse the correction, update both grasps."""
        started = time.perf_counter()
        c = self.config.correction
        unusable: dict[str, str] = {}
        clouds: dict[str, tuple[float, np.ndarray]] = {}
        for side, (stream, index) in frames.items():
            tilt_rad = c.image_contact_tilt_rad if stream.from_images else c.cloud_contact_tilt_rad
            if tilt_rad > 0.0:  # a reconstruction's tilt error (config)
                self.tilt_rad[side] = tilt_rad
            stamp = float(stream.timestamps_s[index])
            try:
                points = np.asarray(stream.load(index), dtype=np.float64).reshape(-1, 3)
            except InputError as exc:
                unusable[side] = f"unreadable ({exc})"
                continue
            # the one rule for what the gel felt, however the stream was built (a folder's reader applies it too)
            points = felt_contact(points[np.isfinite(points).all(axis=1)])
            if len(points) < MIN_TACTILE_POINTS:
                unusable[side] = f"too few points ({len(points)})"
                continue
            clouds[side] = (stamp, points)
        stamps = np.array([stamp for stamp, _ in clouds.values()] + [instant_s])
        sensors = sensor_poses(self.streams, stamps, self.config.fusion, self.jitter)
        self._predict(sensors, instant_s)
        if not self.moving and self._left_rest(sensors):
            self.moving = True
            for resting in self.pads.values():
                resting.settle(self.rest_solver)
            self.rest_read = {
                side: np.median(np.array(reads), axis=0) for side, reads in self.rest_reads.items() if reads
            }
        for side in frames:  # a gel without contact whose sensor leaves the object predicts nothing until it touches
            if side in clouds:
                self.lifted.discard(side)
            elif unusable.get(side, "").startswith("too few points") and self._apart(side, sensors):
                self.lifted.add(side)
        for row, side in enumerate(clouds):
            if side in self.gone and len(self.gone) < len(SIDES) and sensors.covered[side][row]:
                self._touch_again(side, row, sensors, clouds[side][0])
        predicted = self.fuse(sensors)
        shallow, reads = self._shallow(clouds, sensors)
        points_predicted: dict[str, np.ndarray] = {}
        points_sensor: dict[str, np.ndarray] = {}  # each side's registered samples (pad error removed), sensor frame
        raw_samples: dict[str, np.ndarray] = {}  # ... and as the frame gave them
        T_predicted_sensors: dict[str, np.ndarray] = {}
        pose_noise: dict[str, np.ndarray] = {}
        rows = {side: row for row, side in enumerate(clouds)}
        for row, (side, (_, points)) in enumerate(clouds.items()):
            if not sensors.covered[side][row]:
                unusable[side] = "no sensor pose at the frame's time"
                continue
            if side in shallow:
                unusable[side] = shallow[side]
                continue
            T_predicted_sensor = invert_transform(predicted[row]) @ sensors.T_world_sensor[side][row]
            sampled = contact_samples(points, c)
            raw_samples[side] = sampled
            pad = self.pads.get(side)
            if pad is not None:  # the pad's error learnt so far is removed (with the rest map: learnt at rest)
                if not self.moving and c.pad_error.rest_map:
                    pad.add_rest_frame(self.model, sampled, T_predicted_sensor, self.rest_solver)
                sampled = pad.correct(sampled)
            if c.image_depth_scale > 0.0 and frames[side][0].from_images:  # the reconstruction's depth scale error
                sampled, _ = without_depth_scale(self.model, sampled, T_predicted_sensor, c.image_depth_scale, c)
            points_predicted[side] = transform_points(T_predicted_sensor, sampled)
            points_sensor[side], T_predicted_sensors[side] = sampled, T_predicted_sensor
            pose_noise[side] = self._pose_noise(side, T_predicted_sensor)

        record = Correction(timestamp_s=instant_s, used=(), unusable=unusable, indentation_m=reads)
        if points_predicted:
            correction, fractions = self._register(points_predicted, T_predicted_sensors)
            bad = {side for side, fraction in fractions.items() if fraction < c.min_inlier_fraction}
            if bad and len(bad) < len(points_predicted):  # one side fits badly: try the other alone
                for side in bad:
                    unusable[side] = f"bad fit ({fractions[side]:.0%} of points on the surface)"
                    del points_predicted[side]
                correction, fractions = self._register(points_predicted, T_predicted_sensors)
                bad = {side for side, fraction in fractions.items() if fraction < c.min_inlier_fraction}
            if bad:
                for side in points_predicted:
                    unusable[side] = f"bad fit ({fractions[side]:.0%} of points on the surface)"
            else:
                refused = self._update(points_predicted, pose_noise, correction, T_predicted_sensors)
                for side in points_predicted if refused else ():
                    unusable[side] = refused
                if not refused:
                    record.used = tuple(points_predicted)
                    record.inlier_fraction = float(np.mean(list(fractions.values())))
                    record.correction_m, record.correction_rad = self.last_correction
                    error = self.covariance[:6, :6]
                    record.sigma_rad = float(np.sqrt(np.linalg.eigvalsh(error[:3, :3])[-1]))
                    record.sigma_m = float(np.sqrt(np.linalg.eigvalsh(error[3:, 3:])[-1]))
                    record.held = self._hold_weak()
                    record.guard = self._guard(
                        instant_s, sensors, rows, {side: points_sensor[side] for side in record.used}, fractions
                    )
                    if self.pads and (self.moving or not c.pad_error.rest_map):  # what the registered frames leave
                        for side in record.used:  # unexplained teaches the pads' sliding maps
                            self.pads[side].learn_frame(
                                self.model,
                                points_sensor[side],
                                correction @ T_predicted_sensors[side],
                                c.max_distance_m,
                            )
                            if c.bias_follows_pads and not self.moving:
                                raw = raw_samples[side]
                                self.rest_reference[side] = (
                                    raw,
                                    correction @ T_predicted_sensors[side],
                                    raw[:, 2] - self.pads[side].correct(raw)[:, 2],
                                )
                        if c.bias_follows_pads and self.moving:
                            self._follow_pads()
        slip = self._slip()
        record.slip_m = float(np.linalg.norm(slip[:3, 3]))
        record.slip_rad = rotation_angle_rad(slip, np.eye(4))
        record.latency_ms = 1000.0 * (time.perf_counter() - started)
        return record

    def _shallow(
        self, clouds: dict[str, tuple[float, np.ndarray]], sensors: SensorPoses
    ) -> tuple[dict[str, str], dict[str, float]]:
        """The frames that read their press much shallower than they should, each with why, and how deep every
        frame reads its press (`frame_indentation_m`), per side. At rest a frame should read the press the touch's
        pose puts on its pad (`misread_fraction`); a pad whose rest frames read it that shallow (their median) is
        left out of the motion as well: its reconstruction misreads this contact's shape (a flat face read as a
        partial one). In motion a frame should read about what its pad read at rest while the sensors stand no
        further apart (`shallow_gap_m`): a rigid grasp keeps its press as the object slips along the pads, and a
        frame far below it is the reconstruction losing part of the contact, which registered reads as a slide."""
        c = self.config.correction
        gap = float(
            np.linalg.norm(sensors.T_world_sensor["left"][-1][:3, 3] - sensors.T_world_sensor["right"][-1][:3, 3])
        )
        shallow, reads = {}, {}
        for side, (_, points) in clouds.items():
            read = frame_indentation_m(points)
            reads[side] = read
            if not self.moving:
                self.rest_reads[side].append((read, gap))
            if c.shallow_read_fraction <= 0.0:
                continue
            press = self.touch_press[side]
            if not self.moving:
                if press > 0.0 and read < c.misread_fraction * press:
                    shallow[side] = f"shallow read ({read * 1e3:.2f} mm, the touch presses {press * 1e3:.2f})"
                continue
            if side not in self.rest_read:
                continue
            rest_read, rest_gap = self.rest_read[side]
            if press > 0.0 and rest_read < c.misread_fraction * press:
                shallow[side] = f"shallow read ({rest_read * 1e3:.2f} mm at rest, the touch presses {press * 1e3:.2f})"
            elif gap <= rest_gap + c.shallow_gap_m and read < c.shallow_read_fraction * rest_read:
                shallow[side] = f"shallow read ({read * 1e3:.2f} mm, {rest_read * 1e3:.2f} at rest)"
        return shallow, reads

    def _follow_pads(self) -> None:
        """Move the registrations' bias by the shift the pads' maps, as they are now, would make to the registration
        of the last frames used at rest, against the maps the bias was learnt with (`bias_follows_pads`)."""
        c = self.config.correction
        normal, gradient = np.zeros((6, 6)), np.zeros(6)
        for side, (raw, T_object_sensor, removed) in self.rest_reference.items():
            now = raw[:, 2] - self.pads[side].correct(raw)[:, 2]
            points_object = transform_points(T_object_sensor, raw - np.outer(now, [0.0, 0.0, 1.0]))
            _, matched, _, normals = plane_distances(self.model, points_object, c.max_distance_m)
            jacobian = point_to_plane_jacobian(points_object, normals)[matched]
            # removing `now - removed` more moves each point by that much against the sensor's z
            change = -(now - removed)[matched] * (normals[matched] @ T_object_sensor[:3, 2])
            normal += jacobian.T @ jacobian
            gradient += jacobian.T @ change
            self.rest_reference[side] = (raw, T_object_sensor, now)
        if not gradient.any():
            return
        # the registration's own prior, in the units of these unweighted normal equations
        prior = c.surface_noise_m**2 * registration_prior(c)
        self.bias = self.bias - np.linalg.solve(normal + prior, gradient)

    def _left_rest(self, sensors: SensorPoses) -> bool:
        """Whether a sensor has moved more than `pad_error.rest_m` from its pose at the touch (rotation counted at
        `turn_radius_m`): the frames after that no longer see the object where it rested."""
        c = self.config.correction
        for side in SIDES:
            at_touch, now = self.touch_sensors.T_world_sensor[side][0], sensors.T_world_sensor[side][-1]
            moved = np.linalg.norm(now[:3, 3] - at_touch[:3, 3]) + c.turn_radius_m * rotation_angle_rad(at_touch, now)
            if moved > c.pad_error.rest_m:
                return True
        return False

    def _pose_noise(self, side: str, T_object_sensor: np.ndarray) -> np.ndarray:
        """Covariance (6, 6) of the object-frame twist (rotation about the centroid first) by which the sensor's
        pose jitter moves its contact's points: rotation jitter about the sensor turns them about its origin."""
        jitter = self.jitter[side]
        lever = skew(T_object_sensor[:3, 3])  # the sensor's origin relative to the centroid, object frame
        var_r, var_t = jitter.smoothed_rotation_rad**2, jitter.smoothed_translation_m**2
        # points move by w x (p - s) + t = w x p + (s x w + t): the twist (w, [s]_x w + t)
        return np.block(
            [[var_r * np.eye(3), var_r * lever.T], [var_r * lever, var_t * np.eye(3) + var_r * lever @ lever.T]]
        )

    def _observed(self, shared: np.ndarray, lone: bool) -> np.ndarray:
        """The projection (6, 6) of an object-frame twist onto the directions an instant's contacts pin (oblique in
        rad and m, orthogonal in units of `observable_rotation_rad` and `observable_translation_m`): all but those
        the divergence guard found free (`unpinned`), and for a `lone` contact only the eigen-directions of its
        shared-error information along which that error moves the fit by less than one unit."""
        free = np.eye(6) if self.unpinned is None else np.eye(6) - self.unpinned.T @ self.unpinned
        if lone:
            values, vectors = np.linalg.eigh(free @ (shared * np.outer(self.unit, self.unit)) @ free)
            pinned = vectors[:, values > 1.0]
            free = pinned @ pinned.T
        return free * np.outer(self.unit, 1.0 / self.unit)

    def _update(
        self,
        points_predicted: dict[str, np.ndarray],
        pose_noise: dict[str, np.ndarray],
        correction: np.ndarray,
        T_predicted_sensors: dict[str, np.ndarray],
    ) -> str:
        """Kalman update with the registration's twist z = error + bias + noise (information form), then the new
        grasps, slip rate and bias. Each contact's information is discounted by its sensor's pose jitter,
        (H^-1 + S)^-1 = H (I + S H)^-1. Returns why the correction was refused (a jump larger than slip makes),
        or "" when it was applied."""
        c = self.config.correction
        twist = twist_of_pose(correction)
        white, shared = np.zeros((6, 6)), np.zeros((6, 6))
        registered = {side: transform_points(correction, side_points) for side, side_points in points_predicted.items()}
        tilts = {  # each image frame's pad axes (registered frame) and its tilt's sigma
            side: ((correction[:3, :3] @ T_predicted_sensors[side][:3, :2]).T, self.tilt_rad[side])
            for side in registered
            if side in self.tilt_rad
        }
        for side, (per_frame, bias) in self._information(registered, tilts).items():
            white += per_frame @ np.linalg.inv(np.eye(6) + pose_noise[side] @ per_frame)
            shared += bias
        lone = len(points_predicted) <= c.observable_max_contacts
        observed = self._observed(shared, lone) if lone or self.unpinned is not None else None
        if observed is not None:
            white = observed.T @ white @ observed  # the information of the correction's observed part alone
        covariance = self.covariance.copy()
        if self.bias_covariance is None:  # the bias's size in each direction, from the first contact's shape
            self.bias_covariance = np.linalg.inv(shared + registration_prior(c))
            covariance[12:, 12:] = self.bias_covariance
        observe = np.hstack([np.eye(6), np.zeros((6, 6)), np.eye(6)])  # z = error + bias
        # A registration further from the prediction than the filter expects (normalized innovation squared above
        # its bound) counts less: its information is scaled down by bound / NIS (a Huber-like robust update).
        innovation = twist - self.bias
        predicted = observe @ covariance @ observe.T
        nis = float(innovation @ white @ np.linalg.solve(np.eye(6) + predicted @ white, innovation))
        if nis > c.innovation_bound:
            white = white * (c.innovation_bound / nis)
        prior_precision = np.linalg.inv(covariance)
        precision = prior_precision + observe.T @ white @ observe
        prior_mean = np.concatenate([np.zeros(6), self.rate, self.bias])
        mean = np.linalg.solve(precision, prior_precision @ prior_mean + observe.T @ white @ twist)
        if observed is not None:  # along the directions the instant does not pin, the prediction stands: no change
            # through the filter's correlations either (error, slip rate and bias alike)
            mean = prior_mean + np.kron(np.eye(3), observed) @ (mean - prior_mean)
        moved_m, turned_rad = float(np.linalg.norm(mean[3:6])), float(np.linalg.norm(mean[:3]))
        if moved_m > c.max_correction_m or turned_rad > c.max_correction_rad:
            return f"jump ({moved_m * 1e3:.1f} mm, {np.degrees(turned_rad):.1f} deg)"
        self.covariance = np.linalg.inv(precision)
        if len(points_predicted) == 2:
            self.pair_shared += shared
            self.pair_instants += 1
        self._apply(mean[:6])
        self.rate, self.bias = mean[6:12], mean[12:]
        self.last_correction = (moved_m, turned_rad)
        return ""
