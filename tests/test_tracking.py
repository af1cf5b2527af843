"""Open-loop tracking from two sensor streams: exactness, jitter averaging, glitches, dropouts, arm lag, touch time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import TOL

from yoto.contacts import ContactPair, TactileContact
from yoto.geometry import invert_transform, make_transform, random_perturbation, random_rotations, so3_exp, so3_log
from yoto.simulate.trajectory import TrajectoryConfig, _as_recorded
from yoto.tracking.fusion import FusionConfig, smooth_stream, stream_jitter
from yoto.tracking.track import Touch, TrackConfig, find_touch_time, touch_from_pair, track
from yoto.trajectory import PoseStream

START = 1_700_000_000.0
RAW = TrackConfig(fusion=FusionConfig(smoothing_s=0.0))  # streams used as sampled: exact where they are exact


def object_motion(times: np.ndarray) -> np.ndarray:
    """A smooth motion of the object (canonical frame): a turn about a tilted axis and a curved translation."""
    s = times - START
    poses = np.zeros((len(s), 4, 4))
    poses[:, :3, :3] = so3_exp(np.outer(0.15 * np.sin(s), [0.3, 0.5, 0.8]))
    poses[:, :3, 3] = np.stack([0.5 + 0.03 * s, 0.02 * np.sin(2 * s), 0.1 + 0.01 * s**2], axis=1)
    poses[:, 3, 3] = 1.0
    return poses


def sensor_stream(times: np.ndarray, grasp: np.ndarray, rng=None, jitter_m=0.0, jitter_rad=0.0) -> PoseStream:
    """T_world_sensor = T_world_object @ T_object_sensor, with optional jitter on every sample."""
    poses = object_motion(times) @ invert_transform(grasp)
    if rng is not None:
        poses = np.array([pose @ random_perturbation(rng, jitter_m, jitter_rad) for pose in poses])
    return PoseStream(times, poses)


@pytest.fixture
def grasps(rng):
    """Each sensor's pose in the object's frame inverted: T_sensor_object, sensors ~4 cm from the centroid."""
    rotations = random_rotations(rng, 2)
    return {
        "left": invert_transform(make_transform(rotations[0], [0.04, 0.0, 0.01])),
        "right": invert_transform(make_transform(rotations[1], [-0.03, 0.02, -0.01])),
    }


def touch_at(grasps, time_s=START) -> Touch:
    return Touch(time_s, object_motion(np.array([time_s]))[0], grasps)


def errors(result) -> tuple[np.ndarray, np.ndarray]:
    return pose_errors(result.timestamps_s, result.T_world_object)


def pose_errors(times: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    truth = object_motion(times)
    translation = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    relative = np.einsum("nji,njk->nik", truth[:, :3, :3], poses[:, :3, :3])
    rotation = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1))
    return translation, rotation


def test_rigid_grasp_is_tracked_exactly_at_shared_timestamps(grasps):
    times = START + np.arange(0, 2.0, 0.01)
    streams = {side: sensor_stream(times, grasp) for side, grasp in grasps.items()}
    result = track(touch_at(grasps), streams, config=RAW)
    translation, rotation = errors(result)
    assert len(result.timestamps_s) == len(times)
    assert translation.max() < TOL["pose_exact_m"] and rotation.max() < TOL["arccos_rad"]
    assert not result.closed_loop and result.skipped_times == 0


def test_streams_at_different_rates_are_interpolated(grasps):
    """120 Hz and 100 Hz with a phase offset: outputs at the union of timestamps, errors far below jitter."""
    streams = {
        "left": sensor_stream(START + np.arange(0, 2.0, 1 / 120), grasps["left"]),
        "right": sensor_stream(START + 0.0037 + np.arange(0, 2.0, 1 / 100), grasps["right"]),
    }
    result = track(touch_at(grasps), streams)
    assert len(result.timestamps_s) == len(np.union1d(streams["left"].timestamps_s, streams["right"].timestamps_s))
    translation, rotation = errors(result)
    assert translation.max() < 2e-5 and rotation.max() < np.radians(0.01)


def test_jitter_of_one_sensor_is_averaged_not_followed(grasps, rng):
    times = START + np.arange(0, 3.0, 0.01)
    clean = {side: sensor_stream(times, grasp) for side, grasp in grasps.items()}
    noisy_left = sensor_stream(times, grasps["left"], rng, 0.001, np.radians(0.5))
    result = track(touch_at(grasps), {"left": noisy_left, "right": clean["right"]})
    translation, _ = errors(result)
    followed, _ = pose_errors(times, noisy_left.T_world_frame @ grasps["left"])  # the left sensor alone
    # The jitter estimate says which stream to trust: the fused pose stays with the clean sensor.
    assert np.sqrt(np.mean(translation**2)) < 0.05 * np.sqrt(np.mean(followed**2))
    assert result.sensor_weights[:, 0].max() < 0.01

    # Both sensors equally noisy: the fused pose is better than either, about 1/sqrt(2) ...
    right_noisy = sensor_stream(times, grasps["right"], rng, 0.001, np.radians(0.5))
    both = track(touch_at(grasps), {"left": noisy_left, "right": right_noisy}, config=RAW)
    alone, _ = pose_errors(times, right_noisy.T_world_frame @ grasps["right"])
    ratio = np.sqrt(np.mean(errors(both)[0] ** 2) / np.mean(alone**2))
    assert 0.55 < ratio < 0.85
    # ... and smoothing each stream in time (+- 50 ms of samples) halves it again.
    smoothed = track(touch_at(grasps), {"left": noisy_left, "right": right_noisy})
    assert np.sqrt(np.mean(errors(smoothed)[0] ** 2) / np.mean(errors(both)[0] ** 2)) < 0.5


def test_smoothing_keeps_smooth_motion(grasps):
    """A quadratic over +- 50 ms follows the motion: noise-free streams move by micrometres at most."""
    times = START + np.arange(0, 2.0, 0.01)
    streams = {side: sensor_stream(times, grasp) for side, grasp in grasps.items()}
    translation, rotation = errors(track(touch_at(grasps), streams))
    assert translation.max() < 5e-6 and rotation.max() < np.radians(0.001)


def test_the_smoothing_window_follows_each_streams_jitter_rate_and_bend(grasps, rng):
    """A 30 Hz stream with 0.4 mm / 0.2 deg of jitter: +- 50 ms hold 5 samples (67 ms: the smoothed pose keeps 0.7 of
    the jitter); the windows chosen for it (widened while the predicted noise plus bias exceeds 0.12 mm / 0.06 deg)
    come much closer to the motion. A 120 Hz stream with 0.2 mm keeps +- 50 ms. A noisy stream that bends fast (a
    4 Hz, 3 mm shake) keeps a short window: a long one would cut the shake's corners."""
    times = START + np.arange(0, 3.0, 1 / 30)
    clean = sensor_stream(times, grasps["left"])
    noisy = sensor_stream(times, grasps["left"], rng, 4e-4, np.radians(0.2))

    def smoothed_error(stream: PoseStream, truth: PoseStream, config: FusionConfig) -> tuple[float, float]:
        jitter = stream_jitter(stream, config)
        poses = smooth_stream(stream, jitter, config).T_world_frame
        rotation = so3_log(np.einsum("nji,njk->nik", truth.T_world_frame[:, :3, :3], poses[:, :3, :3]))
        translation = poses[:, :3, 3] - truth.T_world_frame[:, :3, 3]
        return float(np.sqrt(np.mean(translation**2))), float(np.sqrt(np.mean(rotation**2)))

    fixed = FusionConfig(max_smoothing_s=0.05)  # +- 50 ms whatever the stream (the window before stop 19)
    fixed_t, fixed_r = smoothed_error(noisy, clean, fixed)
    chosen_t, chosen_r = smoothed_error(noisy, clean, FusionConfig())
    sigma_r = np.radians(0.2) / np.sqrt(3.0)  # per rotation-vector component: the angle's 0.2 deg about any axis
    assert fixed_t > 0.6 * 4e-4 and fixed_r > 0.6 * sigma_r  # 0.65, 0.70 of the jitter
    assert chosen_t < 0.45 * 4e-4 and chosen_r < 0.6 * sigma_r
    jitter = stream_jitter(noisy)
    smooth_stream(noisy, jitter)
    assert jitter.smoothing_s[0] > 0.2 and jitter.smoothing_s[1] > 0.1
    assert max(jitter.smoothing_s) <= FusionConfig().max_smoothing_s + 1 / 60
    usual = sensor_stream(START + np.arange(0, 3.0, 1 / 120), grasps["left"], rng, 2e-4, np.radians(0.1))
    jitter = stream_jitter(usual)
    smooth_stream(usual, jitter)
    assert jitter.smoothing_s == pytest.approx((0.05, 0.05), abs=1e-4)

    times = START + np.arange(0, 3.0, 1 / 120)
    shake = np.zeros((len(times), 4, 4))
    shake[:, :3, :3] = np.eye(3)
    shake[:, :3, 3] = 0.003 * np.sin(2 * np.pi * 4.0 * (times - START))[:, None] * [1.0, 0.5, 0.0]
    shake[:, 3, 3] = 1.0
    shaken = PoseStream(times, shake @ clean.T_world_frame[:1].repeat(len(times), 0))
    shaken_noisy = PoseStream(
        times, np.array([pose @ random_perturbation(rng, 4e-4, 0.0) for pose in shaken.T_world_frame])
    )
    jitter = stream_jitter(shaken_noisy)
    smooth_stream(shaken_noisy, jitter)
    wide = FusionConfig(smoothing_s=FusionConfig().max_smoothing_s)
    assert jitter.smoothing_s[0] < 0.1  # 75 ms: 113 would cut the corners
    assert smoothed_error(shaken_noisy, shaken, FusionConfig())[0] < 2e-4
    assert smoothed_error(shaken_noisy, shaken, wide)[0] > 5e-4


