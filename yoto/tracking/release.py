"""Letting go and grasping again: `ReleaseWatch` sees a release of both gels or one gel letting go on its own
(`LetGo`); `NewTouchSearch` makes a new touch after a release (`Regrasp`, through a `NewTouchEstimator`: the pose
stage); `open_loop_poses` is the open loop carried by the sides that still hold, as the closed loop changed its grasps.

When both gels stay without contact (`ReleaseWatch`: a few frames each, a fifth of a second), the object was let go:
the grasp ends there, and the poses after it hold the last pose before it (`TrackResult.released_s`). Given the pose
stage (`track`'s `new_touch`), both gels touching again make a new touch: its pose estimated from that pair (the
hypothesis nearest the last pose where it is ambiguous), tracked on from there (`TrackResult.regrasps`). One gel
without contact whose sensor leaves the object (`lifted_apart_m`) leaves the other to predict the pose; one without
contact as long as a release let go (`LetGo`): the other alone carries the object, open loop too, until the side
touches again, when its grasp is the tracked pose in its live sensor pose.

Frames: `T_world_object` in the canonical `object` frame; grasps `T_sensor_object` in each sensor's frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from yoto.contacts import MIN_TACTILE_POINTS, SIDES, ContactPair, TactileContact
from yoto.errors import InputError, YotoError
from yoto.geometry import invert_transform
from yoto.tracking.config import ReleaseConfig, TrackConfig
from yoto.tracking.correction import Correction, OpenLoopChange
from yoto.tracking.fusion import SensorPoses, StreamJitter, fuse_holding, sensor_poses
from yoto.tracking.streams import TactileStream, felt_contact
from yoto.tracking.touch import Touch, pose_distance_m
from yoto.trajectory import PoseStream


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


class ReleaseWatch:
    """Sees the object let go: after a frame with contact, both sensors' frames show none ("too few points": the
    gel flat) for at least `release_s` from each side's first such frame, in at least `release_frames` frames. One side
    alone without contact as long, while the other's latest frame touches, let go on its own (`let_go`): the other
    holds the object. A side lifting off for less, or both for a moment, is neither (the closed loop keeps its
    prediction through it). A frame that could not be read neither counts nor breaks a stretch; any other (used, or
    left out as a bad fit or a shallow read) shows contact. Needs frames of both sensors: without one side's,
    nothing says that side let go."""

    def __init__(self, config: ReleaseConfig, sides: tuple[str, ...]):
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


class NewTouchSearch:
    """After a release: waits for both gels to touch again (contact on both, each pressed deeper than a kiss, in every
    instant over `regrasp_s`, at least `regrasp_frames` instants in a row) and estimates the object's pose from that
    pair; where the estimate is ambiguous, takes the hypothesis nearest the last tracked pose. Keeps why estimates
    were refused."""

    def __init__(
        self,
        estimate: NewTouchEstimator,
        config: TrackConfig,
        streams: dict[str, PoseStream],
        jitter: dict[str, StreamJitter],
    ):
        self.estimate, self.config, self.streams, self.jitter = estimate, config, streams, jitter
        self.run = 0  # instants in a row with both gels touching ...
        self.run_from_s = 0.0  # ... since this one's time
        self.refused: list[str] = []

    def saw(
        self, instant_s: float, frames: dict[str, tuple[TactileStream, int]], last_pose: np.ndarray
    ) -> Regrasp | None:
        """Take one instant; the new touch when it makes one."""
        if len(frames) < len(SIDES) or len(self.refused) >= self.config.release.regrasp_attempts:
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
        if self.run == 0:
            self.run_from_s = instant_s
        self.run += 1
        settled = instant_s - self.run_from_s >= self.config.release.regrasp_s - 1e-9
        if self.run < self.config.release.regrasp_frames or not settled:
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
            chosen = int(np.argmin(pose_distance_m(last_pose, hypotheses)))
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


def open_loop_poses(
    sensors: SensorPoses, T_sensor_object: dict[str, np.ndarray], changes: list[OpenLoopChange], rows: slice
) -> tuple[np.ndarray, np.ndarray]:
    """The open loop (K, 4, 4) over `rows` from one touch's grasps as the closed loop changed them where sides let
    go and touched again (`ClosedLoop.open_changes`), and the sensors' weights (K, 2): from a side's first frame
    without contact the other alone, and from its frame touching again the grasp the closed loop took for it then
    (the open-loop pose in its live sensor pose)."""
    times = sensors.timestamps_s
    first, last = rows.start or 0, len(times) if rows.stop is None else rows.stop
    grasps, holding = dict(T_sensor_object), set(SIDES)
    poses, weights = np.empty((last - first, 4, 4)), np.empty((last - first, len(SIDES)))
    row = first
    ordered = sorted(changes, key=lambda change: (change.time_s, change.T_sensor_object is not None))
    for change in [*ordered, OpenLoopChange(np.inf, "", None)]:
        upto = int(np.clip(np.searchsorted(times, change.time_s - 1e-9), row, last))
        if upto > row:
            poses[row - first : upto - first], weights[row - first : upto - first] = fuse_holding(
                sensors, grasps, holding, slice(row, upto)
            )
        row = upto
        if not change.side:
            break
        if change.T_sensor_object is None:
            holding.discard(change.side)
        else:
            grasps[change.side] = change.T_sensor_object
            holding.add(change.side)
    return poses, weights
