"""Time-stamped mocap streams and matching them in time: rigid-body poses, single markers, their dropouts.

A stream holds only the samples the mocap delivered (occluded frames are absent or were NaN in the file);
`dropped` counts the frames missing from its nominal rate. Streams from different sources share one clock
(ROS header stamps, or the Motive take's time); they are matched by interpolating between neighbouring
samples, never across a gap longer than `max_gap_s` (a long dropout leaves those times unmatched).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from yoto.errors import InputError
from yoto.geometry import quaternion_xyzw_to_rotation, rotation_to_quaternion_xyzw
from yoto.trajectory import LARGEST_PLAUSIBLE_POSITION_M

# A stream whose timestamps step back, or jump forward by more than this, has a broken clock.
MAX_CLOCK_JUMP_S = 5.0
# Interpolation never bridges a gap longer than this (a dropout of more than a few mocap frames).
DEFAULT_MAX_GAP_S = 0.05


@dataclass
class Stream:
    """What every time-stamped stream has: where it came from, its timestamps and its dropouts."""

    source: Path  # the recording it was read from
    name: str  # topic, rigid-body or marker name
    timestamps_s: np.ndarray  # (N,) float64 seconds, strictly increasing
    dropped: int = 0  # frames the mocap did not deliver (occlusion), counted from the nominal rate
    rate_hz: float = 0.0  # nominal rate (median of the sample spacing)

    def describe(self) -> str:
        return f"{self.source}: '{self.name}'"

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def span_s(self) -> tuple[float, float]:
        return (float(self.timestamps_s[0]), float(self.timestamps_s[-1])) if len(self.timestamps_s) else (0.0, 0.0)

    def gaps(self, min_gap_s: float) -> list[tuple[float, float]]:
        """(start, end) of every interval between samples longer than `min_gap_s`."""
        steps = np.diff(self.timestamps_s)
        return [
            (float(self.timestamps_s[i]), float(self.timestamps_s[i + 1])) for i in np.flatnonzero(steps > min_gap_s)
        ]

    def _brackets(self, times_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each query time: the samples before and after, the blend weight, and whether both are usable."""
        t = self.timestamps_s
        after = np.clip(np.searchsorted(t, times_s, side="left"), 1, max(len(t) - 1, 1))
        before = after - 1
        if len(t) < 2:
            exact = np.isclose(times_s, t[0]) if len(t) else np.zeros(len(times_s), bool)
            return np.zeros(len(times_s), int), np.zeros(len(times_s)), exact
        span = t[after] - t[before]
        weight = np.clip((times_s - t[before]) / np.maximum(span, 1e-12), 0.0, 1.0)
        inside = (times_s >= t[0] - 1e-9) & (times_s <= t[-1] + 1e-9)
        return before, weight, inside & (span <= max_gap_s)


@dataclass
class PoseStream(Stream):
    """A rigid body's pose over time: `T_world_body[i]` maps body coordinates to the mocap world at `timestamps_s[i]`.

    Unpacks as `(timestamps_s, T_world_body)`: `t, T = read_pose_stream(path, "RigLeft")`.
    """

    T_world_body: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # (N, 4, 4) metres

    def __iter__(self):
        return iter((self.timestamps_s, self.T_world_body))

    def at(self, times_s: np.ndarray, max_gap_s: float = DEFAULT_MAX_GAP_S) -> tuple[np.ndarray, np.ndarray]:
        """Poses at arbitrary times (linear in translation, spherical-linear in rotation between neighbouring
        samples): (M, 4, 4) and a (M,) bool mask of the times that could be matched (NaN poses elsewhere)."""
        times_s = np.asarray(times_s, dtype=np.float64)
        before, weight, valid = self._brackets(times_s, max_gap_s)
        out = np.full((len(times_s), 4, 4), np.nan)
        if not valid.any():
            return out, valid
        b, w = before[valid], weight[valid]
        a_index = np.minimum(b + 1, len(self.timestamps_s) - 1)
        T_a, T_b = self.T_world_body[b], self.T_world_body[a_index]
        q_a, q_b = rotation_to_quaternion_xyzw(T_a), rotation_to_quaternion_xyzw(T_b)
        q_b = q_b * np.where(np.sum(q_a * q_b, axis=1) < 0, -1.0, 1.0)[:, None]
        q = slerp(q_a, q_b, w)
        out[valid] = np.eye(4)
        out[valid, :3, :3] = quaternion_xyzw_to_rotation(q)
        out[valid, :3, 3] = (1 - w)[:, None] * T_a[:, :3, 3] + w[:, None] * T_b[:, :3, 3]
        return out, valid