def test_jitter_estimate_and_glitches(grasps, rng):
    times = START + np.arange(0, 3.0, 1 / 120)
    stream = sensor_stream(times, grasps["left"])
    noise = rng.normal(size=(len(times), 3)) * 3e-4
    stream.T_world_frame[:, :3, 3] += noise
    stream.T_world_frame[200, :3, 3] += [0.01, 0.0, 0.0]  # one 10 mm glitch
    jitter = stream_jitter(stream, FusionConfig())
    assert jitter.translation_m == pytest.approx(3e-4, rel=0.15)
    assert jitter.glitch[200] and jitter.glitch.sum() <= 3  # the glitch, at most its two neighbours
    # A smooth stream is not trusted beyond the floor.
    assert stream_jitter(sensor_stream(times, grasps["left"])).translation_m == FusionConfig().min_jitter_translation_m


def test_a_glitch_in_one_stream_does_not_reach_the_output(grasps):
    times = START + np.arange(0, 2.0, 0.01)
    streams = {side: sensor_stream(times, grasp) for side, grasp in grasps.items()}
    streams["left"].T_world_frame[100, :3, 3] += [0.0, 0.02, 0.0]
    translation, _ = errors(track(touch_at(grasps), streams))
    assert translation.max() < 1e-4


def mocap_streams(grasps, rng) -> dict[str, PoseStream]:
    """Both streams at 120 Hz for 3 s, with 0.2 mm / 0.1 deg of jitter."""
    times = START + np.arange(0, 3.0, 1 / 120)
    return {side: sensor_stream(times, grasp, rng, 2e-4, np.radians(0.1)) for side, grasp in grasps.items()}


