"""Tracking after one touch: open loop from the live sensor poses (paper Sec. 4.3), closed loop from the gel.

**Open loop.** The touch's pose estimate fixes the object in each sensor's frame, its grasp
`T_sensor_object = T_world_sensor^-1 @ T_world_object` (sensor poses as the contact pair gives them). At every later
time each live sensor pose gives `T_world_sensor(t) @ T_sensor_object`; the two are averaged (`fusion.py`).

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
the loop re-anchors on that fit and from then on lets the prediction stand along the departure's direction.
Both grasps then take the corrected pose. A frame is unusable, and the prediction (open loop) stands, when it has
too few points (contact lost), when too few of its points lie on the surface after registration (a bad fit),
or when it asks for a jump larger than slip can make; when one sensor's frame is unusable, the other's is used
alone.
When both gels stay without contact (`ReleaseWatch`: a few frames each, a fifth of a second), the object was let go:
the grasp ends there, and the poses after it hold the last pose before it (`TrackResult.released_s`). Given the pose
stage (`track`'s `new_touch`), both gels touching again make a new touch: its pose estimated from that pair (the
hypothesis nearest the last pose where it is ambiguous), tracked on from there (`TrackResult.regrasps`). One gel
without contact whose sensor leaves the object (`lifted_apart_m`) leaves the other to predict the pose; one without
contact as long as a release let go (`LetGo`): the other alone carries the object, open loop too, until the side
touches again, when its grasp is the tracked pose in its live sensor pose.

Frames: YOTO's canonical `object` frame inside (origin at the centroid: corrections rotate about it); results
convert to the mesh file's frame with `T_world_mesh = T_world_object @ T_object_mesh`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from yoto.contacts import MIN_TACTILE_POINTS, MINI_PAD_M, SIDES, ContactPair, TactileContact
from yoto.errors import InputError, YotoError
from yoto.geometry import (
    invert_transform,
    pose_from_twist,
    rotation_angle_rad,
    skew,
    so3_log,
    transform_points,
    twist_of_pose,
)
from yoto.objects.model import ObjectModel
from yoto.registration import (
    GaussNewtonConfig,
    SurfaceCloud,
    one_blas_thread,
    plane_distances,
    point_to_plane_gauss_newton,
    point_to_plane_jacobian,
    truncated_plane_fit,
)
from yoto.tracking.fusion import (
    FusionConfig,
    SensorPoses,
    StreamJitter,
    fuse_object_poses,
    sensor_poses,
    smooth_stream,
    stream_jitter,
)
from yoto.tracking.pad_error import PadError, PadErrorConfig
from yoto.tracking.streams import TactileStream, felt_contact
from yoto.trajectory import PoseStream

TOUCH_MATCH_ROTATION_M_PER_RAD = 0.05  # how rotation counts against translation when matching the touch in time


@dataclass(frozen=True)
class CorrectionConfig:
    """How tactile frames during motion correct the tracked pose (closed loop)."""

    points_per_contact: int = 250  # tactile points registered per contact, after voxel down-sampling
    voxel_m: float = 0.0004  # side of the square bins over the pad (sensor x, y) whose means are those points
    min_depth_fraction: float = 0.4  # only points pressed at least this share of the frame's deepest point count:
    # the rim, where the gel barely touches and sinks in beside the object, is where reconstructions are off
    sync_tolerance_s: float = 0.02  # a left and a right frame this close in time are registered together; or
    # closer than half the slower gel's frame period where that is longer (`instant_window_s`)
    iterations: int = 10  # Gauss-Newton iterations at most ...
    step_tolerance_m: float = 1e-6  # ... stopping when a step moves less than this ...
    step_tolerance_rad: float = 1e-5  # ... and turns less than this (far below what a frame can tell)
    max_distance_m: float = 0.002  # correspondences further than this are ignored (the capture range per frame)
    surface_noise_m: float = 3e-5  # 1-sigma of a tactile point's distance from the surface (robust scale floor)
    registration_prior_rotation_rad: float = float(np.radians(3.0))  # weak prior on the prediction inside the
    registration_prior_translation_m: float = 0.003  # registration (keeps free directions put)
    pixel_noise_m: float = 4e-5  # 1-sigma error of a tactile point that is new in every frame (camera noise, and
    # what registering a frame adds: its mask edge, its sampling)
    bias_points: float = 3.0  # the error a contact's points share from frame to frame (calibration, lighting,
    bias_noise_m: float = 3e-5  # integration drift) is smooth over the patch: as if this many points had this error
    bias_travel_m: float = 1.0  # that shared error is fixed on the pad (calibration, lighting) and changes only as
    # the contact slides over it, millimetres along a path: fully over this much travel of the sensors
    inlier_distance_m: float = 0.0003  # a registered point this close to the surface lies on it
    min_inlier_fraction: float = 0.5  # a frame with fewer of its points on the surface after registration is unusable
    observable_max_contacts: int = 1  # instants with at most this many contacts (1: a lone contact; 2: all; 0: none)
    # correct only the directions they pin, where a reconstruction's smooth error (`bias_noise_m` over
    # `bias_points`) moves the fit by less than this turn and this shift (in those units, one unit); along the
    # others (a lone contact's spin and lever, the line through two flat contacts) the prediction stands
    observable_rotation_rad: float = float(np.radians(2.0))  # that turn ...
    observable_translation_m: float = 0.002  # ... and that shift
    innovation_bound: float = 12.6  # a registration whose normalized innovation squared exceeds this (chi-square,
    # 6 degrees of freedom, 95%) has its information scaled down by bound / NIS
    max_correction_m: float = 0.003  # a frame asking for a larger jump than this is unusable (a wrong fit) ...
    max_correction_rad: float = float(np.radians(3.0))  # ... or a larger turn than this
    touch_translation_m: float = 0.001  # 1-sigma uncertainty of the touch's pose: how far the first frames may
    touch_rotation_rad: float = float(np.radians(2.0))  # move it
    slip_rate_translation: float = 0.03  # 1-sigma prior of the slip rate: metres of slip per metre of travel ...
    slip_rate_rotation: float = float(np.radians(20.0))  # ... and radians per metre (paper: 1-3 mm, 1-2 deg / 100 mm)
    slip_travel_m: float = 0.1  # over this much travel the slip rate may change by its prior, and the slip may
    slip_wander_translation_m: float = 0.001  # leave its rate by this (elastic, inertial slip) ...
    slip_wander_rotation_rad: float = float(np.radians(1.0))  # ... and this
    turn_radius_m: float = 0.05  # the sensors turning by one radian count as this much travel
    creep_translation_m: float = 1e-5  # 1-sigma slip per second at rest (per square root of a second) ...
    creep_rotation_rad: float = float(np.radians(0.01))  # ... and its rotation
    pad_error: PadErrorConfig = PadErrorConfig()  # each pad's fixed reconstruction error, learnt at rest, removed
    bias_follows_pads: bool = True  # where a pad's map, learning on, changes what it removes under the contact at
    # rest (where the filter learnt the registrations' bias), the bias moves by the registration shift that change
    # makes there: the map's later knowledge revises the bias instead of reading as slip
    guard_bound: float = 22.46  # divergence guard: when the tracked slip leaves what the slip model allows over the
    # travel so far (its squared Mahalanobis distance above this: chi-square, 6 degrees of freedom, 99.9%), the
    # instant's frames are registered from the open-loop pose as well ...
    guard_fit_margin: float = 1.1  # ... and where they fit there within this factor of the closed loop's RMS (and
    # its inlier share), the frames never asked for the departure: the loop re-anchors on that fit
    guard_support_fraction: float = 0.5  # ... and stay there: the fit moves the pose less than this share of the
    # departure (observable units); frames that see a real pivot lead it away from the open loop
    guard_every: int = 5  # instants between two such checks while the slip stays beyond the bound
    secant_directions: int = 3  # an instant's information (both contacts; a lone contact's own rule is above) is
    # checked along its this many weakest directions (observable units): its points re-matched to the surface at
    # +-`secant_step` there, the cost's actual rise against the planes' prediction; where the surface rises less (a
    # scanned mesh's tilted planes claim a spin its surface of revolution leaves free), the information there is
    # scaled down to what re-matching shows (0: off)
    secant_step: float = 0.5  # that step, in observable units (`observable_rotation_rad`, `observable_translation_m`)
    shallow_read_fraction: float = 0.5  # a frame reading its press shallower than this share of what it should is
    # left out (0: off): in motion, of what its pad read at rest (median) while the sensors stand no further apart
    # than then (within `shallow_gap_m`): the reconstruction lost part of the contact, and would read as a slide ...
    misread_fraction: float = 0.25  # ... at rest, of the press the touch's pose puts on its pad; a pad whose rest
    # frames read that shallow (median) is left out of the motion too: it misreads this contact's shape (0.5 also
    # drops the cracker box's left pad through `shading:3`, 0.42 of its press, whose track met the target)
    shallow_gap_m: float = 0.001  # (the reported sensor poses put the sensors' distance a few tenths off)
    release_frames: int = 5  # the object is released (let go) when, after contact, both sensors' frames show no
    release_s: float = 0.2  # contact (too few points) for at least this many frames each, over at least this long:
    # the track ends there (a lift-off of one side, or both for a few frames, keeps the prediction); 0 frames: off.
    # One side alone without contact as long, the other touching, let go: the other carries the object alone
    lifted_apart_m: float = 0.002  # a side whose frame shows no contact and whose grasp puts the object this far
    # from where the other side's puts it (position plus 50 mm per radian) predicts nothing until it touches again:
    # its sensor is leaving the object (a lift-off in place, the sides agreeing, keeps both)
    regrasp_frames: int = 3  # after a release, both gels touching in this many instants in a row make a new touch
    # (its pose estimated from the latest pair: the press has settled), when `track` is given a `NewTouchEstimator`
    regrasp_attempts: int = 3  # new touches whose estimate was refused before the track stops looking until the end


@dataclass(frozen=True)
class TrackConfig:
    """How `track` follows the object after the touch."""

    fusion: FusionConfig = FusionConfig()
    correction: CorrectionConfig = CorrectionConfig()
    touch_mismatch_warning_m: float = 0.005  # warn when the streams never come this close to the pair's sensor poses
    min_touch_confidence: float = 0.5  # warn when the touch's pose is less likely than this to be right
    weak_pinning_warning: float = 1.0  # warn when the two contacts pin a direction of the pose only this loosely
    # (`Pinning.spread`, observable units: 1 is 2 deg / 2 mm): slip along it is not observable from the contacts
    retouch_above: float = 0.25  # beyond this spread of the weakest direction (the drift target, 0.5 deg / 0.5 mm),
    # `yoto track` says where on the object a contact would see it (`retouch`)


@dataclass
class Touch:
    """What the touch fixes: its time, the object's pose then, and each sensor's grasp of the object."""

    time_s: float
    T_world_object: np.ndarray  # (4, 4) the touch's pose estimate, canonical object frame
    T_sensor_object: dict[str, np.ndarray]  # side -> (4, 4) the object in the sensor's frame
    time_source: str = ""  # how the time was found (pair file, given, matched to the streams)
    mismatch_m: float = 0.0  # how far the streams were from the pair's sensor poses at that time (`touch_time_of`)


def touch_from_pair(pair: ContactPair, T_world_object: np.ndarray, time_s: float, time_source: str = "") -> Touch:
    """The grasps `T_sensor_object` of a touch from its pair's sensor poses and the pose estimated from it."""
    grasps = {side: invert_transform(pair.contact(side).T_world_sensor) @ T_world_object for side in SIDES}
    return Touch(float(time_s), np.asarray(T_world_object, dtype=np.float64), grasps, time_source)


