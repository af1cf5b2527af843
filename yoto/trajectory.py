"""Pose streams: time-stamped poses of one frame, TUM trajectory files, interpolation between samples.

SPEC ("Sensor pose streams and tracked poses"): a TUM trajectory file holds one pose a line,
`timestamp tx ty tz qx qy qz qw` (seconds, metres, unit quaternion in x y z w order), the pose `T_world_X` of one
named frame X (a sensor, the object). Lines starting with `#` are comments. The sensor streams `yoto track` reads,
the object poses it writes and the ground truth the simulator writes are all such files; the rig's readers turn
bags and Motive exports into the same `PoseStream`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from yoto.errors import InputError
from yoto.geometry import quaternion_xyzw_to_rotation, rotation_to_quaternion_xyzw, so3_exp, so3_log
from yoto.io import write_text_atomic

TUM_COLUMNS = "timestamp tx ty tz qx qy qz qw"
QUATERNION_NORM_TOLERANCE = 0.01  # quaternions further than this from unit norm are refused, not normalised
LARGEST_PLAUSIBLE_POSITION_M = 50.0  # positions beyond this are most likely millimetres
LARGEST_PLAUSIBLE_TIMESTAMP_S = 1e11  # timestamps beyond this (the year 5138) are not seconds


@dataclass
class PoseStream:
    """Time-stamped poses `T_world_X` of one frame X: samples sorted by time, no two at the same time."""

    timestamps_s: np.ndarray  # (N,) float64, strictly increasing
    T_world_frame: np.ndarray  # (N, 4, 4) float64, the frame's pose at each timestamp
    name: str = ""  # what the stream is ("left sensor", a file name), for messages
    source: Path | None = None  # the file it came from, for messages

    def __post_init__(self) -> None:
        self.timestamps_s = np.asarray(self.timestamps_s, dtype=np.float64).reshape(-1)
        self.T_world_frame = np.asarray(self.T_world_frame, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps_s) != len(self.T_world_frame):
            raise ValueError(f"{len(self.timestamps_s)} timestamps for {len(self.T_world_frame)} poses")
        if len(self.timestamps_s) == 0:
            raise InputError(f"{self.name or 'pose stream'} holds no poses", self.source)
        if np.any(np.diff(self.timestamps_s) <= 0):
            raise InputError(f"{self.name or 'pose stream'}: timestamps are not strictly increasing", self.source)

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def start_s(self) -> float:
        return float(self.timestamps_s[0])

    @property
    def end_s(self) -> float:
        return float(self.timestamps_s[-1])

    def dropout_gap_s(self, floor_s: float) -> float:
        """The longest gap between two samples that is still the stream's own rhythm rather than a dropout:
        `floor_s`, or 1.5 sample periods (median) of a slower stream (a 5 Hz robot stream is not all dropouts)."""
        if len(self) < 2:
            return floor_s
        return max(floor_s, 1.5 * float(np.median(np.diff(self.timestamps_s))))

    def interpolate(self, timestamps_s: np.ndarray, max_gap_s: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Poses at arbitrary times: (M, 4, 4) poses and an (M,) mask of the times the stream covers.

        Between two samples the translation is interpolated linearly and the rotation along the geodesic
        (slerp); a sample's own time gives the sample exactly. A time is covered when it lies within the
        stream and its two neighbouring samples are at most `max_gap_s` apart (a longer gap is a dropout,
        not something to bridge). Uncovered times get the nearest sample's pose.
        """
        times = np.asarray(timestamps_s, dtype=np.float64).reshape(-1)
        stamps, poses = self.timestamps_s, self.T_world_frame
        if len(stamps) == 1:
            covered = np.abs(times - stamps[0]) <= 0.0
            return np.repeat(poses, len(times), axis=0), covered
        upper = np.clip(np.searchsorted(stamps, times, side="right"), 1, len(stamps) - 1)
        lower = upper - 1
        span = stamps[upper] - stamps[lower]
        fraction = np.clip((times - stamps[lower]) / span, 0.0, 1.0)
        covered = (times >= stamps[0]) & (times <= stamps[-1]) & (span <= max_gap_s)
        # Exact samples stay exact (the last sample is reached as fraction 1 of the last interval).
        rotation_lower, rotation_upper = poses[lower, :3, :3], poses[upper, :3, :3]
        step = so3_log(np.swapaxes(rotation_lower, 1, 2) @ rotation_upper)
        out = np.zeros((len(times), 4, 4))
        out[:, :3, :3] = rotation_lower @ so3_exp(step * fraction[:, None])
        out[:, :3, 3] = (1.0 - fraction)[:, None] * poses[lower, :3, 3] + fraction[:, None] * poses[upper, :3, 3]
        out[:, 3, 3] = 1.0
        exact_lower, exact_upper = fraction == 0.0, fraction == 1.0
        out[exact_lower] = poses[lower[exact_lower]]
        out[exact_upper] = poses[upper[exact_upper]]
        return out, covered

    def between(self, start_s: float, end_s: float) -> PoseStream:
        """The samples with start_s <= t <= end_s."""
        keep = (self.timestamps_s >= start_s) & (self.timestamps_s <= end_s)
        return PoseStream(self.timestamps_s[keep], self.T_world_frame[keep], self.name, self.source)