@dataclass
class PointStream(Stream):
    """A single marker's position over time (mocap world frame, metres). Unpacks as `(timestamps_s, p_world)`."""

    p_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (N, 3)

    def __iter__(self):
        return iter((self.timestamps_s, self.p_world))

    def at(self, times_s: np.ndarray, max_gap_s: float = DEFAULT_MAX_GAP_S) -> tuple[np.ndarray, np.ndarray]:
        """Positions at arbitrary times (linear interpolation), (M, 3), and the mask of matched times."""
        times_s = np.asarray(times_s, dtype=np.float64)
        before, weight, valid = self._brackets(times_s, max_gap_s)
        out = np.full((len(times_s), 3), np.nan)
        b, w = before[valid], weight[valid]
        a_index = np.minimum(b + 1, len(self.timestamps_s) - 1)
        out[valid] = (1 - w)[:, None] * self.p_world[b] + w[:, None] * self.p_world[a_index]
        return out, valid


def slerp(q_a: np.ndarray, q_b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Spherical-linear interpolation of (M, 4) unit quaternions (same hemisphere) by weights (M,) in [0, 1]."""
    dot = np.clip(np.sum(q_a * q_b, axis=1), -1.0, 1.0)
    angle = np.arccos(dot)
    small = angle < 1e-6
    sin_angle = np.where(small, 1.0, np.sin(angle))
    wa = np.where(small, 1.0 - weight, np.sin((1.0 - weight) * angle) / sin_angle)
    wb = np.where(small, weight, np.sin(weight * angle) / sin_angle)
    q = wa[:, None] * q_a + wb[:, None] * q_b
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def clean_timeline(
    timestamps_s: np.ndarray, valid: np.ndarray, source: Path, name: str, max_jump_s: float = MAX_CLOCK_JUMP_S
) -> tuple[np.ndarray, int, float]:
    """Check a stream's clock and count its dropouts. `valid` marks the samples with data (not NaN, tracked).

    Returns the indices of the valid samples in time order, the dropped-frame count and the nominal rate.
    Raises InputError naming the file and stream for a clock that steps back or jumps (a restarted
    recorder, a mixed-up time base), and for a stream with fewer than 2 valid samples.
    """
    timestamps_s = np.asarray(timestamps_s, dtype=np.float64)
    if len(timestamps_s) and not np.isfinite(timestamps_s).all():
        raise InputError(f"stream '{name}' has timestamps that are not finite numbers", source)
    steps = np.diff(timestamps_s)
    backward = np.flatnonzero(steps < 0)
    if len(backward):
        i = backward[0]
        raise InputError(
            f"stream '{name}': the clock jumps back by {-steps[i]:.3f} s at t = {timestamps_s[i]:.3f} s "
            f"(sample {i + 1}; {len(backward)} backward steps in all): a restarted recorder or mixed clocks",
            source,
        )
    jumps = np.flatnonzero(steps > max_jump_s)
    if len(jumps):
        i = jumps[0]
        raise InputError(
            f"stream '{name}': the clock jumps forward by {steps[i]:.1f} s at t = {timestamps_s[i]:.3f} s "
            f"(more than {max_jump_s:g} s without a sample: a paused recorder, or a clock reset)",
            source,
        )
    kept = np.flatnonzero(np.asarray(valid, bool))
    if len(kept) < 2:
        raise InputError(
            f"stream '{name}' has {len(kept)} usable samples of {len(timestamps_s)} (the body or marker was never "
            "tracked)",
            source,
        )
    times = timestamps_s[kept]
    duplicate = np.flatnonzero(np.diff(times) <= 0)
    if len(duplicate):
        keep = np.ones(len(kept), bool)
        keep[duplicate + 1] = False
        kept, times = kept[keep], times[keep]
    all_steps = np.diff(timestamps_s[np.isfinite(timestamps_s)]) if len(timestamps_s) > 1 else np.diff(times)
    period = float(np.median(all_steps[all_steps > 0])) if np.any(all_steps > 0) else 0.0
    nominal_frames = int(round((times[-1] - times[0]) / period)) + 1 if period > 0 else len(times)
    # Frames present but invalid (NaN, untracked) plus frames missing from the timeline altogether.
    dropped = max(nominal_frames - len(times), 0)
    return kept, dropped, (1.0 / period if period > 0 else 0.0)


def check_metres(positions: np.ndarray, source: Path, name: str) -> np.ndarray:
    """`positions` (N, 3), refused naming the stream when they reach beyond LARGEST_PLAUSIBLE_POSITION_M (a mocap
    world is a room): a stream in millimetres (a bridge publishing Motive's units; ROS messages are metres)."""
    finite = positions[np.isfinite(positions).all(axis=1)]
    reach = float(np.abs(finite).max()) if len(finite) else 0.0
    if reach > LARGEST_PLAUSIBLE_POSITION_M:
        raise InputError(
            f"'{name}': positions reach {reach:.0f} m from the mocap origin, beyond any room: is the stream in "
            "millimetres? (ROS PoseStamped / PointStamped and YOTO's streams are metres)",
            source,
        )
    return positions


def make_pose_stream(
    source: Path, name: str, timestamps_s: np.ndarray, positions: np.ndarray, quaternions_xyzw: np.ndarray
) -> PoseStream:
    """A PoseStream from raw samples; NaN or zero quaternions and NaN positions are dropouts."""
    positions = check_metres(np.asarray(positions, dtype=np.float64).reshape(-1, 3), source, name)
    quaternions_xyzw = np.asarray(quaternions_xyzw, dtype=np.float64).reshape(-1, 4)
    norms = np.linalg.norm(quaternions_xyzw, axis=1)
    valid = np.isfinite(positions).all(axis=1) & np.isfinite(quaternions_xyzw).all(axis=1) & (norms > 0.5)
    kept, dropped, rate = clean_timeline(timestamps_s, valid, source, name)
    T = np.tile(np.eye(4), (len(kept), 1, 1))
    T[:, :3, :3] = quaternion_xyzw_to_rotation(quaternions_xyzw[kept])
    T[:, :3, 3] = positions[kept]
    return PoseStream(source, name, np.asarray(timestamps_s, np.float64)[kept], dropped, rate, T)


def make_point_stream(source: Path, name: str, timestamps_s: np.ndarray, positions: np.ndarray) -> PointStream:
    """A PointStream from raw samples; NaN positions are dropouts."""
    positions = check_metres(np.asarray(positions, dtype=np.float64).reshape(-1, 3), source, name)
    kept, dropped, rate = clean_timeline(timestamps_s, np.asarray(np.isfinite(positions).all(axis=1)), source, name)
    return PointStream(source, name, np.asarray(timestamps_s, np.float64)[kept], dropped, rate, positions[kept])


def static_segments(
    stream: PoseStream,
    max_speed_m_s: float = 0.01,
    max_angular_speed_rad_s: float = np.radians(5.0),
    min_duration_s: float = 0.3,
    window_s: float = 0.1,
) -> list[tuple[float, float]]:
    """(start, end) times of the intervals where a rigid body stands still (hand-held poses, holds).

    Speeds are measured over `window_s` (so mocap jitter does not look like motion); a segment must last
    `min_duration_s`. A dropout longer than the window ends a segment.
    """
    t, T = stream.timestamps_s, stream.T_world_body
    if len(t) < 3:
        return []
    later = np.searchsorted(t, t + window_s)
    later = np.minimum(later, len(t) - 1)
    span = t[later] - t
    usable = span > 0.5 * window_s
    moved = np.linalg.norm(T[later, :3, 3] - T[:, :3, 3], axis=1)
    relative = np.einsum("nji,njk->nik", T[:, :3, :3], T[later, :3, :3])
    turned = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1))
    still = usable & (moved <= max_speed_m_s * np.maximum(span, 1e-9)) & (turned <= max_angular_speed_rad_s * span)
    # A still sample vouches for the window after it.
    covered = np.zeros(len(t), bool)
    for k in np.flatnonzero(still):
        covered[k : later[k] + 1] = True
    segments = []
    start: float | None = None
    for i in range(len(t)):
        gap = i > 0 and t[i] - t[i - 1] > window_s
        if covered[i] and start is not None and gap:
            segments.append((start, float(t[i - 1])))
            start = None
        if covered[i] and start is None:
            start = float(t[i])
        if not covered[i] and start is not None:
            segments.append((start, float(t[i - 1])))
            start = None
    if start is not None:
        segments.append((start, float(t[-1])))
    return [(a, b) for a, b in segments if b - a >= min_duration_s]
