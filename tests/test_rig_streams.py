"""Recordings in: Motive CSV takes (as Motive writes them), ROS1/ROS2 bags through rosbags, time matching, bad input."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest
from conftest import TOL

from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations
from yoto.rig.motive import read_motive_csv, write_motive_csv
from yoto.rig.streams import open_recording, read_image_stream, read_point_stream, read_pose_stream
from yoto.rig.timeline import clean_timeline, make_pose_stream

CSV_M = 1e-6  # Motive CSV cells carry 6 decimals: 1e-6 m in metres, 1e-9 m in millimetres


def _take(rng, frames=50):
    times = np.arange(frames) / 100.0
    T = np.tile(np.eye(4), (frames, 1, 1))
    T[:, :3, :3] = random_rotations(rng, frames)
    T[:, :3, 3] = rng.uniform(-1, 1, size=(frames, 3))
    marker = rng.uniform(-1, 1, size=(frames, 3))
    T[[3, 4, 5]] = np.nan  # occluded
    marker[[10]] = np.nan
    return times, T, marker


@pytest.mark.parametrize("units", ["Meters", "Millimeters"])
def test_motive_csv_round_trip(tmp_path, rng, units):
    times, T, marker = _take(rng)
    path = write_motive_csv(
        tmp_path / "take.csv",
        times,
        {"RigLeft": T},
        {"GelBall": marker},
        capture_start=dt.datetime(2024, 3, 1, 14, 15, 30, 250000),
        frame_rate_hz=100.0,
        length_units=units,
    )
    t, T_read = read_pose_stream(path, "RigLeft")
    valid = np.isfinite(T).all(axis=(1, 2))
    np.testing.assert_allclose(t, times[valid], atol=TOL["float"])
    np.testing.assert_allclose(T_read[:, :3, 3], T[valid, :3, 3], atol=CSV_M)
    np.testing.assert_allclose(T_read[:, :3, :3], T[valid, :3, :3], atol=1e-5)
    stream = read_pose_stream(path, "RigLeft")
    assert stream.dropped == 3 and abs(stream.rate_hz - 100.0) < 1e-6
    points = read_point_stream(path, "GelBall")
    assert len(points) == len(times) - 1 and points.dropped == 1
    np.testing.assert_allclose(points.p_world, marker[np.isfinite(marker).all(axis=1)], atol=CSV_M)
    take = read_motive_csv(path)
    assert take.capture_start_epoch_s == dt.datetime(2024, 3, 1, 14, 15, 30, 250000).timestamp()


MOTIVE_EXPORT = """Format Version,1.23,Take Name,Take 2024-03-01 02.15.30 PM,Take Notes,,Capture Frame Rate,120.000000,\
Export Frame Rate,120.000000,Capture Start Time,2024-03-01 02.15.30.250 P.M.,Capture Start Frame,11234,\
Total Frames in Take,3,Total Exported Frames,3,Rotation Type,Quaternion,Length Units,Millimeters,Coordinate Space,Global

