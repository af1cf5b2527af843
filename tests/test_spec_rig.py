"""Recordings as another lab's tools write them (SPEC "The real rig"), never through yoto's writers: ROS1 and ROS2
bags written with the `rosbags` package's own writers, OptiTrack Motive CSV exports written from Motive's layout.
yoto's readers must take them, or refuse them naming the file and the problem."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from conftest import TOL

from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations, rotation_to_quaternion_xyzw
from yoto.rig.streams import read_image_stream, read_point_stream, read_pose_stream

T0 = 1_700_000_000.0


class ForeignBag:
    """A bag written with rosbags' writers and typestores directly, as a lab's recorder would."""

    def __init__(self, path: Path, kind: str, compress: bool = False):
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.kind = kind
        if kind == "ros1":
            from rosbags.rosbag1 import Writer

            self.store = get_typestore(Stores.ROS1_NOETIC)
            self.store.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n", "tf2_msgs/msg/TFMessage")
            )
            self.writer = Writer(path)
            if compress:
                self.writer.set_compression(Writer.CompressionFormat.BZ2)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            self.store = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.SQLITE3 if kind == "db3" else StoragePlugin.MCAP
            self.writer = Writer(path, version=8, storage_plugin=plugin)
        self.writer.open()
        self.connections: dict[str, object] = {}
        self.types = self.store.types

    def header(self, stamp_s: float, frame: str):
        sec = int(stamp_s)
        stamp = self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp_s - sec) * 1e9)))
        if self.kind == "ros1":
            return self.types["std_msgs/msg/Header"](seq=7, stamp=stamp, frame_id=frame)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def write(self, topic: str, msgtype: str, receive_s: float, message) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        if self.kind == "ros1":
            data = self.store.serialize_ros1(message, msgtype)
        else:
            data = self.store.serialize_cdr(message, msgtype)
        self.writer.write(self.connections[topic], int(receive_s * 1e9), data)

    def quaternion(self, T: np.ndarray):
        q = rotation_to_quaternion_xyzw(T[:3, :3])
        return self.types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])

    def pose(self, stamp_s: float, frame: str, T: np.ndarray):
        position = self.types["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3])
        pose = self.types["geometry_msgs/msg/Pose"](position=position, orientation=self.quaternion(T))
        return self.types["geometry_msgs/msg/PoseStamped"](header=self.header(stamp_s, frame), pose=pose)

    def tf(self, stamp_s: float, parent: str, child: str, T: np.ndarray):
        translation = self.types["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3])
        transform = self.types["geometry_msgs/msg/Transform"](translation=translation, rotation=self.quaternion(T))
        stamped = self.types["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_s, parent), child_frame_id=child, transform=transform
        )
        return self.types["tf2_msgs/msg/TFMessage"](transforms=[stamped])

    def point(self, stamp_s: float, frame: str, p: np.ndarray):
        point = self.types["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2])
        return self.types["geometry_msgs/msg/PointStamped"](header=self.header(stamp_s, frame), point=point)

    def image(self, stamp_s: float, rgb: np.ndarray, encoding: str, padding: int):
        pixels = rgb if encoding == "rgb8" else rgb[:, :, ::-1]
        height, width = rgb.shape[:2]
        rows = np.zeros((height, width * 3 + padding), np.uint8)  # step > width x 3: padded rows (valid ROS)
        rows[:, : width * 3] = pixels.reshape(height, -1)
        return self.types["sensor_msgs/msg/Image"](
            header=self.header(stamp_s, "gelsight"),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=width * 3 + padding,
            data=rows.reshape(-1),
        )

    def compressed(self, stamp_s: float, rgb: np.ndarray, fmt: str):
        from PIL import Image

        buffer = io.BytesIO()
        Image.fromarray(rgb).save(buffer, format="JPEG" if fmt == "jpeg" else "PNG", quality=95)
        return self.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_s, "gelsight"),
            format=f"bgr8; {fmt} compressed bgr8",
            data=np.frombuffer(buffer.getvalue(), np.uint8),
        )

    def close(self) -> None:
        self.writer.close()


def _poses(rng, count):
    return np.array([make_transform(R, rng.normal(size=3) * 0.3) for R in random_rotations(rng, count)])


def _smooth_frame(rng) -> np.ndarray:
    """A GelSight-like frame (smooth shading): JPEG keeps it within a few levels."""
    rows, cols = np.mgrid[0:240, 0:320]
    base = np.stack(
        [120 + 60 * np.sin(cols / 40.0), 110 + 50 * np.cos(rows / 30.0), 140 + 40 * np.sin((rows + cols) / 50.0)]
    )
    return np.clip(base.transpose(1, 2, 0) + rng.normal(0, 1, size=(240, 320, 3)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One recording in each bag kind: stamps out of order, a TF tree, markers, raw and compressed frames."""
    pytest.importorskip("rosbags")
    rng = np.random.default_rng(11)
    folder = tmp_path_factory.mktemp("bags")
    truth = {
        "rig": _poses(rng, 40),
        "body": _poses(rng, 40),
        "arm": _poses(rng, 40),
        "world_mocap": _poses(rng, 1)[0],
        "frame": _smooth_frame(rng),
    }
    # Header stamps at 100 Hz; the recorder received them 0-30 ms late, so in the bag neighbours swap places.
    stamps = T0 + 0.01 * np.arange(40)
    receive = stamps + rng.uniform(0.0, 0.03, size=40)
    truth["stamps"] = stamps
    paths = {}
    for kind in ("ros1", "db3", "mcap"):
        path = folder / ("rec.bag" if kind == "ros1" else f"rec_{kind}")
        bag = ForeignBag(path, kind)
        bag.write("/tf_static", "tf2_msgs/msg/TFMessage", T0, bag.tf(T0, "world", "mocap", truth["world_mocap"]))
        for k in np.argsort(receive):
            t, T = stamps[k], truth["rig"][k]
            bag.write(
                "/vrpn_client_node/RigLeft/pose", "geometry_msgs/msg/PoseStamped", receive[k], bag.pose(t, "world", T)
            )
            bag.write("/mocap/GelBall", "geometry_msgs/msg/PointStamped", receive[k], bag.point(t, "world", T[:3, 3]))
            # The object two frames down: world -> mocap (static) -> Object; a gripper: mocap -> Arm -> Gripper.
            bag.write("/tf", "tf2_msgs/msg/TFMessage", receive[k], bag.tf(t, "mocap", "Object", truth["body"][k]))
            bag.write("/tf", "tf2_msgs/msg/TFMessage", receive[k], bag.tf(t, "mocap", "Arm", truth["arm"][k]))
            bag.write("/tf", "tf2_msgs/msg/TFMessage", receive[k], bag.tf(t, "Arm", "Gripper", truth["rig"][k]))
        for k in range(4):
            t = stamps[10 * k + 3]
            frame = np.roll(truth["frame"], k, axis=1)
            bag.write("/gelsight/image_raw", "sensor_msgs/msg/Image", t, bag.image(t, frame, "rgb8", 0))
            bag.write("/gelsight/bgr", "sensor_msgs/msg/Image", t, bag.image(t, frame, "bgr8", 64))
            for fmt in ("jpeg", "png"):
                topic = f"/gelsight/image_raw/compressed_{fmt}"
                bag.write(topic, "sensor_msgs/msg/CompressedImage", t, bag.compressed(t, frame, fmt))
        bag.close()
        paths[kind] = path
    return paths, truth


