"""Two live sensor poses -> one object pose: interpolation to common times, jitter estimates, weighted averaging.

After the touch each sensor holds the object at a fixed pose `T_sensor_object` (its grasp), so each live sensor pose
gives a candidate `T_world_object = T_world_sensor @ T_sensor_object`. The two candidates differ by the jitter of
each stream, by dual-arm asynchrony (the arms are never exactly in step) and by slip. They are averaged, not
followed:
- each stream's jitter is estimated from the stream itself: the scatter of each sample about a quadratic fit of
  its neighbours in time (smooth motion fits, noise does not). A sample far off its fit is a glitch and its
  sensor is trusted little around it;
- each stream is smoothed in time (a local quadratic over +- `smoothing_s`, glitches left out): jitter averages
  over the samples of the window, smooth motion passes;
- both streams are interpolated to each output time (they have their own rates and phases); a time inside a
  dropout (samples further apart than `max_gap_s`, or 1.5 periods of a slower stream) uses the other sensor alone;
- rotations are averaged with weights 1 / sigma_rotation^2 and positions of the object's centroid with weights
  1 / (sigma_translation^2 + (sigma_rotation * lever)^2), where the lever is the sensor's distance from the
  centroid (a sensor's rotation jitter moves a far-away object more).
Poses here are of YOTO's canonical `object` frame (origin at the centroid), so "position" is the centroid's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.contacts import SIDES
from yoto.geometry import so3_exp, so3_log
from yoto.trajectory import PoseStream

GLITCH_WEIGHT = 1e-6  # relative weight of a sensor near a glitch sample (not 0: with one sensor it still counts)


@dataclass(frozen=True)
class FusionConfig:
    """How the two sensor streams are smoothed, interpolated and weighted."""

    max_gap_s: float = 0.1  # a stream is not interpolated across samples further apart than this (a dropout)
    jitter_neighbours: int = 4  # samples on each side of the local quadratic fit that measures a stream's jitter
    min_jitter_translation_m: float = 2e-5  # floors on the jitter estimates (a perfectly smooth stream, e.g. a
    min_jitter_rotation_rad: float = float(np.radians(0.01))  # simulated one, is not trusted infinitely)
    glitch_sigmas: float = 6.0  # a sample this many jitters off its neighbours' fit is a glitch
    smoothing_s: float = 0.05  # each stream is replaced by a local quadratic fit over +- this (0: raw samples).
    # Centred: a pose uses samples up to this far ahead (offline files; a live loop would wait this long)


@dataclass
class StreamJitter:
    """How noisy one pose stream is, measured on the stream itself."""

    translation_m: float  # robust 1-sigma per axis of a raw sample about the smooth motion
    rotation_rad: float  # robust 1-sigma per rotation-vector component
    glitch: np.ndarray  # (N,) bool, samples far off the fit of their neighbours
    smoothing_gain: float = 1.0  # variance of a smoothed sample's noise over a raw sample's (1: not smoothed)

    @property
    def smoothed_translation_m(self) -> float:
        return self.translation_m * float(np.sqrt(self.smoothing_gain))

    @property
    def smoothed_rotation_rad(self) -> float:
        return self.rotation_rad * float(np.sqrt(self.smoothing_gain))

    def describe(self) -> str:
        return (
            f"jitter {self.translation_m * 1e3:.3f} mm / {np.degrees(self.rotation_rad):.3f} deg, "
            f"{int(self.glitch.sum())} glitches"
            + (f", smoothed to {self.smoothed_translation_m * 1e3:.3f} mm" if self.smoothing_gain < 1.0 else "")
        )


def _windows(stream: PoseStream, neighbours: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each sample's window of 2k + 1 samples (itself included; shifted inside the stream at its ends): the indices
    (N, W), the times relative to the sample in sample periods (N, W), and the window's translations and
    rotation vectors relative to the sample, (N, W, 3) each."""
    count = len(stream)
    first = np.clip(np.arange(count) - neighbours, 0, count - 2 * neighbours - 1)
    window = first[:, None] + np.arange(2 * neighbours + 1)[None, :]
    period = max(float(np.median(np.diff(stream.timestamps_s))), 1e-9)  # times in periods: a sane system
    offsets = (stream.timestamps_s[window] - stream.timestamps_s[:, None]) / period
    poses = stream.T_world_frame
    translations = poses[window, :3, 3] - poses[:, None, :3, 3]
    rotations = so3_log(np.einsum("nji,nwjk->nwik", poses[:, :3, :3], poses[window, :3, :3]))  # R_n^T R_w
    return window, offsets, translations, rotations