def sensor_pose_mismatch(
    pair: ContactPair, streams: dict[str, PoseStream], times_s: np.ndarray, config: FusionConfig = FusionConfig()
) -> np.ndarray:
    """(2, N) how far each sensor's (left, right) stream pose at `times_s` is from the pair's sensor pose: metres,
    rotation counted at 5 cm per radian; NaN where the stream does not cover the time."""
    poses = sensor_poses(streams, times_s, config)
    mismatch = np.full((len(SIDES), len(times_s)), np.nan)
    for k, side in enumerate(SIDES):
        target = pair.contact(side).T_world_sensor
        live = poses.T_world_sensor[side]
        angles = np.linalg.norm(so3_log(np.einsum("ji,njk->nik", target[:3, :3], live[:, :3, :3])), axis=1)
        offsets = np.linalg.norm(live[:, :3, 3] - target[:3, 3], axis=1) + TOUCH_MATCH_ROTATION_M_PER_RAD * angles
        mismatch[k, poses.covered[side]] = offsets[poses.covered[side]]
    return mismatch


def find_touch_time(
    pair: ContactPair, streams: dict[str, PoseStream], config: FusionConfig = FusionConfig()
) -> tuple[float, float]:
    """When the streams' sensor poses are nearest the pair's: (timestamp, mismatch), the mismatch in metres with
    rotation counted at 5 cm per radian, summed over both sensors."""
    times = np.union1d(streams["left"].timestamps_s, streams["right"].timestamps_s)
    mismatch = sensor_pose_mismatch(pair, streams, times, config).sum(axis=0)  # NaN unless both cover the time
    if not np.isfinite(mismatch).any():
        raise InputError("the two sensor pose streams never overlap in time")
    best = int(np.nanargmin(mismatch))
    return float(times[best]), float(mismatch[best])


def touch_time_of(
    pair: ContactPair, streams: dict[str, PoseStream], given_s: float | None, config: TrackConfig
) -> tuple[float, str, float]:
    """The touch's time: given, else the pair file's `timestamp`, else matched to the streams. Returns (time, how it
    was found, mismatch): how far the streams' sensor poses are from the pair's then (`sensor_pose_mismatch` summed
    over the sensors whose streams cover the time; matched: the least over the streams)."""
    if given_s is not None:
        time_s, source = float(given_s), "given"
    elif pair.extra.get("timestamp") is not None:
        stamp = pair.extra["timestamp"]
        try:
            time_s, source = float(stamp), "the pair file's timestamp"
        except (TypeError, ValueError):
            raise InputError(f"'timestamp' must be a number of seconds, got {stamp!r}", pair.path) from None
    else:
        found, mismatch = find_touch_time(pair, streams, config.fusion)
        return found, "matched to the streams", mismatch
    mismatch = float(np.nansum(sensor_pose_mismatch(pair, streams, np.array([time_s]), config.fusion)))
    return time_s, source, mismatch


# ------------------------------------------------------------------------------------------------ results
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
    sigma_rad: float = 0.0  # the filter's 1-sigma of the object's pose after the instant, along its least certain
    sigma_m: float = 0.0  # turn and shift (what it believes; the weakly pinned directions of `TrackResult.pinning`)
    indentation_m: dict[str, float] = field(default_factory=dict)  # side -> how deep its frame read the press


