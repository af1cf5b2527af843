"""SPEC's GelSight images as other programs write them (stop 14): frames and backgrounds in BGR order (OpenCV's
`imwrite` given an RGB array), bag image encodings other than rgb8 / bgr8, tactile frames during motion as images
(a folder of time-stamped PNGs, a bag's image topics) with an unreadable frame in the middle, and a touch whose sides
are images for `yoto track`.

Each writer follows SPEC.md or the format's own text (Pillow for PNG / JPEG, `rosbags`' own writers for bags), never
yoto's writers; see tests/test_spec_files.py and tests/test_spec_rig.py for the first pass.
"""

from __future__ import annotations

import io
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from yoto.cli import main
from yoto.errors import InputError
from yoto.geometry import make_transform
from yoto.sensor.spec import GELSIGHT_MINI as SPEC


@pytest.fixture(scope="module")
def gelsight():
    """A GelSight with other LEDs, gel and camera than the nominal one, calibrated from 8 ball presses it renders."""
    from yoto.sensor.shading import ShadingSensor, calibrate_shading_sensor

    rng = np.random.default_rng(5)
    sensor = ShadingSensor().varied(rng, 1.0)
    return sensor, calibrate_shading_sensor(sensor, rng, presses=8)


def _png(path: Path, rgb: np.ndarray) -> Path:
    Image.fromarray(np.ascontiguousarray(rgb)).save(path)
    return path


def _as_opencv_writes_rgb(path: Path, rgb: np.ndarray) -> Path:
    """`cv2.imwrite(path, rgb)`: OpenCV takes the array for BGR, so the file holds blue where red belongs."""
    return _png(path, rgb[:, :, ::-1])


def _height_map(points_sensor: np.ndarray) -> np.ndarray:
    """The height map a reconstruction's cloud samples (SPEC: a point per pixel centre, z <= 0), untouched gel 0."""
    height = np.zeros((SPEC.height_px, SPEC.width_px))
    columns = np.rint(points_sensor[:, 0] / SPEC.pixel_size_m + (SPEC.width_px - 1) / 2).astype(int)
    rows = np.rint(points_sensor[:, 1] / SPEC.pixel_size_m + (SPEC.height_px - 1) / 2).astype(int)
    height[rows, columns] = points_sensor[:, 2]
    return height


def _press(centre_px: tuple[float, float], radius_px: float = 26.0) -> np.ndarray:
    from yoto.sensor.sphere import press_height_map

    return press_height_map(*centre_px, radius_px, 3.155e-3, SPEC)


# ---------------------------------------------------------------------------------------------------------
# GelSight frames in BGR order