,Type,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body,Rigid Body Marker,\
Rigid Body Marker,Rigid Body Marker,Rigid Body Marker,Marker,Marker,Marker
,Name,Drill,Drill,Drill,Drill,Drill,Drill,Drill,Drill,Drill:Marker1,Drill:Marker1,Drill:Marker1,Drill:Marker1,\
Unlabeled 1000,Unlabeled 1000,Unlabeled 1000
,ID,1,1,1,1,1,1,1,1,1:1,1:1,1:1,1:1,1000,1000,1000
,,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Mean Marker Error,Position,Position,Position,\
Marker Quality,Position,Position,Position
Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,,X,Y,Z,,X,Y,Z
0,0.000000,0.000000,0.000000,0.707107,0.707107,100.000000,200.000000,300.000000,0.000120,101.0,201.0,301.0,1.0,5.0,6.0,7.0
1,0.008333,,,,,,,,,,,,,5.1,6.1,7.1
2,0.016667,0.000000,0.000000,0.707107,0.707107,100.500000,200.000000,300.000000,0.000130,101.5,201.0,301.0,1.0,,,
"""


def test_reads_a_file_as_motive_exports_it(tmp_path):
    """Not our writer's output: Motive's own columns (rigid-body markers, marker quality, an occluded frame)."""
    path = tmp_path / "drill.csv"
    path.write_text(MOTIVE_EXPORT)
    t, T = read_pose_stream(path, "Drill")
    np.testing.assert_allclose(t, [0.0, 0.016667])
    np.testing.assert_allclose(T[0, :3, 3], [0.1, 0.2, 0.3], atol=TOL["float"])
    np.testing.assert_allclose(T[1, :3, 3], [0.1005, 0.2, 0.3], atol=TOL["float"])
    np.testing.assert_allclose(T[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)  # 90 deg about z
    _, p = read_point_stream(path, "Drill:Marker1")
    np.testing.assert_allclose(p[1], [0.1015, 0.201, 0.301], atol=TOL["float"])
    times, p = read_point_stream(path, "Unlabeled 1000")
    assert len(times) == 2
    with pytest.raises(InputError, match="no rigid body 'Mug'.*rigid bodies: Drill"):
        read_pose_stream(path, "Mug")


def test_motive_euler_export_and_unknown_units_are_refused(tmp_path):
    path = tmp_path / "euler.csv"
    path.write_text(MOTIVE_EXPORT.replace("Rotation Type,Quaternion", "Rotation Type,XYZ"))
    with pytest.raises(InputError, match=r"euler.csv.*'XYZ'.*Quaternion"):
        read_pose_stream(path, "Drill")
    path.write_text(MOTIVE_EXPORT.replace("Length Units,Millimeters", "Length Units,Furlongs"))
    with pytest.raises(InputError, match="Furlongs"):
        read_pose_stream(path, "Drill")


def test_interpolation_is_exact_on_uniform_motion_and_never_bridges_a_long_gap(rng):
    times = np.concatenate([np.arange(0, 1, 0.01), np.arange(1.5, 2, 0.01)])  # a 0.5 s dropout
    angles = 0.5 * times
    q = np.stack([np.zeros_like(times), np.zeros_like(times), np.sin(angles / 2), np.cos(angles / 2)], axis=1)
    positions = np.outer(times, [0.1, -0.2, 0.3])
    stream = make_pose_stream(Path("x"), "body", times, positions, q)
    query = np.array([0.123, 0.5555, 1.73])
    T, ok = stream.at(query)
    assert ok.all()
    np.testing.assert_allclose(T[:, :3, 3], np.outer(query, [0.1, -0.2, 0.3]), atol=TOL["float"])
    expected = np.stack([make_transform(_rz(0.5 * t), np.zeros(3))[:3, :3] for t in query])
    np.testing.assert_allclose(T[:, :3, :3], expected, atol=TOL["float"])
    _, ok = stream.at(np.array([1.2, 2.5]))
    assert not ok.any()  # inside the dropout, after the end
    assert stream.dropped == 50  # 1.00 to 1.49 s


def _rz(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_clock_jumps_are_refused_with_the_time_and_stream():
    with pytest.raises(InputError, match=r"rec.bag.*'/rig'.*jumps back by 0.500 s at t = 1.000"):
        clean_timeline(np.array([0.0, 0.5, 1.0, 0.5, 1.1]), np.ones(5, bool), Path("rec.bag"), "/rig")
    with pytest.raises(InputError, match="jumps forward by 100.0 s"):
        clean_timeline(np.array([0.0, 0.5, 100.5]), np.ones(3, bool), Path("rec.bag"), "/rig")
    with pytest.raises(InputError, match="never tracked"):
        clean_timeline(np.array([0.0, 0.5, 1.0]), np.array([False, True, False]), Path("rec.bag"), "/rig")


# ---------------------------------------------------------------------------------------------------------
# Bags


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(3)
    return [rng.integers(0, 256, size=(240, 320, 3), dtype=np.uint8) for _ in range(3)]


def _write_bag(path, kind, frames, rng, encoding="rgb8", size=(240, 320)):
    from yoto.rig.bags import BagWriter

    poses = []
    with BagWriter(path, kind) as writer:
        for k in range(20):
            t = 1_700_000_000.0 + 0.01 * k
            T = make_transform(random_rotations(rng, 1)[0], rng.normal(size=3))
            poses.append(T)
            writer.write(
                "/vrpn_client_node/RigLeft/pose", "geometry_msgs/msg/PoseStamped", t, writer.pose_stamped(t, "world", T)
            )
            writer.write("/tf", "tf2_msgs/msg/TFMessage", t, writer.tf_message(t, "world", "Object", T))
            writer.write(
                "/mocap/marker/GelBall", "geometry_msgs/msg/PointStamped", t, writer.point_stamped(t, "world", T[:3, 3])
            )
        for k, frame in enumerate(frames):
            t = 1_700_000_000.0 + 0.05 * k
            image = frame[: size[0], : size[1]]
            writer.write("/gelsight/image_raw", "sensor_msgs/msg/Image", t, writer.image(t, "gel", image, encoding))
            writer.write(
                "/gelsight/compressed", "sensor_msgs/msg/CompressedImage", t, writer.compressed_image(t, "gel", image)
            )
    return np.array(poses)


@pytest.mark.parametrize("kind", ["ros1", "ros2-db3", "ros2-mcap"])
def test_bags_round_trip(tmp_path, rng, frames, kind):
    pytest.importorskip("rosbags")
    from yoto.rig.bags import bag_topics

    path = tmp_path / ("rec.bag" if kind == "ros1" else "rec")
    poses = _write_bag(path, kind, frames, rng, encoding="bgr8")
    for selector in ("/vrpn_client_node/RigLeft/pose", "RigLeft", "Object"):  # topic, name, TF child frame
        t, T = read_pose_stream(path, selector)
        np.testing.assert_allclose(t - 1_700_000_000.0, 0.01 * np.arange(20), atol=1e-6)
        np.testing.assert_allclose(T, poses, atol=1e-12)
    _, p = read_point_stream(path, "GelBall")
    np.testing.assert_allclose(p, poses[:, :3, 3], atol=1e-12)
    for topic in ("/gelsight/image_raw", "/gelsight/compressed"):
        stream = read_image_stream(path, topic)
        assert len(stream) == 3
        for index, frame in stream.frames([2, 0]):
            np.testing.assert_array_equal(frame, frames[index])
    topics = {s.name: s for s in bag_topics(path)}
    assert topics["/vrpn_client_node/RigLeft/pose"].count == 20
    assert abs(topics["/vrpn_client_node/RigLeft/pose"].rate_hz - 100.0) < 0.01
    assert topics["/gelsight/image_raw"].size == "320x240 bgr8"


def test_bag_errors_name_the_file_the_topic_and_the_problem(tmp_path, rng, frames):
    pytest.importorskip("rosbags")
    path = tmp_path / "rec.bag"
    _write_bag(path, "ros1", frames, rng)
    with pytest.raises(
        InputError, match=r"rec.bag: no topic '/natnet/RigRight/pose'.*topics in the bag: .*/gelsight/image_raw"
    ):
        read_pose_stream(path, "/natnet/RigRight/pose")
    with pytest.raises(
        InputError, match="topic '/gelsight/image_raw' has type sensor_msgs/msg/Image, but a rigid body"
    ):
        read_pose_stream(path, "/gelsight/image_raw")
    small = tmp_path / "small.bag"
    _write_bag(small, "ros1", frames, rng, size=(120, 160))
    with pytest.raises(InputError, match=r"small.bag: topic '/gelsight/image_raw': frames are 160x120 px.*320x240"):
        read_image_stream(small, "/gelsight/image_raw")
    mono = tmp_path / "mono.bag"
    from yoto.rig.bags import BagWriter

    with BagWriter(mono, "ros1") as writer:
        message = writer.image(1.0, "gel", frames[0], "rgb8")
        message.encoding = "mono16"
        writer.write("/gelsight/image_raw", "sensor_msgs/msg/Image", 1.0, message)
    with pytest.raises(InputError, match="mono.bag.*encoding 'mono16' is not supported"):
        read_image_stream(mono, "/gelsight/image_raw")
    (tmp_path / "take.txt").write_text("x")
    with pytest.raises(InputError, match="take.txt: not a recording YOTO reads"):
        open_recording(tmp_path / "take.txt")


def test_an_aborted_bag_leaves_nothing(tmp_path):
    pytest.importorskip("rosbags")
    from yoto.rig.bags import BagWriter

    with pytest.raises(RuntimeError), BagWriter(tmp_path / "rec.bag", "ros1") as writer:
        writer.write("/x", "geometry_msgs/msg/PointStamped", 1.0, writer.point_stamped(1.0, "w", np.zeros(3)))
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def _png_folder(folder: Path, names: list[str]) -> Path:
    from PIL import Image

    folder.mkdir()
    for k, name in enumerate(names):
        frame = np.full((240, 320, 3), 40 + k, np.uint8)  # each frame's grey level says which file it came from
        Image.fromarray(frame).save(folder / name)
    return folder


def test_png_folders_are_read_in_time_order_and_numbered_frames_are_refused(tmp_path):
    stamped = _png_folder(tmp_path / "stamped", ["left_12.500000.png", "left_12.466667.png", "left_12.533333.png"])
    stream = read_image_stream(stamped, str(stamped), time_offset_s=12.0)
    np.testing.assert_allclose(stream.timestamps_s, [0.466667, 0.5, 0.533333], atol=TOL["float"])
    levels = [int(frame[0, 0, 0]) for _, frame in stream.frames(np.arange(3))]
    assert levels == [41, 40, 42]  # sorted by stamp, not by name
    wall_clock = _png_folder(tmp_path / "wall", ["1712345678.png", "1712345679.png", "1712345680.png"])
    assert np.ptp(read_image_stream(wall_clock, str(wall_clock)).timestamps_s) == 2.0  # whole seconds are seconds
    for name, names in (("padded", ["0000.png", "0001.png", "0002.png"]), ("bare", ["f_8.png", "f_9.png", "f_10.png"])):
        folder = _png_folder(tmp_path / name, names)
        with pytest.raises(InputError, match="frame by frame") as error:
            read_image_stream(folder, str(folder))
        assert str(folder) in str(error.value)
