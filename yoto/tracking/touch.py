"""The touch the track starts from: its time and what it fixes, each sensor's grasp `T_sensor_object =
T_world_sensor^-1 @ T_world_object` of the touch's pose estimate (`Touch`, `touch_from_pair`), and its time matched
to the sensor pose streams where neither the caller nor the pair file gives one (`touch_time_of`, `find_touch_time`,
`sensor_pose_mismatch`).

Frames: `T_world_object` in YOTO's canonical `object` frame; `T_world_sensor` as the contact pair and the streams give
them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.contacts import SIDES, ContactPair
from yoto.errors import InputError
from yoto.geometry import invert_transform, so3_log
from yoto.tracking.config import TrackConfig
from yoto.tracking.fusion import FusionConfig, sensor_poses
from yoto.trajectory import PoseStream

TOUCH_MATCH_ROTATION_M_PER_RAD = 0.05  # how rotation counts against translation when matching the touch in time


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


def pose_distance_m(T_reference: np.ndarray, T_poses: np.ndarray) -> np.ndarray:
    """(N,) how far each of `T_poses` (N, 4, 4) lies from `T_reference` (4, 4): metres of translation plus the rotation
    counted at TOUCH_MATCH_ROTATION_M_PER_RAD (5 cm per radian)."""
    angles = np.linalg.norm(so3_log(np.einsum("ji,njk->nik", T_reference[:3, :3], T_poses[:, :3, :3])), axis=1)
    return np.linalg.norm(T_poses[:, :3, 3] - T_reference[:3, 3], axis=1) + TOUCH_MATCH_ROTATION_M_PER_RAD * angles


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
        offsets = pose_distance_m(target, live)
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
