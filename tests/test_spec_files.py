"""SPEC's files as another program writes them: each writer here follows SPEC.md's text alone (never yoto's writers),
and yoto's readers (and `yoto pose`) must take what it writes, or refuse it naming the file and the problem.

Formats: PLY point clouds, contact-pair JSON files, TUM trajectories, tactile frame folders, object meshes (OBJ,
STL, PLY) and GelSight PNGs.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import TOL
from test_pose import write_foreign_pairs

from yoto.cli import main
from yoto.contacts import read_contact_pair
from yoto.errors import InputError
from yoto.geometry import (
    make_transform,
    quaternion_xyzw_to_rotation,
    random_rotations,
    rotation_about_axis,
    rotation_angle_rad,
)
from yoto.io import read_ply_points
from yoto.tracking.streams import read_tactile_folder
from yoto.trajectory import list_tactile_frames, read_tum

# ---------------------------------------------------------------------------------------------------------
# PLY, written from the PLY format's text: header lines, then the elements in header order.

PLY_TYPES = {"float": "f4", "double": "f8", "float32": "f4", "float64": "f8", "uchar": "u1", "int": "i4"}


def foreign_ply(
    path: Path,
    points: np.ndarray,
    fmt: str = "binary_little_endian",
    coordinate_type: str = "float",
    normals: np.ndarray | None = None,
    colours: np.ndarray | None = None,
    faces: np.ndarray | None = None,
    leading_element: bool = False,
    newline: str = "\n",
) -> Path:
    """A PLY file as another tool writes it: any format, coordinate type, extra vertex properties, a face element
    after the vertices and (`leading_element`) a one-row element before them."""
    columns: list[tuple[str, str, np.ndarray]] = [(axis, coordinate_type, points[:, i]) for i, axis in enumerate("xyz")]
    if normals is not None:
        columns += [(name, coordinate_type, normals[:, i]) for i, name in enumerate(("nx", "ny", "nz"))]
    if colours is not None:
        columns += [(name, "uchar", colours[:, i]) for i, name in enumerate(("red", "green", "blue"))]
    lines = ["ply", f"format {fmt} 1.0", "comment written by another program", "obj_info no yoto here"]
    if leading_element:
        lines += ["element camera 1", "property float focal", "property int width"]
    lines.append(f"element vertex {len(points)}")
    lines += [f"property {kind} {name}" for name, kind, _ in columns]
    if faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    header = newline.join(lines) + newline
    if fmt == "ascii":
        body = []
        if leading_element:
            body.append("4.5 320")
        body += [
            " ".join(repr(float(c[i])) if k != "uchar" else str(int(c[i])) for _, k, c in columns)
            for i in range(len(points))
        ]
        body += [f"3 {a} {b} {c}" for a, b, c in faces] if faces is not None else []
        path.write_bytes((header + newline.join(body) + newline).encode("ascii"))
        return path
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, order + PLY_TYPES[kind]) for name, kind, _ in columns])
    records = np.zeros(len(points), dtype=dtype)
    for name, _, values in columns:
        records[name] = values
    data = b""
    if leading_element:
        data += struct.pack(order + "fi", 4.5, 320)
    data += records.tobytes()
    if faces is not None:
        for face in faces:
            data += struct.pack(order + "B3i", 3, *face)
    path.write_bytes(header.encode("ascii") + data)
    return path


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("coordinate_type", ["float", "double", "float64"])
def test_ply_clouds_of_every_flavour_are_read(tmp_path, rng, fmt, coordinate_type):
    points = rng.normal(size=(50, 3)) * 1e-3
    normals = rng.normal(size=(50, 3))
    colours = rng.integers(0, 256, size=(50, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    stored = points.astype(np.float32).astype(np.float64) if coordinate_type == "float" else points
    for kwargs in ({}, {"normals": normals, "colours": colours, "faces": faces}):
        path = foreign_ply(tmp_path / "cloud.ply", points, fmt, coordinate_type, **kwargs)
        read, read_normals = read_ply_points(path)
        np.testing.assert_allclose(read, stored, atol=TOL["ply_text_m"] if fmt == "ascii" else 0.0, rtol=0)
        assert (read_normals is None) == ("normals" not in kwargs)


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_ply_elements_before_the_vertices_and_windows_line_ends(tmp_path, rng, fmt):
    """PLY puts elements in any order; a one-row element (a camera) before the vertices is skipped. Fails on the old
    reader, which refused any file whose first element was not `vertex`."""
    points = rng.normal(size=(40, 3)) * 1e-3
    path = foreign_ply(tmp_path / "c.ply", points, fmt, "double", leading_element=True, newline="\r\n")
    np.testing.assert_allclose(read_ply_points(path)[0], points, atol=TOL["ply_text_m"], rtol=0)


def test_ply_ascii_blank_lines_between_rows_are_skipped(tmp_path):
    header = (
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    path = tmp_path / "c.ply"
    path.write_text(header + "1 2 3\n\n4 5 6\n")
    np.testing.assert_array_equal(read_ply_points(path)[0], [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    "content, message",
    [
        (b"ply\nformat ascii 1.0\nelement vertex 2x\nproperty float x\nend_header\n", "element count '2x'"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nend_header",
            "truncated",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n" + b"\0" * 20,
            "truncated",
        ),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n", "'z'"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
            b"element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
            "before the vertices",
        ),
    ],
)
def test_broken_ply_files_name_the_file_and_the_problem(tmp_path, content, message):
    """Invalid files: an error naming the file (never a bare ValueError, never numbers read from the header)."""
    path = tmp_path / "broken.ply"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message) as error:
        read_ply_points(path)
    assert "broken.ply" in str(error.value)


# ---------------------------------------------------------------------------------------------------------
# Contact-pair files, rewritten by hand in other flavours, then read and posed


def _rewrite_pair(source: Path, target_dir: Path, matrix_decimals: int | None) -> Path:
    """The pair `source` rewritten as another program might: clouds as big-endian double PLY with normals and
    colours in a subfolder (left) and ASCII PLY with Windows line ends (right); extra keys at every level;
    integer-valued entries as JSON integers; matrices rounded to `matrix_decimals` when given."""
    payload = json.loads(source.read_text())
    clouds = target_dir / "clouds" / "gelsight"
    clouds.mkdir(parents=True, exist_ok=True)

    def matrix(value):
        array = np.asarray(value, dtype=float)
        if matrix_decimals is not None:
            array = np.round(array, matrix_decimals)
        return [[int(v) if v == int(v) else float(v) for v in row] for row in array]

    out = {"format_note": "written by another tool", "object": payload["object"]}
    for side, fmt in (("left", "binary_big_endian"), ("right", "ascii")):
        points, _ = read_ply_points(source.parent / payload[side]["points"])
        name = f"{source.stem}_{side}_cloud.ply"
        foreign_ply(
            clouds / name,
            points,
            fmt,
            "double",
            normals=np.tile([0.0, 0.0, -1.0], (len(points), 1)),
            colours=np.full((len(points), 3), 200),
            newline="\r\n" if fmt == "ascii" else "\n",
        )
        out[side] = {
            "T_world_sensor": matrix(payload[side]["T_world_sensor"]),
            "points": f"clouds/gelsight/{name}",
            "frame_id": f"gelsight_{side}",
            "stamp": 12.5,
        }
    truth = payload["ground_truth"]
    out["ground_truth"] = {
        "T_world_object": matrix(truth["T_world_object"]),
        "left_p_object": truth["left_p_object"],
        "right_p_object": truth["right_p_object"],
        "source": "mocap",
    }
    path = target_dir / source.name
    path.write_text(json.dumps(out))
    return path


def test_pair_files_written_by_another_program_give_the_same_poses(builtin_models, tmp_path, rng, capsys):
    model = builtin_models["figurine"]
    model_path = model.save(tmp_path / "figurine.npz")
    originals = write_foreign_pairs(model, tmp_path / "ours", rng, 3)
    exact = [_rewrite_pair(path, tmp_path / "exact", None) for path in originals]
    rounded = [_rewrite_pair(path, tmp_path / "rounded", 4) for path in originals]
    for folder in ("ours", "exact", "rounded"):
        command = ["pose", str(tmp_path / folder), "--oracle", "--model", str(model_path), "--search", "never"]
        assert main(command) == 0, capsys.readouterr().out
    for original, same, near in zip(originals, exact, rounded):
        pair, foreign = read_contact_pair(original), read_contact_pair(same)
        np.testing.assert_array_equal(foreign.left.points_sensor, pair.left.points_sensor)
        np.testing.assert_array_equal(foreign.right.points_sensor, pair.right.points_sensor)
        assert foreign.extra == {"format_note": "written by another tool"}
        result = json.loads(original.with_suffix(".pose.json").read_text())
        exact_pose = json.loads(same.with_suffix(".pose.json").read_text())["T_world_object"]
        np.testing.assert_allclose(exact_pose, result["T_world_object"], atol=TOL["pose_exact_m"])
        # Sensor poses rounded to 4 decimals (5e-5 per entry) may move the solve along a weakly held direction by a
        # fraction of a degree, never more.
        near_pose = np.asarray(json.loads(near.with_suffix(".pose.json").read_text())["T_world_object"])
        expected = np.asarray(result["T_world_object"])
        assert np.degrees(rotation_angle_rad(near_pose[:3, :3], expected[:3, :3])) < 0.5
        assert np.linalg.norm(near_pose[:3, 3] - expected[:3, 3]) < 2e-4
    # `yoto localize` on the big-endian double clouds: the same contacts as on ours.
    located = []
    for clouds in (
        [read_contact_pair(p).left.source for p in originals],
        sorted((tmp_path / "exact").rglob("*left*.ply")),
    ):
        out = tmp_path / f"located_{len(located)}.json"
        assert main(["localize", *map(str, clouds), "--object", str(model_path), "--out", str(out)]) == 0
        located.append(json.loads(out.read_text()))
    assert len(located[0]) == len(located[1]) == 3
    for ours, theirs in zip(*located):
        np.testing.assert_array_equal(ours["candidates"][0]["p_object"], theirs["candidates"][0]["p_object"])


def test_matrices_written_with_few_decimals_are_accepted(tmp_path, rng):
    """A pose printed with 3 decimals (1 mm, rotation entries to 0.001) is a rotation to ~0.1 deg: read and
    re-orthonormalised. Fails on the old reader (rotations more than 1e-4 off SO(3) refused: every such matrix)."""
    pairs = hand_written_pair(tmp_path, rng)
    payload = json.loads(pairs.read_text())
    rotation = rotation_about_axis(np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0), 0.7)
    T = np.round(make_transform(rotation, [0.51234, -0.2, 0.3]), 3)
    payload["left"]["T_world_sensor"] = T.tolist()
    pairs.write_text(json.dumps(payload))
    pair = read_contact_pair(pairs)
    R = pair.left.T_world_sensor[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=TOL["float_round_trip"])
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ rotation) - 1) / 2, -1, 1))) < 0.1
    payload["left"]["T_world_sensor"] = np.round(T, 1).tolist()  # 0.1 steps: not a rotation any more
    pairs.write_text(json.dumps(payload))
    with pytest.raises(InputError, match="pair.json: left.T_world_sensor is not a rigid transform"):
        read_contact_pair(pairs)


def test_pair_paths_with_windows_separators_and_bad_path_values(tmp_path, rng):
    """A Windows tool writes `clouds\\left.ply`: read as the subfolder (fails on the old reader: file not found).
    A path that is not a string is refused naming the key."""
    path = hand_written_pair(tmp_path, rng)
    (tmp_path / "clouds").mkdir()
    (tmp_path / "left.ply").rename(tmp_path / "clouds" / "left.ply")
    payload = json.loads(path.read_text())
    payload["left"]["points"] = "clouds\\left.ply"
    path.write_text(json.dumps(payload))
    assert read_contact_pair(path).left.source == tmp_path / "clouds" / "left.ply"
    payload["left"]["points"] = None
    path.write_text(json.dumps(payload))
    with pytest.raises(InputError, match="pair.json: left.points must be a file path relative to the pair file"):
        read_contact_pair(path)


def hand_written_pair(folder: Path, rng: np.random.Generator) -> Path:
    """A minimal pair file with two pressed clouds, written by hand."""
    for side in ("left", "right"):
        xy = rng.uniform(-0.004, 0.004, size=(400, 2))
        z = -0.001 + (xy**2).sum(axis=1) * 20.0
        foreign_ply(folder / f"{side}.ply", np.column_stack([xy, np.minimum(z, 0.0)]), "ascii", "double")
    payload = {
        "object": "tool",
        "left": {"points": "left.ply", "T_world_sensor": np.eye(4).tolist()},
        "right": {"points": "right.ply", "T_world_sensor": make_transform(np.eye(3), [0.1, 0, 0]).tolist()},
    }
    path = folder / "pair.json"
    path.write_text(json.dumps(payload))
    return path


# ---------------------------------------------------------------------------------------------------------
# TUM trajectories and tactile frame folders


def test_tum_files_as_other_tools_write_them(tmp_path, rng):
    """Comments, tabs and runs of spaces, Windows line ends, unsorted lines, a repeated line, a repeated time with
    the quaternion's sign flipped (the same rotation: fails on the old reader), 4-decimal quaternions (norm off by
    ~1e-4), exponents."""
    rotations = random_rotations(rng, 4)
    from yoto.geometry import rotation_to_quaternion_xyzw

    quaternions = np.round(rotation_to_quaternion_xyzw(rotations), 4)
    positions = rng.normal(size=(4, 3)) * 0.2
    times = [1700000000.5, 1700000000.25, 1700000000.0, 1700000000.75]
    lines = ["# ground truth from another tool", "# timestamp tx ty tz qx qy qz qw", ""]
    for t, p, q in zip(times, positions, quaternions):
        lines.append(f"{t:.9f}\t{p[0]:.6e}  {p[1]:.6f} {p[2]:.6f}   " + " ".join(f"{v:.4f}" for v in q))
    lines.append(lines[3])  # the first pose again
    lines.append(
        f"{times[1]:.9f} "
        + " ".join(f"{v:.6e}" for v in positions[1])
        + " "
        + " ".join(f"{-v:.4f}" for v in quaternions[1])
    )
    path = tmp_path / "gt.tum"
    path.write_bytes("\r\n".join(lines).encode())
    stream = read_tum(path)
    order = np.argsort(times)
    np.testing.assert_array_equal(stream.timestamps_s, np.array(times)[order])
    np.testing.assert_allclose(stream.T_world_frame[:, :3, 3], positions[order], atol=1e-6)
    expected = quaternion_xyzw_to_rotation(quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True))
    np.testing.assert_allclose(stream.T_world_frame[:, :3, :3], expected[order], atol=TOL["float_round_trip"])
    # A repeated time with another pose, and a quaternion far from unit norm, are refused naming the line.
    path.write_text("1 0 0 0 0 0 0 1\n1 0.001 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="gt.tum: lines 1 and 2 give different poses"):
        read_tum(path)
    path.write_text("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 2\n")
    with pytest.raises(InputError, match="gt.tum: line 2: quaternion of norm 2"):
        read_tum(path)
    # Nanoseconds are not seconds: refused naming the line (the old reader took them as the year 5e10).
    path.write_text("# t x y z qx qy qz qw\n1700000000000000000 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="gt.tum: line 2: timestamp 1.7e\\+18 s .*nanoseconds"):
        read_tum(path)


def test_tum_files_with_a_byte_order_mark_and_a_csv_suffix(tmp_path):
    """Windows tools start text files with a byte-order mark; a TUM file may be named `.csv` (commas between values).
    Both fail on the old readers (line 1 not numeric; "this is a Motive CSV export")."""
    from yoto.tracking.streams import read_sensor_stream

    path = tmp_path / "left.csv"
    path.write_text("# t x y z qx qy qz qw\n1.0,0.1,0,0,0,0,0,1\n2.0,0.2,0,0,0,0,0,1\n", "utf-8-sig")
    stream = read_sensor_stream(path)
    np.testing.assert_array_equal(stream.T_world_frame[:, 0, 3], [0.1, 0.2])
    pair = hand_written_pair(tmp_path, np.random.default_rng(0))
    pair.write_text(pair.read_text(), "utf-8-sig")
    assert read_contact_pair(pair).object_name == "tool"


def test_tactile_frame_names_with_nanoseconds_and_integers(tmp_path, rng):
    folder = tmp_path / "left"
    folder.mkdir()
    names = ["1700000000.123456789.ply", "1700000000.PLY", "1700000000.5.ply", "1.7000000002e9.ply"]
    for name in names:
        xy = rng.uniform(-0.004, 0.004, size=(60, 2))
        foreign_ply(folder / name, np.column_stack([xy, np.full(60, -5e-4)]), "binary_little_endian", "float")
    (folder / "README.md").write_text("frames of the left GelSight")
    timestamps, paths = list_tactile_frames(folder)
    np.testing.assert_allclose(timestamps, [1700000000.0, 1700000000.123456789, 1700000000.2, 1700000000.5], atol=1e-6)
    assert [p.name for p in paths] == [names[1], names[0], names[3], names[2]]
    assert read_tactile_folder(folder).load(1).shape == (60, 3)
    # Nanosecond integers are not seconds (SPEC): refused with the name, not read as the year 5e10.
    (folder / "1700000000123456789.ply").write_bytes((folder / names[0]).read_bytes())
    with pytest.raises(InputError, match=r"1700000000123456789.ply: .*nanoseconds"):
        list_tactile_frames(folder)


# ---------------------------------------------------------------------------------------------------------
# Object meshes


def _box(size=(0.06, 0.04, 0.03)) -> tuple[np.ndarray, np.ndarray]:
    """A closed box mesh, outward triangles."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float) * size
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))])
    return corners, faces


