"""Two live sensor poses -> one object pose: interpolation to common times, jitter estimates, weighted averaging.

After the touch each sensor holds the object at a fixed pose `T_sensor_object` (its grasp), so each live sensor pose
gives a candidate `T_world_object = T_world_sensor @ T_sensor_object`. The two candidates differ by the jitter of
each stream, by dual-arm asynchrony (the arms are never exactly in step) and by slip. They are averaged, not
followed:
- each stream's jitter is estimated from the stream itself: the scatter of each sample about a quadratic fit of
  its neighbours in time (smooth motion fits, noise does not). A sample far off its fit is a glitch and its
  sensor is trusted little around it;
- each stream is smoothed in time (a local quadratic, glitches left out): jitter averages over the samples of the
  window, smooth motion passes. The half-window is chosen per stream, for its positions and its rotations apart,
  between `smoothing_s` and `max_smoothing_s`: widened only while the predicted error of a smoothed sample, its
  noise (the stream's jitter over the samples the window holds) plus its bias (how far a longer window's fits move
  from the shortest's beyond what noise explains: where the motion bends fast, a long window cuts its corners),
  exceeds `smoothed_translation_m` / `smoothed_rotation_rad` (a noisy or slow stream, not the usual ones);
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

ANCHORS = 5  # the longest stretches of a stream between glitches tried as its motion (`implausible_samples`)
GLITCH_WEIGHT = 1e-6  # relative weight of a sensor near a glitch sample (not 0: with one sensor it still counts)


@dataclass(frozen=True)
class FusionConfig:
    """How the two sensor streams are smoothed, interpolated and weighted."""

    max_gap_s: float = 0.1  # a stream is not interpolated across samples further apart than this (a dropout)
    jitter_neighbours: int = 4  # samples on each side of the local quadratic fit that measures a stream's jitter
    min_jitter_translation_m: float = 2e-5  # floors on the jitter estimates (a perfectly smooth stream, e.g. a
    min_jitter_rotation_rad: float = float(np.radians(0.01))  # simulated one, is not trusted infinitely)
    glitch_sigmas: float = 6.0  # a sample this many jitters off its neighbours' fit is a glitch
    smoothing_s: float = 0.05  # each stream is replaced by a local quadratic fit over +- at least this (0: raw
    # samples) ...
    max_smoothing_s: float = 0.25  # ... and at most this, chosen per stream from its jitter, rate and bend (at most
    # smoothing_s: a fixed +- smoothing_s). Centred: a pose uses samples up to this far ahead (offline files)
    smoothed_translation_m: float = 1.2e-4  # a window is widened only while the smoothed stream's predicted error
    smoothed_rotation_rad: float = float(np.radians(0.06))  # exceeds these (per axis; 0.2 mm / 0.1 deg of jitter
    # at 100-120 Hz, smoothed over +- 50 ms, is 0.09 mm / 0.045 deg: left as it is)
    jump_translation_m: float = 0.002  # a stretch of samples between glitches that its neighbours' motion, carried
    jump_rotation_rad: float = float(np.radians(2.0))  # across the glitches, misses by more than this and by more
    # than glitch_sigmas of the carried fit's noise is a mis-fitted rigid body (a flipped one): left out of the stream


@dataclass
class StreamJitter:
    """How noisy one pose stream is, measured on the stream itself."""

    translation_m: float  # robust 1-sigma per axis of a raw sample about the smooth motion
    rotation_rad: float  # robust 1-sigma per rotation-vector component
    glitch: np.ndarray  # (N,) bool, samples far off the fit of their neighbours
    smoothing_gain: float = 1.0  # variance of a smoothed position's noise over a raw sample's (1: not smoothed)
    rotation_smoothing_gain: float = 1.0  # the same for the rotations
    smoothing_s: tuple[float, float] = (0.0, 0.0)  # the half-windows chosen for positions and rotations
    left_out: int = 0  # samples left out of the stream: stretches between glitches its motion could not reach
    dropouts_s: tuple[float, ...] = ()  # gaps longer than `max_gap_s` in the stream (left out samples included):
    # the other sensor alone carries the object there

    @property
    def smoothed_translation_m(self) -> float:
        return self.translation_m * float(np.sqrt(self.smoothing_gain))

    @property
    def smoothed_rotation_rad(self) -> float:
        return self.rotation_rad * float(np.sqrt(self.rotation_smoothing_gain))

    def describe(self) -> str:
        smoothed = (
            f", smoothed to {self.smoothed_translation_m * 1e3:.3f} mm / {np.degrees(self.smoothed_rotation_rad):.3f}"
            f" deg (+- {self.smoothing_s[0] * 1e3:.0f} / {self.smoothing_s[1] * 1e3:.0f} ms)"
        )
        faults = f", {self.left_out} samples off its motion left out" if self.left_out else ""
        if self.dropouts_s:
            faults += (
                f", {len(self.dropouts_s)} dropouts (longest {max(self.dropouts_s):.2f} s): the other sensor alone"
            )
        return (
            f"jitter {self.translation_m * 1e3:.3f} mm / {np.degrees(self.rotation_rad):.3f} deg, "
            f"{int(self.glitch.sum())} glitches" + faults + (smoothed if max(self.smoothing_s) > 0 else "")
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
    """Weighted least-squares quadratics in time through each window: the coefficients (N, 3, C) and the inverse
    normal matrices (N, 3, 3), whose [0, 0] is the fit's noise variance at t = 0 over a sample's. `times`, `weights`
    (N, W); `values` (N, W, C)."""
    design = np.stack([np.ones_like(times), times, times**2], axis=-1)  # (N, W, 3)
    inverse = np.linalg.inv(np.einsum("nw,nwi,nwj->nij", weights, design, design))
    return inverse @ np.einsum("nw,nwi,nwc->nic", weights, design, values), inverse


def _centred_kernel(half_window: int) -> np.ndarray:
    """A local quadratic through 2k + 1 regular samples, at the middle one, as weights on the samples."""
    times = np.arange(-half_window, half_window + 1, dtype=np.float64)
    design = np.stack([np.ones_like(times), times, times**2], axis=-1)
    return np.linalg.solve(design.T @ design, design.T)[0]


def stream_jitter(stream: PoseStream, config: FusionConfig = FusionConfig()) -> StreamJitter:
    """Estimate a stream's jitter from its own samples: each sample against the quadratic through its neighbours
    (itself left out); the robust spread of those residuals, normalised by the fit's own noise."""
    k = config.jitter_neighbours
    count = len(stream)
    if count < 2 * k + 1:  # too short to tell noise from motion: assume the floors
        return StreamJitter(config.min_jitter_translation_m, config.min_jitter_rotation_rad, np.zeros(count, bool))
    window, offsets, translations, rotations = _windows(stream, k)
    others = (offsets != 0.0).astype(np.float64)
    fit_t, inverse = _local_fit(offsets, translations, others)
    fit_r, _ = _local_fit(offsets, rotations, others)
    fit_t, fit_r = fit_t[:, 0, :], fit_r[:, 0, :]
    scale = np.sqrt(1.0 + inverse[:, 0, 0])[:, None]  # var(sample - fit) = var(sample) (1 + the fit's share)
    normalised_t, normalised_r = -fit_t / scale, -fit_r / scale  # the sample's own value is 0 in its frame
    sigma_t = max(1.4826 * float(np.median(np.abs(normalised_t))), config.min_jitter_translation_m)
    sigma_r = max(1.4826 * float(np.median(np.abs(normalised_r))), config.min_jitter_rotation_rad)
    glitch = (np.linalg.norm(normalised_t, axis=1) > config.glitch_sigmas * sigma_t) | (
        np.linalg.norm(normalised_r, axis=1) > config.glitch_sigmas * sigma_r
    )
    return StreamJitter(sigma_t, sigma_r, glitch)