@pytest.mark.parametrize("kind", ["ros1", "db3", "mcap"])
def test_bags_from_rosbags_writers_stamps_out_of_order(recorded, kind):
    """Header stamps that lag the bag's receive order are the clock: sorted, not refused (fails on the old reader,
    which refused a stream whose clock stepped back)."""
    paths, truth = recorded
    t, T = read_pose_stream(paths[kind], "RigLeft")
    np.testing.assert_allclose(t, truth["stamps"], atol=1e-6, rtol=0)
    np.testing.assert_allclose(T, truth["rig"], atol=TOL["float_round_trip"])
    t, p = read_point_stream(paths[kind], "GelBall")
    np.testing.assert_allclose(p, truth["rig"][:, :3, 3], atol=TOL["float"])


@pytest.mark.parametrize("kind", ["ros1", "db3", "mcap"])
def test_tf_frames_down_the_tree_are_composed_to_the_world(recorded, kind):
    """A TF child two frames below the world (static and moving parents) is given in the world frame (the old
    reader returned its pose in its parent's frame: a silent wrong answer)."""
    paths, truth = recorded
    _, T = read_pose_stream(paths[kind], "Object")
    np.testing.assert_allclose(T, truth["world_mocap"] @ truth["body"], atol=TOL["float_round_trip"])
    t, T = read_pose_stream(paths[kind], "Gripper")
    np.testing.assert_allclose(t, truth["stamps"], atol=1e-6, rtol=0)
    np.testing.assert_allclose(T, truth["world_mocap"] @ truth["arm"] @ truth["rig"], atol=TOL["float_round_trip"])


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_bag_images_raw_padded_and_compressed(recorded, kind):
    paths, truth = recorded
    for topic, tolerance in (
        ("/gelsight/image_raw", 0),
        ("/gelsight/bgr", 0),
        ("/gelsight/image_raw/compressed_png", 0),
        ("/gelsight/image_raw/compressed_jpeg", 6),
    ):
        stream = read_image_stream(paths[kind], topic)
        np.testing.assert_allclose(stream.timestamps_s, truth["stamps"][[3, 13, 23, 33]], atol=1e-6, rtol=0)
        for index, frame in stream.frames([0, 3]):
            expected = np.roll(truth["frame"], index, axis=1).astype(int)
            assert np.abs(frame.astype(int) - expected).mean() <= tolerance / 3, topic
            assert np.abs(frame.astype(int) - expected).max() <= max(tolerance * 5, 0), topic


