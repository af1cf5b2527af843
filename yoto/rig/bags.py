"""ROS bags without ROS, through the `rosbags` package: ROS1 `.bag` files and ROS2 bags (`.db3` or `.mcap`,
a bag folder with its `metadata.yaml` or the storage file alone).

Reading: `bag_topics` (what `yoto rig inspect` prints), `read_messages` (one topic's messages with their header
stamps), `resolve_topic` (a topic named outright, or found from a rigid-body / marker name). Writing:
`BagWriter` (the recording simulator's output; also handy to convert a Motive take to a bag).

Message types understood (SPEC "The real rig"): rigid bodies as `geometry_msgs/PoseStamped` (also
`TransformStamped`, `PoseWithCovarianceStamped`, `nav_msgs/Odometry`, and TF: `tf2_msgs/TFMessage` by child frame,
composed up to the root of the TF tree), single markers as `geometry_msgs/PointStamped`, GelSight frames as
`sensor_msgs/Image` or `CompressedImage`. Header stamps are the clock (the bag's receive time only where a header
stamp is zero); messages are sorted by them where they lag the bag's receive order.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError, MissingDependencyError
from yoto.io import png_bytes

BAG_KINDS = ("ros1", "ros2-db3", "ros2-mcap")
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
)
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_TYPES = (TF_TYPE, "tf/msg/tfMessage")  # tf2's, and ROS1's older tf package's (same fields)
POINT_TYPES = ("geometry_msgs/msg/PointStamped",)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
TF_MSG_DEFINITION = "geometry_msgs/TransformStamped[] transforms\n"


def require_rosbags(purpose: str):
    try:
        import rosbags
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError("rosbags", "rig", purpose) from exc
    return rosbags


def is_bag(path: str | Path) -> bool:
    """A ROS1 .bag file, a ROS2 storage file (.db3, .mcap) or a ROS2 bag folder (with metadata.yaml)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(path.glob("*.db3")) or any(path.glob("*.mcap"))
    return path.suffix in (".bag", ".db3", ".mcap")


def _bag_path(path: Path) -> Path:
    """The path rosbags opens: a ROS2 folder without metadata.yaml is read through its single storage file."""
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        storage = sorted(path.glob("*.db3")) + sorted(path.glob("*.mcap"))
        if len(storage) != 1:
            raise InputError(
                f"a ROS2 bag folder without metadata.yaml must hold one .db3 or .mcap file, found {len(storage)}", path
            )
        return storage[0]
    return path


@contextlib.contextmanager
def open_bag(path: str | Path) -> Iterator[Any]:
    """An open `rosbags.highlevel.AnyReader` on one bag; errors name the file."""
    require_rosbags("reading ROS bags")
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise InputError("recording not found", path)
    try:
        reader = AnyReader([_bag_path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, FileNotFoundError, OSError, ValueError, KeyError) as exc:
        raise InputError(f"not a readable ROS bag ({type(exc).__name__}: {exc})", path) from exc
    try:
        yield reader
    finally:
        reader.close()


@dataclass
class TopicSummary:
    """One topic of a bag, as `yoto rig inspect` lists it."""

    name: str
    msgtype: str
    count: int
    start_s: float  # first and last header stamp (receive time for messages without a header)
    end_s: float
    frame: str  # header frame_id of the first message ("" without a header)
    size: str = ""  # image size and encoding of the first frame, for image topics

    @property
    def rate_hz(self) -> float:
        return (self.count - 1) / (self.end_s - self.start_s) if self.count > 1 and self.end_s > self.start_s else 0.0


def _stamp_s(message: Any, log_time_ns: int) -> float:
    header = getattr(message, "header", None)
    if header is None:
        return log_time_ns * 1e-9
    stamp = header.stamp
    value = float(stamp.sec) + float(stamp.nanosec) * 1e-9
    return value if value > 0 else log_time_ns * 1e-9


def bag_topics(path: str | Path) -> list[TopicSummary]:
    """Every topic of a bag with its type, message count, time span (header stamps) and rate."""
    summaries = []
    with open_bag(path) as reader:
        for name, info in sorted(reader.topics.items()):
            first = last = None
            frame, size = "", ""
            count = 0
            for connection, log_time, message in raw_messages(reader, Path(path), name):
                stamp = _stamp_s(message, log_time)
                if first is None:
                    first = stamp
                    header = getattr(message, "header", None)
                    frame = str(getattr(header, "frame_id", "")) if header is not None else ""
                    if connection.msgtype == "sensor_msgs/msg/Image":
                        size = f"{message.width}x{message.height} {message.encoding}"
                    elif connection.msgtype == "sensor_msgs/msg/CompressedImage":
                        size = f"compressed {message.format}"
                last = stamp
                count += 1
            summaries.append(TopicSummary(name, str(info.msgtype), count, first or 0.0, last or 0.0, frame, size))
    return summaries


def _topic_list(reader: Any) -> str:
    return ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(reader.topics.items())) or "none"