def _write_obj(path, vertices, faces):
    lines = ["# another exporter", "o Box", "mtllib box.mtl"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += ["vt 0 0", "vn 0 0 1", "usemtl grey", "s off"]
    lines += [f"f {a + 1}/1/1 {b + 1}/1/1 {c + 1}/1/1" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _write_stl_ascii(path, vertices, faces):
    lines = ["solid box"]
    for face in faces:
        a, b, c = vertices[face]
        n = np.cross(b - a, c - a)
        lines += [f"facet normal {n[0]:e} {n[1]:e} {n[2]:e}", "outer loop"]
        lines += [f"vertex {v[0]:e} {v[1]:e} {v[2]:e}" for v in (a, b, c)]
        lines += ["endloop", "endfacet"]
    path.write_text("\n".join(lines + ["endsolid box"]) + "\n")


def _write_stl_binary(path, vertices, faces):
    data = b"binary STL by another exporter".ljust(80, b" ") + struct.pack("<I", len(faces))
    for face in faces:
        data += struct.pack("<12fH", 0, 0, 0, *vertices[face].reshape(-1), 0)
    path.write_bytes(data)


@pytest.mark.parametrize("kind", ["obj", "stl_ascii", "stl_binary", "ply"])
def test_meshes_y_up_off_origin_and_open_are_loaded_in_their_own_frame(tmp_path, kind):
    from yoto.objects.mesh import load_mesh

    box, faces = _box()
    # y-up (the box's long side along y), 1.2 m from the origin.
    T_file_box = make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.pi / 2), [0.4, 1.1, -0.3])
    vertices = box @ T_file_box[:3, :3].T + T_file_box[:3, 3]
    for open_mesh in (False, True):
        used = faces[:-1] if open_mesh else faces  # one triangle missing: not watertight
        suffix = {"obj": ".obj", "ply": ".ply"}.get(kind, ".stl")
        path = tmp_path / f"box_{open_mesh}{suffix}"
        {"obj": _write_obj, "stl_ascii": _write_stl_ascii, "stl_binary": _write_stl_binary}.get(
            kind, lambda p, v, f: foreign_ply(p, v, "binary_big_endian", "double", faces=f)
        )(path, vertices, used)
        mesh, report, scale = load_mesh(path)
        assert scale == 1.0
        found = {tuple(np.round(v, 6)) for v in np.asarray(mesh.vertices)}
        assert found == {tuple(np.round(v, 6)) for v in vertices}
        assert mesh.volume == pytest.approx(0.06 * 0.04 * 0.03, rel=1e-4)  # outward, holes filled
        np.testing.assert_allclose(mesh.bounds, [vertices.min(axis=0), vertices.max(axis=0)], atol=1e-6)
        assert report.watertight


