"""OptiTrack Motive CSV exports: rigid bodies and markers, read as Motive writes them, and written the same way.

The layout of a Motive export (format versions 1.2x, Motive 2 and 3), one row each:

    Format Version,1.23,Take Name,...,Capture Frame Rate,120.000000,Export Frame Rate,120.000000,
        Capture Start Time,2024-03-01 02.15.30.250 PM,...,Rotation Type,Quaternion,Length Units,Meters,...
    (blank)
    ,Type,Rigid Body,Rigid Body,...,Rigid Body Marker,...,Marker,...
    ,Name,RigLeft,RigLeft,...,RigLeft:Marker1,...,GelBall,...
    ,ID,1,1,...                              (and, in some versions, a Parent row)
    ,,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Mean Marker Error,Position,...
    Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,,X,Y,Z,...
    0,0.000000,...

Cells of occluded frames are empty. Rotations must be exported as quaternions (x y z w); lengths are in the
unit the header's `Length Units` names (metres, centimetres, millimetres), converted to metres here. Time is
seconds since the take started (`Time (Seconds)`); `Capture Start Time` (local wall-clock time) anchors it.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from yoto.errors import InputError
from yoto.geometry import rotation_to_quaternion_xyzw
from yoto.io import write_text_atomic
from yoto.rig.timeline import PointStream, PoseStream, make_point_stream, make_pose_stream

LENGTH_UNITS = {
    "meters": 1.0,
    "metres": 1.0,
    "centimeters": 0.01,
    "centimetres": 0.01,
    "millimeters": 0.001,
    "millimetres": 0.001,
    "inches": 0.0254,
}
LABEL_ROWS = ("Type", "Name", "ID", "Parent")
TIME_FORMATS = ("%Y-%m-%d %I.%M.%S.%f %p", "%Y-%m-%d %H.%M.%S.%f", "%Y-%m-%d %I.%M.%S %p", "%Y-%m-%d %H.%M.%S")


@dataclass
class MotiveTake:
    """A parsed Motive CSV: its header, time column and the columns of every rigid body and marker."""

    path: Path
    header: dict[str, str]
    times_s: np.ndarray  # (F,) seconds since the take started
    scale_to_m: float  # length unit -> metres
    columns: dict[tuple[str, str], dict[str, int]] = field(default_factory=dict)  # (type, name) -> "Position X" -> col
    table: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (F, C) float64, NaN where empty

    def names(self, kind: str) -> list[str]:
        return sorted(name for (type_, name) in self.columns if type_ == kind)

    def describe(self) -> str:
        bodies = ", ".join(self.names("Rigid Body")) or "none"
        markers = ", ".join(self.names("Marker")) or "none"
        return f"rigid bodies: {bodies}; markers: {markers}"

    @property
    def capture_start_epoch_s(self) -> float | None:
        """The take's start as a POSIX time, reading `Capture Start Time` as this machine's local time."""
        text = self.header.get("Capture Start Time", "").replace("P.M.", "PM").replace("A.M.", "AM").strip()
        for fmt in TIME_FORMATS:
            try:
                return dt.datetime.strptime(text, fmt).timestamp()
            except ValueError:
                continue
        return None

    def _component(self, kind: str, name: str, component: str) -> np.ndarray:
        found = self.columns[(kind, name)]
        axes = ("X", "Y", "Z", "W") if component == "Rotation" else ("X", "Y", "Z")
        missing = [axis for axis in axes if f"{component} {axis}" not in found]
        if missing:
            raise InputError(f"{kind} '{name}' has no {component} {'/'.join(missing)} columns", self.path)
        return self.table[:, [found[f"{component} {axis}"] for axis in axes]]

    def rigid_body(self, name: str) -> PoseStream:
        if ("Rigid Body", name) not in self.columns:
            raise InputError(f"no rigid body '{name}' in the take ({self.describe()})", self.path)
        quaternions = self._component("Rigid Body", name, "Rotation")
        positions = self._component("Rigid Body", name, "Position") * self.scale_to_m
        return make_pose_stream(self.path, name, self.times_s, positions, quaternions)

    def marker(self, name: str) -> PointStream:
        for kind in ("Marker", "Rigid Body Marker"):
            if (kind, name) in self.columns:
                positions = self._component(kind, name, "Position") * self.scale_to_m
                return make_point_stream(self.path, name, self.times_s, positions)
        raise InputError(f"no marker '{name}' in the take ({self.describe()})", self.path)


def is_motive_csv(path: str | Path) -> bool:
    path = Path(path)
    if path.suffix.lower() != ".csv" or not path.is_file():
        return False
    with open(path, encoding="utf-8-sig", errors="replace") as handle:
        return handle.readline().startswith("Format Version")


def read_motive_csv(path: str | Path) -> MotiveTake:
    """Parse a Motive CSV export. Errors name the file: not a Motive export, Euler rotations, unknown units."""
    path = Path(path)
    if not path.is_file():
        raise InputError("Motive CSV file not found", path)
    text = path.read_text(encoding="utf-8-sig", errors="replace")
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or not rows[0] or rows[0][0].strip() != "Format Version":
        if rows and rows[0] and rows[0][0].startswith("Format Version;"):
            raise InputError(
                "the cells are separated by ';' (a spreadsheet in another locale saved it): use the CSV as Motive "
                "exported it (',' between cells, '.' as the decimal point)",
                path,
            )
        raise InputError("not a Motive CSV export (the first cell is not 'Format Version')", path)
    first = [cell.strip() for cell in rows[0]]
    header = {first[i]: first[i + 1] for i in range(0, len(first) - 1, 2) if first[i]}
    rotation_type = header.get("Rotation Type", "Quaternion")
    if rotation_type.lower() != "quaternion":
        raise InputError(
            f"rotations are exported as '{rotation_type}'; YOTO reads quaternions: re-export the take from Motive with "
            "Rotation Type = Quaternion",
            path,
        )
    units = header.get("Length Units", "Meters")
    if units.lower() not in LENGTH_UNITS:
        raise InputError(f"unknown Length Units '{units}' (expected Meters, Centimeters or Millimeters)", path)
    axis_row = next(
        (
            i
            for i, row in enumerate(rows)
            if len(row) > 1 and row[0].strip() == "Frame" and row[1].strip().startswith("Time")
        ),
        None,
    )
    if axis_row is None or axis_row < 2:
        raise InputError("no 'Frame,Time (Seconds),...' column row: not a Motive CSV export", path)
    labels = {row[1].strip(): row for row in rows[1:axis_row] if len(row) > 1 and row[1].strip() in LABEL_ROWS}
    if "Type" not in labels or "Name" not in labels:
        raise InputError("the column header has no 'Type' and 'Name' rows", path)
    component_row = rows[axis_row - 1]
    axes = rows[axis_row]
    columns: dict[tuple[str, str], dict[str, int]] = {}
    for column in range(2, len(axes)):
        kind = _cell(labels["Type"], column)
        name = _cell(labels["Name"], column)
        component = _cell(component_row, column)
        axis = axes[column].strip()
        if kind and name and component and axis:
            columns.setdefault((kind, name), {})[f"{component} {axis}"] = column
    data = [row for row in rows[axis_row + 1 :] if row and row[0].strip()]
    if not data:
        raise InputError("the take has no frames", path)
    width = len(axes)
    table = np.full((len(data), width), np.nan)
    for i, row in enumerate(data):
        if any(cell.strip() for cell in row[width:]):
            raise InputError(
                f"frame row {i + axis_row + 2} has {len(row)} cells but the column header {width}: numbers written "
                "with decimal commas (a spreadsheet in another locale)? Export or save with '.' as the decimal point",
                path,
            )
        for j, cell in enumerate(row[:width]):
            cell = cell.strip()
            if cell:
                try:
                    table[i, j] = float(cell)
                except ValueError as exc:
                    raise InputError(f"frame row {i + axis_row + 2}: '{cell}' is not a number", path) from exc
    times = table[:, 1]
    if not np.isfinite(times).all():
        raise InputError("some frames have no 'Time (Seconds)' value", path)
    return MotiveTake(path, header, times, LENGTH_UNITS[units.lower()], columns, table)


def _cell(row: list[str], column: int) -> str:
    return row[column].strip() if column < len(row) else ""


def write_motive_csv(
    path: str | Path,
    times_s: np.ndarray,
    bodies: dict[str, np.ndarray],
    markers: dict[str, np.ndarray],
    *,
    capture_start: dt.datetime,
    frame_rate_hz: float,
    length_units: str = "Millimeters",
    take_name: str = "Take",
) -> Path:
    """Write a take as Motive exports it: rigid bodies `name -> (F, 4, 4)` poses (NaN rows: occluded) and
    markers `name -> (F, 3)` positions, in metres, written in `length_units`."""
    scale = 1.0 / LENGTH_UNITS[length_units.lower()]
    header = [
        "Format Version",
        "1.23",
        "Take Name",
        take_name,
        "Take Notes",
        "",
        "Capture Frame Rate",
        f"{frame_rate_hz:.6f}",
        "Export Frame Rate",
        f"{frame_rate_hz:.6f}",
        "Capture Start Time",
        capture_start.strftime("%Y-%m-%d %I.%M.%S.")
        + f"{capture_start.microsecond // 1000:03d} "
        + capture_start.strftime("%p"),
        "Capture Start Frame",
        "0",
        "Total Frames in Take",
        str(len(times_s)),
        "Total Exported Frames",
        str(len(times_s)),
        "Rotation Type",
        "Quaternion",
        "Length Units",
        length_units,
        "Coordinate Space",
        "Global",
    ]
    types, names, ids, components, axes = ["", "Type"], ["", "Name"], ["", "ID"], ["", ""], ["Frame", "Time (Seconds)"]
    blocks = []
    for index, (name, T) in enumerate(bodies.items()):
        for component, axis_names in (("Rotation", "XYZW"), ("Position", "XYZ")):
            for axis in axis_names:
                types.append("Rigid Body")
                names.append(name)
                ids.append(str(index + 1))
                components.append(component)
                axes.append(axis)
        types.append("Rigid Body")
        names.append(name)
        ids.append(str(index + 1))
        components.append("Mean Marker Error")
        axes.append("")
        quaternions = rotation_to_quaternion_xyzw(np.nan_to_num(T[:, :3, :3]))
        occluded = ~np.isfinite(T).all(axis=(1, 2))
        values = np.hstack([quaternions, T[:, :3, 3] * scale, np.full((len(T), 1), 0.0002 * scale)])
        values[occluded] = np.nan
        blocks.append(values)
    for name, p in markers.items():
        for axis in "XYZ":
            types.append("Marker")
            names.append(name)
            ids.append(f"Marker{len(ids)}")
            components.append("Position")
            axes.append(axis)
        blocks.append(np.asarray(p) * scale)
    table = np.hstack(blocks) if blocks else np.zeros((len(times_s), 0))
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    writer.writerow([])
    for row in (types, names, ids, components, axes):
        writer.writerow(row)
    for frame, (t, values) in enumerate(zip(times_s, table)):
        writer.writerow([str(frame), f"{t:.6f}"] + ["" if not np.isfinite(v) else f"{v:.6f}" for v in values])
    return write_text_atomic(path, out.getvalue())
