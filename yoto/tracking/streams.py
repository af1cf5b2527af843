"""What `yoto track` reads during motion: the sensors' pose streams and their tactile frames, from any source.

- Pose streams: TUM files (SPEC) are read here; ROS bags (ROS1 `.bag`, ROS2 folders or `.db3` / `.mcap` files) and
  OptiTrack Motive CSV exports go to the rig stage's reader, `yoto.rig.streams.read_pose_stream(path, topic_or_body)`,
  with the topic (PoseStamped or TF) or rigid-body name the user gives.
- Tactile frames: a folder of `<timestamp>.ply` clouds (SPEC; read lazily, frame by frame), a bag's GelSight image
  topic (the rig's `read_image_stream`, then the sensor stage's `reconstruct` with a calibration), or frames in
  memory (the benchmark).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from yoto.contacts import without_untouched_gel
from yoto.errors import InputError
from yoto.io import read_ply_points
from yoto.rig.motive import is_motive_csv
from yoto.rig.streams import read_image_stream, read_pose_stream
from yoto.trajectory import PoseStream, list_tactile_frames, read_tum

TUM_SUFFIXES = (".tum", ".txt")
BAG_SUFFIXES = (".bag", ".db3", ".mcap")
MOTIVE_SUFFIXES = (".csv",)


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

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @classmethod
    def in_memory(cls, timestamps_s: np.ndarray, clouds: list[np.ndarray], name: str = "") -> TactileStream:
        order = np.argsort(timestamps_s)
        return cls(np.asarray(timestamps_s, dtype=np.float64)[order], lambda i: clouds[order[i]], name)


def read_tactile_folder(folder: str | Path, name: str | None = None) -> TactileStream:
    """The `<timestamp>.ply` frames of a folder (SPEC), read when asked for."""
    timestamps, paths = list_tactile_frames(folder)

    def load(index: int) -> np.ndarray:
        points, _ = read_ply_points(paths[index])
        points = points[np.isfinite(points).all(axis=1)]  # an organised cloud's pixels without data
        return without_untouched_gel(points) if len(points) else points  # a cloud of the whole pad: its contact

    return TactileStream(timestamps, load, name or Path(folder).name, Path(folder))


def read_tactile_stream(
    source: str | Path, topic: str | None = None, calibration: str | Path | None = None, name: str | None = None
) -> TactileStream:
    """Tactile frames from a folder of `<timestamp>.ply` clouds, or from a bag's GelSight image topic (each image
    reconstructed with the sensor `calibration`)."""
    path = Path(source)
    if not path.exists():
        raise InputError("tactile frames not found", path)
    if not is_recording(path):
        return read_tactile_folder(path, name)
    if not topic or calibration is None:
        raise InputError(
            "tactile frames from a bag need its GelSight image topic and the sensor's calibration "
            "(--left-tactile-topic, --calibration)",
            path,
        )
    from yoto.sensor import load_calibration, reconstruct

    images = read_image_stream(path, topic)
    sensor = load_calibration(calibration)

    def load(index: int) -> np.ndarray:
        return reconstruct(images.frame(index), sensor, source=f"{path}:{topic} frame {index}").points_sensor

    return TactileStream(np.asarray(images.timestamps_s, dtype=np.float64), load, name or f"{path.name}:{topic}", path)