def _carried(times: np.ndarray, poses: np.ndarray, to_time: float, to_pose: np.ndarray) -> tuple[float, float, float]:
    """How far `to_pose` at `to_time` is from the motion of a stretch of samples (`times` in periods, `poses`)
    carried there by a polynomial (a quadratic where the stretch has 3 samples or more): the translation (m) and
    rotation (rad) missed, and the carried fit's noise over a sample's (1-sigma ratio)."""
    centre = float(np.mean(times))  # times about the stretch's middle: a well-conditioned fit
    degree = min(len(times), 3)
    design = np.vander(times - centre, degree, increasing=True)
    reference = poses[-1, :3, :3]
    rotations = so3_log(np.einsum("ji,njk->nik", reference, poses[:, :3, :3]))  # R_ref^T R_n
    inverse = np.linalg.inv(design.T @ design)
    at_target = np.vander(np.array([to_time - centre]), degree, increasing=True)[0]
    fit = at_target @ inverse @ design.T @ np.concatenate([poses[:, :3, 3], rotations], axis=1)
    missed_t = float(np.linalg.norm(to_pose[:3, 3] - fit[:3]))
    missed_r = float(np.linalg.norm(so3_log((so3_exp(fit[None, 3:])[0].T @ reference.T @ to_pose[:3, :3])[None])))
    return missed_t, missed_r, float(np.sqrt(1.0 + at_target @ inverse @ at_target))