def poses_to_tum_rows(timestamps_s: np.ndarray, T_world_frame: np.ndarray) -> np.ndarray:
    """(N, 8) rows `timestamp tx ty tz qx qy qz qw` of poses (quaternions with w >= 0)."""
    poses = np.asarray(T_world_frame, dtype=np.float64).reshape(-1, 4, 4)
    quaternions = rotation_to_quaternion_xyzw(poses[:, :3, :3])
    return np.column_stack([np.asarray(timestamps_s, dtype=np.float64).reshape(-1), poses[:, :3, 3], quaternions])


def write_tum(path: str | Path, stream: PoseStream, comment: str | None = None) -> Path:
    """Write a stream as a TUM trajectory file (atomically), with `comment` and the column names as `#` lines."""
    rows = poses_to_tum_rows(stream.timestamps_s, stream.T_world_frame)
    header = "".join(f"# {line}\n" for line in (comment or "").splitlines() if line.strip())
    header += f"# {TUM_COLUMNS}\n"
    # Timestamps as the shortest decimal that reads back as the same double (exact, and 1700000000.2 stays that);
    # positions to the nanometre, quaternions to 1e-9.
    body = "".join(
        np.format_float_positional(row[0], trim="-") + "".join(f" {value:.9f}" for value in row[1:]) + "\n"
        for row in rows
    )
    return write_text_atomic(path, header + body)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_tum(path: str | Path, name: str | None = None) -> PoseStream:
    """Read a TUM trajectory file. Errors name the file, the line and the problem.

    Accepts blank lines, `#` comments, commas between values and a first row of column names. Samples out of time
    order are sorted; repeated timestamps are dropped when they repeat the pose and refused when they disagree.
    Quaternions are normalised when within 1% of unit norm and refused otherwise (a wrong column order, most often).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("trajectory file not found", path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # -sig: a byte-order mark (Windows tools) is skipped
    except UnicodeDecodeError as exc:
        raise InputError(f"not a text file ({exc}); a TUM trajectory is text, '{TUM_COLUMNS}' a line", path) from exc
    rows: list[list[float]] = []
    lines: list[int] = []
    header_seen = False
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").split()
        if not content:
            continue
        if len(content) != 8:
            raise InputError(f"line {number} has {len(content)} values; a TUM line is '{TUM_COLUMNS}'", path)
        try:
            values = [float(value) for value in content]
        except ValueError as exc:
            if not rows and not header_seen and not any(_is_number(value) for value in content):
                header_seen = True
                continue  # a header row of column names without '#' (a CSV export): "timestamp,tx,ty,tz,qx,qy,qz,qw"
            raise InputError(f"line {number} is not numeric ({exc})", path) from exc
        rows.append(values)
        lines.append(number)
    if not rows:
        raise InputError(f"no poses in the file (expected lines of '{TUM_COLUMNS}')", path)
    table, line_numbers = np.array(rows), np.array(lines)
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        raise InputError(f"line {line_numbers[bad][0]} holds NaN or infinite values", path)
    norms = np.linalg.norm(table[:, 4:], axis=1)
    off_unit = np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE
    if off_unit.any():
        first = int(np.flatnonzero(off_unit)[0])
        raise InputError(
            f"line {line_numbers[first]}: quaternion of norm {norms[first]:.4g}, not a unit quaternion (the columns "
            f"must be '{TUM_COLUMNS}', quaternion x y z w)",
            path,
        )
    largest = float(np.abs(table[:, 1:4]).max())
    if largest > LARGEST_PLAUSIBLE_POSITION_M:
        raise InputError(
            f"positions reach {largest:.0f}: TUM files are in metres (are these millimetres?)",
            path,
        )
    late = np.flatnonzero(np.abs(table[:, 0]) > LARGEST_PLAUSIBLE_TIMESTAMP_S)
    if len(late):
        raise InputError(
            f"line {line_numbers[late[0]]}: timestamp {table[late[0], 0]:.4g} s is after the year 5000: TUM "
            "timestamps are seconds (are these nanoseconds or milliseconds since 1970?)",
            path,
        )
    order = np.argsort(table[:, 0], kind="stable")
    table, line_numbers = table[order], line_numbers[order]
    repeated = np.flatnonzero(np.diff(table[:, 0]) == 0.0)
    if len(repeated):
        earlier, later = table[repeated], table[repeated + 1]
        same_position = np.isclose(earlier[:, 1:4], later[:, 1:4], atol=1e-9).all(axis=1)
        same_rotation = np.isclose(earlier[:, 4:], later[:, 4:], atol=1e-9).all(axis=1)
        same_rotation |= np.isclose(earlier[:, 4:], -later[:, 4:], atol=1e-9).all(axis=1)  # q and -q: one rotation
        differing = repeated[~(same_position & same_rotation)]
        if len(differing):
            i = differing[0]
            raise InputError(
                f"lines {line_numbers[i]} and {line_numbers[i + 1]} give different poses at the same time "
                f"{table[i, 0]:.9f}",
                path,
            )
        keep = np.ones(len(table), dtype=bool)
        keep[repeated + 1] = False
        table = table[keep]
    poses = np.zeros((len(table), 4, 4))
    poses[:, :3, :3] = quaternion_xyzw_to_rotation(table[:, 4:])
    poses[:, :3, 3] = table[:, 1:4]
    poses[:, 3, 3] = 1.0
    return PoseStream(table[:, 0], poses, name or path.name, path)


# ---------------------------------------------------------------------------------------------------------
# Tactile frames during motion: one folder per sensor of `<timestamp>.ply` clouds (sensor frame, metres)

TACTILE_SUFFIX = ".ply"


def tactile_frame_name(timestamp_s: float) -> str:
    """The file name of the tactile frame taken at `timestamp_s`: seconds with microseconds, `.ply`."""
    return f"{timestamp_s:.6f}{TACTILE_SUFFIX}"


def list_tactile_frames(folder: str | Path) -> tuple[np.ndarray, list[Path]]:
    """The tactile frames of a folder, sorted by time: (N,) timestamps (seconds, from the file names) and paths.

    Every `*.ply` file counts (other files are ignored); its name without the suffix must be the timestamp in
    seconds, as in the TUM files.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("tactile frame folder not found", folder)
    stamped = []
    for path in folder.iterdir():
        if path.name.startswith(".") or path.suffix.lower() != TACTILE_SUFFIX or not path.is_file():
            continue
        try:
            timestamp = float(path.stem)
        except ValueError:
            raise InputError(
                "tactile frame files must be named <timestamp>.ply (seconds, as in the TUM files)", path
            ) from None
        if not np.isfinite(timestamp):
            raise InputError("the file name is not a finite timestamp", path)
        if abs(timestamp) > LARGEST_PLAUSIBLE_TIMESTAMP_S:
            raise InputError(
                f"the file name reads as {timestamp:.4g} s, after the year 5000: tactile frames are named by their "
                "time in seconds (are these nanoseconds or milliseconds since 1970?)",
                path,
            )
        stamped.append((timestamp, path))
    if not stamped:
        raise InputError(
            "no tactile frames (<timestamp>.ply clouds, or <timestamp>.png GelSight images) in the folder", folder
        )
    stamped.sort()
    timestamps = np.array([timestamp for timestamp, _ in stamped])
    repeated = np.flatnonzero(np.diff(timestamps) == 0.0)
    if len(repeated):
        i = int(repeated[0])
        raise InputError(f"{stamped[i][1].name} and {stamped[i + 1][1].name} have the same timestamp", folder)
    return timestamps, [path for _, path in stamped]


__all__ = [
    "TUM_COLUMNS",
    "PoseStream",
    "list_tactile_frames",
    "poses_to_tum_rows",
    "read_tum",
    "tactile_frame_name",
    "write_tum",
]
