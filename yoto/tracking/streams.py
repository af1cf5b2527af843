"""What `yoto track` reads during motion: the sensors' pose streams and their tactile frames, from any source.

- Pose streams: TUM files (SPEC) are read here; ROS bags (ROS1 `.bag`, ROS2 folders or `.db3` / `.mcap` files) and
  OptiTrack Motive CSV exports go to the rig stage's reader, `yoto.rig.streams.read_pose_stream(path, topic_or_body)`,
  with the topic (PoseStamped or TF) or rigid-body name the user gives.
- Tactile frames: a folder of `<timestamp>.ply` clouds (SPEC; read lazily, frame by frame), GelSight images (a bag's
  image topic, or a folder of `<timestamp>.png` beside a Motive take: the rig's `read_image_stream`, then the sensor
  stage's `reconstruct` with the sensor's calibration), or frames in memory (the benchmark). A frame that cannot be
  read or reconstructed raises InputError when it is loaded: the tracker leaves it out and goes on.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from yoto.contacts import GelReading, read_gel
from yoto.errors import InputError
from yoto.io import read_ply_points
from yoto.rig.motive import is_motive_csv
from yoto.rig.streams import IMAGE_SUFFIXES, read_image_stream, read_pose_stream
from yoto.sensor.calibration import SensorCalibration
from yoto.trajectory import TACTILE_SUFFIX, PoseStream, list_tactile_frames, read_tum

TUM_SUFFIXES = (".tum", ".txt")
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
MOTIVE_SUFFIXES = (".csv",)
READ_AHEAD_FRAMES = 32  # GelSight frames read from a recording in one pass


def is_recording(path: Path) -> bool:
    """A ROS bag (file or ROS2 folder) or a Motive CSV export, as opposed to a TUM file (whatever its suffix, `.csv`
    included) or a frame folder."""
    if path.suffix.lower() in MOTIVE_SUFFIXES:
        return is_motive_csv(path)
    if path.suffix.lower() in BAG_SUFFIXES:
        return True
    return path.is_dir() and (
        (path / "metadata.yaml").is_file() or any(p.suffix in (".db3", ".mcap") for p in path.iterdir())
    )


def read_sensor_stream(path: str | Path, topic: str | None = None, name: str | None = None) -> PoseStream:
    """A pose stream `T_world_X` from a TUM file, a ROS bag or a Motive CSV export.

    `topic`: for a bag, the PoseStamped or TF topic (e.g. `/vrpn_client_node/GelLeft/pose`); for a Motive export,
    the rigid body's name. A TUM file needs none.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("pose stream not found", path)
    if not is_recording(path):
        if topic is not None:
            raise InputError(
                f"a topic or body ({topic!r}) was given, but this is a TUM file, which holds one stream", path
            )
        return read_tum(path, name)
    kind = "a Motive CSV export" if path.suffix.lower() in MOTIVE_SUFFIXES else "a ROS bag"
    if not topic:
        raise InputError(
            f"this is {kind}: name the {'rigid body' if 'Motive' in kind else 'pose topic'} of the sensor "
            "(--left-topic / --right-topic)",
            path,
        )
    timestamps, poses = read_pose_stream(path, topic)
    return PoseStream(np.asarray(timestamps), np.asarray(poses), name or f"{path.name}:{topic}", path)


@dataclass
class TactileStream:
    """Time-stamped tactile clouds of one sensor (sensor frame, metres), loaded frame by frame."""

    timestamps_s: np.ndarray  # (N,) sorted
    load: Callable[[int], np.ndarray]  # frame index -> (M, 3) points; raises InputError for an unreadable frame
    name: str = ""
    source: Path | None = None
    from_images: bool = False  # each frame reconstructed from a GelSight image when loaded (`image_frames`)

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @classmethod
    def in_memory(cls, timestamps_s: np.ndarray, clouds: list[np.ndarray], name: str = "") -> TactileStream:
        order = np.argsort(timestamps_s)
        return cls(np.asarray(timestamps_s, dtype=np.float64)[order], lambda i: clouds[order[i]], name)


MAX_FRAME_EXTENT_M = 0.1  # a tactile frame wider than this is no GelSight's (millimetres, pixels)


def frame_contact(points_sensor: np.ndarray, path: Path) -> np.ndarray:
    """A tactile frame's contact points: its finite points (an organised cloud marks pixels without data NaN), without
    the untouched gel of a cloud of the whole pad (`GelReading.felt`); none where the object only kisses the gel or the
    gel is not pressed beyond its noise (`GelReading.kiss`, `pressed`: the gel lost contact, and its flat gel or a speck
    of a few pixels is no contact surface to register; the closed loop keeps its prediction, the open loop's, for that
    frame). A frame in millimetres (or pixels) or with its z flipped raises InputError naming it, so the tracker leaves
    it out saying why (in millimetres it would size the tracker's sampling grid by metres: an out-of-memory crash)."""
    finite = np.isfinite(points_sensor)
    points = points_sensor if finite.all() else points_sensor[finite.all(axis=1)]  # a whole pad's copy costs 1 ms
    if len(points) == 0:
        return points
    extent = max(float(np.ptp(points[:, axis])) for axis in range(3))
    if extent > MAX_FRAME_EXTENT_M:
        raise InputError(
            f"tactile frame spans {extent * 1e3:.0f} mm, more than any GelSight pad: is it in metres, sensor frame?",
            path,
        )
    gel = read_gel(points)  # one reading decides both: is it pressed, and which points are the contact
    if not gel.pressed and read_gel(points * np.array([1.0, 1.0, -1.0])).pressed:
        raise InputError(
            "tactile frame is not pressed into the gel but its mirror is: are its z values flipped? "
            "(SPEC: z <= 0 where the gel is pressed)",
            path,
        )
    return felt_contact(points, gel)