# ---------------------------------------------------------------------------------------------------------
# GelSight PNGs: 8-bit RGB, RGBA, palette, 16-bit RGB


def _png(path: Path, pixels: np.ndarray, colour_type: int, bit_depth: int = 8) -> Path:
    """A PNG written from the PNG specification (zlib-compressed scanlines, filter 0)."""
    height, width = pixels.shape[:2]
    dtype = ">u2" if bit_depth == 16 else "u1"
    raw = b"".join(b"\0" + pixels[row].astype(dtype).tobytes() for row in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )
    return path


def test_gelsight_pngs_rgb_rgba_and_16_bit(tmp_path, rng):
    from yoto.rig.streams import read_image_stream
    from yoto.sensor.presses import load_image

    frame = rng.integers(0, 256, size=(240, 320, 3)).astype(np.uint8)
    alpha = np.full((240, 320, 1), 255, np.uint8)
    wide = frame.astype(np.uint16) * 257  # the 8-bit levels scaled to 16 bits, as converters write them
    variants = {
        "rgb": _png(tmp_path / "rgb.png", frame, 2),
        "rgba": _png(tmp_path / "rgba.png", np.concatenate([frame, alpha], axis=2), 6),
        "rgb16": _png(tmp_path / "rgb16.png", wide, 2, 16),
    }
    for name, path in variants.items():
        np.testing.assert_array_equal(load_image(path), frame, err_msg=name)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, name in enumerate(variants):
        (folder / f"left_{12.5 + 0.04 * k:.6f}.png").write_bytes(variants[name].read_bytes())
    stream = read_image_stream(folder, str(folder))
    for _, image in stream.frames([0, 1, 2]):
        np.testing.assert_array_equal(image, frame)
    # Greyscale (a depth map, a mono camera) is refused by both readers, naming the file: not a GelSight frame.
    grey = _png(tmp_path / "grey.png", frame[:, :, 0].astype(np.uint16) * 257, 0, 16)
    with pytest.raises(InputError, match="grey.png: expected an 8-bit colour image"):
        load_image(grey)
    (folder / f"left_{12.62:.6f}.png").write_bytes(grey.read_bytes())
    with pytest.raises(InputError, match="expected an 8-bit colour image"):
        list(read_image_stream(folder, str(folder)).frames([3]))