def test_a_flipped_rigid_body_is_left_out(grasps, rng):
    """A second of the left body fitted half a turn about an axis through its markers' centre (a flip about a symmetry
    axis of the marker set): its ends are glitches, its inside a smooth motion. Main 7b24095 fused it: 104 mm /
    180 deg off at worst."""
    streams = mocap_streams(grasps, rng)
    times = streams["left"].timestamps_s
    flip = make_transform(so3_exp(np.pi * np.array([0.0, 0.6, 0.8])), np.zeros(3))
    centre = np.array([0.03, 0.02, 0.0])
    flip[:3, 3] = centre - flip[:3, :3] @ centre
    inside = (times > START + 1.0) & (times < START + 2.0)
    streams["left"].T_world_frame[inside] = streams["left"].T_world_frame[inside] @ flip
    result = track(touch_at(grasps), streams)
    translation, rotation = errors(result)
    assert translation.max() < 1e-3 and np.degrees(rotation.max()) < 0.5
    left = result.jitter["left"]
    assert left.left_out == inside.sum()  # the flip, its first and last samples (glitches) too, nothing else
    assert len(left.dropouts_s) == 1 and 0.99 < left.dropouts_s[0] < 1.01
    assert result.jitter["right"].left_out == 0 and "left out" in left.describe()


def test_a_burst_longer_than_the_glitch_test_is_left_out(grasps, rng):
    """The right body mis-fitted for 100 ms (12 samples) by 10 mm / 8 deg: the glitch test marks only the burst's ends
    (each middle sample's neighbours are mostly the burst's own). Main 7b24095 fused its middle: 32 mm / 3.6 deg off
    at worst."""
    streams = mocap_streams(grasps, rng)
    burst = slice(150, 162)
    offset = make_transform(so3_exp(np.radians(8.0) * np.array([0.6, 0.8, 0.0])), [0.0, 0.01, 0.0])
    streams["right"].T_world_frame[burst] = offset @ streams["right"].T_world_frame[burst]
    result = track(touch_at(grasps), streams)
    translation, rotation = errors(result)
    assert translation.max() < 1e-3 and np.degrees(rotation.max()) < 0.5
    assert result.jitter["right"].left_out == 12 and len(result.jitter["right"].dropouts_s) == 1  # 108 ms


def test_the_simulators_pose_streams_as_mocap_and_arms_deliver_them(grasps, rng):
    """`TrajectoryConfig.pose_*` and `arm_error_*` (`simulate.trajectory._as_recorded`): bursts off by what they
    say, a flip of half a turn, dropouts of one stream at a time, a smooth bounded arm error; nothing changed where
    they are off."""
    streams = mocap_streams(grasps, rng)
    after, end = START + 0.2, START + 3.0

    def recorded(**changes):
        return _as_recorded(streams, TrajectoryConfig(**changes), np.random.default_rng(0), after, end)

    def turn_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.degrees(np.linalg.norm(so3_log(np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])), axis=1))

    for side, stream in recorded().items():
        assert np.array_equal(stream.T_world_frame, streams[side].T_world_frame)
    faulty = recorded(pose_outlier_share=0.02)["left"].T_world_frame
    off = np.linalg.norm(faulty[:, :3, 3] - streams["left"].T_world_frame[:, :3, 3], axis=1) > 0
    assert 0.005 < off.mean() < 0.04
    turned = turn_deg(faulty[off], streams["left"].T_world_frame[off])
    assert np.all((turned > 4.99) & (turned < 30.01))
    flipped = recorded(pose_flips=1)["right"]
    turned = turn_deg(flipped.T_world_frame, streams["right"].T_world_frame)
    assert np.sum(turned > 179.99) == 120 and np.all((turned < 1e-6) | (turned > 179.99))  # 1 s at 120 Hz
    gaps = []
    for stream in recorded(pose_dropouts=2, pose_dropout_s=(0.2, 0.4)).values():
        steps = np.diff(stream.timestamps_s)
        long = steps > 0.1
        assert np.sum(long) == 2 and np.all((steps[long] > 0.2) & (steps[long] < 0.4 + 2 / 120))
        starts = stream.timestamps_s[:-1][long]
        assert np.all(starts >= after)
        gaps += [(a, a + b) for a, b in zip(starts, steps[long], strict=True)]
    gaps.sort()
    assert all(first[1] < second[0] for first, second in zip(gaps, gaps[1:], strict=False))  # one at a time
    arm = recorded(arm_error_m=3e-4, arm_error_rad=float(np.radians(0.1)))["left"].T_world_frame
    error = np.linalg.norm(arm[:, :3, 3] - streams["left"].T_world_frame[:, :3, 3], axis=1)
    assert error.max() < 3e-4 * np.sqrt(3) and np.abs(np.diff(error)).max() < 5e-6  # smooth: no step at 120 Hz
    assert np.ptp(error) > 1e-5  # it changes with where the arm is
    assert turn_deg(arm, streams["left"].T_world_frame).max() < 0.1 * np.sqrt(3)


def test_dropouts_use_the_other_sensor(grasps):
    times = START + np.arange(0, 2.0, 0.01)
    streams = {side: sensor_stream(times, grasp) for side, grasp in grasps.items()}
    keep = (times < START + 0.8) | (times > START + 1.3)  # half a second occluded
    streams["left"] = PoseStream(times[keep], streams["left"].T_world_frame[keep])
    result = track(touch_at(grasps), streams, config=RAW)
    inside = (result.timestamps_s > START + 0.85) & (result.timestamps_s < START + 1.25)
    assert np.all(result.sensor_weights[inside, 0] == 0.0)
    translation, _ = errors(result)
    assert translation.max() < TOL["pose_exact_m"] * 10