@pytest.mark.parametrize("kind", ["ros1", "db3", "mcap"])
def test_compressed_ros1_chunks_and_ros2_storage_without_metadata(tmp_path, rng, kind):
    pytest.importorskip("rosbags")
    path = tmp_path / ("rec.bag" if kind == "ros1" else "rec")
    bag = ForeignBag(path, kind, compress=True)
    poses = _poses(rng, 5)
    for k, T in enumerate(poses):
        bag.write("/rig/pose", "geometry_msgs/msg/PoseStamped", T0 + 0.01 * k, bag.pose(T0 + 0.01 * k, "world", T))
    bag.close()
    if kind != "ros1":
        (path / "metadata.yaml").unlink()  # the storage file alone, as copied off a robot
    np.testing.assert_allclose(read_pose_stream(path, "/rig/pose").T_world_body, poses, atol=TOL["float_round_trip"])


def test_gelsight_frames_whose_stamps_lag_the_bag_order_come_with_their_own_stamps(tmp_path, rng):
    pytest.importorskip("rosbags")
    bag = ForeignBag(tmp_path / "late.bag", "ros1")
    stamps = [10.0, 10.1, 10.05, 10.2, 10.15, 10.3]  # receive order; neighbours' header stamps swapped
    base = _smooth_frame(rng)
    for k, stamp in enumerate(stamps):
        frame = base.copy()
        frame[0, 0, 0] = k  # which message it is
        bag.write("/gel/image_raw", "sensor_msgs/msg/Image", 20.0 + 0.1 * k, bag.image(stamp, frame, "rgb8", 0))
    bag.close()
    stream = read_image_stream(tmp_path / "late.bag", "/gel/image_raw")
    np.testing.assert_allclose(stream.timestamps_s, sorted(stamps), atol=1e-9)
    for index, frame in stream.frames(range(6)):
        assert stamps[frame[0, 0, 0]] == pytest.approx(stream.timestamps_s[index], abs=1e-9)