def _foreign_tum(path: Path, stream) -> None:
    """A TUM file as another tool writes it: a header comment, tab separators, lines in reverse time order."""
    from yoto.geometry import rotation_to_quaternion_xyzw

    lines = ["# timestamp tx ty tz qx qy qz qw (another tool)"]
    quaternions = rotation_to_quaternion_xyzw(stream.T_world_frame[:, :3, :3])
    for t, T, q in zip(stream.timestamps_s, stream.T_world_frame, quaternions):
        lines.append("\t".join([f"{t:.9f}", *(f"{v:.12f}" for v in T[:3, 3]), *(f"{v:.12f}" for v in -q)]))
    path.write_text("\n".join([lines[0], *reversed(lines[1:])]) + "\n")


def test_track_command_on_streams_and_frames_written_by_another_program(builtin_models, tmp_path, capsys):
    """`yoto track` on TUM streams (comments, tabs, reverse order, quaternions of the other sign), tactile frames as
    ASCII double PLY named with nanoseconds, and a hand-written touch file: the same track as from yoto's own files."""
    pytest.importorskip("open3d")
    from yoto.simulate.trajectory import TrajectoryConfig, TrajectorySimulator, write_trajectory

    model = builtin_models["fruit"]
    model_path = model.save(tmp_path / "fruit.npz")
    config = TrajectoryConfig(motion_s=0.4, settle_s=0.1, hold_s=0.1, tactile_rate_hz=5.0)
    ours = write_trajectory(TrajectorySimulator(model, config).trajectory(3, 1), model, tmp_path / "ours")
    theirs = tmp_path / "theirs"
    touch = _rewrite_pair(ours / "touch.json", theirs, None)
    payload = json.loads(touch.read_text())
    payload["timestamp"] = json.loads((ours / "touch.json").read_text())["timestamp"]
    touch.write_text(json.dumps(payload))
    for side in ("left", "right"):
        _foreign_tum(theirs / f"{side}.tum", read_tum(ours / f"{side}.tum"))
        (theirs / f"{side}_frames").mkdir()
        for stamp, path in zip(*list_tactile_frames(ours / f"{side}_tactile")):
            foreign_ply(theirs / f"{side}_frames" / f"{stamp:.9f}.ply", read_ply_points(path)[0], "ascii", "double")
    tracked = {}
    for folder, frames in ((ours, "tactile"), (theirs, "frames")):
        args = ["track", str(folder / "touch.json"), "--left", str(folder / "left.tum"), "--right"]
        args += [str(folder / "right.tum"), "--model", str(model_path), "--method", "oracle"]
        args += ["--left-tactile", str(folder / f"left_{frames}"), "--right-tactile", str(folder / f"right_{frames}")]
        args += ["--out", str(folder / "object.tum")]
        assert main(args) == 0, capsys.readouterr()
        tracked[folder.name] = read_tum(folder / "object.tum")
    np.testing.assert_array_equal(tracked["theirs"].timestamps_s, tracked["ours"].timestamps_s)
    np.testing.assert_allclose(tracked["theirs"].T_world_frame, tracked["ours"].T_world_frame, atol=1e-8)