@dataclass
class LetGo:
    """One gel let go while the other held on (`ReleaseWatch`): from `time_s` the other sensor alone carries the
    object (open and closed loop), until this side touches again, if it does: its grasp is then the tracked pose in
    its live sensor pose."""

    side: str
    time_s: float  # its first frame without contact
    seen_s: float  # the frame that made the stretch long enough (the closed loop's prediction used both until then)
    touched_again_s: float | None = None  # its first frame with contact after it


@dataclass
class Regrasp:
    """A new touch after a release: both gels touching again, the object's pose estimated from that pair."""

    touch: Touch  # its time, pose (the hypothesis taken) and grasps; the track goes on from it
    pose_from: str  # how the pose was found (localizer, confidence)
    confidence: float  # the estimate's confidence that its most probable pose is within 5 mm / 5 deg
    ambiguous: bool  # the estimate left several poses ...
    hypothesis: int  # ... and this one (0: the most probable) was taken: the nearest the last tracked pose
    released_s: float | None = None  # when this grasp was let go in turn (None: held to the end)


# (the object's pose from a new contact pair, as `yoto.pose.estimate_pose` gives it; raises YotoError when refused)
NewTouchEstimator = Callable[[ContactPair], Any]


@dataclass
class TrackResult:
    """The tracked object poses after a touch."""

    timestamps_s: np.ndarray  # (M,) the sensor streams' timestamps from the touch on (those with a sensor pose)
    T_world_object: np.ndarray  # (M, 4, 4) canonical frame: closed loop where tactile frames were given
    T_world_object_open_loop: np.ndarray  # (M, 4, 4) the open-loop poses at the same times
    sensor_weights: np.ndarray  # (M, 2) how much (left, right) counted in each rotation
    touch: Touch
    jitter: dict[str, StreamJitter]
    closed_loop: bool
    corrections: list[Correction] = field(default_factory=list)
    skipped_times: int = 0  # stream timestamps after the touch where neither sensor had a pose (dropouts)
    pad_errors: dict[str, PadError] = field(default_factory=dict)  # side -> the pad's error the closed loop learnt
    pinning: Pinning | None = None  # how well the two contacts pinned each direction (their shared-error information
    # averaged over the instants both corrected); None without such an instant
    released_s: float | None = None  # when both gels lost contact for good (`ReleaseWatch`): the first of the frames
    # without contact on the side that held on longer; poses from then on hold the pose before it. None: held on
    frames_after_release: int = 0  # tactile frames after the (last) release, not tracked
    let_go: list[LetGo] = field(default_factory=list)  # one gel let go while the other held, in time order
    regrasps: list[Regrasp] = field(default_factory=list)  # new touches after a release, each tracked to its own
    # release (`released_s` is the first grasp's); poses between a release and the next touch hold the last pose
    regrasps_refused: list[str] = field(default_factory=list)  # new touches whose pose estimate was refused, why

    def grasps(self) -> list[tuple[Touch, float | None]]:
        """Each grasp's touch and release time (None: held to the end): the touch's, then each regrasp's."""
        return [(self.touch, self.released_s)] + [(regrasp.touch, regrasp.released_s) for regrasp in self.regrasps]

    def grasp_rows(self, index: int) -> np.ndarray:
        """(M,) bool: the output times of grasp `index` (`grasps`), its touch to its release."""
        touch, released = self.grasps()[index]
        rows = self.timestamps_s >= touch.time_s - 1e-9 if index else np.ones(len(self.timestamps_s), dtype=bool)
        return rows if released is None else rows & (self.timestamps_s < released)

    @property
    def grasped(self) -> np.ndarray:
        """(M,) bool: the output times while the object was held, from a touch to its release."""
        if self.released_s is None:
            return np.ones(len(self.timestamps_s), dtype=bool)
        return np.any([self.grasp_rows(index) for index in range(1 + len(self.regrasps))], axis=0)

    def T_world_mesh(self, model: ObjectModel, open_loop: bool = False) -> np.ndarray:
        """The tracked poses in the mesh file's frame."""
        poses = self.T_world_object_open_loop if open_loop else self.T_world_object
        return poses @ model.T_object_mesh

    def correction_summary(self) -> dict[str, Any]:
        """Counts of used and unusable frames, and the speed of the closed loop."""
        reasons: dict[str, int] = {}
        for correction in self.corrections:
            for reason in correction.unusable.values():
                key = reason.split(" (")[0]
                reasons[key] = reasons.get(key, 0) + 1
        latency = np.array([c.latency_ms for c in self.corrections]) if self.corrections else np.zeros(1)
        frames = sum(len(c.used) + len(c.unusable) for c in self.corrections)
        median = float(np.median(latency))
        return {
            "instants": len(self.corrections),
            "frames": frames,
            "frames_used": sum(len(c.used) for c in self.corrections),
            "guard_checks": sum(bool(c.guard) for c in self.corrections),
            "reanchored": sum(c.guard == "re-anchored" for c in self.corrections),
            "unusable": reasons,
            "latency_median_ms": median,
            "latency_p90_ms": float(np.percentile(latency, 90)),
            "latency_max_ms": float(latency.max()),
            "instants_per_s": 1000.0 / median if median > 0 else float("inf"),
            "frames_per_s": 1000.0 * frames / max(float(latency.sum()), 1e-9),
            "released_s": self.released_s,
            "frames_after_release": self.frames_after_release,
        }


# ------------------------------------------------------------------------------------------------ tracking
def _output_times(streams: dict[str, PoseStream], touch_time_s: float) -> np.ndarray:
    times = np.union1d(streams["left"].timestamps_s, streams["right"].timestamps_s)
    return times[times >= touch_time_s - 1e-9]