def test_arm_lag_is_averaged(grasps):
    """The right arm 20 ms late: the fused pose sits between the two arms, halving the error of either alone."""
    times = START + np.arange(0, 2.0, 0.01)
    left = sensor_stream(times, grasps["left"])
    right = PoseStream(times, object_motion(times - 0.02) @ invert_transform(grasps["right"]))
    fused, _ = errors(track(touch_at(grasps), {"left": left, "right": right}))
    right_only, _ = pose_errors(times, right.T_world_frame @ grasps["right"])
    assert np.mean(fused) == pytest.approx(0.5 * np.mean(right_only), rel=0.1)


def test_the_touch_fixes_the_grasps_and_its_time(grasps):
    times = START + np.arange(0, 2.0, 0.01)
    streams = {side: sensor_stream(times, grasp) for side, grasp in grasps.items()}
    k = 37
    T_world_object = object_motion(times[k : k + 1])[0]
    contacts = {side: TactileContact(np.zeros((30, 3)), streams[side].T_world_frame[k]) for side in ("left", "right")}
    pair = ContactPair("thing", contacts["left"], contacts["right"])
    found, mismatch = find_touch_time(pair, streams)
    assert found == times[k] and mismatch < TOL["float"]
    touch = touch_from_pair(pair, T_world_object, found)
    for side in ("left", "right"):
        assert np.abs(touch.T_sensor_object[side] - grasps[side]).max() < TOL["float"]
    result = track(touch, streams)
    assert result.timestamps_s[0] == times[k]  # poses from the touch on


def test_batched_inverse_matches_the_single_one(rng):
    poses = np.array([make_transform(r, rng.normal(size=3)) for r in random_rotations(rng, 5)])
    batched = invert_transform(poses.reshape(5, 1, 4, 4))
    for pose, inverse in zip(poses, batched[:, 0], strict=True):
        assert np.abs(inverse - invert_transform(pose)).max() < TOL["float"]
        assert np.abs(inverse @ pose - np.eye(4)).max() < TOL["float"]


def test_tactile_frames_of_both_sensors_are_paired_in_time():
    from yoto.tracking.streams import TactileStream
    from yoto.tracking.track import group_frames

    left = TactileStream.in_memory(np.array([0.9, 1.00, 1.02, 1.04, 1.06, 1.20]), [np.zeros((1, 3))] * 6)
    right = TactileStream.in_memory(np.array([1.01, 1.03, 1.05, 1.055, 1.30]), [np.zeros((1, 3))] * 5)
    instants = group_frames({"left": left, "right": right}, start_s=1.0, tolerance_s=0.005)
    assert instants == [  # left's median period 0.02 s: frames within 0.01 s pair
        (1.01, [("left", 1), ("right", 0)]),
        (1.03, [("left", 2), ("right", 1)]),
        (1.05, [("left", 3), ("right", 2)]),
        (1.06, [("left", 4), ("right", 3)]),
        (1.20, [("left", 5)]),
        (1.30, [("right", 4)]),
    ]


def test_out_of_phase_gels_at_15_fps_pair_every_frame():
    """Two cameras at 15 fps half a period apart (33 ms): each frame with the other gel's next one, not every
    frame alone (a fixed 20 ms window paired none of them)."""
    from yoto.tracking.streams import TactileStream
    from yoto.tracking.track import group_frames, instant_window_s

    left_s = np.round(100.0 + np.arange(12) / 15.0, 6)
    right_s = np.round(left_s + 0.5 / 15.0, 6)
    tactile = {
        "left": TactileStream.in_memory(left_s, [np.zeros((1, 3))] * 12),
        "right": TactileStream.in_memory(right_s, [np.zeros((1, 3))] * 12),
    }
    assert abs(instant_window_s(tactile, 0.02) - 0.5 / 15.0) < 2e-5
    instants = group_frames(tactile, start_s=100.0, tolerance_s=0.02)
    assert [frames for _, frames in instants] == [[("left", i), ("right", i)] for i in range(12)]
    assert [time for time, _ in instants] == list(right_s)
    default_rate = {side: TactileStream.in_memory(np.arange(10) / 25.0, [np.zeros((1, 3))] * 10) for side in tactile}
    assert abs(instant_window_s(default_rate, 0.02) - 0.02) < 2e-5  # 25 fps: the 20 ms window as before


def _bench_record(touch_mm: float, drift_mm: float, right: bool) -> dict:
    figures = {figure: {"mm": drift_mm, "deg": 0.1} for figure in ("motion_mean", "motion_peak", "settled")}
    loop = {**figures, "settled_drift": {"mm": drift_mm, "deg": 0.1}, "touch": {"mm": touch_mm, "deg": 0.2}}
    loop["final_drift"] = {"mm": 0.5 * drift_mm, "deg": 0.05}
    speed = {"latency_median_ms": 10.0, "latency_p90_ms": 20.0, "instants_per_s": 100.0, "frames_per_s": 150.0}
    return {
        "open_loop": loop,
        "closed_loop": loop,
        "slip": {"slip_final_mm": 2.0, "slip_final_deg": 1.5},
        "closed_loop_speed": {**speed, "frames_used": 3, "frames": 4},
        "right_touch": right,
    }