def implausible_samples(stream: PoseStream, jitter: StreamJitter, config: FusionConfig = FusionConfig()) -> np.ndarray:
    """(N,) bool: samples the stream's motion cannot have reached: a rigid body mis-fitted for longer than the
    glitch test sees (a flipped body; a burst whose glitches mark only its ends).

    The glitches cut the stream into stretches of consecutive samples. Two stretches agree when the motion of each
    (a quadratic through its samples next to the other), carried across whatever lies between them, meets the
    other's nearest sample within `glitch_sigmas` of the carried fit's noise or within the jump floors
    (`jump_translation_m`, `jump_rotation_rad`), in translation and in rotation. From each of the longest stretches
    a chain goes out both ways, joining each stretch that agrees with the last one joined; the chain holding the
    most samples is the stream's motion, and the stretches outside it are left out; so is each glitch that the motion
    of the samples kept nearest it misses by as much (a glitch within it stays, left out of the smoothing)."""
    count = len(stream)
    implausible = np.zeros(count, bool)
    good = np.flatnonzero(~jitter.glitch)
    if len(good) == 0 or len(good) == count:
        return implausible
    stretches = np.split(good, np.flatnonzero(np.diff(good) > 1) + 1)
    if len(stretches) < 2:
        return implausible
    fit_samples = 2 * config.jitter_neighbours + 1
    period = max(float(np.median(np.diff(stream.timestamps_s))), 1e-9)
    times, poses = stream.timestamps_s / period, stream.T_world_frame
    agreed: dict[tuple[int, int], bool] = {}

    def within(missed: tuple[float, float, float]) -> bool:
        limit = config.glitch_sigmas * missed[2]
        return missed[0] <= max(limit * jitter.translation_m, config.jump_translation_m) and missed[1] <= max(
            limit * jitter.rotation_rad, config.jump_rotation_rad
        )

    def agree(before: int, after: int) -> bool:
        if (before, after) not in agreed:
            tail, head = stretches[before][-fit_samples:], stretches[after][:fit_samples][::-1]
            agreed[before, after] = within(_carried(times[tail], poses[tail], times[head[-1]], poses[head[-1]]))
            agreed[before, after] &= within(_carried(times[head], poses[head], times[tail[-1]], poses[tail[-1]]))
        return agreed[before, after]

    sizes = [len(stretch) for stretch in stretches]
    best: tuple[int, list[int]] = (-1, [])
    for anchor in [int(i) for i in np.argsort(sizes)[::-1][:ANCHORS]]:
        chain, last, first = [anchor], anchor, anchor
        for other in range(anchor + 1, len(stretches)):
            if agree(last, other):
                chain.append(other)
                last = other
        for other in range(anchor - 1, -1, -1):
            if agree(other, first):
                chain.append(other)
                first = other
        size = sum(sizes[i] for i in chain)
        if size > best[0]:
            best = (size, chain)
    for index in set(range(len(stretches))) - set(best[1]):
        implausible[stretches[index]] = True
    # Each glitch against the motion of the stream's samples kept nearest it in time (a flipped body's first and last
    # samples are glitches, the samples beside them too): one that motion cannot reach is left out as well.
    kept = np.flatnonzero(~implausible & ~jitter.glitch)
    for glitch in np.flatnonzero(jitter.glitch):
        before, after = kept[kept < glitch][-fit_samples:], kept[kept > glitch][:fit_samples][::-1]
        nearest = [side for side in (before, after) if len(side)]
        side = min(nearest, key=lambda samples: abs(times[samples[-1]] - times[glitch]))
        implausible[glitch] = not within(_carried(times[side], poses[side], times[glitch], poses[glitch]))
    return implausible