def track(
    touch: Touch,
    streams: dict[str, PoseStream],
    model: ObjectModel | None = None,
    tactile: dict[str, TactileStream] | None = None,
    config: TrackConfig = TrackConfig(),
    new_touch: NewTouchEstimator | None = None,
) -> TrackResult:
    """Track the object from the touch on: open loop from the streams, corrected by tactile frames when given.

    `streams`: side -> `T_world_sensor` stream. `tactile`: side -> that sensor's frames (either side may be
    absent); the closed loop needs the object `model`. Returns poses at every stream timestamp from the touch on.
    With frames of both sides, a side that lets go leaves the other to carry the object, and a release of both ends
    the grasp; given `new_touch` (the pose stage on a contact pair), both gels touching again after a release make a
    new touch (`Regrasp`) tracked on from its estimate; without it the track ends at the first release.
    """
    times = _output_times(streams, touch.time_s)
    if len(times) == 0:
        raise InputError(f"the sensor streams end before the touch at {touch.time_s:.6f} s")
    jitter = {side: stream_jitter(streams[side], config.fusion) for side in SIDES}
    streams = {side: smooth_stream(streams[side], jitter[side], config.fusion) for side in SIDES}
    sensors = sensor_poses(streams, times, config.fusion, jitter)
    keep = sensors.any_covered
    if not keep.any():
        raise InputError(f"no stream timestamp from the touch at {touch.time_s:.6f} s on has a pose of either sensor")
    sensors = sensors.select(keep)
    open_loop, weights = fuse_object_poses(sensors, touch.T_sensor_object)
    result = TrackResult(
        timestamps_s=sensors.timestamps_s,
        T_world_object=open_loop,
        T_world_object_open_loop=open_loop,
        sensor_weights=weights,
        touch=touch,
        jitter=sensors.jitter,
        closed_loop=bool(tactile),
        skipped_times=int((~keep).sum()),
    )
    if not tactile:
        return result
    if model is None:
        raise ValueError("the closed loop registers tactile frames on the object: pass its model")
    times = sensors.timestamps_s
    corrector = first = _Corrector(model, touch, streams, sensors.jitter, config)
    instants = group_frames(tactile, touch.time_s, config.correction.sync_tolerance_s)
    starts = np.searchsorted(times, [instant_time for instant_time, _ in instants], side="left")
    closed = np.empty_like(open_loop)
    open_loop, weights = open_loop.copy(), weights.copy()
    begin = 0  # the first output row not yet written
    grasp_let_go: list[list[LetGo]] = [[]]  # each grasp's sides that let go on their own
    searching: _NewTouchSearch | None = None  # after a release, with `new_touch`: waiting for both gels again
    # Each instant's products are small (a few hundred points, the sliding map's few hundred nodes): on a busy
    # 2-core machine two BLAS threads waiting for each other made the closed loop 10-40x slower.
    release = ReleaseWatch(config.correction, tuple(tactile))
    with one_blas_thread():
        for number, ((instant_time, frames), start) in enumerate(zip(instants, starts, strict=True)):
            instant_frames = {side: (tactile[side], i) for side, i in frames}
            if searching is not None:
                regrasp = searching.saw(instant_time, instant_frames, closed[begin - 1])
                if regrasp is None:
                    continue
                result.regrasps.append(regrasp)
                result.regrasps_refused += searching.refused
                result.frames_after_release = 0
                begin = int(np.searchsorted(times, regrasp.touch.time_s - 1e-9))
                if begin >= len(times):
                    break
                corrector = _Corrector(model, regrasp.touch, streams, sensors.jitter, config)
                open_loop[begin:], weights[begin:] = fuse_object_poses(
                    sensors, regrasp.touch.T_sensor_object, slice(begin, None)
                )
                release, searching = ReleaseWatch(config.correction, tuple(tactile)), None
                grasp_let_go.append([])
                continue
            if start > begin:  # the outputs before this instant follow the grasps as they were
                closed[begin:start] = corrector.fuse(sensors, slice(begin, start))
                begin = start
            record = corrector.correct(instant_time, instant_frames)
            result.corrections.append(record)
            for side, stamp in corrector.touched_again:  # a side that let go touches again
                event = next(e for e in reversed(grasp_let_go[-1]) if e.side == side)
                event.touched_again_s = stamp
            corrector.touched_again.clear()
            stamps = {side: float(tactile[side].timestamps_s[i]) for side, i in frames}
            released_s = release.saw(record, stamps)
            for event in release.let_go(stamps):  # the outputs since its first frame without contact: the other
                corrector.let_go(event.side)  # side alone
                grasp_let_go[-1].append(event)
                since = int(np.searchsorted(times, event.time_s - 1e-9))
                if since < begin:
                    closed[since:begin] = corrector.fuse(sensors, slice(since, begin))
            if released_s is None:
                continue
            # let go: nothing moves the object with the sensors any more; the outputs from then on hold the last
            # pose before it (until a new touch)
            held = max(int(np.searchsorted(times, released_s - 1e-9)), 1)
            if held > begin:
                closed[begin:held] = corrector.fuse(sensors, slice(begin, held))
            closed[held:] = closed[held - 1]
            begin = held
            if result.regrasps:
                result.regrasps[-1].released_s = released_s
            else:
                result.released_s = released_s
            result.frames_after_release = sum(len(later) for _, later in instants[number + 1 :])
            if new_touch is None:
                break
            searching = _NewTouchSearch(new_touch, config, streams, sensors.jitter)
        else:
            if begin < len(closed) and searching is None:
                closed[begin:] = corrector.fuse(sensors, slice(begin, None))
        if searching is not None:
            result.regrasps_refused += searching.refused
    result.let_go = [event for events in grasp_let_go for event in events]
    touches = [grasp_touch for grasp_touch, _ in result.grasps()]
    grasp_starts = np.searchsorted(times, [grasp_touch.time_s - 1e-9 for grasp_touch in touches] + [np.inf])
    for index, events in enumerate(grasp_let_go):  # the open loop carried by the sides that hold, grasp by grasp
        if events:
            rows = slice(int(grasp_starts[index]), int(grasp_starts[index + 1]))
            open_loop[rows], weights[rows] = open_loop_poses(sensors, touches[index].T_sensor_object, events, rows)
    result.T_world_object = closed
    result.T_world_object_open_loop, result.sensor_weights = open_loop, weights
    result.pad_errors = corrector.pads
    if first.pair_instants:
        result.pinning = Pinning.of(first.pair_shared / first.pair_instants, first.unit)
    return result


class _NewTouchSearch:
    """After a release: waits for both gels to touch again (`regrasp_frames` instants in a row with contact on both,
    each pressed deeper than a kiss) and estimates the object's pose from that pair; where the estimate is ambiguous,
    takes the hypothesis nearest the last tracked pose. Keeps why estimates were refused."""

    def __init__(
        self,
        estimate: NewTouchEstimator,
        config: TrackConfig,
        streams: dict[str, PoseStream],
        jitter: dict[str, StreamJitter],
    ):
        self.estimate, self.config, self.streams, self.jitter = estimate, config, streams, jitter
        self.run = 0  # instants in a row with both gels touching
        self.refused: list[str] = []

    def saw(
        self, instant_s: float, frames: dict[str, tuple[TactileStream, int]], last_pose: np.ndarray
    ) -> Regrasp | None:
        """Take one instant; the new touch when it makes one."""
        if len(frames) < len(SIDES) or len(self.refused) >= self.config.correction.regrasp_attempts:
            return None  # a lone frame neither counts nor breaks the run
        clouds = {}
        for side, (stream, index) in frames.items():
            try:
                points = np.asarray(stream.load(index), dtype=np.float64).reshape(-1, 3)
            except InputError:
                return None
            points = felt_contact(points[np.isfinite(points).all(axis=1)])  # none where the gel only kisses
            if len(points) < MIN_TACTILE_POINTS:
                self.run = 0
                return None
            clouds[side] = (float(stream.timestamps_s[index]), points)
        self.run += 1
        if self.run < self.config.correction.regrasp_frames:
            return None
        stamps = np.array([stamp for stamp, _ in clouds.values()])
        sensors = sensor_poses(self.streams, stamps, self.config.fusion, self.jitter)
        if not all(sensors.covered[side][row] for row, side in enumerate(clouds)):
            return None
        T_world_sensor = {side: sensors.T_world_sensor[side][row] for row, side in enumerate(clouds)}
        left, right = (TactileContact(clouds[side][1], T_world_sensor[side]) for side in SIDES)
        pair = ContactPair("", left, right)
        try:
            estimate = self.estimate(pair)
        except YotoError as exc:
            self.refused.append(f"{instant_s:.3f} s: {exc}")
            self.run = 0
            return None
        hypotheses = np.asarray(estimate.hypotheses.T_world_object) if estimate.ambiguous else None
        chosen = 0
        if hypotheses is not None and len(hypotheses) > 1:
            angles = np.linalg.norm(so3_log(np.einsum("ji,njk->nik", last_pose[:3, :3], hypotheses[:, :3, :3])), axis=1)
            offsets = np.linalg.norm(hypotheses[:, :3, 3] - last_pose[:3, 3], axis=1)
            chosen = int(np.argmin(offsets + TOUCH_MATCH_ROTATION_M_PER_RAD * angles))
        T_world_object = hypotheses[chosen] if hypotheses is not None else np.asarray(estimate.T_world_object)
        grasps = {side: invert_transform(T_world_sensor[side]) @ T_world_object for side in SIDES}
        touch = Touch(instant_s, T_world_object, grasps, "both gels touching again after a release")
        return Regrasp(
            touch,
            f"yoto pose ({estimate.method}), confidence {estimate.confidence:.2f}",
            float(estimate.confidence),
            bool(estimate.ambiguous),
            chosen,
        )