def test_benchmark_report_separates_right_touches():
    from yoto.tracking.bench import TrackBenchConfig, build_report, format_markdown

    records = {"thing": {"100mm": [_bench_record(0.1, 0.2, True), _bench_record(30.0, 0.9, False)]}}
    report = build_report(records, TrackBenchConfig(trajectories=2))
    entry = report["results"]["thing"]["100mm"]
    assert entry["right_touches"] == 1
    assert entry["right_touch"]["touch"]["mm"]["mean"] == pytest.approx(0.1)
    assert entry["all"]["touch"]["mm"]["mean"] == pytest.approx(15.05)
    assert entry["right_touch"]["closed_loop_drift_met"] == 1
    assert entry["all"]["closed_loop_drift_met"] == 1
    assert entry["speed"]["frames_per_s"]["mean"] == pytest.approx(150.0)
    text = format_markdown(report)
    assert "| closed loop: drift under the target, right touches | 1 of 1 |" in text
    assert "| closed loop: drift under the target, all trajectories | 1 of 2 |" in text


def test_benchmark_report_counts_settled_errors_within_the_touchs_own_beside_the_drift():
    """A loop that ends nearer the truth than its touch (settled 0.2 mm against a 0.1 mm touch: within 0.5 mm of it)
    counts beside the drift target; one that ends 0.8 mm further than its touch does not, whatever its drift."""
    from yoto.tracking.bench import TrackBenchConfig, build_report, format_markdown

    corrected, departed = _bench_record(0.1, 0.2, True), _bench_record(0.1, 0.9, True)
    departed["closed_loop"] = {**departed["closed_loop"], "settled_drift": {"mm": 0.3, "deg": 0.1}}
    report = build_report({"thing": {"100mm": [corrected, departed]}}, TrackBenchConfig(trajectories=2))
    entry = report["results"]["thing"]["100mm"]["right_touch"]
    assert entry["closed_loop_within_touch"] == 1 and entry["closed_loop_drift_met"] == 2
    row = "settled error within the touch's own + 0.5 mm / 0.5 deg, right touches | 1 of 2 |"
    assert row in format_markdown(report)
    # the final drift counts apart from the per-frame one: 0.1 and 0.45 mm meet it, a 1.2 mm one would not
    departed["closed_loop"]["final_drift"] = {"mm": 1.2, "deg": 0.05}
    report = build_report({"thing": {"100mm": [corrected, departed]}}, TrackBenchConfig(trajectories=2))
    assert report["results"]["thing"]["100mm"]["right_touch"]["closed_loop_final_drift_met"] == 1
    assert "just before the motion) under the target, right touches | 1 of 2 |" in format_markdown(report)


class _Surface:
    """A sampled surface for registration: points, normals, and their k-d tree."""

    def __init__(self, points: np.ndarray, normals: np.ndarray):
        from scipy.spatial import cKDTree

        self.points_object, self.normals_object, self.kdtree = points, normals, cKDTree(points)


def _cylinder(radius_m: float, normal_tilt_rad: float, rng) -> _Surface:
    """A cylinder about z (30 mm high) sampled every ~0.3 mm, its normals tilted at random by `normal_tilt_rad`
    (as a scanned mesh's are)."""
    angles, heights = np.meshgrid(np.arange(0.0, 2 * np.pi, 0.0003 / radius_m), np.arange(-0.015, 0.015, 0.0003))
    angles, heights = angles.ravel(), heights.ravel()
    points = np.stack([radius_m * np.cos(angles), radius_m * np.sin(angles), heights], axis=1)
    radial = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    tangent = np.cross(radial, rng.normal(size=radial.shape))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normals = np.cos(normal_tilt_rad) * radial + np.sin(normal_tilt_rad) * tangent
    return _Surface(points, normals)


def _two_contacts(radius_m: float) -> np.ndarray:
    """Points of two opposite 8 x 8 mm contacts on the cylinder (at +x and -x), on its exact surface."""
    arc, heights = np.meshgrid(np.linspace(-0.004, 0.004, 16), np.linspace(-0.004, 0.004, 16))
    angles = (arc / radius_m).ravel()
    side = np.stack([radius_m * np.cos(angles), radius_m * np.sin(angles), heights.ravel()], axis=1)
    return np.vstack([side, side * [-1.0, -1.0, 1.0]])


def test_information_a_scanned_surface_of_revolution_does_not_give_is_taken_back(rng):
    """Tilted sample normals claim a spin about a cylinder's axis (and slides along it) that its surface leaves
    free; re-matching at a step shows it, and the check scales those directions down while what the surface does
    pin (the contacts' common normal) keeps its information."""
    from yoto.registration import plane_distances, point_to_plane_jacobian
    from yoto.tracking.track import CorrectionConfig, secant_scaling

    radius, config = 0.03, CorrectionConfig()
    unit = np.array([config.observable_rotation_rad] * 3 + [config.observable_translation_m] * 3)
    points = _two_contacts(radius)
    surface = _cylinder(radius, np.radians(9.0), rng)
    _, matched, _, normals = plane_distances(surface, points, config.max_distance_m)
    jacobian = point_to_plane_jacobian(points, normals)[matched]
    normal = jacobian.T @ jacobian
    spin, slide_z, push_x = np.eye(6)[2], np.eye(6)[5], np.eye(6)[3]
    claimed = (normal[2, 2] * unit[2] ** 2, normal[5, 5] * unit[5] ** 2)
    # the planes claim the free directions at a few percent of what the contacts' normal gets: far from free
    assert min(claimed) > 1e-3 * normal[3, 3] * unit[3] ** 2
    checked = secant_scaling(surface, normal, points, unit, config)  # the 3 weakest: turns about z and x, slide y
    assert spin @ checked @ normal @ checked.T @ spin < 0.1 * (spin @ normal @ spin)
    # every direction checked: the slide along the axis goes too, what the surface really pins keeps its information
    everything = secant_scaling(surface, normal, points, unit, dataclasses.replace(config, secant_directions=6))
    after = everything @ normal @ everything.T
    assert slide_z @ after @ slide_z < 0.1 * (slide_z @ normal @ slide_z)
    assert push_x @ after @ push_x > 0.8 * (push_x @ normal @ push_x)
    # off: the normal matrix as it was
    off = secant_scaling(surface, normal, points, unit, dataclasses.replace(config, secant_directions=0))
    np.testing.assert_array_equal(off, np.eye(6))


