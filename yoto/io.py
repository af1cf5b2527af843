"""File input and output shared by every stage: atomic writes, PLY point clouds, JSON, npz archives.

Writes go to a temporary file in the destination folder and are renamed into place, so an interrupted
run never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError

# ---------------------------------------------------------------------------------------------------------
# Atomic writes

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[Any]:
    """Open a temporary file next to `path`; on success it replaces `path`, on error it is removed."""
    path = Path(path)
    if path.is_dir():
        raise InputError("this output is a folder; give the file to write (a name inside it)", path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # a read-only folder, a file where a folder should be, a full disk
        raise InputError(f"cannot write here ({exc.strerror or exc})", path) from exc
    os.chmod(tmp_name, 0o666 & ~_UMASK)  # mkstemp creates 0600; give the file the mode open() would
    try:
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    with atomic_open(path, "wb") as handle:
        handle.write(data)
    return Path(path)


def png_bytes(image: np.ndarray) -> bytes:
    """An 8-bit image ((rows, cols, 3) RGB, or grey) encoded as PNG (lossless; fast compression)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8)).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def write_text_atomic(path: str | Path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def _to_jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


_NUMBER_LIST = re.compile(r"\[\s*(-?[\d.eE+-]+(?:,\s*-?[\d.eE+-]+)*)\s*\]")


def write_json_atomic(path: str | Path, payload: Any) -> Path:
    """Indented JSON with each list of numbers (a matrix row, a point) on one line."""
    text = json.dumps(payload, indent=2, default=_to_jsonable)
    text = _NUMBER_LIST.sub(lambda match: "[" + ", ".join(v.strip() for v in match.group(1).split(",")) + "]", text)
    return write_text_atomic(path, text + "\n")


def read_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path)
    try:
        return json.loads(path.read_text(encoding="utf-8-sig"))  # -sig: a byte-order mark (Windows tools) is skipped
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not a valid JSON file ({exc})", path) from exc


def settings_changed(
    out_dir: Path, stored: dict[str, Any] | None, settings: dict[str, Any], what: str, overwrite: bool
) -> bool:
    """Whether a resumable output folder was made with other settings than `settings` (its `stored` ones).

    Refused unless `overwrite`, naming the settings that differ: a folder never mixes two runs' outputs.
    """
    if stored is None or stored == settings:
        return False
    if not overwrite:
        changed = sorted(key for key in settings if stored.get(key) != settings[key])
        raise InputError(
            f"this folder holds {what} simulated with other settings ({', '.join(changed)} differ); pass "
            "--overwrite to replace them, or choose another --out",
            out_dir,
        )
    return True


def read_json_format(
    path: str | Path, format_name: str, version: int, what: str, keys: tuple[str, ...] = (), how_to_make: str = ""
) -> dict[str, Any]:
    """A JSON file of one of YOTO's versioned formats (`"format"`, `"format_version"`), with the `keys` it needs;
    errors name the file, the `what` it should be and, where given, the command that makes one."""
    payload = read_json(path)
    if not isinstance(payload, dict) or payload.get("format") != format_name:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        hint = f"; make one with `{how_to_make}`" if how_to_make else ""
        raise InputError(f"not a {what} (format '{found}', expected '{format_name}'){hint}", path)
    if payload.get("format_version") != version:
        raise InputError(f"{what} version {payload.get('format_version')} is not supported", path)
    for key in keys:
        if key not in payload:
            raise InputError(f"{what} has no '{key}'", path)
    return payload


