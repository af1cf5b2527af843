"""Pose streams (TUM files, SPEC), interpolation, tactile frame folders, and reading streams from other sources."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from conftest import TOL

from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations, rotation_angle_rad, so3_exp
from yoto.io import write_ply_points
from yoto.tracking.streams import read_sensor_stream, read_tactile_stream
from yoto.trajectory import PoseStream, list_tactile_frames, read_tum, tactile_frame_name, write_tum


def _random_stream(rng, count=20, start=1_700_000_000.0):
    times = start + np.cumsum(rng.uniform(0.005, 0.02, size=count))
    poses = np.array([make_transform(r, rng.normal(size=3)) for r in random_rotations(rng, count)])
    return PoseStream(times, poses, "random")


def test_tum_round_trip_keeps_times_exact_and_poses_to_the_nanometre(tmp_path, rng):
    stream = _random_stream(rng)
    path = write_tum(tmp_path / "stream.tum", stream, "a comment\non two lines")
    text = path.read_text()
    assert text.startswith("# a comment\n# on two lines\n# timestamp tx ty tz qx qy qz qw\n")
    back = read_tum(path)
    assert np.array_equal(back.timestamps_s, stream.timestamps_s)  # shortest round-trip decimals
    assert np.abs(back.T_world_frame - stream.T_world_frame).max() < TOL["tum_text"]
    # Every written quaternion has w >= 0 (one of the two signs, chosen the same way every time).
    assert all(float(line.split()[7]) >= 0 for line in text.splitlines() if not line.startswith("#"))


def test_tum_reader_sorts_and_accepts_what_other_writers_write(tmp_path):
    half = np.sqrt(0.5)
    path = tmp_path / "other.txt"
    path.write_text(
        "# from another program\n\n"
        f"2.0, 1, 0, 0, 0, 0, {half}, {half}\n"
        "1.0 0 0 0 0 0 0 -1  # a trailing comment, and q = -identity\n"
        "1.0 0 0 0 0 0 0 -1\n"
    )
    stream = read_tum(path)
    assert stream.timestamps_s.tolist() == [1.0, 2.0]  # sorted, the exact repeat dropped
    assert np.allclose(stream.T_world_frame[0], np.eye(4))
    assert rotation_angle_rad(stream.T_world_frame[1], np.eye(4)) == pytest.approx(np.pi / 2, abs=TOL["arccos_rad"])
    assert np.allclose(stream.T_world_frame[1][:3, 3], [1, 0, 0])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "no poses"),
        ("1 0 0 0 0 0 0\n", "line 1 has 7 values"),
        ("1 0 0 0 0 0 0 1\n2 0 0 0 x 0 0 1\n", "line 2 is not numeric"),
        ("1 0 0 0 0 0 0 2\n", "not a unit quaternion"),
        ("1 0 0 0 0 0 0 1\n1 0 0 1 0 0 0 1\n", "different poses at the same time"),
        ("1 120 300 40 0 0 0 1\n", "millimetres"),
        ("1 nan 0 0 0 0 0 1\n", "NaN"),
    ],
)
def test_tum_reader_names_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as error:
        read_tum(path)
    assert str(path) in str(error.value)


def test_interpolation_is_exact_at_samples_and_geodesic_between(rng):
    rotation = random_rotations(rng, 1)[0]
    turn = so3_exp(np.array([0.0, 0.0, 0.8]))
    poses = np.array([make_transform(rotation, [0, 0, 0]), make_transform(rotation @ turn, [0.2, 0.0, -0.1])])
    stream = PoseStream(np.array([10.0, 11.0]), poses)
    sampled, covered = stream.interpolate(np.array([10.0, 10.25, 11.0, 9.0, 11.5]))
    assert covered.tolist() == [True, True, True, False, False]
    assert np.array_equal(sampled[0], poses[0]) and np.array_equal(sampled[2], poses[1])
    expected = make_transform(rotation @ so3_exp(np.array([0.0, 0.0, 0.2])), [0.05, 0.0, -0.025])
    assert np.abs(sampled[1] - expected).max() < TOL["float_round_trip"]
    # A gap longer than max_gap_s is a dropout: not covered, whatever lies on either side.
    _, covered = stream.interpolate(np.array([10.5]), max_gap_s=0.5)
    assert not covered[0]


def test_tactile_frame_folders(tmp_path, rng):
    folder = tmp_path / "left_tactile"
    stamps = [1_700_000_000.04, 1_700_000_000.0, 1_700_000_000.08]
    for stamp in stamps:
        points = rng.normal(size=(40, 3)) * 1e-3
        points[:, 2] = -np.abs(points[:, 2]) - 5e-4  # pressed into the gel (a flat noisy frame is no contact)
        write_ply_points(folder / tactile_frame_name(stamp), points)
    (folder / "notes.txt").write_text("ignored")
    timestamps, paths = list_tactile_frames(folder)
    assert timestamps.tolist() == sorted(stamps)
    stream = read_tactile_stream(folder)
    assert len(stream) == 3 and stream.load(1).shape == (40, 3)
    (folder / "frame_7.ply").write_bytes(b"")
    with pytest.raises(InputError, match="named <timestamp>.ply") as error:
        list_tactile_frames(folder)
    assert "frame_7.ply" in str(error.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no tactile frames"):
        list_tactile_frames(tmp_path / "empty")


def test_recordings_are_read_through_the_rig_readers(tmp_path, rng):
    """A Motive take and a ROS1 bag give `yoto track` the same sensor stream a TUM file would."""
    import datetime as dt

    from yoto.rig.motive import write_motive_csv

    expected = _random_stream(rng, 5, start=0.0)  # a take's clock starts at its first frame
    take = write_motive_csv(
        tmp_path / "take.csv",
        expected.timestamps_s,
        {"GelLeft": expected.T_world_frame},
        {},
        capture_start=dt.datetime(2024, 3, 1, 14, 15, 30),
        frame_rate_hz=100.0,
        length_units="Meters",
    )
    with pytest.raises(InputError, match="name the rigid body") as error:
        read_sensor_stream(take)
    assert str(take) in str(error.value)
    stream = read_sensor_stream(take, "GelLeft")
    np.testing.assert_allclose(stream.timestamps_s, expected.timestamps_s, atol=1e-6)
    np.testing.assert_allclose(stream.T_world_frame[:, :3, 3], expected.T_world_frame[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(stream.T_world_frame[:, :3, :3], expected.T_world_frame[:, :3, :3], atol=1e-5)

    pytest.importorskip("rosbags")
    from yoto.rig.bags import BagWriter

    bag = tmp_path / "session.bag"
    with BagWriter(bag, "ros1") as writer:
        for t, T in zip(expected.timestamps_s + 1.7e9, expected.T_world_frame, strict=True):
            topic, kind = "/vrpn_client_node/GelLeft/pose", "geometry_msgs/msg/PoseStamped"
            writer.write(topic, kind, t, writer.pose_stamped(t, "world", T))
    with pytest.raises(InputError, match="name the pose topic"):
        read_sensor_stream(bag)
    stream = read_sensor_stream(bag, "/vrpn_client_node/GelLeft/pose")
    np.testing.assert_allclose(stream.timestamps_s - 1.7e9, expected.timestamps_s, atol=1e-6)
    np.testing.assert_allclose(stream.T_world_frame, expected.T_world_frame, atol=1e-6)


def test_trajectory_options_for_streams_unlike_the_defaults(capsys):
    """`yoto simulate trajectory`'s options for another recorder's streams: rates, the gels' phase, cloud density
    and whole-pad clouds reach the simulator's config; the default is left as it was."""
    from yoto.cli import build_parser, main
    from yoto.simulate.cli import trajectory_config
    from yoto.simulate.trajectory import TrajectoryConfig, trajectory_settings

    base = ["simulate", "trajectory", "--object", "fruit", "-n", "1"]
    foreign = build_parser().parse_args(
        base
        + ["--pose-hz", "30", "--tactile-fps", "15", "--tactile-phase-ms", "33", "--pixel-stride", "4", "--whole-pad"]
    )
    config = trajectory_config(foreign)
    assert (config.left_rate_hz, config.right_rate_hz, config.tactile_rate_hz) == (30.0, 30.0, 15.0)
    assert config.tactile_phase_s == pytest.approx(0.033) and config.tactile_pixel_stride == 4
    assert config.tactile_whole_pad
    assert trajectory_config(build_parser().parse_args(base)) == TrajectoryConfig()
    fruit = SimpleNamespace(name="fruit", meta={})  # a folder of the defaults keeps the settings stored before them
    assert "tactile_whole_pad" not in trajectory_settings(fruit, 0, TrajectoryConfig())["config"]
    assert trajectory_settings(fruit, 0, config)["config"]["tactile_whole_pad"] is True
    assert main(base + ["--tactile-fps", "0"]) == 2
    assert "--tactile-fps must be positive" in capsys.readouterr().err


def test_commands_refuse_bad_arguments(capsys):
    from yoto.cli import main

    assert main(["simulate", "trajectory", "--object", "fruit", "-n", "0"]) == 2
    assert "-n must be at least 1" in capsys.readouterr().err
    assert main(["simulate", "trajectory", "--object", "fruit", "-n", "1", "--slip-mm", "-1"]) == 2
    assert "--slip-mm must not be negative" in capsys.readouterr().err
    assert main(["track-bench", "--objects", "fruit", "--path-lengths-mm", "0"]) == 2
    assert "path lengths must be positive" in capsys.readouterr().err