def test_frames_and_backgrounds_written_in_bgr_order_are_read_as_rgb(gelsight, tmp_path, caplog):
    """A pair whose PNGs (frames and background) an OpenCV script wrote from RGB arrays reconstructs to the very clouds
    of the same pair written in RGB, with a warning naming each file; before, the frames were refused as "another
    sensor, or the lighting changed". A frame of another sensor (channels rotated) is still refused, and frames of
    another size or in greyscale are errors naming the file."""
    from yoto.contacts import read_contact_pair
    from yoto.sensor.pair_images import ImageSides
    from yoto.sensor.reconstruction import reconstruct

    sensor, calibration = gelsight
    frames = {"left": sensor.render(_press((110.0, 90.0)), np.random.default_rng(1))}
    frames["right"] = sensor.render(_press((200.0, 150.0), 30.0), np.random.default_rng(2))
    background = sensor.background(np.random.default_rng(3))
    poses = {
        "left": make_transform(np.eye(3), [0.0, 0.0, 0.1]),
        "right": make_transform(np.diag([1, -1, -1]), [0, 0, 0]),
    }
    clouds = {}
    for name, write in (("rgb", _png), ("opencv", _as_opencv_writes_rgb)):
        folder = tmp_path / name
        (folder / "sensors").mkdir(parents=True)
        calibration.save(folder / "sensors" / "mini.npz")
        payload: dict = {"object": "fruit"}
        write(folder / "background.png", background)
        for side, frame in frames.items():
            write(folder / f"{side}.png", frame)
            payload[side] = {"image": f"{side}.png", "background": "background.png", "calibration": "sensors/mini.npz"}
            payload[side]["T_world_sensor"] = poses[side].tolist()
        (folder / "pair.json").write_text(json.dumps(payload))
        with caplog.at_level(logging.WARNING, logger="yoto"):
            pair = read_contact_pair(folder / "pair.json", ImageSides())
        clouds[name] = {side: pair.contact(side).points_sensor for side in frames}
    for side in frames:
        assert len(clouds["rgb"][side]) > 500
        np.testing.assert_array_equal(clouds["opencv"][side], clouds["rgb"][side])
    swapped = [r.getMessage() for r in caplog.records if "BGR order" in r.getMessage()]
    assert len(swapped) == 3 and all(str(tmp_path / "opencv") in message for message in swapped), swapped
    # Channels rotated (no writer's order: another sensor's colours) are not "corrected": refused, naming the frame.
    with pytest.raises(InputError, match="another sensor"):
        reconstruct(np.roll(frames["left"], 1, axis=2), calibration, source="rotated.png")
    # Another size (a 640x480 camera mode, a crop) and greyscale: errors naming the file and what it is.
    from yoto.sensor.pair_images import read_frame

    big = _png(tmp_path / "big.png", np.repeat(np.repeat(frames["left"], 2, axis=0), 2, axis=1))
    with pytest.raises(
        InputError, match=r"big.png: image is 640x480 with 3 channels but the gelsight_mini gives 320x240"
    ):
        read_frame(big, calibration)
    grey = _png(tmp_path / "grey.png", frames["left"].mean(axis=2).astype(np.uint8))
    with pytest.raises(InputError, match="grey.png: expected an 8-bit colour image"):
        read_frame(grey, calibration)


def test_sensor_reconstruct_reads_a_bgr_png_as_its_rgb_twin(gelsight, tmp_path):
    """`yoto sensor reconstruct` on a frame OpenCV wrote from an RGB array: the same cloud as from the RGB file."""
    from yoto.io import read_ply_points

    sensor, calibration = gelsight
    frame = sensor.render(_press((150.0, 120.0)), np.random.default_rng(4))
    cal = calibration.save(tmp_path / "mini.npz")
    clouds = []
    for name, write in (("rgb", _png), ("opencv", _as_opencv_writes_rgb)):
        image = write(tmp_path / f"{name}.png", frame)
        assert (
            main(
                ["sensor", "reconstruct", str(image), "--calibration", str(cal), "--out", str(tmp_path / f"{name}.ply")]
            )
            == 0
        )
        clouds.append(read_ply_points(tmp_path / f"{name}.ply")[0])
    assert len(clouds[0]) > 500
    np.testing.assert_array_equal(clouds[1], clouds[0])


# ---------------------------------------------------------------------------------------------------------
# Bag image encodings