def resolve_topic(reader: Any, path: Path, selector: str, types: tuple[str, ...], what: str) -> str:
    """The topic a selector names: the topic itself, or the one topic of a matching type whose name contains
    the selector as a path segment (`RigLeft` -> `/vrpn_client_node/RigLeft/pose`). Errors list what exists."""
    topics = reader.topics
    if selector in topics:
        msgtype = topics[selector].msgtype
        if msgtype not in types:
            raise InputError(f"topic '{selector}' has type {msgtype}, but {what} needs {' or '.join(types)}", path)
        return selector
    name = selector.strip("/")
    candidates = [
        topic for topic, info in topics.items() if info.msgtype in types and name in topic.strip("/").split("/")
    ]
    if len(candidates) == 1:
        return candidates[0]
    if len(candidates) > 1:
        raise InputError(
            f"'{selector}' matches several {what} topics ({', '.join(sorted(candidates))}): name the topic", path
        )
    raise InputError(
        f"no topic '{selector}' for {what} ({' or '.join(types)}); topics in the bag: {_topic_list(reader)}", path
    )


def raw_messages(reader: Any, path: Path | None, topic: str, **window: int) -> Iterator[tuple[Any, int, Any]]:
    """`reader.messages` of one topic (`window`: its `start` / `stop` in ns), with the messages decoded: (connection,
    receive time in ns, message). A damaged bag (a record cut short or overwritten: rosbags' reader and the message
    decoder raise many types) raises InputError naming the bag and the topic."""
    connections = [c for c in reader.connections if c.topic == topic]
    try:
        for connection, log_time, raw in reader.messages(connections=connections, **window):
            yield connection, log_time, reader.deserialize(raw, connection.msgtype)
    except Exception as exc:
        raise InputError(
            f"the bag is damaged: reading topic '{topic}' failed ({type(exc).__name__}: {exc})", path
        ) from exc


def read_messages(reader: Any, topic: str, path: str | Path | None = None) -> Iterator[tuple[float, int, Any]]:
    """(header stamp in seconds, receive time in ns, message) of every message on a topic, in bag order; `path`
    names the bag in errors."""
    for _, log_time, message in raw_messages(reader, None if path is None else Path(path), topic):
        yield _stamp_s(message, log_time), log_time, message


@dataclass
class TfLink:
    """Every transform a bag's TF topics give for one child frame: `T_parent_child` at each header stamp."""

    parents: set[str]  # parent frame ids seen (one in a valid tree)
    topics: set[str]  # the TF topics it came on
    static: bool  # all of it on a static topic (/tf_static): one fixed transform
    stamps_s: list[float]
    positions: list[tuple[float, float, float]]
    quaternions_xyzw: list[tuple[float, float, float, float]]


def tf_links(reader: Any, path: str | Path | None = None) -> dict[str, TfLink]:
    """child frame -> its TfLink, over every TF topic of the bag (/tf, /tf_static, ...); frame ids without '/'."""
    links: dict[str, TfLink] = {}
    for topic, info in sorted(reader.topics.items()):
        if info.msgtype not in TF_TYPES:
            continue
        static = "static" in topic
        for _, _, message in read_messages(reader, topic, path):
            for transform in message.transforms:
                child = str(transform.child_frame_id).strip("/")
                link = links.setdefault(child, TfLink(set(), set(), static, [], [], []))
                link.parents.add(str(transform.header.frame_id).strip("/"))
                link.topics.add(topic)
                link.static = link.static and static
                stamp = transform.header.stamp
                t, q = transform.transform.translation, transform.transform.rotation
                link.stamps_s.append(float(stamp.sec) + float(stamp.nanosec) * 1e-9)
                link.positions.append((t.x, t.y, t.z))
                link.quaternions_xyzw.append((q.x, q.y, q.z, q.w))
    return links


def pose_fields(message: Any, msgtype: str) -> tuple[Any, Any]:
    """(position-like, quaternion-like) of a pose message."""
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return message.pose.position, message.pose.orientation
    if msgtype == "geometry_msgs/msg/TransformStamped":
        return message.transform.translation, message.transform.rotation
    return message.pose.pose.position, message.pose.pose.orientation  # PoseWithCovarianceStamped, Odometry