class ReleaseWatch:
    """Sees the object let go: after a frame with contact, both sensors' frames show none ("too few points": the
    gel flat) for at least `release_frames` frames each and `release_s` from each side's first such frame. One side
    alone without contact as long, while the other's latest frame touches, let go on its own (`let_go`): the other
    holds the object. A side lifting off for less, or both for a moment, is neither (the closed loop keeps its
    prediction through it). A frame that could not be read neither counts nor breaks a stretch; any other (used, or
    left out as a bad fit or a shallow read) shows contact. Needs frames of both sensors: without one side's,
    nothing says that side let go."""

    def __init__(self, config: CorrectionConfig, sides: tuple[str, ...]):
        self.frames, self.span_s = config.release_frames, config.release_s
        self.watching = config.release_frames > 0 and set(sides) >= set(SIDES)
        self.touched = False  # a frame with contact seen since the touch
        self.lost: dict[str, list[float]] = {side: [] for side in SIDES}  # side -> its frames without contact since
        # its last frame with contact
        self.gone: set[str] = set()  # the sides that let go on their own and have not touched again
        self.released_s: float | None = None

    def _long(self, lost: list[float]) -> bool:
        return len(lost) >= self.frames and lost[-1] - lost[0] >= self.span_s - 1e-9

    def saw(self, record: Correction, stamps: dict[str, float]) -> float | None:
        """Take one instant (its record, each side's frame time); the release time once it is seen, else None."""
        if not self.watching:
            return None
        for side, stamp in stamps.items():
            reason = record.unusable.get(side, "")
            if reason.startswith("too few points"):
                if self.touched:
                    self.lost[side].append(stamp)
            elif not reason.startswith("unreadable"):  # the gel felt the object (whether or not it was used)
                self.touched = True
                self.lost[side].clear()
                self.gone.discard(side)
        if all(self._long(lost) for lost in self.lost.values()):
            self.released_s = max(lost[0] for lost in self.lost.values())
        return self.released_s

    def let_go(self, stamps: dict[str, float]) -> list[LetGo]:
        """After `saw`: the sides that have just let go on their own (the other side's latest frame touching)."""
        if not self.watching or self.released_s is not None:
            return []
        out = []
        for side, other in (SIDES, SIDES[::-1]):
            lost = self.lost[side]
            if side not in self.gone and not self.lost[other] and self._long(lost):
                self.gone.add(side)
                out.append(LetGo(side, lost[0], max(stamps.values())))
        return out


def tactile_timing_warnings(
    tactile: dict[str, TactileStream], streams: dict[str, PoseStream], touch_time_s: float, tolerance_s: float = 0.2
) -> list[str]:
    """Warnings for tactile frames whose times do not fit the pose streams, each naming its source: frames
    outside the sensor's pose stream (no pose to register them at), or ending well before it while starting before
    the touch, which is what a clock offset between the tactile and the pose recordings looks like; the frames still
    fit the surface at the wrong sensor poses, so the track would be silently worse. Frames before the touch are
    counted in such a warning (they are never used), but alone they are a camera that ran before the touch."""
    warnings = []
    for side, frames in tactile.items():
        if len(frames) == 0:
            continue
        source = str(frames.source) if frames.source is not None else frames.name or side
        poses = streams[side].timestamps_s
        first, last = float(frames.timestamps_s[0]), float(frames.timestamps_s[-1])
        problems = []
        outside = int(
            ((frames.timestamps_s < poses[0] - tolerance_s) | (frames.timestamps_s > poses[-1] + tolerance_s)).sum()
        )
        if outside:
            problems.append(f"{outside} beyond the {side} pose stream's {poses[0]:.3f}-{poses[-1]:.3f} s (not used)")
        if last < poses[-1] - tolerance_s and first < touch_time_s - tolerance_s:
            problems.append(f"the frames end {poses[-1] - last:.2f} s before the pose stream")
        early = int((frames.timestamps_s < touch_time_s - tolerance_s).sum())
        if early and problems:  # alone, frames before the touch are a camera that ran before it, not an offset
            problems.insert(0, f"{early} stamped up to {touch_time_s - first:.2f} s before the touch (not used)")
        if problems:
            warnings.append(
                f"{side} tactile frames ({source}, {first:.3f}-{last:.3f} s): " + "; ".join(problems) + ": is there a "
                "clock offset between the tactile and the pose recordings? Frames at the wrong times are registered "
                "at the wrong sensor poses"
            )
    return warnings


STAMP_RESOLUTION_S = 1e-5  # timestamps rounded to microseconds (file names) are this close to the true half period


def instant_window_s(tactile: dict[str, TactileStream], tolerance_s: float) -> float:
    """How far apart a left and a right frame may be to be registered together: `tolerance_s`, or half the slower
    gel's frame period (median) where that is longer. Two cameras out of phase, or slower than 25 fps, leave up to
    half a period between a frame and the other gel's nearest; a fixed window would then leave most frames alone,
    and a lone contact corrects only the directions it pins. Each frame is registered at its own time's sensor
    pose, so the pair's time difference costs only the slip between the two (2 mm per 100 mm of travel: a few
    hundredths of a millimetre over 1/30 s at 50 mm/s)."""
    periods = [float(np.median(np.diff(stream.timestamps_s))) for stream in tactile.values() if len(stream) > 1]
    return max(tolerance_s, 0.5 * max(periods, default=0.0) + STAMP_RESOLUTION_S)


def group_frames(
    tactile: dict[str, TactileStream], start_s: float, tolerance_s: float
) -> list[tuple[float, list[tuple[str, int]]]]:
    """Tactile instants from the touch on: each left frame with the nearest right frame within `tolerance_s`, or
    half the slower gel's frame period where that is longer (`instant_window_s`), not already taken; the rest
    alone. Returns (instant time = its latest frame's, [(side, frame index)]) by time."""
    tolerance_s = instant_window_s(tactile, tolerance_s)
    stamps = {side: tactile[side].timestamps_s if side in tactile else np.empty(0) for side in SIDES}
    right = stamps["right"]
    taken = right < start_s - 1e-6  # frames before the touch are never used
    instants: list[tuple[float, list[tuple[str, int]]]] = []
    for i, t_left in enumerate(stamps["left"]):
        if t_left < start_s - 1e-6:
            continue
        frames = [("left", i)]
        latest = float(t_left)
        after = int(np.searchsorted(right, t_left))
        nearby = [j for j in (after - 1, after) if 0 <= j < len(right) and not taken[j]]
        if nearby:
            j = min(nearby, key=lambda j: abs(right[j] - t_left))
            if abs(right[j] - t_left) <= tolerance_s:
                taken[j] = True
                frames.append(("right", j))
                latest = max(latest, float(right[j]))
        instants.append((latest, frames))
    instants += [(float(right[j]), [("right", int(j))]) for j in np.flatnonzero(~taken)]
    instants.sort(key=lambda item: item[0])
    return instants