def test_bag_image_encodings_other_recorders_use(tmp_path):
    """sensor_msgs/Image as other recorders write GelSight frames: rgba8 / bgra8 (alpha dropped), cv_bridge's 8UC3
    (OpenCV's BGR), 16 bits a channel in either byte order (the top 8 bits): all the same RGB frame. mono8 and 16UC1
    (a depth image) are refused naming the topic and the encoding."""
    pytest.importorskip("rosbags", reason="the rig extra (pip install 'yoto[rig]') is not installed")
    from rosbags.typesys import Stores, get_typestore

    from yoto.rig.streams import decode_image_message

    types = get_typestore(Stores.ROS2_HUMBLE).types
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, size=(240, 320, 3)).astype(np.uint8)
    alpha = np.full((240, 320, 1), 200, np.uint8)
    wide = rgb.astype(np.uint16) * 256 + rng.integers(0, 256, size=rgb.shape).astype(np.uint16)  # low byte: noise
    written = {
        "rgba8": (np.concatenate([rgb, alpha], axis=2), 0),
        "bgra8": (np.concatenate([rgb[:, :, ::-1], alpha], axis=2), 0),
        "8UC3": (rgb[:, :, ::-1], 0),
        "rgb16": (wide.astype(">u2"), 1),
        "bgr16": (wide[:, :, ::-1].astype("<u2"), 0),
    }

    def message(encoding: str, pixels: np.ndarray, big_endian: int):
        data = np.frombuffer(np.ascontiguousarray(pixels).tobytes(), np.uint8)
        header = types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="gel"
        )
        return types["sensor_msgs/msg/Image"](
            header=header,
            height=240,
            width=320,
            encoding=encoding,
            is_bigendian=big_endian,
            step=len(data) // 240,
            data=data,
        )

    for encoding, (pixels, big_endian) in written.items():
        frame = decode_image_message(
            message(encoding, pixels, big_endian), "sensor_msgs/msg/Image", SPEC, "topic '/gel'", tmp_path
        )
        np.testing.assert_array_equal(frame, rgb, err_msg=encoding)
    for encoding, pixels in (("mono8", rgb[:, :, 0]), ("16UC1", wide[:, :, 0].astype("<u2"))):
        with pytest.raises(InputError, match=f"topic '/gel': image encoding '{encoding}' is not supported"):
            decode_image_message(message(encoding, pixels, 0), "sensor_msgs/msg/Image", SPEC, "topic '/gel'", tmp_path)


# ---------------------------------------------------------------------------------------------------------
# Tactile frames during motion as images; a touch given as images


class _ForeignBag:
    """A ROS2 bag (mcap) written with rosbags' own writer: one GelSight image topic per sensor."""

    def __init__(self, path: Path):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_HUMBLE)
        self.writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections: dict[str, object] = {}

    def write(self, topic: str, stamp_s: float, message, msgtype: str) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        self.writer.write(self.connections[topic], int(stamp_s * 1e9), self.store.serialize_cdr(message, msgtype))

    def header(self, stamp_s: float):
        types = self.store.types
        sec = int(stamp_s)
        stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp_s - sec) * 1e9)))
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id="gelsight")


def test_an_image_topic_without_messages_is_named(tmp_path):
    """A bag whose GelSight topic holds no message (a recorder that subscribed and never got a frame): the error names
    the bag and the topic, not only "no GelSight frames"."""
    pytest.importorskip("rosbags", reason="the rig extra (pip install 'yoto[rig]') is not installed")
    from yoto.rig.streams import read_image_stream

    bag = _ForeignBag(tmp_path / "rec")
    bag.connections["/gelsight/image_raw"] = bag.writer.add_connection(
        "/gelsight/image_raw", "sensor_msgs/msg/Image", typestore=bag.store
    )
    bag.writer.close()
    with pytest.raises(InputError, match=r"rec: topic '/gelsight/image_raw' holds no frames"):
        read_image_stream(tmp_path / "rec", "/gelsight/image_raw")