def felt_contact(points_sensor: np.ndarray, gel: GelReading | None = None) -> np.ndarray:
    """What the gel felt of a frame's finite points (`contacts.read_gel`, the one rule): the untouched gel of a cloud
    of the whole pad taken out (`GelReading.felt`), none where the object only kisses the gel or it is not pressed
    beyond its noise (its flat gel or a speck would be registered as the contact). A cloud of the contact alone is
    returned as it is, so applying it twice changes nothing."""
    gel = read_gel(points_sensor) if gel is None else gel
    if gel.kiss or not gel.pressed:
        return points_sensor[:0]
    return gel.felt(points_sensor)


def read_tactile_folder(folder: str | Path, name: str | None = None) -> TactileStream:
    """The `<timestamp>.ply` frames of a folder (SPEC), read when asked for (`frame_contact`)."""
    timestamps, paths = list_tactile_frames(folder)

    def load(index: int) -> np.ndarray:
        return frame_contact(read_ply_points(paths[index])[0], paths[index])

    return TactileStream(timestamps, load, name or Path(folder).name, Path(folder))


def holds_images(path: str | Path) -> bool:
    """Whether tactile frames at `path` are GelSight images (a bag, or a folder of images and no `.ply` clouds), which
    need the sensor's calibration, rather than clouds."""
    path = Path(path)
    if not path.exists():
        return False  # the reader says it is not there
    if is_recording(path):
        return True
    if not path.is_dir():
        return False
    suffixes = {p.suffix.lower() for p in path.iterdir() if not p.name.startswith(".")}
    return TACTILE_SUFFIX not in suffixes and bool(suffixes & set(IMAGE_SUFFIXES))


def read_tactile_stream(
    source: str | Path,
    topic: str | None = None,
    calibration: str | Path | SensorCalibration | None = None,
    name: str | None = None,
    recording: str | Path | None = None,
) -> TactileStream:
    """Tactile frames from a folder of `<timestamp>.ply` clouds (SPEC), or GelSight images reconstructed with the
    sensor `calibration`: a bag's image topic, or a folder of images named by their time (`<timestamp>.png`, or
    `left_<timestamp>.png`), as a Motive take has beside it; with `recording` the take the folder belongs to, the
    images' stamps are put on its clock (its own, or the wall clock through its start time; `yoto.rig.streams`)."""
    path = Path(source)
    if not path.exists():
        raise InputError("tactile frames not found", path)
    if not holds_images(path):
        return read_tactile_folder(path, name)
    from_bag = is_recording(path)
    if from_bag and not topic:
        raise InputError("tactile frames from a bag need its GelSight image topic (--left-tactile-topic)", path)
    if calibration is None:
        what = "a bag's GelSight frames" if from_bag else "a folder of GelSight images (no <timestamp>.ply clouds)"
        raise InputError(
            f"tactile frames from {what} are reconstructed with the sensor's calibration: give it (--calibration, "
            'or a "calibration" entry in the touch\'s side)',
            path,
        )
    from yoto.sensor import load_calibration

    sensor = calibration if isinstance(calibration, SensorCalibration) else load_calibration(calibration)
    if from_bag:
        images = read_image_stream(path, str(topic), spec=sensor.spec)
    elif recording is not None and is_motive_csv(Path(recording)):
        images = read_image_stream(recording, str(path), spec=sensor.spec)
    else:
        images = read_image_stream(path, str(path), spec=sensor.spec)
    files = images.details.get("files")
    ahead: dict[int, np.ndarray] = {}  # frames read ahead: the tracker asks for them in time order

    def frame(index: int) -> np.ndarray:
        """Frame `index`, read with the next ones in one pass over the bag (a bag opened per frame costs 8x the
        frame's decoding); a frame that cannot be decoded ends the pass, and raises when it is asked for."""
        if index not in ahead:
            ahead.clear()
            with contextlib.suppress(InputError):
                for k, image in images.frames(list(range(index, min(index + READ_AHEAD_FRAMES, len(images))))):
                    ahead[k] = image
        return ahead[index] if index in ahead else images.frame(index)

    def where(index: int) -> str:
        return str(files[index]) if files else f"{path}:{topic} frame {index}"

    label = f"{path.name}:{topic}" if from_bag else path.name
    return image_frames(np.asarray(images.timestamps_s, dtype=np.float64), frame, sensor, name or label, path, where)


def image_frames(
    timestamps_s: np.ndarray,
    image: Callable[[int], np.ndarray],
    sensor: SensorCalibration,
    name: str = "",
    source: Path | None = None,
    where: Callable[[int], str] | None = None,
) -> TactileStream:
    """GelSight images (`image(index)`: (rows, cols, 3) uint8, sorted by time) as tactile frames: each reconstructed
    with the sensor's calibration when the tracker asks for it (the contact's points; none where it finds no
    contact). `where(index)` names a frame in errors and warnings."""
    from yoto.sensor import reconstruct
    from yoto.sensor.pair_images import in_rgb_order

    swapped: list[str] = []  # frames read in BGR order: warned about once

    def load(index: int) -> np.ndarray:
        named = where(index) if where is not None else f"{name or 'image'} frame {index}"
        raw = image(index)
        rgb = in_rgb_order(raw, sensor.background, named, warn=not swapped)
        if rgb is not raw:
            swapped.append(named)
        return reconstruct(rgb, sensor, source=named).points_sensor

    return TactileStream(np.asarray(timestamps_s, dtype=np.float64), load, name, source, from_images=True)