def contact_samples(points_sensor: np.ndarray, config: CorrectionConfig) -> np.ndarray:
    """A fixed, spatially even subset of a tactile cloud's firmly pressed points: the means of square bins over the
    pad (`voxel_m`, x and y only), those pressed at least `min_depth_fraction` of the deepest bin's depth, then at
    most `points_per_contact`.

    Binned and chosen so that a reconstruction's pixel noise leaves no pattern: 3-d voxels would split each column
    of the gel by its noisy depth (which points a voxel keeps shifts its mean), and choosing single points by their
    noisy depth keeps, along the chosen patch's edge, those whose noise made them deeper; both are errors fixed on
    the pad or the contact that move the registrations as the contact slides. Bins are chosen by their depth
    averaged with their neighbours'."""
    step = max(1, len(points_sensor) // (40 * config.points_per_contact))  # thin huge clouds before binning
    thinned = points_sensor[::step]
    cells = np.floor(thinned[:, :2] / config.voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    shape = tuple(cells.max(axis=0) + 1)
    counts = np.zeros(shape)
    sums = np.zeros(shape + (3,))
    np.add.at(counts, (cells[:, 0], cells[:, 1]), 1.0)
    np.add.at(sums, (cells[:, 0], cells[:, 1]), thinned)
    occupied = counts > 0
    means = sums[occupied] / counts[occupied, None]
    depth = ndimage.uniform_filter(sums[..., 2], 3, mode="constant") / np.maximum(
        ndimage.uniform_filter(counts, 3, mode="constant"), 1e-12
    )
    depth = depth[occupied]
    deepest = float(depth.min())
    points = means[depth <= config.min_depth_fraction * deepest] if deepest < 0 else means
    if len(points) < MIN_TACTILE_POINTS:  # a shallow, noisy frame: keep what there is
        points = means
    if len(points) > config.points_per_contact:
        points = points[np.random.default_rng(0).choice(len(points), config.points_per_contact, replace=False)]
    return points


def frame_indentation_m(points_sensor: np.ndarray) -> float:
    """How deep a tactile frame reads its press: its deepest points' depth (the 99th percentile, against pixel
    noise; the gel's rest surface is z = 0, pressed points lie below it)."""
    return max(float(np.percentile(-points_sensor[:, 2], 99.0)), 0.0)


def predicted_indentation_m(model: ObjectModel, T_object_sensor: np.ndarray) -> float:
    """How deep the object, placed at T_object_sensor, presses into the pad: the deepest of its surface points that
    face the sensor over the pad (sensor frame, below the gel's rest surface z = 0; negative: the gap to the pad);
    nan where no surface faces the pad."""
    half = np.array(MINI_PAD_M) / 2.0
    near = model.kdtree.query_ball_point(T_object_sensor[:3, 3], float(np.hypot(*half)))
    if not near:
        return float("nan")
    points = transform_points(invert_transform(T_object_sensor), model.points_object[near].astype(np.float64))
    facing = model.normals_object[near] @ T_object_sensor[:3, 2] < 0.0  # outward normal against the sensor's z
    over = facing & (np.abs(points[:, 0]) <= half[0]) & (np.abs(points[:, 1]) <= half[1])
    return float(-points[over, 2].min()) if over.any() else float("nan")


def registration_solver(config: CorrectionConfig) -> GaussNewtonConfig:
    """The Gauss-Newton settings with which the closed loop registers a tactile instant."""
    return GaussNewtonConfig(
        iterations=config.iterations,
        max_distance_m=config.max_distance_m,
        surface_noise_m=config.surface_noise_m,
        prior_rotation_rad=config.registration_prior_rotation_rad,
        prior_translation_m=config.registration_prior_translation_m,
        step_tolerance_m=config.step_tolerance_m,
        step_tolerance_rad=config.step_tolerance_rad,
    )


def pad_rest_solver(config: CorrectionConfig) -> GaussNewtonConfig:
    """The Gauss-Newton settings with which a sensor's frames at rest are registered before its pad's error is
    read off them (`PadError.settle`)."""
    return dataclasses.replace(
        registration_solver(config),
        prior_rotation_rad=config.pad_error.rest_fit_rotation_rad,
        prior_translation_m=config.pad_error.rest_fit_translation_m,
    )


def registration_prior(config: CorrectionConfig) -> np.ndarray:
    """(6, 6) the information of the registration's prior on the prediction: rotation (rad^-2), translation (m^-2)."""
    return np.diag([config.registration_prior_rotation_rad**-2] * 3 + [config.registration_prior_translation_m**-2] * 3)


def secant_scaling(
    surface: SurfaceCloud, normal: np.ndarray, points_object: np.ndarray, unit: np.ndarray, config: CorrectionConfig
) -> np.ndarray:
    """The map S (6, 6) that scales a registration's normal matrix N (of `points_object`, registered, object frame,
    rotation about the origin), as S N S^T, down along its `secant_directions` weakest directions (in `unit`s of
    each twist component) to the curvature the surface shows: the truncated sum of squared plane distances with
    every point matched afresh at +-`secant_step` along each direction, its second difference against the planes'
    prediction (step^2 times N there). The planes of the nearest surface samples predict a rise wherever they are
    tilted to the motion, also where the surface itself slides along (a scanned mug's wall under a spin about its
    axis); matched afresh, the points find the surface where it is. S is the identity where the check is off."""
    if config.secant_directions <= 0:
        return np.eye(6)
    values, vectors = np.linalg.eigh(normal * np.outer(unit, unit))
    reach = config.max_distance_m

    def cost(T_object_moved: np.ndarray) -> float:
        distance, matched, _, _ = plane_distances(surface, transform_points(T_object_moved, points_object), reach)
        return float(np.sum(np.where(matched, np.minimum(distance**2, reach**2), reach**2)))

    at_fit = cost(np.eye(4))
    shrink = np.eye(6)  # in units: I - sum (1 - sqrt(keep)) v v^T over the orthonormal directions v checked
    for value, vector in zip(values[: config.secant_directions], vectors.T[: config.secant_directions]):
        predicted = config.secant_step**2 * value
        if predicted <= 0.0:
            continue
        step = pose_from_twist(config.secant_step * vector * unit)
        rise = 0.5 * (cost(step) + cost(invert_transform(step))) - at_fit
        keep = min(max(rise / predicted, 0.0), 1.0)
        shrink -= (1.0 - np.sqrt(keep)) * np.outer(vector, vector)
    return (1.0 / unit)[:, None] * shrink * unit[None, :]


def contact_information(
    model: ObjectModel, points_object: dict[str, np.ndarray], config: CorrectionConfig, check_surface: bool = True
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per side, the Gauss-Newton normal matrices (6, 6) of its contact's registered points (object frame, rotation
    about the origin): for the noise new in every frame (all points, `pixel_noise_m`) and for the error the contact's
    points share (`bias_points` points of `bias_noise_m`: a reconstruction's smooth error), checked against the
    surface (`secant_scaling`, over all sides together) when `check_surface`."""
    normals, counts = {}, {}
    for side, side_points in points_object.items():
        _, matched, _, surface_normals = plane_distances(model, side_points, config.max_distance_m)
        jacobian = point_to_plane_jacobian(side_points, surface_normals)[matched]
        normals[side], counts[side] = jacobian.T @ jacobian, len(jacobian)
    unit = observable_unit(config)
    scaling = (
        secant_scaling(model, sum(normals.values()), np.vstack(list(points_object.values())), unit, config)
        if check_surface
        else np.eye(6)
    )
    information = {}
    for side, normal in normals.items():
        normal = scaling @ normal @ scaling.T
        bias_share = config.bias_points / max(counts[side], 1)
        information[side] = (normal / config.pixel_noise_m**2, normal * bias_share / config.bias_noise_m**2)
    return information


def observable_unit(config: CorrectionConfig) -> np.ndarray:
    """(6,) one observable unit of each twist component (rad, m): where rotation and translation meet."""
    return np.array([config.observable_rotation_rad] * 3 + [config.observable_translation_m] * 3)


@dataclass(frozen=True)
class Pinning:
    """How well the contacts' geometry pins each direction of the object's pose: the spread a reconstruction's
    smooth error (`CorrectionConfig.bias_points` points of `bias_noise_m` per contact) gives a registration along
    the eigen-directions of the contacts' shared information. A frame's error of that kind is fixed to the pad and
    changes as the contact slides, so along a direction it moves the fit by more than the drift target no
    registration can hold the object to the target, whatever the filter does: the slip there is not observable
    from contact geometry."""

    directions: np.ndarray  # (6, 6) rows: orthonormal directions in observable units (`observable_unit`), weakest
    # first
    spread: np.ndarray  # (6,) 1-sigma of the fit's offset along each direction, observable units
    unit: np.ndarray  # (6,) the observable unit (rad, m)

    @classmethod
    def of(cls, shared: np.ndarray, unit: np.ndarray) -> Pinning:
        """From the contacts' shared-error information (6, 6; rad, m), summed over the contacts."""
        values, vectors = np.linalg.eigh(shared * np.outer(unit, unit))
        spread = 1.0 / np.sqrt(np.maximum(values, 1e-12))
        return cls(vectors.T, spread, unit)

    def twist(self, index: int) -> np.ndarray:
        """(6,) direction `index` as a twist (rad, m) of unit size in observable units."""
        return self.directions[index] * self.unit

    def split(self, twist: np.ndarray, weak_above: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """A twist (rad, m) as (pinned part, weakly pinned part): its components along the directions whose spread is
        at most / more than `weak_above` observable units (orthogonal in those units)."""
        weak = self.directions[self.spread > weak_above]
        along = (weak.T @ (weak @ (twist / self.unit))) * self.unit
        return twist - along, along

    def describe(self, index: int = 0) -> str:
        """Direction `index` (default the weakest) in words: its turn and shift per observable unit, and its spread."""
        twist = self.twist(index)
        turn, shift = np.degrees(twist[:3]), 1e3 * twist[3:]
        return (
            f"turn ({turn[0]:+.2f}, {turn[1]:+.2f}, {turn[2]:+.2f}) deg with shift ({shift[0]:+.2f}, {shift[1]:+.2f}, "
            f"{shift[2]:+.2f}) mm (object frame, about the centroid), pinned to {self.spread[index]:.2f} of that"
        )


@dataclass(frozen=True)
class Retouch:
    """Where on the object a contact would see one direction of the pose (`retouch`): a contact pins a direction by
    how far that motion moves the surface under it along the surface's normal (sliding along itself, the surface
    shows nothing)."""

    point: np.ndarray  # (3,) the surface sample whose patch sees the direction most (the surface's frame: the
    # canonical object frame for a model; `in_frame` maps it)
    normal: np.ndarray  # (3,) its outward normal: a sensor would press there along -normal
    seen_m: float  # root mean square over that patch of the surface's motion along its normal per observable unit
    seen_at_contacts_m: float  # the same over the touch's contact points: information grows with its square

    def in_frame(self, T_frame_surface: np.ndarray) -> Retouch:
        """The same advice with its point and normal mapped by `T_frame_surface` (e.g. `T_mesh_object`)."""
        point = transform_points(T_frame_surface, self.point[None])[0]
        return dataclasses.replace(self, point=point, normal=T_frame_surface[:3, :3] @ self.normal)

    def describe(self) -> str:
        """In words (millimetres)."""
        point, normal = 1e3 * self.point, self.normal
        return (
            f"a contact at ({point[0]:+.1f}, {point[1]:+.1f}, {point[2]:+.1f}) mm, surface normal ({normal[0]:+.2f}, "
            f"{normal[1]:+.2f}, {normal[2]:+.2f}), would see it move the surface {1e3 * self.seen_m:.3f} mm along "
            f"its normal per unit, the touch's contacts {1e3 * self.seen_at_contacts_m:.3f} mm"
        )


def retouch(
    surface: SurfaceCloud,
    twist: np.ndarray,
    contacts_object: np.ndarray,
    patch_points: int = 64,
    candidates: int = 3000,
) -> Retouch:
    """Where a contact would pin the direction `twist` (rad, m; object frame about its origin, e.g.
    `Pinning.twist(0)`, the weakest): each surface sample moves by w x p + v under it, and a contact there sees the
    part along the surface's normal. Over patches of `patch_points` nearest samples (about a contact's size on a
    model's parent cloud) around `candidates` evenly taken samples, the patch where that motion's root mean square
    is largest, against the same over `contacts_object` (the touch's contact points, object frame). On a surface of
    revolution spun about its axis, or a cylinder slid along it, no patch sees the motion: no re-touch pins it."""
    points = np.asarray(surface.points_object, dtype=np.float64)
    normals = np.asarray(surface.normals_object, dtype=np.float64)

    def seen(where: np.ndarray, normal: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", normal, np.cross(twist[:3], where) + twist[3:])

    along = seen(points, normals)
    picked = np.arange(0, len(points), max(1, len(points) // candidates))
    tree = surface.kdtree if isinstance(surface.kdtree, cKDTree) else cKDTree(points)  # a model's, built already
    _, patches = tree.query(points[picked], k=min(patch_points, len(points)))
    patch_rms = np.sqrt(np.mean(along[patches.reshape(len(picked), -1)] ** 2, axis=1))
    best = picked[int(np.argmax(patch_rms))]
    _, nearest = tree.query(np.asarray(contacts_object, dtype=np.float64))
    return Retouch(
        points[best],
        normals[best],
        float(patch_rms.max()),
        float(np.sqrt(np.mean(seen(points[nearest], normals[nearest]) ** 2))),
    )


def touch_pinning(
    model: ObjectModel, pair: ContactPair, T_world_object: np.ndarray, config: CorrectionConfig = CorrectionConfig()
) -> Pinning:
    """How well the touch's two contacts pin the object at `T_world_object` (canonical frame): their clouds sampled
    as the closed loop samples its frames (`contact_samples`), placed on the object through the pair's sensor
    poses, their shared-error information checked against the surface."""
    points = {
        side: transform_points(
            invert_transform(T_world_object) @ pair.contact(side).T_world_sensor,
            contact_samples(pair.contact(side).points_sensor, config),
        )
        for side in SIDES
    }
    shared = np.sum([bias for _, bias in contact_information(model, points, config).values()], axis=0)
    return Pinning.of(shared, observable_unit(config))


def fuse_holding(
    sensors: SensorPoses, grasps: dict[str, np.ndarray], holding: set[str], rows: np.ndarray | slice = slice(None)
) -> tuple[np.ndarray, np.ndarray]:
    """`fuse_object_poses` (poses and sensor weights at the chosen rows) from the sensors that hold the object: a
    side that let go carries it no more, as if its stream had no pose there."""
    if len(holding) < len(SIDES):
        covered = {side: sensors.covered[side] & (side in holding) for side in SIDES}
        sensors = dataclasses.replace(sensors, covered=covered)
    return fuse_object_poses(sensors, grasps, rows)


def open_loop_poses(
    sensors: SensorPoses, T_sensor_object: dict[str, np.ndarray], let_go: list[LetGo], rows: slice
) -> tuple[np.ndarray, np.ndarray]:
    """The open loop (K, 4, 4) over `rows` from one touch's grasps where sides let go (`LetGo`, in time order), and
    the sensors' weights (K, 2): from each side's `time_s` the other alone, and from its `touched_again_s` its grasp
    the fused pose then in its live sensor pose."""
    times = sensors.timestamps_s
    first, last = rows.start or 0, len(times) if rows.stop is None else rows.stop
    changes = sorted(
        [(event.time_s, 0, event.side) for event in let_go]
        + [(event.touched_again_s, 1, event.side) for event in let_go if event.touched_again_s is not None]
    )
    grasps, holding = dict(T_sensor_object), set(SIDES)
    poses, weights = np.empty((last - first, 4, 4)), np.empty((last - first, len(SIDES)))
    row = first
    for time_s, again, side in changes + [(np.inf, 0, "")]:
        upto = int(np.clip(np.searchsorted(times, time_s - 1e-9), row, last))
        if upto > row:
            poses[row - first : upto - first], weights[row - first : upto - first] = fuse_holding(
                sensors, grasps, holding, slice(row, upto)
            )
        row = upto
        if not side:
            break
        if not again:
            holding.discard(side)
        elif row < last:
            now = fuse_holding(sensors, grasps, holding, slice(row, row + 1))[0][0]
            grasps[side] = invert_transform(sensors.T_world_sensor[side][row]) @ now
            holding.add(side)
    return poses, weights


class _Corrector:
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
        self.open_grasps = dict(touch.T_sensor_object)  # the open loop's grasps (the divergence guard's anchor)
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
        self.guard_wait = 0  # instants until the divergence guard may check again
        self.pair_shared, self.pair_instants = np.zeros((6, 6)), 0  # the shared-error information summed over the
        # applied two-contact instants, and their count (`TrackResult.pinning`)
        self.unpinned: np.ndarray | None = None  # (K, 6) orthonormal directions (observable units) the guard found
        # the frames leave free: the departures it undid; the prediction stands along them from then on
        self.gone: set[str] = set()  # the sides that let go (`ReleaseWatch.let_go`): their grasps carry nothing ...
        self.lifted: set[str] = set()  # ... and those without contact whose sensor left the object (`lifted_apart_m`):
        # while the other touches, it alone predicts the pose (a side letting go, its sensor withdrawing)
        self.touched_again: list[tuple[str, float]] = []  # (side, its frame's time) of each let-go side touching again

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

    def _slip_beyond_model(self) -> bool:
        """Whether the tracked slip since the touch (closed loop against open loop, object frame) lies beyond what
        the slip model allows over the travel so far: a rate drawn from its prior and wandering as it may, the
        elastic wander, and the touch's own uncertainty."""
        c = self.config.correction
        slip = twist_of_pose(self._slip())
        travel, share = self.travel_m, self.travel_m / c.slip_travel_m
        spread = travel**2 + travel**3 / (3.0 * c.slip_travel_m)  # a constant rate and its random walk
        variance = np.array(
            [c.slip_rate_rotation**2 * spread + c.slip_wander_rotation_rad**2 * share + c.touch_rotation_rad**2] * 3
            + [c.slip_rate_translation**2 * spread + c.slip_wander_translation_m**2 * share + c.touch_translation_m**2]
            * 3
        )
        return float(np.sum(slip**2 / variance)) > c.guard_bound

    def _guard(
        self,
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
        Returns "" (no check), "kept" or "re-anchored"."""
        c = self.config.correction
        if self.guard_wait > 0:
            self.guard_wait -= 1
            return ""
        if not self._slip_beyond_model():
            return ""
        self.guard_wait = c.guard_every
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

    def let_go(self, side: str) -> None:
        """`side` let go: from now on the other side's grasp alone carries the object (its own grasp still follows
        the corrections, unused, until it touches again)."""
        self.gone.add(side)

    def _apart(self, side: str, sensors: SensorPoses) -> bool:
        """Whether `side`'s grasp puts the object more than `lifted_apart_m` from where the other side's puts it, at
        the instant (the last row of `sensors`; False where either sensor has no pose then)."""
        other = SIDES[1 - SIDES.index(side)]
        if other in self.gone or not (sensors.covered[side][-1] and sensors.covered[other][-1]):
            return False
        here = sensors.T_world_sensor[side][-1] @ self.grasps[side]
        there = sensors.T_world_sensor[other][-1] @ self.grasps[other]
        apart = np.linalg.norm(here[:3, 3] - there[:3, 3]) + TOUCH_MATCH_ROTATION_M_PER_RAD * rotation_angle_rad(
            here, there
        )
        return bool(apart > self.config.correction.lifted_apart_m)

    def _touch_again(self, side: str, row: int, sensors: SensorPoses, stamp: float) -> None:
        """A side that had let go touches again: its grasps (closed and open loop) are the object's pose now, from
        the side that held on, in the side's live sensor pose; what its pad read at rest no longer applies."""
        T_sensor_world = invert_transform(sensors.T_world_sensor[side][row])
        self.grasps[side] = T_sensor_world @ self.fuse(sensors, slice(row, row + 1))[0]
        open_now = fuse_holding(sensors, self.open_grasps, self.holding, slice(row, row + 1))[0][0]
        self.open_grasps[side] = T_sensor_world @ open_now
        self.gone.discard(side)
        self.touch_press[side] = predicted_indentation_m(self.model, invert_transform(self.grasps[side]))
        self.rest_read.pop(side, None)
        self.touched_again.append((side, stamp))

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

    def _information(self, points_object: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each contact's information (`contact_information`), the surface check where more than
        `observable_max_contacts` contacts register together."""
        check = len(points_object) > self.config.correction.observable_max_contacts
        return contact_information(self.model, points_object, self.config.correction, check)

    def _register(
        self, points: dict[str, np.ndarray], sensors: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, dict[str, float]]:
        """The correction T_object_predicted bringing the sides' points (predicted object frame) onto the surface,
        and each side's inlier fraction after it. `sensors`: each side's T_predicted_sensor; its points match only
        surface facing that sensor (the other face of a thin wall, 1 mm behind the contact on a mug, is not theirs)."""
        c = self.config.correction
        stacked = np.vstack(list(points.values()))
        # The surface's outward normal at a contact is against the sensor's z (which points into the object).
        facing = np.vstack([np.broadcast_to(-sensors[side][:3, 2], (len(p), 3)) for side, p in points.items()])
        correction = point_to_plane_gauss_newton(
            self.model, stacked, np.eye(4)[None], self.solver, facing_source=facing
        )[0]
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
                refused = self._update(points_predicted, pose_noise, correction)
                for side in points_predicted if refused else ():
                    unusable[side] = refused
                if not refused:
                    record.used = tuple(points_predicted)
                    record.inlier_fraction = float(np.mean(list(fractions.values())))
                    record.correction_m, record.correction_rad = self.last_correction
                    error = self.covariance[:6, :6]
                    record.sigma_rad = float(np.sqrt(np.linalg.eigvalsh(error[:3, :3])[-1]))
                    record.sigma_m = float(np.sqrt(np.linalg.eigvalsh(error[3:, 3:])[-1]))
                    record.guard = self._guard(
                        sensors, rows, {side: points_sensor[side] for side in record.used}, fractions
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
        self, points_predicted: dict[str, np.ndarray], pose_noise: dict[str, np.ndarray], correction: np.ndarray
    ) -> str:
        """Kalman update with the registration's twist z = error + bias + noise (information form), then the new
        grasps, slip rate and bias. Each contact's information is discounted by its sensor's pose jitter,
        (H^-1 + S)^-1 = H (I + S H)^-1. Returns why the correction was refused (a jump larger than slip makes),
        or "" when it was applied."""
        c = self.config.correction
        twist = twist_of_pose(correction)
        white, shared = np.zeros((6, 6)), np.zeros((6, 6))
        registered = {side: transform_points(correction, side_points) for side, side_points in points_predicted.items()}
        for side, (per_frame, bias) in self._information(registered).items():
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