def _local_fit(times: np.ndarray, values: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares quadratics in time through each window: the fit at t = 0 (N, C) and its noise
    variance over a sample's (N,). `times`, `weights` (N, W); `values` (N, W, C)."""
    design = np.stack([np.ones_like(times), times, times**2], axis=-1)  # (N, W, 3)
    inverse = np.linalg.inv(np.einsum("nw,nwi,nwj->nij", weights, design, design))
    coefficients = inverse @ np.einsum("nw,nwi,nwc->nic", weights, design, values)  # (N, 3 terms, C)
    return coefficients[:, 0, :], inverse[:, 0, 0]


def stream_jitter(stream: PoseStream, config: FusionConfig = FusionConfig()) -> StreamJitter:
    """Estimate a stream's jitter from its own samples: each sample against the quadratic through its neighbours
    (itself left out); the robust spread of those residuals, normalised by the fit's own noise."""
    k = config.jitter_neighbours
    count = len(stream)
    if count < 2 * k + 1:  # too short to tell noise from motion: assume the floors
        return StreamJitter(config.min_jitter_translation_m, config.min_jitter_rotation_rad, np.zeros(count, bool))
    window, offsets, translations, rotations = _windows(stream, k)
    others = (offsets != 0.0).astype(np.float64)
    fit_t, fit_noise = _local_fit(offsets, translations, others)
    fit_r, _ = _local_fit(offsets, rotations, others)
    scale = np.sqrt(1.0 + fit_noise)[:, None]  # var(sample - fit) = var(sample) (1 + the fit's share)
    normalised_t, normalised_r = -fit_t / scale, -fit_r / scale  # the sample's own value is 0 in its frame
    sigma_t = max(1.4826 * float(np.median(np.abs(normalised_t))), config.min_jitter_translation_m)
    sigma_r = max(1.4826 * float(np.median(np.abs(normalised_r))), config.min_jitter_rotation_rad)
    glitch = (np.linalg.norm(normalised_t, axis=1) > config.glitch_sigmas * sigma_t) | (
        np.linalg.norm(normalised_r, axis=1) > config.glitch_sigmas * sigma_r
    )
    return StreamJitter(sigma_t, sigma_r, glitch)


def smooth_stream(stream: PoseStream, jitter: StreamJitter, config: FusionConfig = FusionConfig()) -> PoseStream:
    """The stream with each sample replaced by a local quadratic fit (glitches left out of every fit) over
    +- `smoothing_s`; `jitter.smoothing_gain` is set to the median noise reduction (variance ratio)."""
    if config.smoothing_s <= 0 or len(stream) < 3:
        return stream
    period = float(np.median(np.diff(stream.timestamps_s)))
    k = int(min(round(config.smoothing_s / period), (len(stream) - 1) // 2))
    if k < 1:
        return stream
    window, offsets, translations, rotations = _windows(stream, k)
    weights = (~jitter.glitch[window]).astype(np.float64)
    weights[np.abs(offsets) * period > config.smoothing_s * 1.5] = 0.0  # samples across a dropout
    usable = weights.sum(axis=1) >= 3
    weights[~usable] = 1.0  # too few: the raw sample is kept below (these rows' fits are only kept invertible)
    fit_t, gain = _local_fit(offsets, translations, weights)
    fit_r, _ = _local_fit(offsets, rotations, weights)
    poses = stream.T_world_frame.copy()
    poses[:, :3, 3] += np.where(usable[:, None], fit_t, 0.0)
    poses[:, :3, :3] = poses[:, :3, :3] @ so3_exp(np.where(usable[:, None], fit_r, 0.0))
    jitter.smoothing_gain = float(np.median(gain[usable])) if usable.any() else 1.0
    return PoseStream(stream.timestamps_s, poses, stream.name, stream.source)


@dataclass
class SensorPoses:
    """Both sensors' poses interpolated to common times, with how much each is trusted there."""

    timestamps_s: np.ndarray  # (M,)
    T_world_sensor: dict[str, np.ndarray]  # side -> (M, 4, 4)
    covered: dict[str, np.ndarray]  # side -> (M,) bool: the stream has samples around this time
    jitter: dict[str, StreamJitter]  # side -> the stream's jitter
    near_glitch: dict[str, np.ndarray]  # side -> (M,) bool: a neighbouring sample is a glitch

    @property
    def any_covered(self) -> np.ndarray:
        return self.covered["left"] | self.covered["right"]

    def select(self, keep: np.ndarray) -> SensorPoses:
        return SensorPoses(
            self.timestamps_s[keep],
            {side: poses[keep] for side, poses in self.T_world_sensor.items()},
            {side: mask[keep] for side, mask in self.covered.items()},
            self.jitter,
            {side: mask[keep] for side, mask in self.near_glitch.items()},
        )


def sensor_poses(
    streams: dict[str, PoseStream],
    timestamps_s: np.ndarray,
    config: FusionConfig = FusionConfig(),
    jitter: dict[str, StreamJitter] | None = None,
) -> SensorPoses:
    """Interpolate both streams to `timestamps_s` and mark where each can be trusted."""
    times = np.asarray(timestamps_s, dtype=np.float64)
    jitter = jitter or {side: stream_jitter(streams[side], config) for side in SIDES}
    poses, covered, near_glitch = {}, {}, {}
    for side in SIDES:
        stream = streams[side]
        poses[side], covered[side] = stream.interpolate(times, stream.dropout_gap_s(config.max_gap_s))
        upper = np.clip(np.searchsorted(stream.timestamps_s, times, side="left"), 0, len(stream) - 1)
        lower = np.clip(upper - 1, 0, len(stream) - 1)
        near_glitch[side] = jitter[side].glitch[upper] | jitter[side].glitch[lower]
    return SensorPoses(times, poses, covered, jitter, near_glitch)


def fuse_object_poses(
    sensors: SensorPoses, T_sensor_object: dict[str, np.ndarray], rows: np.ndarray | slice = slice(None)
) -> tuple[np.ndarray, np.ndarray]:
    """The fused T_world_object at the chosen rows of `sensors`, given each sensor's grasp `T_sensor_object`.

    Returns (K, 4, 4) poses and (K, 2) the normalised rotation weights of (left, right), which say which sensor
    the pose came from (rows covered by neither sensor get weights 0 and the left candidate).
    """
    candidates, weight_t, weight_r = [], [], []
    for side in SIDES:
        T_world_sensor = sensors.T_world_sensor[side][rows]
        candidate = T_world_sensor @ T_sensor_object[side]
        jitter = sensors.jitter[side]
        lever = np.linalg.norm(candidate[:, :3, 3] - T_world_sensor[:, :3, 3], axis=1)
        trust = np.where(sensors.near_glitch[side][rows], GLITCH_WEIGHT, 1.0) * sensors.covered[side][rows]
        candidates.append(candidate)
        sigma_t, sigma_r = jitter.smoothed_translation_m, jitter.smoothed_rotation_rad
        weight_t.append(trust / (sigma_t**2 + (sigma_r * lever) ** 2))
        weight_r.append(trust / sigma_r**2)
    stacked = np.stack(candidates)  # (2, K, 4, 4)
    w_t, w_r = np.stack(weight_t), np.stack(weight_r)  # (2, K)
    none = w_r.sum(axis=0) <= 0
    w_t[0, none], w_r[0, none] = 1.0, 1.0
    w_t, w_r = w_t / w_t.sum(axis=0), w_r / w_r.sum(axis=0)
    reference = stacked[0, :, :3, :3]
    offsets = so3_log(np.einsum("kji,skjl->skil", reference, stacked[:, :, :3, :3]))  # R_ref^T R_s, (2, K, 3)
    fused = stacked[0].copy()
    fused[:, :3, :3] = reference @ so3_exp(np.einsum("sk,skc->kc", w_r, offsets))
    fused[:, :3, 3] = np.einsum("sk,skc->kc", w_t, stacked[:, :, :3, 3])
    weights = w_r.T.copy()
    weights[none] = 0.0
    return fused, weights