def test_ros1_tf_of_the_older_tf_package(tmp_path, rng):
    """ROS1 bags recorded with the `tf` package carry `tf/tfMessage` (the fields of tf2's TFMessage)."""
    pytest.importorskip("rosbags")
    from rosbags.typesys import get_types_from_msg

    bag = ForeignBag(tmp_path / "old_tf.bag", "ros1")
    bag.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n", "tf/msg/tfMessage"))
    poses = _poses(rng, 6)
    for k, T in enumerate(poses):
        stamp = T0 + 0.01 * k
        message = bag.types["tf/msg/tfMessage"](transforms=bag.tf(stamp, "/world", "/RigLeft", T).transforms)
        bag.write("/tf", "tf/msg/tfMessage", stamp, message)
    bag.close()
    _, T = read_pose_stream(tmp_path / "old_tf.bag", "RigLeft")
    np.testing.assert_allclose(T, poses, atol=TOL["float_round_trip"])


def test_a_depth_topic_is_not_read_as_gelsight_frames(tmp_path):
    """A 16-bit greyscale PNG topic (a depth camera) is refused; the old reader clipped it to white frames."""
    pytest.importorskip("rosbags")
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.full((240, 320), 1000, np.uint16)).save(buffer, format="PNG")
    bag = ForeignBag(tmp_path / "depth.bag", "ros1")
    message = bag.types["sensor_msgs/msg/CompressedImage"](
        header=bag.header(T0, "depth"), format="16UC1; png compressed", data=np.frombuffer(buffer.getvalue(), np.uint8)
    )
    bag.write("/camera/depth/compressed", "sensor_msgs/msg/CompressedImage", T0, message)
    bag.close()
    with pytest.raises(InputError, match=r"depth.bag: topic '/camera/depth/compressed': .* not a colour image"):
        read_image_stream(tmp_path / "depth.bag", "/camera/depth/compressed")


def test_a_restarted_clock_is_still_refused(tmp_path):
    pytest.importorskip("rosbags")
    bag = ForeignBag(tmp_path / "restart.bag", "ros1")
    for k, stamp in enumerate([10.0, 10.01, 10.02, 3.0, 3.01, 3.02]):
        bag.write("/rig/pose", "geometry_msgs/msg/PoseStamped", 20.0 + 0.01 * k, bag.pose(stamp, "world", np.eye(4)))
    bag.close()
    with pytest.raises(InputError, match=r"restart.bag: stream '/rig/pose': the clock jumps back by 7.020 s"):
        read_pose_stream(tmp_path / "restart.bag", "/rig/pose")


# ---------------------------------------------------------------------------------------------------------
# Motive CSV, written from Motive's export layout