def test_the_pinning_names_the_directions_two_contacts_leave_free_and_splits_a_drift_along_them(rng):
    """Two opposite contacts on a cylinder pin the push along their normal, not the spin about the axis nor the slide
    along it, and the turn about the line through them only by the surface's curvature: spreads weakest first, and a
    drift split by the pinning puts its spin and slide in the weak part, its push in the pinned part."""
    from yoto.tracking.track import CorrectionConfig, Pinning, contact_information, observable_unit

    radius, config = 0.03, CorrectionConfig()
    points = _two_contacts(radius)
    surface = _cylinder(radius, 0.0, rng)  # exact normals: the check against the surface changes nothing
    sides = {"left": points[: len(points) // 2], "right": points[len(points) // 2 :]}
    information = contact_information(surface, sides, config)
    pinning = Pinning.of(sum(bias for _, bias in information.values()), observable_unit(config))
    spin, slide_z, push_x = np.eye(6)[2], np.eye(6)[5], np.eye(6)[3]
    free = pinning.directions[:2]  # the two weakest, orthonormal in observable units
    assert np.linalg.norm(free @ spin) > 0.99 and np.linalg.norm(free @ slide_z) > 0.99
    assert pinning.spread[1] > 10.0 and np.all(np.diff(pinning.spread) <= 0.0)  # free: 20 deg and more
    line = int(np.argmax(np.abs(pinning.directions @ np.eye(6)[0])))  # the turn about the line through both
    assert line == 2 and 1.0 < pinning.spread[line] < 5.0  # weakly pinned, as the figurine's grasp
    # each contact's shared error counts as `bias_points` points of `bias_noise_m`: the push's spread
    normal = sum(per_frame for per_frame, _ in information.values()) * config.pixel_noise_m**2
    expected = config.bias_noise_m / np.sqrt(config.bias_points * normal[3, 3] / len(sides["left"])) / 0.002
    assert pinning.spread[np.argmax(np.abs(pinning.directions @ push_x))] == pytest.approx(expected, rel=0.05)
    drift = np.radians(1.0) * spin + 0.0002 * slide_z + 0.0003 * push_x + np.radians(0.1) * np.eye(6)[0]
    pinned, weak = pinning.split(drift)
    np.testing.assert_allclose(pinned + weak, drift, atol=1e-15)
    turn_x = np.radians(0.1) * np.eye(6)[0]  # weak beyond 1 unit, pinned within 5
    np.testing.assert_allclose(weak, np.radians(1.0) * spin + 0.0002 * slide_z + turn_x, atol=2e-6)
    pinned, weak = pinning.split(drift, weak_above=5.0)
    np.testing.assert_allclose(pinned, 0.0003 * push_x + turn_x, atol=2e-6)
    assert "pinned to" in pinning.describe(0)


def _cylinder_sensors(radius_m: float) -> dict[str, np.ndarray]:
    """T_object_sensor of the two opposite contacts of `_two_contacts`: each sensor's z into the cylinder, its x
    along the cylinder's axis."""
    sensors = {}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2] = [0.0, 0.0, 1.0], [0.0, sign, 0.0], [-sign, 0.0, 0.0]
        T[:3, 3] = [sign * radius_m, 0.0, 0.0]
        sensors[side] = T
    return sensors


def test_a_contacts_own_tilt_left_out_leaves_a_turn_only_the_tilts_pin_to_the_tilts_prior(rng):
    """Two opposite contacts on a cylinder pin a turn about an axis in both pads (y here) only through each
    contact's tilt: with each contact's tilt a nuisance of sigma, that turn keeps about 2 / sigma^2 of information
    (each contact's own share C / (C + (pixel / sigma)^2) of it), the push along their normal all of its own, and the
    turn about the line through them (pinned by the curvature, no tilt) most of its own."""
    from yoto.tracking.frame_registration import contact_information
    from yoto.tracking.track import CorrectionConfig

    radius, sigma = 0.03, 0.003
    points = _two_contacts(radius)
    surface = _cylinder(radius, 0.0, rng)
    sides = {"left": points[: len(points) // 2], "right": points[len(points) // 2 :]}
    tilts = {side: (T[:3, :2].T, sigma) for side, T in _cylinder_sensors(radius).items()}
    config = CorrectionConfig()
    plain = sum(f for f, _ in contact_information(surface, sides, config, False).values())
    without = sum(f for f, _ in contact_information(surface, sides, config, False, tilts).values())
    turn_x, turn_y, push_x = np.eye(6)[0], np.eye(6)[1], np.eye(6)[3]
    tilt_points = (sides["left"][:, 2] - sides["left"][:, 2].mean()) ** 2  # each contact's C about its pad's x
    ratio = (config.pixel_noise_m / sigma) ** 2
    expected = 2.0 / sigma**2 * tilt_points.sum() / (tilt_points.sum() + ratio)
    assert turn_y @ without @ turn_y == pytest.approx(expected, rel=0.02)
    assert turn_y @ plain @ turn_y > 4.0 * expected  # the tilts alone, believed, pin it far more
    assert push_x @ without @ push_x == pytest.approx(push_x @ plain @ push_x, rel=1e-6)
    assert turn_x @ without @ turn_x > 0.8 * (turn_x @ plain @ turn_x)
    # sigma 0: the normal matrices as they were
    off = {side: (axes, 0.0) for side, (axes, _) in tilts.items()}
    np.testing.assert_array_equal(
        sum(f for f, _ in contact_information(surface, sides, config, False, off).values()), plain
    )


def test_a_contact_read_tilted_turns_the_registration_by_what_its_tilts_prior_leaves(rng):
    """One contact on a cylinder read turned by 5 mrad about its pad's y axis (through its centre): registered
    alone, the correction turns the object back by all of it; with its tilt a nuisance of sigma equal to the
    registration's rotation prior, by half (the two priors share it), the estimate of the joint Gauss-Newton."""
    from yoto.geometry import pose_from_twist, twist_of_pose
    from yoto.tracking.frame_registration import register_contacts, registration_solver
    from yoto.tracking.track import CorrectionConfig

    radius, tilt = 0.03, 0.005
    points = _two_contacts(radius)[:256]
    centre = points.mean(axis=0)
    sensors = _cylinder_sensors(radius)
    turn = pose_from_twist(np.array([0.0, tilt, 0.0, 0.0, 0.0, 0.0]))
    read = (points - centre) @ turn[:3, :3].T + centre  # a turn about y moves the contact along its normal
    surface = _cylinder(radius, 0.0, rng)
    config = CorrectionConfig()
    solver = registration_solver(config)
    sides, facing = {"left": read}, {"left": sensors["left"]}
    believed = twist_of_pose(register_contacts(surface, sides, facing, solver))
    assert believed[1] == pytest.approx(-tilt, rel=0.03)
    prior = config.registration_prior_rotation_rad
    nuisance = twist_of_pose(register_contacts(surface, sides, facing, solver, {"left": prior}))
    assert nuisance[1] == pytest.approx(-tilt / 2.0, rel=0.05)
    np.testing.assert_allclose(nuisance[[0, 2]], 0.0, atol=2e-4)


def _wedge(half_gap_m: float, slant_rad: float) -> tuple[_Surface, dict[str, np.ndarray]]:
    """Two flat 30 x 30 mm faces at +-x leaning toward +z by `slant_rad` (a wedge), sampled every 0.3 mm, and the
    points of an 8 x 8 mm contact on each (left at +x, right at -x; the sensors of `_cylinder_sensors(half_gap_m)`).
    A spin about x (the line through the contacts) tilts each face by the spin times sin(slant): the pair pins it
    only through their planes, a tilt of theirs by 1 / tan(slant) times as much."""
    u, v = (
        grid.ravel()[:, None]
        for grid in np.meshgrid(np.arange(-0.015, 0.015, 0.0003), np.arange(-0.015, 0.015, 0.0003))
    )
    a, b = (
        grid.ravel()[:, None] for grid in np.meshgrid(np.linspace(-0.004, 0.004, 16), np.linspace(-0.004, 0.004, 16))
    )
    points, normals, contacts = [], [], {}
    for side, sign in (("left", 1.0), ("right", -1.0)):
        normal = np.array([sign * np.cos(slant_rad), 0.0, np.sin(slant_rad)])
        up = np.array([-sign * np.sin(slant_rad), 0.0, np.cos(slant_rad)])  # along the face, y the other way
        centre, across = np.array([sign * half_gap_m, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
        points.append(centre + u * across + v * up)
        normals.append(np.broadcast_to(normal, points[-1].shape))
        contacts[side] = centre + a * across + b * up
    return _Surface(np.vstack(points), np.vstack(normals)), contacts


def _turned(points: np.ndarray, axis: list[float], angle_rad: float) -> np.ndarray:
    """A contact's points turned about their centre."""
    from yoto.geometry import so3_exp

    centre = points.mean(axis=0)
    return (points - centre) @ so3_exp((np.array(axis) * angle_rad)[None])[0].T + centre


def test_a_tilt_that_would_move_the_landing_far_is_not_estimated_and_one_that_would_not_is():
    """A wedge 1 deg off square: its two contacts read tilted by 1 mrad each about their pads' x (world z), in the
    pattern a spin about the line through them makes (left and right opposite). The registration without tilts
    spins the object by the lever 1 / tan(1 deg) (1.2 units); with every tilt estimated (stop 20) the tilts take
    0.37 units of it; with the move limit that combination (0.3 units per 1 mrad, above the 0.15 limit) is not
    estimated and the landing is the untilted one's. On a cylinder (its contacts pinned by the curvature) a contact
    read tilted 3 mrad about the cylinder's axis is still taken up as with every tilt estimated."""
    from yoto.geometry import twist_of_pose
    from yoto.tracking.frame_registration import observable_unit, register_contacts, registration_solver
    from yoto.tracking.track import CorrectionConfig

    config = CorrectionConfig()
    solver, unit = registration_solver(config), observable_unit(config)
    limit = 0.15 * unit  # stop 21's measured limit (`contact_tilt_move_units`, off by default)
    sigma = {"left": 0.001, "right": 0.001}

    def landing(surface, sides, sensors, tilts=None, move_limit=None) -> np.ndarray:
        return twist_of_pose(register_contacts(surface, sides, sensors, solver, tilts, move_limit)) / unit

    half_gap = 0.015
    surface, sides = _wedge(half_gap, np.radians(1.0))
    sensors = _cylinder_sensors(half_gap)
    read = {
        "left": _turned(sides["left"], [0.0, 0.0, 1.0], 0.001),
        "right": _turned(sides["right"], [0.0, 0.0, 1.0], -0.001),
    }
    untilted = landing(surface, read, sensors)
    assert untilted[0] > 1.0  # 1 mrad read as more than 2 deg (1.64 units by the lever, less the prior's pull)
    every = landing(surface, read, sensors, sigma)
    assert untilted[0] - every[0] > 0.3
    limited = landing(surface, read, sensors, sigma, limit)
    np.testing.assert_allclose(limited, untilted, atol=0.005)
    np.testing.assert_allclose(landing(surface, sides, sensors, sigma, limit), 0.0, atol=1e-3)  # read exact

    radius = 0.03
    surface, points = _cylinder(radius, 0.0, np.random.default_rng(0)), _two_contacts(radius)
    sensors = _cylinder_sensors(radius)
    read = {"left": _turned(points[:256], [0.0, 0.0, 1.0], 0.003), "right": points[256:]}
    untilted, every = landing(surface, read, sensors), landing(surface, read, sensors, sigma)
    assert untilted[2] < -0.15 and every[2] > -0.1  # about the axis the spin it would mean, half taken up
    np.testing.assert_allclose(landing(surface, read, sensors, sigma, limit), every, atol=1e-3)


def test_a_retouch_is_found_where_the_surface_moves_along_its_normal_and_none_where_it_slides_along_itself(rng):
    """Two opposite contacts at +-x on a cylinder about z: a turn about x (the line through them) moves the surface
    along its normal most at +-y and the cylinder's ends (|z| 15 mm: 0.52 mm per unit of 2 deg), barely at the
    contacts; the cylinder's spin about its axis and a slide along it move no point along its normal."""
    from yoto.tracking.track import CorrectionConfig, observable_unit, retouch

    radius, unit = 0.03, observable_unit(CorrectionConfig())
    surface = _cylinder(radius, 0.0, rng)
    contacts = _two_contacts(radius)
    turn_x = np.eye(6)[0] * unit
    advice = retouch(surface, turn_x, contacts)
    assert abs(advice.point[1]) > 0.028 and abs(advice.point[2]) > 0.012  # at +-y, near an end
    assert abs(advice.normal[1]) > 0.99
    assert advice.seen_m == pytest.approx(0.014 * unit[0], rel=0.1)  # the patch's |z| about 14 mm
    assert advice.seen_at_contacts_m < 0.1 * advice.seen_m
    for free in (np.eye(6)[2] * unit, np.eye(6)[5] * unit):  # spin about z, slide along z
        assert retouch(surface, free, contacts).seen_m < 1e-3 * advice.seen_m
    moved = advice.in_frame(np.diag([1.0, -1.0, -1.0, 1.0]))  # the same advice in a frame turned about x
    np.testing.assert_allclose(moved.point, advice.point * [1.0, -1.0, -1.0])
    assert "mm along its normal" in advice.describe()


def test_the_final_drift_is_the_offset_the_motion_left_without_the_outputs_jitter(rng):
    """Errors that jitter frame to frame (0.1 mm, 0.05 deg per axis) about an offset that the motion moved by 0.3 mm
    / 0.2 deg: the final drift (mean error settled against the mean just before the motion) finds that change; the
    per-frame drift, from one reference frame, carries that frame's jitter and is several times further off."""
    from yoto.geometry import pose_from_twist
    from yoto.tracking.evaluate import TrackingErrors, summarize_errors

    times = np.arange(0.0, 5.0, 0.01)
    final, per_frame = [], []
    for _ in range(10):
        twists = np.hstack([rng.normal(0.0, np.radians(0.05), (len(times), 3)), rng.normal(0.0, 1e-4, (len(times), 3))])
        twists += [np.radians(0.5), 0.0, 0.0, 0.0, 2e-4, 0.0]  # the touch's error, the same before and after
        twists[times > 3.0] += [0.0, np.radians(0.2), 0.0, 3e-4, 0.0, 0.0]
        summary = summarize_errors(TrackingErrors(times, pose_from_twist(twists), np.eye(4)), (1.0, 3.0))
        final.append([summary["final_drift"]["mm"] - 0.3, summary["final_drift"]["deg"] - 0.2])
        per_frame.append([summary["settled_drift"]["mm"] - 0.3, summary["settled_drift"]["deg"] - 0.2])
    final_off, per_frame_off = np.abs(final), np.abs(per_frame)
    assert final_off[:, 0].max() < 0.07 and final_off[:, 1].max() < 0.04
    assert per_frame_off.mean(axis=0)[0] > 2 * final_off.mean(axis=0)[0]
    assert per_frame_off.mean(axis=0)[1] > 2 * final_off.mean(axis=0)[1]


def test_benchmark_report_gives_the_drifts_growth_with_path_length_and_its_standard_error():
    """Two touches tracked at 100 and 200 mm: their final drifts grow by 0.1 and 0.3 deg, so the growth per 100 mm is
    0.2 +- 0.1 deg (mean, standard error); a pair with a wrong touch at either length is left out."""
    from yoto.tracking.bench import TrackBenchConfig, build_report, format_markdown

    def record(final_deg: float, right: bool = True) -> dict:
        entry = _bench_record(0.1, 0.2, right)
        entry["closed_loop"] = {**entry["closed_loop"], "final_drift": {"mm": 0.1, "deg": final_deg}}
        return entry

    records = {
        "thing": {
            "100mm": [record(0.2), record(0.4), record(0.3)],
            "200mm": [record(0.3), record(0.7), record(2.0, right=False)],
        }
    }
    config = TrackBenchConfig(trajectories=3, path_lengths_m=(0.1, 0.2))
    report = build_report(records, config)
    growth = report["growth"]["all"]
    assert growth["pairs"] == 2
    assert growth["final_drift_deg"]["mean"] == pytest.approx(0.2)
    assert growth["final_drift_deg"]["standard_error"] == pytest.approx(0.1)
    assert growth["final_drift_mm"]["mean"] == pytest.approx(0.0)
    assert "| thing | 2 | +0.200 +- 0.100 |" in format_markdown(report)
    assert build_report(records, TrackBenchConfig(trajectories=3))["growth"] == {}
