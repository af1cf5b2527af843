"""Tracking after one touch: open loop from the live sensor poses (paper Sec. 4.3), closed loop from the gel.

**Open loop.** The touch's pose estimate fixes the object in each sensor's frame, its grasp
`T_sensor_object = T_world_sensor^-1 @ T_world_object` (sensor poses as the contact pair gives them). At every later
time each live sensor pose gives `T_world_sensor(t) @ T_sensor_object`; the two are averaged (`fusion.py`).

**Closed loop** (`correction.py`): each new tactile frame, registered on the object's surface, corrects the pose
through a small Kalman filter on the object-frame error, slip rate and measurement bias; frames of both sensors
taken at about the same time are registered together (`group_frames` pairs them here). **Release and regrasp**
(`release.py`): both gels without contact end the grasp, one alone leaves the other to carry the object, and both
touching again make a new touch.

This module holds the driver: `track` (the open loop, then each tactile instant through the closed loop, release and
regrasp), its `TrackResult`, the pairing of frames into instants (`group_frames`, `instant_window_s`) and the check
of the frames' times against the pose streams (`tactile_timing_warnings`). The other parts: `config.py`
(`TrackConfig`, `CorrectionConfig`), `touch.py` (`Touch`, the touch's time), `frame_registration.py` (a frame's
samples, its registration's settings and information), `pinning.py` (`Pinning`, `retouch`), `correction.py`,
`release.py`; the names other code imported from this module before it was split are importable from here still.

Frames: YOTO's canonical `object` frame inside (origin at the centroid: corrections rotate about it); results
convert to the mesh file's frame with `T_world_mesh = T_world_object @ T_object_mesh`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from yoto.contacts import SIDES
from yoto.errors import InputError
from yoto.objects.model import ObjectModel
from yoto.registration import one_blas_thread
from yoto.tracking.config import CorrectionConfig, TrackConfig
from yoto.tracking.correction import ClosedLoop, Correction
from yoto.tracking.frame_registration import (
    contact_information,
    contact_samples,
    observable_unit,
    pad_rest_solver,
    registration_solver,
    secant_scaling,
)
from yoto.tracking.fusion import StreamJitter, fuse_object_poses, sensor_poses, smooth_stream, stream_jitter
from yoto.tracking.pad_error import PadError
from yoto.tracking.pinning import Pinning, Retouch, retouch, touch_pinning
from yoto.tracking.release import LetGo, NewTouchEstimator, NewTouchSearch, Regrasp, ReleaseWatch, open_loop_poses
from yoto.tracking.streams import TactileStream
from yoto.tracking.touch import Touch, find_touch_time, touch_from_pair, touch_time_of
from yoto.trajectory import PoseStream


# ------------------------------------------------------------------------------------------------ results
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
            "held": sum(c.held for c in self.corrections),
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
    corrector = ClosedLoop(model, touch, streams, sensors.jitter, config)
    correctors = [corrector]  # each grasp's closed loop
    instants = group_frames(tactile, touch.time_s, config.correction.sync_tolerance_s)
    starts = np.searchsorted(times, [instant_time for instant_time, _ in instants], side="left")
    closed = np.empty_like(open_loop)
    open_loop, weights = open_loop.copy(), weights.copy()
    begin = 0  # the first output row not yet written
    grasp_let_go: list[list[LetGo]] = [[]]  # each grasp's sides that let go on their own
    searching: NewTouchSearch | None = None  # after a release, with `new_touch`: waiting for both gels again
    # Each instant's products are small (a few hundred points, the sliding map's few hundred nodes): on a busy
    # 2-core machine two BLAS threads waiting for each other made the closed loop 10-40x slower.
    release = ReleaseWatch(config.release, tuple(tactile))
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
                corrector = ClosedLoop(model, regrasp.touch, streams, sensors.jitter, config)
                correctors.append(corrector)
                open_loop[begin:], weights[begin:] = fuse_object_poses(
                    sensors, regrasp.touch.T_sensor_object, slice(begin, None)
                )
                release, searching = ReleaseWatch(config.release, tuple(tactile)), None
                grasp_let_go.append([])
                continue
            if start > begin:  # the outputs before this instant follow the grasps as they were
                closed[begin:start] = corrector.fuse(sensors, slice(begin, start))
                begin = start
            changes_before = len(corrector.open_changes)
            record = corrector.correct(instant_time, instant_frames)
            result.corrections.append(record)
            for change in corrector.open_changes[changes_before:]:  # a side that let go touching again
                if change.T_sensor_object is not None:
                    event = next(e for e in reversed(grasp_let_go[-1]) if e.side == change.side)
                    event.touched_again_s = change.time_s
            stamps = {side: float(tactile[side].timestamps_s[i]) for side, i in frames}
            released_s = release.saw(record, stamps)
            for event in release.let_go(stamps):  # the outputs since its first frame without contact: the other
                corrector.let_go(event.side, event.time_s)  # side alone
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
            searching = NewTouchSearch(new_touch, config, streams, sensors.jitter)
        else:
            if begin < len(closed) and searching is None:
                closed[begin:] = corrector.fuse(sensors, slice(begin, None))
        if searching is not None:
            result.regrasps_refused += searching.refused
    result.let_go = [event for events in grasp_let_go for event in events]
    touches = [grasp_touch for grasp_touch, _ in result.grasps()]
    grasp_starts = np.searchsorted(times, [grasp_touch.time_s - 1e-9 for grasp_touch in touches] + [np.inf])
    for index, grasp_loop in enumerate(correctors):  # the open loop carried by the sides that hold, grasp by grasp
        if grasp_loop.open_changes:
            rows = slice(int(grasp_starts[index]), int(grasp_starts[index + 1]))
            changes = grasp_loop.open_changes
            open_loop[rows], weights[rows] = open_loop_poses(sensors, touches[index].T_sensor_object, changes, rows)
    result.T_world_object = closed
    result.T_world_object_open_loop, result.sensor_weights = open_loop, weights
    result.pad_errors = corrector.pads
    result.pinning = correctors[0].pair_pinning()
    return result


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


# this module's names, and those of its parts that other code imported from here before the split
__all__ = [
    "Correction",
    "CorrectionConfig",
    "LetGo",
    "NewTouchEstimator",
    "Pinning",
    "Regrasp",
    "ReleaseWatch",
    "Retouch",
    "STAMP_RESOLUTION_S",
    "Touch",
    "TrackConfig",
    "TrackResult",
    "contact_information",
    "contact_samples",
    "find_touch_time",
    "group_frames",
    "instant_window_s",
    "observable_unit",
    "open_loop_poses",
    "pad_rest_solver",
    "registration_solver",
    "retouch",
    "secant_scaling",
    "tactile_timing_warnings",
    "touch_from_pair",
    "touch_pinning",
    "touch_time_of",
    "track",
]