def save_npz_atomic(path: str | Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> Path:
    """Save arrays and a JSON metadata dict (stored as the `meta_json` entry) into one npz file."""
    buffer = io.BytesIO()
    meta_entry = np.frombuffer(json.dumps(meta, default=_to_jsonable).encode("utf-8"), dtype=np.uint8)
    entries: dict[str, Any] = {"meta_json": meta_entry, **arrays}  # Any: numpy's stub also types allow_pickle
    np.savez(buffer, **entries)
    return write_bytes_atomic(path, buffer.getvalue())


def load_npz(path: str | Path, kind: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Load an npz written by `save_npz_atomic`; `kind` names what the file should be, for errors."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{kind} file not found", path)
    with open(path, "rb") as handle:
        magic = handle.read(6)
    if not magic.startswith(b"PK"):  # an npz is a zip archive
        what = "a single NumPy array (.npy)" if magic == b"\x93NUMPY" else "not a zip archive"
        raise InputError(f"not a readable {kind} file: YOTO writes it as a NumPy .npz archive, this is {what}", path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except Exception as exc:  # numpy raises several unrelated types for corrupt archives
        raise InputError(f"not a readable {kind} file ({exc})", path) from exc
    if "meta_json" not in arrays:
        raise InputError(f"not a YOTO {kind} file (no metadata entry)", path)
    try:
        meta = json.loads(arrays.pop("meta_json").tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{kind} file's metadata is damaged ({exc})", path) from exc
    if not isinstance(meta, dict):
        raise InputError(f"{kind} file's metadata is not a JSON object", path)
    return arrays, meta


def sha256_of_file(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------------------------
# PLY point clouds (vertex element only). Written as binary little-endian float32; read in any PLY flavour.

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def write_ply_points(path: str | Path, points: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """Write an (N, 3) point cloud (and optional (N, 3) normals) as a binary little-endian PLY."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    names = ["x", "y", "z"]
    columns = [points]
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(f"normals {normals.shape} do not match points {points.shape}")
        names += ["nx", "ny", "nz"]
        columns.append(normals)
    data = np.ascontiguousarray(np.hstack(columns).astype("<f4"))
    header = "ply\nformat binary_little_endian 1.0\ncomment written by yoto\n"
    header += f"element vertex {len(points)}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    return write_bytes_atomic(path, header.encode("ascii") + data.tobytes())


def read_ply_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a PLY file: (N, 3) float64 points and (N, 3) normals or None.

    Supports ascii, binary_little_endian and binary_big_endian files, any vertex property layout (x, y, z and
    optionally nx, ny, nz are read, other properties skipped), Windows line ends and blank lines between ascii rows.
    Elements after the vertex element (faces, say) are ignored, and so are elements before it (a camera) unless a
    binary file gives them list properties. Raises InputError naming the file for anything malformed.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("point cloud file not found", path)
    raw = path.read_bytes()
    if not raw.startswith(b"ply"):
        raise InputError("not a PLY file (it does not start with 'ply')", path)
    header_lines, body_start = [], -1
    start = 0
    while start < len(raw):
        stop = raw.find(b"\n", start)
        stop = len(raw) if stop < 0 else stop
        line = raw[start:stop].decode("ascii", errors="replace").strip()
        start = stop + 1
        if line == "end_header":
            body_start = min(start, len(raw))
            break
        header_lines.append(line)
    if body_start < 0:
        raise InputError("PLY header has no 'end_header' line", path)

    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header_lines:
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            if not words[2].isdigit():
                raise InputError(f"PLY element count '{words[2]}' of element '{words[1]}' is not a number", path)
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) >= 3:
            if words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise InputError(f"unknown PLY property type '{words[1]}'", path)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unsupported PLY format '{fmt}'", path)
    vertex = next((i for i, element in enumerate(elements) if element[0] == "vertex"), None)
    if vertex is None:
        raise InputError("PLY file has no 'vertex' element", path)
    _, count, properties = elements[vertex]
    names = [name for name, _ in properties]
    if any(kind == "list" for _, kind in properties):
        raise InputError("PLY vertex element has list properties, which a point cloud cannot have", path)
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise InputError(f"PLY vertices have no '{axis}' property", path)

    if fmt == "ascii":
        skipped = sum(element[1] for element in elements[:vertex])  # one row a line, whatever its properties
        text = raw[body_start:].decode("ascii", errors="replace").splitlines()
        rows = [row.split() for row in text if row.strip()][skipped : skipped + count]
        if len(rows) < count or any(len(row) < len(names) for row in rows):
            raise InputError(f"PLY file is truncated (expected {count} vertex rows)", path)
        try:
            table = np.array([[float(value) for value in row[: len(names)]] for row in rows], dtype=np.float64)
        except ValueError as exc:
            raise InputError(f"PLY vertex data is not numeric ({exc})", path) from exc
        table = table.reshape(count, len(names))
        column = {name: table[:, i] for i, name in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        offset = body_start
        for name, rows_before, before in elements[:vertex]:
            if any(kind == "list" for _, kind in before):
                raise InputError(
                    f"binary PLY element '{name}' before the vertices has list properties (its size is unknown "
                    "without reading it); write the vertex element first",
                    path,
                )
            offset += rows_before * np.dtype([(n, order + kind) for n, kind in before]).itemsize
        dtype = np.dtype([(name, order + kind) for name, kind in properties])
        if len(raw) - offset < dtype.itemsize * count:
            raise InputError(f"PLY file is truncated (expected {count} vertices)", path)
        records = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
        column = {name: records[name].astype(np.float64) for name in names}

    points = np.stack([column["x"], column["y"], column["z"]], axis=1)
    normals = None
    if all(axis in column for axis in ("nx", "ny", "nz")):
        normals = np.stack([column["nx"], column["ny"], column["nz"]], axis=1)
    return points, normals


def check_finite(array: np.ndarray, what: str, path: str | Path | None = None) -> np.ndarray:
    """Raise InputError naming `what` (and the file) if `array` holds NaN or infinite values."""
    bad = ~np.isfinite(array)
    if bad.any():
        raise InputError(f"{what} contains {int(bad.sum())} NaN or infinite values", path)
    return array