def test_an_object_model_from_a_y_up_off_origin_obj_stays_in_the_file_frame(tmp_path):
    """The model built from another exporter's OBJ (y-up, 1.3 m from the origin) maps its parent cloud back onto the
    file's surface: poses come out in the mesh file's frame."""
    from yoto.objects.builtin import builtin_mesh
    from yoto.objects.mesh import load_mesh
    from yoto.objects.model import ObjectModelConfig, build_object_model
    from yoto.raycast import MeshRaycaster

    tool = builtin_mesh("tool")
    T_file_tool = make_transform(rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.pi / 2), [0.3, 1.2, -0.4])
    vertices = np.asarray(tool.vertices) @ T_file_tool[:3, :3].T + T_file_tool[:3, 3]
    _write_obj(tmp_path / "tool.obj", vertices, np.asarray(tool.faces))
    mesh, _, _ = load_mesh(tmp_path / "tool.obj")
    model = build_object_model(mesh, "tool_y_up", ObjectModelConfig(num_points=20_000))
    p_mesh = model.points_object[::10] @ model.T_mesh_object[:3, :3].T + model.T_mesh_object[:3, 3]
    distance = np.linalg.norm(MeshRaycaster(vertices, np.asarray(tool.faces)).closest_points(p_mesh) - p_mesh, axis=1)
    assert distance.max() < 5e-4  # the parent cloud's own spread about the facets is ~0.2 mm
