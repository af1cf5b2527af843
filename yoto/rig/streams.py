"""Recordings in, time-stamped streams out: the one entry point to bags, Motive CSV takes and GelSight PNG folders.

    read_pose_stream(path, topic_or_body) -> PoseStream     (unpacks as timestamps_s, T_world_body (N, 4, 4))
    read_point_stream(path, topic_or_marker) -> PointStream (unpacks as timestamps_s, p_world (N, 3))
    read_image_stream(path, topic_or_folder) -> ImageStream (timestamps and frames loaded on demand)
    open_recording(path) -> Recording                       (the same, for several streams of one recording)

`path` is a ROS1 `.bag`, a ROS2 bag (folder, `.db3` or `.mcap`) or a Motive `.csv`. A rigid body is named by its
topic (`/vrpn_client_node/RigLeft/pose`), by its name (the one pose topic whose path holds it, else its TF child
frame) or, in a Motive take, by its rigid-body name. GelSight frames come from an image topic of a bag, or from
a folder of PNGs named by their timestamp in seconds (`1712.345678.png`), beside a Motive take: PNG stamps on
the take's clock (seconds since it started) or on the wall clock (POSIX seconds; matched through the take's
`Capture Start Time`, read as local time); `time_offset_s` overrides.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError
from yoto.geometry import make_transform, quaternion_xyzw_to_rotation, rotation_to_quaternion_xyzw
from yoto.rig import bags
from yoto.rig.motive import MotiveTake, is_motive_csv, read_motive_csv
from yoto.rig.timeline import PointStream, PoseStream, Stream, clean_timeline, make_point_stream, make_pose_stream
from yoto.sensor.presses import COLOUR_IMAGE_MODES, PNG_HEADER_BYTES, is_grey_png, load_image
from yoto.sensor.spec import GELSIGHT_MINI, GelSightSpec
from yoto.trajectory import LARGEST_PLAUSIBLE_TIMESTAMP_S

IMAGE_SUFFIXES = (".png",)
FRAMES_CHECKED_UP_FRONT = 5  # a stream is refused when none of its first frames is a GelSight frame of the size
FRAME_NUMBER_BELOW = 1e6  # integer PNG names below this, one apart, are frame numbers, not seconds
# sensor_msgs/Image encodings of colour frames: channels, their order, bytes per channel. `8uc3` is what cv_bridge
# writes for an OpenCV image without an encoding: OpenCV's BGR. Alpha is dropped; 16-bit channels keep their top 8 bits.
RAW_ENCODINGS = {
    "rgb8": (3, "rgb", 1),
    "bgr8": (3, "bgr", 1),
    "rgba8": (4, "rgb", 1),
    "bgra8": (4, "bgr", 1),
    "8uc3": (3, "bgr", 1),
    "rgb16": (3, "rgb", 2),
    "bgr16": (3, "bgr", 2),
    "rgba16": (4, "rgb", 2),
    "bgra16": (4, "bgr", 2),
}
# A bag stores messages in receive order; header stamps may lag that order by network delays up to this. Further
# back is a broken clock (a restarted recorder), refused by `clean_timeline`.
MAX_REORDER_S = 1.0


@dataclass
class ImageStream(Stream):
    """Time-stamped GelSight frames; `frames(indices)` loads (H, W, 3) uint8 RGB frames on demand."""

    loader: Callable[[np.ndarray], Iterator[tuple[int, np.ndarray]]] | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def frames(self, indices: np.ndarray | list[int]) -> Iterator[tuple[int, np.ndarray]]:
        """(index, frame) for the requested indices (in time order, or a bag's order where its stamps lag it)."""
        assert self.loader is not None
        yield from self.loader(np.unique(np.asarray(indices, dtype=int)))

    def frame(self, index: int) -> np.ndarray:
        return next(self.frames([index]))[1]


def stamp_order(stamps_s: np.ndarray) -> np.ndarray:
    """The order that sorts a bag topic's header stamps, when they lag the bag's receive order by at most
    MAX_REORDER_S; else the bag order, which `clean_timeline` then refuses naming the step back."""
    bag_order = np.arange(len(stamps_s))
    if len(stamps_s) == 0 or not np.isfinite(stamps_s).all():
        return bag_order
    if (np.maximum.accumulate(stamps_s) - stamps_s).max() > MAX_REORDER_S:
        return bag_order
    return np.argsort(stamps_s, kind="stable")


# ---------------------------------------------------------------------------------------------------------
# Image decoding and checks


def check_frame_shape(frame: np.ndarray, spec: GelSightSpec, where: str, path: Path) -> np.ndarray:
    if frame.shape != (spec.height_px, spec.width_px, 3):
        raise InputError(
            f"{where}: GelSight frames are {frame.shape[1]}x{frame.shape[0]} px, but the {spec.name} gives "
            f"{spec.width_px}x{spec.height_px} (RGB): is this the GelSight topic, and is the camera at full size?",
            path,
        )
    return frame


def decode_image_message(message: Any, msgtype: str, spec: GelSightSpec, where: str, path: Path) -> np.ndarray:
    """An (H, W, 3) uint8 RGB frame from a sensor_msgs/Image (RAW_ENCODINGS) or CompressedImage (PNG, JPEG)."""
    if msgtype == "sensor_msgs/msg/CompressedImage":
        from PIL import Image, UnidentifiedImageError

        if is_grey_png(bytes(message.data[:PNG_HEADER_BYTES])):
            raise InputError(
                f"{where}: a compressed frame ({message.format}) is not a colour image (a greyscale PNG): is this the "
                "GelSight topic?",
                path,
            )
        try:
            with Image.open(io.BytesIO(bytes(message.data))) as image:
                if image.mode not in COLOUR_IMAGE_MODES:
                    raise InputError(
                        f"{where}: a compressed frame ({message.format}) is not a colour image (Pillow mode "
                        f"'{image.mode}'): is this the GelSight topic?",
                        path,
                    )
                frame = np.asarray(image.convert("RGB"))
        except (UnidentifiedImageError, OSError) as exc:
            raise InputError(
                f"{where}: a compressed frame ({message.format}) could not be decoded: {exc}", path
            ) from exc
        return check_frame_shape(frame, spec, where, path)
    encoding = str(message.encoding).lower()
    if encoding not in RAW_ENCODINGS:
        raise InputError(
            f"{where}: image encoding '{message.encoding}' is not supported; GelSight frames are colour: "
            f"{', '.join(RAW_ENCODINGS)}",
            path,
        )
    if (message.width, message.height) != (spec.width_px, spec.height_px):
        raise InputError(
            f"{where}: frames are {message.width}x{message.height} px, but the {spec.name} gives "
            f"{spec.width_px}x{spec.height_px}: is this the GelSight topic, and is the camera at full size?",
            path,
        )
    channels, order, size = RAW_ENCODINGS[encoding]
    row_bytes = message.width * channels * size
    data = np.frombuffer(bytes(message.data), dtype=np.uint8)
    if len(data) < message.step * message.height or message.step < row_bytes:
        raise InputError(f"{where}: image data is shorter than height x step ({len(data)} bytes)", path)
    rows = data[: message.step * message.height].reshape(message.height, message.step)[:, :row_bytes]
    if size == 2:  # 16 bits a channel: the top 8 bits, in the message's byte order
        wide = np.ascontiguousarray(rows).view(">u2" if message.is_bigendian else "<u2")
        rows = (wide >> 8).astype(np.uint8)
    frame = rows.reshape(message.height, message.width, channels)[:, :, :3]
    return np.ascontiguousarray(frame if order == "rgb" else frame[:, :, ::-1])


def first_readable(read: Callable[[int], np.ndarray], count: int) -> np.ndarray:
    """The first of a stream's first FRAMES_CHECKED_UP_FRONT frames that `read` decodes (a stream is refused up
    front for its size or encoding, not for one frame cut short at its start); raises the first frame's error when
    none of them reads."""
    errors: list[InputError] = []
    for k in range(min(count, FRAMES_CHECKED_UP_FRONT)):
        try:
            return read(k)
        except InputError as exc:
            errors.append(exc)
    if errors:
        raise errors[0]
    raise InputError("no GelSight frames")


def _stamp_text(path: Path) -> str:
    """The part of a frame's file name that holds its timestamp: after the last underscore, before the suffix."""
    return path.name[: -len(path.suffix)].rsplit("_", 1)[-1]


def png_timestamp(path: Path) -> float:
    """The timestamp (seconds) in a frame's file name: `1712.345678.png` or `left_1712.345678.png`."""
    try:
        stamp = float(_stamp_text(path))
    except ValueError as exc:
        raise InputError("GelSight PNG names must be their timestamp in seconds (e.g. 1712.345678.png)", path) from exc
    if not abs(stamp) <= LARGEST_PLAUSIBLE_TIMESTAMP_S:
        raise InputError(
            f"the file name reads as {stamp:.4g} s, after the year 5000: GelSight PNGs are named by their time in "
            "seconds (are these milliseconds or nanoseconds since 1970?)",
            path,
        )
    return stamp


def _refuse_frame_numbers(files: list[Path], times_s: np.ndarray, folder: Path) -> None:
    """Refuse a folder whose PNGs are numbered frame by frame (`0000.png`, `frame_0001.png`) rather than stamped:
    read as seconds, a 30 frames/s capture would pass for one frame a second and match the wrong mocap samples.
    Whole-second wall-clock stamps (`1712345678.png`) are ~1e9 and pass."""
    stamps = [_stamp_text(p) for p in files]
    if len(files) < 2 or not all(s.isdigit() for s in stamps):
        return
    steps = np.diff(np.sort(times_s))
    numbered = any(len(s) > 1 and s.startswith("0") for s in stamps) or times_s.max() < FRAME_NUMBER_BELOW
    if numbered and np.all(steps == 1):
        raise InputError(
            f"the {len(files)} GelSight PNGs are numbered {times_s.min():.0f} to {times_s.max():.0f} frame by frame, "
            "not named by their timestamp in seconds (e.g. 1712.345678.png): rename them to their capture times",
            folder,
        )


def image_folder_stream(folder: Path, spec: GelSightSpec = GELSIGHT_MINI, offset_s: float = 0.0) -> ImageStream:
    """The PNGs of a folder, in time order (times shifted by -offset_s onto the recording's clock)."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not files:
        raise InputError("no GelSight frames (*.png named by their timestamp) in the folder", folder)
    times = np.array([png_timestamp(p) for p in files])
    prefixes = sorted({p.name[: -len(p.suffix) - len(_stamp_text(p))] for p in files})
    if len(prefixes) > 1:  # `left_12.3.png` beside `right_12.3.png`: two sensors' frames would be read as one's
        named = ", ".join(f"{prefix or '(none)'}*.png" for prefix in prefixes)
        raise InputError(
            f"the folder holds GelSight PNGs of several sensors ({named}): give each sensor a folder of its own", folder
        )
    _refuse_frame_numbers(files, times, folder)
    order = np.argsort(times, kind="stable")
    files, times = [files[i] for i in order], times[order]
    kept, dropped, rate = clean_timeline(times, np.ones(len(times), bool), folder, folder.name)
    files, times = [files[i] for i in kept], times[kept]
    first_readable(lambda k: load_image(files[k], spec), len(files))  # colour, the sensor's size: checked up front

    def load(indices: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
        for i in indices:
            yield int(i), load_image(files[i], spec)

    return ImageStream(folder, folder.name, times - offset_s, dropped, rate, load, {"files": files})


def bag_image_stream(reader: Any, path: Path, topic: str, spec: GelSightSpec) -> ImageStream:
    msgtype = reader.topics[topic].msgtype
    where = f"topic '{topic}'"
    stamps, log_times, first = [], [], []
    for k, (stamp, log_time, message) in enumerate(bags.read_messages(reader, topic, path)):
        if k < FRAMES_CHECKED_UP_FRONT:
            first.append(message)
        stamps.append(stamp)
        log_times.append(log_time)
    if not stamps:
        raise InputError(f"topic '{topic}' holds no frames", path)
    # Size and encoding, up front (a depth topic, a camera at another size).
    first_readable(lambda k: decode_image_message(first[k], msgtype, spec, where, path), len(first))
    order = stamp_order(np.asarray(stamps))
    times = np.asarray(stamps)[order]
    kept, dropped, rate = clean_timeline(times, np.ones(len(times), bool), path, topic)
    kept = order[kept]  # indices of the messages in bag order, in time order
    log_ns = np.asarray(log_times, dtype=np.int64)
    kept_log = log_ns[kept]

    by_log_time: dict[int, list[int]] = {}
    for original, log_time in enumerate(log_times):
        by_log_time.setdefault(int(log_time), []).append(original)

    def load(indices: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
        if len(indices) == 0:
            return
        wanted = {int(kept[i]): int(i) for i in indices}
        start, stop = int(kept_log[indices].min()), int(kept_log[indices].max()) + 1
        seen: dict[int, int] = {}
        with bags.open_bag(path) as bag:
            for connection, log_time, message in bags.raw_messages(bag, path, topic, start=start, stop=stop):
                # The message's place in the topic: messages sharing a receive time come in bag order.
                k = seen.get(log_time, 0)
                seen[log_time] = k + 1
                same_time = by_log_time.get(int(log_time), [])
                original = same_time[k] if k < len(same_time) else -1
                if original in wanted:
                    yield wanted[original], decode_image_message(message, connection.msgtype, spec, where, path)

    return ImageStream(path, topic, np.asarray(stamps)[kept], dropped, rate, load, {"msgtype": msgtype})


# ---------------------------------------------------------------------------------------------------------
# Recordings


class Recording:
    """One recording (bag or Motive take) and the streams in it."""

    def __init__(self, path: str | Path, time_offset_s: float | None = None, spec: GelSightSpec = GELSIGHT_MINI):
        self.path = Path(path)
        self.spec = spec
        self.time_offset_s = time_offset_s
        self.take: MotiveTake | None = None
        if not self.path.exists():
            raise InputError("recording not found", self.path)
        if is_motive_csv(self.path):
            self.take = read_motive_csv(self.path)
        elif not bags.is_bag(self.path):
            raise InputError(
                "not a recording YOTO reads: expected a ROS1 .bag, a ROS2 bag (folder, .db3 or .mcap) or a Motive "
                ".csv export",
                self.path,
            )

    @property
    def kind(self) -> str:
        return "motive" if self.take is not None else "bag"

    def pose(self, selector: str) -> PoseStream:
        """A rigid body's pose stream (see the module docstring for how it is named)."""
        if self.take is not None:
            return self.take.rigid_body(selector)
        with bags.open_bag(self.path) as reader:
            types = bags.POSE_TYPES
            try:
                topic = bags.resolve_topic(reader, self.path, selector, types, "a rigid body")
            except InputError:
                links = bags.tf_links(reader, self.path)
                child = selector.strip("/")
                if child not in links:
                    raise
                return self._tf_stream(links, child)
            msgtype = reader.topics[topic].msgtype
            stamps, positions, quaternions = [], [], []
            for stamp, _, message in bags.read_messages(reader, topic, self.path):
                position, orientation = bags.pose_fields(message, msgtype)
                stamps.append(stamp)
                positions.append((position.x, position.y, position.z))
                quaternions.append((orientation.x, orientation.y, orientation.z, orientation.w))
        if not stamps:
            raise InputError(f"topic '{topic}' holds no messages", self.path)
        order = stamp_order(np.asarray(stamps))
        return make_pose_stream(
            self.path, topic, np.asarray(stamps)[order], np.asarray(positions)[order], np.asarray(quaternions)[order]
        )

    def _tf_link_stream(self, link: bags.TfLink, frame: str) -> PoseStream:
        """One TF link's `T_parent_frame` over time, in header-stamp order."""
        name = f"{'/'.join(sorted(link.topics))}:{frame}"
        order = stamp_order(np.asarray(link.stamps_s))
        positions, quaternions = np.asarray(link.positions)[order], np.asarray(link.quaternions_xyzw)[order]
        return make_pose_stream(self.path, name, np.asarray(link.stamps_s)[order], positions, quaternions)

    def _tf_stream(self, links: dict[str, bags.TfLink], child: str) -> PoseStream:
        """A TF child frame's pose in the root of its TF tree (the mocap world): its transforms composed with its
        ancestors', each taken at the child's stamps (a static one as it is; a moving one interpolated)."""
        body = self._tf_link_stream(links[child], child)
        stamps, T_root_child = body.timestamps_s, body.T_world_body
        covered = np.ones(len(stamps), bool)
        chain = [child]
        while True:
            parents = links[chain[-1]].parents
            if len(parents) > 1:
                raise InputError(
                    f"TF frame '{chain[-1]}' has several parents ({', '.join(sorted(parents))}): not a tree", self.path
                )
            parent = next(iter(parents))
            if parent in chain:
                raise InputError(f"the TF frames {' -> '.join([*chain, parent])} form a loop", self.path)
            if parent not in links:
                break  # the root: the mocap world frame
            chain.append(parent)
            link = links[parent]
            if link.static:
                rotation = quaternion_xyzw_to_rotation(np.asarray(link.quaternions_xyzw[-1]))
                T_root_child = make_transform(rotation, np.asarray(link.positions[-1])) @ T_root_child
            else:
                T_parent_at, matched = self._tf_link_stream(link, parent).at(stamps)
                covered &= matched
                T_root_child = np.where(matched[:, None, None], T_parent_at, np.eye(4)) @ T_root_child
        positions = np.where(covered[:, None], T_root_child[:, :3, 3], np.nan)  # uncovered: dropouts
        quaternions = rotation_to_quaternion_xyzw(T_root_child[:, :3, :3])
        name = body.name if len(chain) == 1 else f"{body.name} (TF {' <- '.join([parent, *reversed(chain)])})"
        return make_pose_stream(self.path, name, stamps, positions, quaternions)

    def point(self, selector: str) -> PointStream:
        """A single marker's position stream (PointStamped topic or name; a Motive marker name)."""
        if self.take is not None:
            return self.take.marker(selector)
        with bags.open_bag(self.path) as reader:
            topic = bags.resolve_topic(reader, self.path, selector, bags.POINT_TYPES, "a marker")
            stamps, positions = [], []
            for stamp, _, message in bags.read_messages(reader, topic, self.path):
                stamps.append(stamp)
                positions.append((message.point.x, message.point.y, message.point.z))
        if not stamps:
            raise InputError(f"topic '{topic}' holds no messages", self.path)
        order = stamp_order(np.asarray(stamps))
        return make_point_stream(self.path, topic, np.asarray(stamps)[order], np.asarray(positions)[order])

    def images(self, selector: str) -> ImageStream:
        """GelSight frames: an image topic of a bag, or a folder of time-stamped PNGs beside a Motive take."""
        if self.take is None:
            with bags.open_bag(self.path) as reader:
                topic = bags.resolve_topic(reader, self.path, selector, bags.IMAGE_TYPES, "GelSight images")
                return bag_image_stream(reader, self.path, topic, self.spec)
        folder = Path(selector)
        if not folder.is_absolute() and not folder.is_dir():
            folder = self.path.parent / selector
        if not folder.is_dir():
            raise InputError(
                f"GelSight frames for a Motive take come from a folder of PNGs; no folder '{selector}'", self.path
            )
        raw = image_folder_stream(folder, self.spec)
        offset = self.time_offset_s if self.time_offset_s is not None else self._image_offset(raw)
        raw.timestamps_s = raw.timestamps_s - offset
        raw.details["time_offset_s"] = offset
        return raw

    def _image_offset(self, stream: ImageStream) -> float:
        """Which clock the PNG stamps use: the take's (offset 0) or the wall clock (the take's start time)."""
        assert self.take is not None
        t0, t1 = float(self.take.times_s[0]), float(self.take.times_s[-1])
        a, b = stream.span_s
        candidates = [0.0]
        start = self.take.capture_start_epoch_s
        if start is not None:
            candidates.append(start)
        for offset in candidates:
            overlap = min(b - offset, t1) - max(a - offset, t0)
            if overlap > 0.5 * min(b - a, t1 - t0):
                return offset
        raise InputError(
            f"the GelSight frames in {stream.source} ({a:.3f} to {b:.3f} s) do not overlap the take ({t0:.3f} to "
            f"{t1:.3f} s after its start, {self.take.header.get('Capture Start Time', 'no start time')}): give the "
            "offset between the two clocks (--time-offset)",
            self.path,
        )

    def describe(self) -> str:
        if self.take is not None:
            return self.take.describe()
        return ", ".join(summary.name for summary in bags.bag_topics(self.path))


def open_recording(path: str | Path, time_offset_s: float | None = None) -> Recording:
    return Recording(path, time_offset_s)


def read_pose_stream(path: str | Path, topic_or_body: str) -> PoseStream:
    """A rigid body's poses `T_world_body` (mocap world frame, metres) from a bag or a Motive CSV.

    Occluded frames are left out (`dropped` counts them). Unpacks as `(timestamps_s, T_world_body)`.
    """
    return Recording(path).pose(topic_or_body)


def read_point_stream(path: str | Path, topic_or_marker: str) -> PointStream:
    """A single marker's positions (mocap world frame, metres). Unpacks as `(timestamps_s, p_world)`."""
    return Recording(path).point(topic_or_marker)


def read_image_stream(
    path: str | Path, topic_or_folder: str, time_offset_s: float | None = None, spec: GelSightSpec = GELSIGHT_MINI
) -> ImageStream:
    """GelSight frames with their timestamps from a bag's image topic, or from a folder of PNGs (`path` may then
    be the folder itself, or the Motive take the folder belongs to); frames of `spec`'s size (the calibration's)."""
    path = Path(path)
    if path.is_dir() and not bags.is_bag(path):
        return image_folder_stream(path, spec, offset_s=time_offset_s or 0.0)
    return Recording(path, time_offset_s, spec).images(topic_or_folder)


__all__ = [
    "ImageStream",
    "PointStream",
    "PoseStream",
    "Recording",
    "open_recording",
    "read_image_stream",
    "read_point_stream",
    "read_pose_stream",
]