def _smoothed(
    stream: PoseStream, jitter: StreamJitter, half_window: int, shortest: int, config: FusionConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each sample's local quadratic over +- `half_window` samples (glitches left out): the fitted translations and
    rotation vectors relative to the sample (N, 3) each, (N,) whether the fit holds enough samples, (N,) its noise
    variance over a sample's."""
    count = len(stream)
    window, offsets, translations, rotations = _windows(stream, half_window)
    weights = (~jitter.glitch[window]).astype(np.float64)
    # Near an end the window stays centred, as wide as the samples there allow (a shifted window extrapolates and its
    # bias grows with its length), and no narrower than the shortest window shifted inside the stream.
    from_end = np.minimum(np.arange(count), np.arange(count)[::-1])
    reach = np.maximum(np.minimum(from_end, half_window), 2 * shortest - from_end)
    weights[np.abs(window - np.arange(count)[:, None]) > reach[:, None]] = 0.0
    period = float(np.median(np.diff(stream.timestamps_s)))
    reach_s = config.smoothing_s if half_window == shortest else half_window * period
    weights[np.abs(offsets) * period > reach_s * 1.5] = 0.0  # samples across a dropout
    usable = weights.sum(axis=1) >= 3
    weights[~usable] = 1.0  # too few: the raw sample is kept (these rows' fits are only kept invertible)
    fits, inverse = _local_fit(offsets, np.concatenate([translations, rotations], axis=2), weights)
    fit = np.where(usable[:, None], fits[:, 0, :], 0.0)
    return fit[:, :3], fit[:, 3:], usable, inverse[:, 0, 0]


def smooth_stream(stream: PoseStream, jitter: StreamJitter, config: FusionConfig = FusionConfig()) -> PoseStream:
    """The stream with each sample replaced by a local quadratic fit (glitches left out of every fit).

    The half-window is chosen, for the positions and for the rotations apart, among lengths from `smoothing_s` to
    `max_smoothing_s` (steps of 1.5x): the shortest whose predicted error of a smoothed sample is within
    `smoothed_translation_m` / `smoothed_rotation_rad`, else the one with the least predicted error: its noise
    (the stream's jitter times the window's noise gain) plus its squared bias, measured on the stream as how far the
    window's fits move from the shortest window's beyond what the two fits' noise explains (mean over the samples
    a full window away from the ends). `jitter.smoothing_gain`, `rotation_smoothing_gain` and `smoothing_s` are set
    to the chosen windows' median noise reduction (variance ratio) and half-widths (s).

    First the samples its motion cannot have reached (`implausible_samples`) are left out of the stream (a stretch
    longer than `max_gap_s` is then a dropout: the other sensor alone there); `jitter.glitch` follows, and
    `jitter.left_out` and `jitter.dropouts_s` say what was left out and which gaps remain."""
    implausible = implausible_samples(stream, jitter, config)
    if implausible.any():
        keep = ~implausible
        stream = PoseStream(stream.timestamps_s[keep], stream.T_world_frame[keep], stream.name, stream.source)
        jitter.glitch = jitter.glitch[keep]
        jitter.left_out = int(implausible.sum())
    if len(stream) > 1:
        gaps = np.diff(stream.timestamps_s)
        jitter.dropouts_s = tuple(float(g) for g in gaps[gaps > stream.dropout_gap_s(config.max_gap_s)])
    if config.smoothing_s <= 0 or len(stream) < 3:
        return stream
    period = float(np.median(np.diff(stream.timestamps_s)))
    shortest = int(min(round(config.smoothing_s / period), (len(stream) - 1) // 2))
    if shortest < 1:
        return stream
    longest = int(min(max(round(config.max_smoothing_s / period), shortest), (len(stream) - 1) // 4))
    if config.smoothing_s / period < 1.4:  # below some 28 Hz (+- 50 ms hold 3 samples, which pass through their
        longest = shortest  # quadratic) the jitter estimate's +- 4 samples do not tell noise from motion: as before
    candidates = [shortest]
    while candidates[-1] < longest:
        candidates.append(min(max(round(candidates[-1] * 1.5), candidates[-1] + 1), longest))
    fits = {shortest: _smoothed(stream, jitter, shortest, shortest, config)}
    count = len(stream)
    interior = np.minimum(np.arange(count), np.arange(count)[::-1]) >= candidates[-1]
    reference = _centred_kernel(shortest)
    chosen = []
    targets = (config.smoothed_translation_m, config.smoothed_rotation_rad)
    for channel, sigma in enumerate((jitter.translation_m, jitter.rotation_rad)):
        best = (np.inf, shortest)
        for k in candidates:
            if k not in fits:
                fits[k] = _smoothed(stream, jitter, k, shortest, config)
            kernel = _centred_kernel(k)
            gain = float(kernel @ kernel)
            # var(fit_k - fit_shortest) from noise alone, per component
            difference = (
                gain + float(reference @ reference) - 2.0 * float(kernel[k - shortest : k + shortest + 1] @ reference)
            )
            rows = interior & fits[k][2] & fits[shortest][2]
            moved = fits[k][channel] - fits[shortest][channel]
            bias_squared = max(float(np.mean(moved[rows] ** 2)) - sigma**2 * difference, 0.0) if rows.any() else 0.0
            best = min(best, (sigma**2 * gain + bias_squared, k))
            if best[0] <= targets[channel] ** 2:  # smooth enough: no longer window
                break
        chosen.append(best[1])
    poses = stream.T_world_frame.copy()
    translations, _, usable_t, gain_t = fits[chosen[0]]
    _, rotations, usable_r, gain_r = fits[chosen[1]]
    poses[:, :3, 3] += translations
    poses[:, :3, :3] = poses[:, :3, :3] @ so3_exp(rotations)
    jitter.smoothing_gain = float(np.median(gain_t[usable_t])) if usable_t.any() else 1.0
    jitter.rotation_smoothing_gain = float(np.median(gain_r[usable_r])) if usable_r.any() else 1.0
    jitter.smoothing_s = (chosen[0] * period, chosen[1] * period)
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


def fuse_holding(
    sensors: SensorPoses, grasps: dict[str, np.ndarray], holding: set[str], rows: np.ndarray | slice = slice(None)
) -> tuple[np.ndarray, np.ndarray]:
    """`fuse_object_poses` (poses and sensor weights at the chosen rows) from the sensors that hold the object: a
    side that let go carries it no more, as if its stream had no pose there."""
    if len(holding) < len(SIDES):
        covered = {side: sensors.covered[side] & (side in holding) for side in SIDES}
        sensors = SensorPoses(
            sensors.timestamps_s, sensors.T_world_sensor, covered, sensors.jitter, sensors.near_glitch
        )
    return fuse_object_poses(sensors, grasps, rows)