def foreign_motive_csv(
    path: Path, times: np.ndarray, T_body: np.ndarray, marker: np.ndarray, units: str, parent_row: bool
) -> Path:
    """A Motive export: header row, blank row, Type / Name / ID (/ Parent) rows, component and axis rows, frames;
    NaN poses written as empty cells (occluded frames)."""
    scale = {"Meters": 1.0, "Millimeters": 1000.0}[units]
    header = (
        "Format Version,1.24,Take Name,Take 2024-05-01 03.12.44 PM,Take Notes,,Capture Frame Rate,120.000000,"
        "Export Frame Rate,120.000000,Capture Start Time,2024-05-01 03.12.44.118 PM,Capture Start Frame,113,"
        f"Total Frames in Take,{len(times)},Total Exported Frames,{len(times)},Rotation Type,Quaternion,"
        f"Length Units,{units},Coordinate Space,Global"
    )
    kinds = ["Rigid Body"] * 8 + ["Rigid Body Marker"] * 4 + ["Marker"] * 3
    names = ["GelLeft"] * 8 + ["GelLeft:Marker1"] * 4 + ["Unlabeled 1001"] * 3
    ids = ["1"] * 8 + ["1"] * 4 + ["Unlabeled 1001"] * 3
    components = ["Rotation"] * 4 + ["Position"] * 3 + ["Mean Marker Error"] + ["Position"] * 3
    components += ["Marker Quality"] + ["Position"] * 3
    axes = ["X", "Y", "Z", "W", "X", "Y", "Z", "", "X", "Y", "Z", "", "X", "Y", "Z"]
    lines = [header, ""]
    lines += [",Type," + ",".join(kinds), ",Name," + ",".join(names), ",ID," + ",".join(ids)]
    if parent_row:
        lines.append(",Parent," + ",".join(["", "", "", "", "", "", "", ""] + ["GelLeft"] * 4 + [""] * 3))
    lines += [",," + ",".join(components), "Frame,Time (Seconds)," + ",".join(axes)]
    for frame, (t, T, p) in enumerate(zip(times, T_body, marker)):
        if np.isfinite(T).all():
            q = rotation_to_quaternion_xyzw(T[:3, :3])
            body = [f"{v:.6f}" for v in q] + [f"{v * scale:.6f}" for v in T[:3, 3]] + ["0.000213"]
            body += [f"{v * scale:.6f}" for v in T[:3, 3] + 0.01] + ["1.0"]
        else:
            body = [""] * 12
        body += [f"{v * scale:.6f}" for v in p]
        lines.append(f"{frame},{t:.6f}," + ",".join(body))
    path.write_text("\r\n".join(lines) + "\r\n", encoding="utf-8-sig")  # Motive writes a BOM and CRLF
    return path


@pytest.mark.parametrize("units, parent_row", [("Meters", False), ("Millimeters", True)])
def test_motive_exports_in_both_units_with_missing_frames(tmp_path, rng, units, parent_row):
    times = np.arange(30) / 120.0
    T_body = _poses(rng, 30)
    missing = [4, 5, 6, 20]
    T_body[missing] = np.nan
    marker = rng.normal(size=(30, 3)) * 0.2
    path = foreign_motive_csv(tmp_path / "take.csv", times, T_body, marker, units, parent_row)
    t, T = read_pose_stream(path, "GelLeft")
    kept = np.setdiff1d(np.arange(30), missing)
    np.testing.assert_allclose(t, times[kept], atol=1e-6, rtol=0)
    # Positions are written to 1e-6 of the file's unit; quaternions to 1e-6.
    np.testing.assert_allclose(T[:, :3, 3], T_body[kept, :3, 3], atol=1e-6 if units == "Meters" else 1e-9)
    np.testing.assert_allclose(T[:, :3, :3], T_body[kept, :3, :3], atol=1e-5)
    _, p = read_point_stream(path, "Unlabeled 1001")
    np.testing.assert_allclose(p, marker, atol=1e-6 if units == "Meters" else 1e-9)
    _, p = read_point_stream(path, "GelLeft:Marker1")
    np.testing.assert_allclose(p, T_body[kept, :3, 3] + 0.01, atol=1e-6 if units == "Meters" else 1e-9)
    with pytest.raises(InputError, match=r"take.csv: no rigid body 'GelRight' in the take \(rigid bodies: GelLeft"):
        read_pose_stream(path, "GelRight")


def test_rig_inspect_lists_what_another_recorder_wrote(recorded, tmp_path, rng, capsys):
    from yoto.cli import main

    paths, _ = recorded
    assert main(["rig", "inspect", str(paths["mcap"])]) == 0
    out = capsys.readouterr().out
    assert "/vrpn_client_node/RigLeft/pose" in out and "jpeg compressed" in out and "320x240 bgr8" in out
    times, T_body = np.arange(5) / 120.0, _poses(rng, 5)
    take = foreign_motive_csv(tmp_path / "take.csv", times, T_body, np.zeros((5, 3)), "Millimeters", False)
    assert main(["rig", "inspect", str(take)]) == 0
    assert "GelLeft" in capsys.readouterr().out