def test_track_reads_tactile_frames_and_a_touch_given_as_images(builtin_models, gelsight, tmp_path, capsys):
    """`yoto track` on a touch whose sides are GelSight images (each naming its calibration), with tactile frames as
    a folder of `left_<t>.png` images and as a bag (left: raw frames tagged rgb8 holding BGR data; right: PNG
    CompressedImage, the first one cut short). Before: the image touch was refused ("needs the sensor's
    calibration") even with --calibration, an image folder was "no tactile frames", the mislabelled frames were all
    dropped and the cut first frame refused the whole topic. Now the image frames give clouds at the PLY frames'
    times and places, the bag's the very clouds of the PNG folder, and the cut frame is left out while the closed
    loop goes on."""
    pytest.importorskip("rosbags", reason="the rig extra (pip install 'yoto[rig]') is not installed")
    pytest.importorskip("open3d")
    from yoto.io import read_ply_points
    from yoto.simulate.trajectory import TrajectoryConfig, TrajectorySimulator, write_trajectory
    from yoto.tracking.streams import read_tactile_stream
    from yoto.trajectory import list_tactile_frames

    sensor, calibration = gelsight
    model = builtin_models["fruit"]
    model_path = model.save(tmp_path / "fruit.npz")
    config = TrajectoryConfig(motion_s=0.4, settle_s=0.1, hold_s=0.1, tactile_rate_hz=10.0, tactile_pixel_stride=1)
    ours = write_trajectory(TrajectorySimulator(model, config).trajectory(3, 1), model, tmp_path / "ours")
    theirs = tmp_path / "theirs"
    (theirs / "sensors").mkdir(parents=True)
    cal = calibration.save(theirs / "sensors" / "mini.npz")
    bag = _ForeignBag(theirs / "recording")
    types = bag.store.types
    frame_times = {}
    for k, side in enumerate(("left", "right")):
        folder = theirs / f"{side}_png"
        folder.mkdir()
        times, paths = list_tactile_frames(ours / f"{side}_tactile")
        frame_times[side] = times
        for i, (t, path) in enumerate(zip(times, paths)):
            frame = sensor.render(_height_map(read_ply_points(path)[0]), np.random.default_rng(100 * k + i))
            _png(folder / f"{side}_{t:.6f}.png", frame)
            if side == "left":  # an rgb8 tag on OpenCV's BGR data
                message = types["sensor_msgs/msg/Image"](
                    header=bag.header(t),
                    height=240,
                    width=320,
                    encoding="rgb8",
                    is_bigendian=0,
                    step=960,
                    data=np.ascontiguousarray(frame[:, :, ::-1]).reshape(-1),
                )
                bag.write("/gelsight_left/image_raw", t, message, "sensor_msgs/msg/Image")
            else:
                buffer = io.BytesIO()
                Image.fromarray(frame).save(buffer, format="PNG")
                data = np.frombuffer(buffer.getvalue(), np.uint8)
                data = data[: len(data) // 3] if i == 0 else data  # the first frame cut short: unreadable
                message = types["sensor_msgs/msg/CompressedImage"](
                    header=bag.header(t), format="rgb8; png compressed bgr8", data=data
                )
                bag.write("/gelsight_right/image_raw/compressed", t, message, "sensor_msgs/msg/CompressedImage")
    bag.writer.close()
    # The touch: its sides as images, each naming its calibration (relative to the touch file); no --calibration.
    touch = json.loads((ours / "touch.json").read_text())
    for side in ("left", "right"):
        points = read_ply_points(ours / touch[side]["points"])[0]
        _png(theirs / f"touch_{side}.png", sensor.render(_height_map(points), np.random.default_rng(7)))
        touch[side] = {
            "image": f"touch_{side}.png",
            "calibration": "sensors/mini.npz",
            **{"T_world_sensor": touch[side]["T_world_sensor"]},
        }
    (theirs / "touch.json").write_text(json.dumps(touch))
    # The touch's pose from a pose result (its truth): the pose stage is tested elsewhere; the touch is still read.
    (theirs / "pose.json").write_text(json.dumps({"T_world_object": touch["ground_truth"]["T_world_object"]}))
    for name in ("left.tum", "right.tum", "object_true.tum"):
        shutil.copy(ours / name, theirs / name)

    # The image folder: the PLY frames' times, clouds where the PLY frames' are.
    png: dict[str, list[np.ndarray]] = {}
    for side in ("left", "right"):
        stream = read_tactile_stream(theirs / f"{side}_png", calibration=cal)
        np.testing.assert_allclose(stream.timestamps_s, frame_times[side], rtol=0, atol=1e-6)
        png[side] = [stream.load(i) for i in range(len(stream))]
        for i, path in enumerate(list_tactile_frames(ours / f"{side}_tactile")[1]):
            truth, cloud = read_ply_points(path)[0], png[side][i]
            assert len(cloud) > 0.5 * len(truth), (side, i)
            assert np.linalg.norm(cloud.mean(axis=0) - truth.mean(axis=0)) < 3e-4, (side, i)
    # The bag: the PNG folder's clouds exactly (the mislabelled left frames read in RGB order); the cut frame refused.
    topics = {"left": "/gelsight_left/image_raw", "right": "/gelsight_right/image_raw/compressed"}
    for side, topic in topics.items():
        stream = read_tactile_stream(theirs / "recording", topic, cal)
        for i in range(len(stream)):
            if side == "right" and i == 0:
                with pytest.raises(InputError, match="could not be decoded"):
                    stream.load(i)
                continue
            np.testing.assert_array_equal(stream.load(i), png[side][i])

    args = ["track", str(theirs / "touch.json"), "--left", str(theirs / "left.tum"), "--right"]
    args += [str(theirs / "right.tum"), "--model", str(model_path), "--pose", str(theirs / "pose.json"), "--out"]
    args += [str(theirs / "object.tum"), "--truth", str(theirs / "object_true.tum")]
    args += ["--left-tactile", str(theirs / "recording"), "--left-tactile-topic", topics["left"]]
    args += ["--right-tactile", str(theirs / "recording"), "--right-tactile-topic", topics["right"]]
    assert main(args) == 0, capsys.readouterr()
    printed = capsys.readouterr().out
    assert "closed loop:" in printed and "unreadable 1" in printed, printed
    assert (theirs / "object.tum").is_file()


def test_image_frames_beside_a_motive_take_are_put_on_its_clock(gelsight, tmp_path):
    """`yoto track --left take.csv --left-topic RigLeft --left-tactile pngs/`: the take's poses are in seconds since
    it started, the PNGs named by their wall-clock time (as a GelSight capture script writes them): the frames come
    on the take's clock, anchored by its `Capture Start Time`, as the rig stage reads them."""
    from test_spec_inputs import _motive_take

    from yoto.rig.motive import read_motive_csv
    from yoto.tracking.streams import read_tactile_stream

    sensor, calibration = gelsight
    times = np.arange(0.0, 2.0, 0.1)
    take = _motive_take(tmp_path / "take.csv", times, {"RigLeft": np.repeat(np.eye(4)[None], len(times), axis=0)})
    start = read_motive_csv(take).capture_start_epoch_s
    assert start is not None
    folder = tmp_path / "left_frames"
    folder.mkdir()
    frame = sensor.render(_press((150.0, 120.0)), np.random.default_rng(4))
    stamps = (0.52, 0.92, 1.32)
    for t in stamps:
        _png(folder / f"gelsight_{start + t:.6f}.png", frame)
    cal = calibration.save(tmp_path / "mini.npz")
    stream = read_tactile_stream(folder, calibration=cal, recording=take)
    np.testing.assert_allclose(stream.timestamps_s, stamps, atol=1e-5)
    assert len(stream.load(1)) > 500
    on_their_own = read_tactile_stream(folder, calibration=cal)  # without the take: the names' own clock
    np.testing.assert_allclose(on_their_own.timestamps_s, np.add(stamps, start), atol=1e-5)


def test_calibrations_from_other_tools_are_refused_saying_what_they_are(gelsight, tmp_path):
    """A per-side `calibration` that is another tool's file (a lookup table saved with `np.save`, a JSON file, a
    pickled model) or a yoto calibration with a model setting this version does not know: errors naming the file
    and what it is (before, a JSON file read as "pickled (object) data"); extra top-level keys are kept."""
    from yoto.io import load_npz, save_npz_atomic
    from yoto.sensor.calibration import load_calibration

    _, calibration = gelsight
    np.save(tmp_path / "table.npy", np.zeros((8, 8, 8, 2)))
    (tmp_path / "calibration.json").write_text('{"gradient": "table.npy"}')
    expected = {"table.npy": r"a single NumPy array \(.npy\)", "calibration.json": "not a zip archive"}
    for name, what in expected.items():
        with pytest.raises(InputError, match=rf"{name}: not a readable sensor calibration file: .*{what}"):
            load_calibration(tmp_path / name)
    arrays, meta = load_npz(calibration.save(tmp_path / "mini.npz"), "sensor calibration")
    save_npz_atomic(tmp_path / "extra.npz", arrays, {**meta, "tool": {"name": "another", "version": 3}})
    assert load_calibration(tmp_path / "extra.npz").meta["tool"]["version"] == 3
    meta["model"]["gradient"]["a_new_setting"] = 1
    save_npz_atomic(tmp_path / "newer.npz", arrays, meta)
    with pytest.raises(InputError, match=r"newer.npz: .*GradientModelConfig settings .* \(a_new_setting\): .*newer"):
        load_calibration(tmp_path / "newer.npz")


def test_image_streams_take_the_size_of_the_calibration(tmp_path):
    """Frames of a sensor calibrated at another size (a 640x480 camera mode, here 64x48) are read at that size from a
    PNG folder when the calibration's spec is given (`yoto track` gives it); before, every such frame was refused as
    not 320x240. Without it, the GelSight Mini's size is still required, naming the file."""
    from yoto.rig.streams import read_image_stream
    from yoto.sensor.spec import GelSightSpec

    small = GelSightSpec(name="small", width_px=64, height_px=48, mm_per_px=0.3)
    frame = np.random.default_rng(3).integers(0, 256, size=(48, 64, 3)).astype(np.uint8)
    folder = tmp_path / "frames"
    folder.mkdir()
    for t in (10.0, 10.04):
        _png(folder / f"{t:.6f}.png", frame)
    stream = read_image_stream(folder, str(folder), spec=small)
    np.testing.assert_array_equal(stream.frame(1), frame)
    with pytest.raises(InputError, match="10.000000.png: image is 64x48 with 3 channels but the gelsight_mini gives"):
        read_image_stream(folder, str(folder))


def test_a_png_folder_of_both_sensors_or_in_milliseconds_is_refused(tmp_path):
    """One folder holding both GelSights' frames (`left_<t>.png`, `right_<t>.png`), as a capture script may write them:
    refused naming the prefixes (before: read as one sensor's frames, the right GelSight's among the left's); names in
    milliseconds refused (before: read as seconds, 50 000 years on)."""
    from yoto.rig.streams import read_image_stream

    frame = np.random.default_rng(3).integers(0, 256, size=(240, 320, 3)).astype(np.uint8)
    folder = tmp_path / "frames"
    folder.mkdir()
    for t in (10.0, 10.04):
        for side in ("left", "right"):
            _png(folder / f"{side}_{t:.6f}.png", frame)
    with pytest.raises(InputError, match=r"several sensors \(left_\*.png, right_\*.png\)"):
        read_image_stream(folder, str(folder))
    for path in folder.glob("right_*.png"):
        path.unlink()
    assert len(read_image_stream(folder, str(folder))) == 2
    # Names in milliseconds since 1970 (a camera driver's stamp): refused as the tactile PLY folders' are.
    millis = tmp_path / "millis"
    millis.mkdir()
    for t in (1_700_000_000_000, 1_700_000_000_040):
        _png(millis / f"left_{t}.png", frame)
    with pytest.raises(InputError, match=r"left_1700000000000.png: .*milliseconds or nanoseconds since 1970"):
        read_image_stream(millis, str(millis))


def test_a_damaged_bag_is_an_error_naming_it_not_a_traceback(tmp_path, capsys):
    """A ROS1 bag whose message record was overwritten (a recorder killed mid-write, a bad copy): every reader says
    the bag is damaged, naming it and the topic (before, rosbags' ReaderError came out of `yoto track` and `yoto rig`
    as a traceback)."""
    pytest.importorskip("rosbags", reason="the rig extra (pip install 'yoto[rig]') is not installed")
    from test_spec_rig import ForeignBag

    from yoto.rig.streams import read_pose_stream

    path = tmp_path / "take.bag"
    bag = ForeignBag(path, "ros1")
    for k in range(20):
        t = 100.0 + 0.01 * k
        bag.write("/vrpn_client_node/RigLeft/pose", "geometry_msgs/msg/PoseStamped", t, bag.pose(t, "world", np.eye(4)))
    bag.close()
    data = bytearray(path.read_bytes())
    record = data.find(b"op=\x02", data.find(b"op=\x02") + 1)  # the second message record's opcode
    data[record + 3] = 9  # no such record type
    path.write_bytes(bytes(data))
    with pytest.raises(
        InputError, match=r"take.bag: the bag is damaged: reading topic '/vrpn_client_node/RigLeft/pose'"
    ):
        read_pose_stream(path, "RigLeft")
    assert main(["rig", "inspect", str(path)]) == 2
    assert "the bag is damaged" in capsys.readouterr().err


def test_a_motive_take_resaved_in_another_locale_is_refused(tmp_path):
    """A take re-saved by a spreadsheet with decimal commas (`0,100000` in a comma-separated file) was read as one
    frame, silently; with ';' between cells it was "not a Motive CSV export". Both are now refused saying why."""
    from test_spec_inputs import _motive_take

    from yoto.rig.streams import read_pose_stream

    times = np.arange(0.0, 1.0, 0.1)
    take = _motive_take(tmp_path / "take.csv", times, {"Body": np.repeat(np.eye(4)[None], len(times), axis=0)})
    assert len(read_pose_stream(take, "Body").timestamps_s) == 10
    text = take.read_text(encoding="utf-8-sig")
    (tmp_path / "commas.csv").write_text(text.replace(".", ","), encoding="utf-8")
    with pytest.raises(InputError, match=r"commas.csv: frame row 8 has 17 cells but the column header 9: .*decimal"):
        read_pose_stream(tmp_path / "commas.csv", "Body")
    (tmp_path / "semicolons.csv").write_text(text.replace(",", ";").replace(".", ","), encoding="utf-8")
    with pytest.raises(InputError, match=r"semicolons.csv: the cells are separated by ';'"):
        read_pose_stream(tmp_path / "semicolons.csv", "Body")


def test_track_refuses_one_source_for_both_sensors(tmp_path, capsys, monkeypatch):
    """`--left-tactile-topic` and `--right-tactile-topic` naming the same bag topic (or one frame folder, or one pose
    file for both sensors): before, the left GelSight's frames were registered as the right one's too, silently."""
    (tmp_path / "frames").mkdir()
    common = ["track", str(tmp_path / "touch.json"), "--out", str(tmp_path / "object.tum")]
    cases = {
        "the left and right tactile frames are the same source, rec.bag (topic /gelsight/image_raw)": [
            *("--left", "l.tum", "--right", "r.tum", "--left-tactile", "rec.bag"),
            *("--right-tactile", "rec.bag", "--left-tactile-topic", "/gelsight/image_raw"),
            *("--right-tactile-topic", "/gelsight/image_raw"),
        ],
        "the left and right tactile frames are the same source, frames: give each sensor its own folder": [
            *("--left", "l.tum", "--right", "r.tum", "--left-tactile", "frames", "--right-tactile", "frames/"),
        ],
        "the left and right pose streams are the same source, l.tum: give each sensor its own file": [
            *("--left", "l.tum", "--right", "./l.tum"),
        ],
    }
    monkeypatch.chdir(tmp_path)
    for message, args in cases.items():
        assert main([*common, *args]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "object.tum").exists()


def test_tum_quaternions_written_w_first_are_named_in_the_touch_warning(builtin_models, tmp_path, rng, capsys):
    """A TUM stream written `timestamp tx ty tz qw qx qy qz` (pyquaternion's / transforms3d's order) holds unit
    quaternions, so it reads; at the touch its rotations are far from the pair's sensor poses. The warning now names
    the file whose quaternions fit when read w x y z (before: only "are they the same recording?")."""
    from test_spec_inputs import _tool_touch_at_ten_seconds, _tum_row

    model_path, touch, _ = _tool_touch_at_ten_seconds(builtin_models, tmp_path, rng)
    payload = json.loads(touch.read_text())
    times = np.arange(9.5, 11.0, 0.1)
    for side, order in (("left", [0, 1, 2, 6, 3, 4, 5]), ("right", list(range(7)))):
        row = _tum_row(np.asarray(payload[side]["T_world_sensor"]))[order]  # tx ty tz (qw) qx qy qz (qw)
        lines = [f"{t:.2f} " + " ".join(f"{v:.12f}" for v in row) for t in times]
        (tmp_path / f"{side}.tum").write_text("\n".join(lines) + "\n")
    args = ["track", str(touch), "--model", str(model_path), "--pose", str(tmp_path / "pose.json"), "--open-loop"]
    args += ["--left", str(tmp_path / "left.tum"), "--right", str(tmp_path / "right.tum")]
    assert main([*args, "--out", str(tmp_path / "object.tum")]) == 0
    printed = capsys.readouterr().out
    assert f"they fit if the quaternions of {tmp_path / 'left.tum'} are read as w x y z" in printed, printed


def test_tactile_frames_in_millimetres_or_flipped_are_left_out_saying_why(tmp_path, rng):
    """PLY frames another tool wrote in millimetres, or with z pointing into the gel: each load raises an InputError
    naming the frame and the likely cause, which the tracker counts as unreadable and prints (before: millimetres
    crashed `yoto track` allocating 33.7 GiB for its sampling grid; flipped frames were a silent "bad fit")."""
    from yoto.io import write_ply_points
    from yoto.tracking.streams import read_tactile_folder

    xy = rng.uniform(-0.004, 0.004, size=(400, 2))
    contact = np.column_stack([xy, -8e-4 + 20.0 * (xy**2).sum(axis=1)])  # a cap 0.8 mm deep, z < 0
    folders = {}
    for name, points in (("metres", contact), ("millimetres", 1e3 * contact), ("flipped", contact * [1, 1, -1])):
        folders[name] = tmp_path / name
        write_ply_points(folders[name] / "1700000000.000000.ply", points)
    np.testing.assert_allclose(read_tactile_folder(folders["metres"]).load(0), contact, atol=1e-7)
    with pytest.raises(InputError, match=r"1700000000.000000.ply: tactile frame spans 79\d\d mm, .*is it in metres"):
        read_tactile_folder(folders["millimetres"]).load(0)
    with pytest.raises(InputError, match="are its z values flipped"):
        read_tactile_folder(folders["flipped"]).load(0)


def test_bag_poses_in_millimetres_are_refused(tmp_path):
    """A mocap bridge that publishes Motive's millimetres in PoseStamped / PointStamped (ROS messages are metres): the
    stream is refused naming the topic (before: read as a rig 1.2 km away; `yoto track` only warned that the streams
    were far from the pair's sensor poses, `yoto rig` calibrated on it)."""
    pytest.importorskip("rosbags", reason="the rig extra (pip install 'yoto[rig]') is not installed")
    from test_spec_rig import ForeignBag

    from yoto.rig.streams import read_point_stream, read_pose_stream

    path = tmp_path / "take.bag"
    bag = ForeignBag(path, "ros1")
    for k in range(20):
        t = 100.0 + 0.01 * k
        T = make_transform(np.eye(3), [800.0 + k, 300.0, 1200.0])  # millimetres
        bag.write("/vrpn_client_node/RigLeft/pose", "geometry_msgs/msg/PoseStamped", t, bag.pose(t, "world", T))
        bag.write("/mocap/GelBall", "geometry_msgs/msg/PointStamped", t, bag.point(t, "world", T[:3, 3] / 1e3))
    bag.close()
    with pytest.raises(InputError, match=r"take.bag: '/vrpn_client_node/RigLeft/pose': positions reach 1200 m .*milli"):
        read_pose_stream(path, "RigLeft")
    np.testing.assert_allclose(read_point_stream(path, "GelBall").p_world[0], [0.8, 0.3, 1.2])