# ---------------------------------------------------------------------------------------------------------
# Writing


class BagWriter:
    """Write a ROS1 or ROS2 bag atomically: into a temporary path, renamed into place by `close()`.

    `kind`: "ros1" (a .bag file), "ros2-db3" or "ros2-mcap" (a bag folder). Use as a context manager; on an
    exception the partial bag is removed, so no half-written bag is left under the final name.
    """

    def __init__(self, path: str | Path, kind: str):
        require_rosbags("writing ROS bags")
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        if kind not in BAG_KINDS:
            raise InputError(f"unknown bag kind '{kind}' (use one of {', '.join(BAG_KINDS)})")
        self.path = Path(path)
        self.kind = kind
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp_dir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self._tmp = self._tmp_dir / self.path.name
        if kind == "ros1":
            from rosbags.rosbag1 import Writer

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            self.typestore.register(get_types_from_msg(TF_MSG_DEFINITION, TF_TYPE))
            self._writer: Any = Writer(self._tmp)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            self.typestore = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.SQLITE3 if kind == "ros2-db3" else StoragePlugin.MCAP
            self._writer = Writer2(self._tmp, version=9, storage_plugin=plugin)
        self._writer.open()
        self._connections: dict[str, Any] = {}
        self._types: dict[str, str] = {}

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def write(self, topic: str, msgtype: str, stamp_s: float, message: Any) -> None:
        """Write one message; its receive time is its header stamp."""
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._types[topic] = msgtype
        if self.kind == "ros1":
            data = self.typestore.serialize_ros1(message, msgtype)
        else:
            data = self.typestore.serialize_cdr(message, msgtype)
        self._writer.write(self._connections[topic], int(round(stamp_s * 1e9)), data)

    def close(self) -> Path:
        self._writer.close()
        if self.path.exists():
            if self.path.is_dir():
                shutil.rmtree(self.path)
            else:
                self.path.unlink()
        os.replace(self._tmp, self.path)
        shutil.rmtree(self._tmp_dir, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self._writer.close()
        shutil.rmtree(self._tmp_dir, ignore_errors=True)

    # ------------------------------------------------------------------------------------------ messages
    def _header(self, stamp_s: float, frame_id: str) -> Any:
        types = self.typestore.types
        sec = int(np.floor(stamp_s))
        stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp_s - sec) * 1e9)) % 1_000_000_000)
        if self.kind == "ros1":
            return types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def pose_stamped(self, stamp_s: float, frame_id: str, T: np.ndarray) -> Any:
        from yoto.geometry import rotation_to_quaternion_xyzw

        types = self.typestore.types
        q = rotation_to_quaternion_xyzw(T[:3, :3])
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            orientation=types["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
            ),
        )
        return types["geometry_msgs/msg/PoseStamped"](header=self._header(stamp_s, frame_id), pose=pose)

    def tf_message(self, stamp_s: float, frame_id: str, child: str, T: np.ndarray) -> Any:
        from yoto.geometry import rotation_to_quaternion_xyzw

        types = self.typestore.types
        q = rotation_to_quaternion_xyzw(T[:3, :3])
        transform = types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=types["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )
        stamped = types["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp_s, frame_id), child_frame_id=child, transform=transform
        )
        return types[TF_TYPE](transforms=[stamped])

    def point_stamped(self, stamp_s: float, frame_id: str, p: np.ndarray) -> Any:
        types = self.typestore.types
        point = types["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2]))
        return types["geometry_msgs/msg/PointStamped"](header=self._header(stamp_s, frame_id), point=point)

    def image(self, stamp_s: float, frame_id: str, rgb: np.ndarray, encoding: str = "rgb8") -> Any:
        """A sensor_msgs/Image of an (H, W, 3) uint8 RGB frame, stored as `rgb8` or `bgr8`."""
        pixels = rgb if encoding == "rgb8" else rgb[:, :, ::-1]
        height, width = rgb.shape[:2]
        return self.typestore.types["sensor_msgs/msg/Image"](
            header=self._header(stamp_s, frame_id),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=width * 3,
            data=np.ascontiguousarray(pixels, dtype=np.uint8).reshape(-1),
        )

    def compressed_image(self, stamp_s: float, frame_id: str, rgb: np.ndarray) -> Any:
        """A sensor_msgs/CompressedImage holding the frame as PNG (lossless)."""
        return self.typestore.types["sensor_msgs/msg/CompressedImage"](
            header=self._header(stamp_s, frame_id),
            format="rgb8; png compressed bgr8",
            data=np.frombuffer(png_bytes(rgb), dtype=np.uint8),
        )
