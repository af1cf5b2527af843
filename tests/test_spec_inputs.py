"""More of SPEC's inputs as other programs write them (stop 13): partial ground truth, meshes with vertices no face
uses, bead picks by a mesh viewer's vertex ids, and commands that fail: they name the file and write nothing.

Each writer here follows SPEC.md or the format's own text (never yoto's writers); see tests/test_spec_files.py.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest
from test_spec_files import foreign_ply, hand_written_pair

from yoto.cli import main
from yoto.contacts import read_contact_pair, write_contact_pair
from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations, transform_points
from yoto.io import write_text_atomic

BOX_MM = np.array([(0, 0, 0), (60, 0, 0), (60, 40, 0), (0, 40, 0), (0, 0, 20), (60, 0, 20), (60, 40, 20), (0, 40, 20)])
BOX_QUADS = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]


def _ply_mesh(path: Path, vertices: np.ndarray, faces: list, fmt: str = "ascii") -> Path:
    """A PLY mesh as a scanner's software writes one: float vertices, a face element of lists (quads allowed)."""
    header = [
        "ply",
        f"format {fmt} 1.0",
        f"element vertex {len(vertices)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    rows = [" ".join(f"{v:.9g}" for v in vertex) for vertex in vertices]
    rows += [" ".join(map(str, [len(face), *face])) for face in faces]
    path.write_text("\n".join(header + rows) + "\n")
    return path


def test_partial_ground_truth_is_read_and_kept(tmp_path, rng):
    """`ground_truth` is optional, and a labelling tool may know only the contacts (or only the pose): both read,
    both written back. Fails on the old reader (a truth without `T_world_object` was refused)."""
    path = hand_written_pair(tmp_path, rng)
    payload = json.loads(path.read_text())
    payload["ground_truth"] = {"left_p_object": [0.01, 0.02, 0.03], "right_p_object": [-0.01, 0.0, 0.02], "by": "x"}
    path.write_text(json.dumps(payload))
    pair = read_contact_pair(path)
    assert pair.T_world_mesh_true is None and not pair.has_ground_truth
    np.testing.assert_array_equal(pair.p_mesh_true["right"], [-0.01, 0.0, 0.02])
    again = read_contact_pair(write_contact_pair(tmp_path / "copy" / "pair.json", pair))
    np.testing.assert_array_equal(again.p_mesh_true["left"], [0.01, 0.02, 0.03])
    payload["ground_truth"] = {}
    path.write_text(json.dumps(payload))
    empty = read_contact_pair(path)
    assert empty.T_world_mesh_true is None and empty.p_mesh_true == {}
    payload["ground_truth"] = {"T_world_object": np.eye(3).tolist()}
    path.write_text(json.dumps(payload))
    with pytest.raises(InputError, match="pair.json: ground_truth.T_world_object"):
        read_contact_pair(path)


def test_a_mesh_with_vertices_no_face_uses_is_sized_by_its_faces(tmp_path):
    """A scan's PLY with a stray vertex 5 m out that no face uses: the object is the 60 x 40 x 20 mm box its faces
    make (fails on the old loader: 'the mesh is 5000 mm across ... with --units in'). Faces that index vertices the
    file does not have are refused naming the file."""
    from yoto.objects.mesh import load_mesh

    vertices = np.vstack([BOX_MM / 1000.0, [[5.0, 5.0, 5.0]]])
    mesh, _, scale = load_mesh(_ply_mesh(tmp_path / "scan.ply", vertices, BOX_QUADS))
    assert scale == 1.0
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [0.06, 0.04, 0.02], atol=1e-9)
    assert mesh.area == pytest.approx(2 * (60 * 40 + 60 * 20 + 40 * 20) * 1e-6, rel=1e-6)  # float properties
    assert mesh.is_watertight and mesh.volume == pytest.approx(60 * 40 * 20 * 1e-9, rel=1e-6)
    broken = [*BOX_QUADS[:-1], (3, 0, 4, 9)]
    with pytest.raises(InputError, match="broken.ply: .*index vertices that do not exist"):
        load_mesh(_ply_mesh(tmp_path / "broken.ply", vertices, broken))


def test_obj_faces_with_relative_indices_and_ngons(tmp_path):
    """OBJ's relative indices (`f -4 -3 -2 -1`: the last four vertices defined so far), written by exporters that emit
    each face after its own vertices, and a pentagon: the 60 x 40 x 20 mm box (fails on the old loader: trimesh counts
    from the file's last vertex, and the box came out 'flat')."""
    from yoto.objects.mesh import load_mesh

    lines = ["# relative indices, a vertex colour", "mtllib box.mtl", "o box"]
    for quad in BOX_QUADS:
        lines += [f"v {x} {y} {z} 0.5 0.5 0.5" for x, y, z in BOX_MM[list(quad)]]
        lines += ["vt 0 0", "vn 0 0 1", "f -4/-1/-1 -3/-1/-1 -2/-1/-1 -1/-1/-1"]
    (tmp_path / "relative.obj").write_text("\n".join(lines) + "\n")
    corners = [f"v {x} {y} {z}" for x, y, z in BOX_MM] + ["v 30 0 20"]  # 9: a point on the top's front edge
    faces = [f"f {' '.join(str(i + 1) for i in quad)}" for quad in BOX_QUADS[:1] + BOX_QUADS[2:]]
    (tmp_path / "ngon.obj").write_text("\n".join([*corners, "l 1 2", *faces, "f 5 9 6 7 8"]) + "\n")
    for name in ("relative.obj", "ngon.obj"):
        mesh, _, _ = load_mesh(tmp_path / name, "mm")
        assert mesh.is_watertight, name
        assert mesh.area == pytest.approx(8800e-6, rel=1e-9), name
        assert mesh.volume == pytest.approx(48000e-9, rel=1e-9), name


def test_bead_vertex_ids_are_the_mesh_files_own(tmp_path, rng):
    """A mesh viewer numbers a PLY's vertices in file order; the object model's mesh is repaired (a duplicate vertex
    merged, an unused one dropped), so its order differs. `yoto rig calibrate-object` reads the ids against the file
    and recovers T_objectbody_mesh; on the old code the ids indexed the repaired mesh: beads a vertex off, the
    fit centimetres wrong."""
    from yoto.objects.build import build_object, load_object_model
    from yoto.objects.model import ObjectModelConfig
    from yoto.rig.beads import bead_centres_mesh, pick_vertices_mesh, read_bead_picks
    from yoto.rig.motive import write_motive_csv

    # The file: an unused vertex first, then the box's corners, the first corner again at the end (a seam) used by
    # one face.
    file_vertices = np.vstack([[[0.3, 0.3, 0.3]], BOX_MM / 1000.0, BOX_MM[:1] / 1000.0])
    faces = [[i + 1 for i in quad] for quad in BOX_QUADS]
    faces[-1] = [4, 9, 5, 8]  # (4, 1, 5, 8) with the seam copy of corner 1
    mesh_path = _ply_mesh(tmp_path / "box.ply", file_vertices, faces)
    chosen = [2, 4, 5, 7, 9]  # corners, not coplanar; 9 is the seam's copy of corner 1
    picks = tmp_path / "beads.json"
    beads = [{"name": f"B{k}", "vertex": v} for k, v in enumerate(chosen)]
    picks.write_text(json.dumps({"bead_radius_mm": 5, "beads": beads}))

    model_path = build_object(mesh_path, "box", ObjectModelConfig(num_points=3000), out=tmp_path / "box.npz")
    model = load_object_model(model_path)
    assert len(model.mesh_vertices_mesh) < len(file_vertices)  # the repair changed the vertex list
    np.testing.assert_allclose(pick_vertices_mesh(model), file_vertices, atol=1e-7)  # float properties
    centres = bead_centres_mesh(
        read_bead_picks(picks, lambda: pick_vertices_mesh(model)), model.mesh_vertices_mesh, model.mesh_faces
    )
    # Each centre is 5 mm off its picked file vertex (the bead sits on the surface there).
    np.testing.assert_allclose(np.linalg.norm(centres - file_vertices[chosen], axis=1), 0.005, atol=1e-6)

    T_world_mesh = make_transform(random_rotations(rng, 1)[0], np.array([0.4, 0.1, 0.2]))
    T_world_body = make_transform(np.eye(3), transform_points(T_world_mesh, centres).mean(axis=0))
    times = np.arange(0, 1, 0.01)
    markers = {f"B{k}": np.tile(transform_points(T_world_mesh, c), (len(times), 1)) for k, c in enumerate(centres)}
    bodies = {"Object": np.tile(T_world_body, (len(times), 1, 1))}
    take = write_motive_csv(
        tmp_path / "beads.csv", times, bodies, markers, capture_start=dt.datetime(2024, 3, 1), frame_rate_hz=100.0
    )
    out = tmp_path / "box.object.json"
    args = ["rig", "calibrate-object", str(take), "--object", str(model_path), "--picks", str(picks)]
    assert main([*args, "--object-body", "Object", "--out", str(out)]) == 0
    T_objectbody_mesh = np.asarray(json.loads(out.read_text())["T_objectbody_mesh"])
    np.testing.assert_allclose(T_objectbody_mesh, np.linalg.inv(T_world_body) @ T_world_mesh, atol=1e-5)
    # The mesh file changed since the build: vertex ids cannot be resolved; said, nothing written.
    mesh_path.write_text(mesh_path.read_text() + "\n")
    out.unlink()
    assert main([*args, "--object-body", "Object", "--out", str(out)]) == 2
    assert not out.exists()


def test_outputs_that_cannot_be_written_and_missing_inputs_are_errors_not_tracebacks(tmp_path, capsys):
    """An output path that is a folder, or under a file, and a mesh that is not there: the command says so (exit 2),
    no traceback (the old code raised IsADirectoryError / FileNotFoundError)."""
    with pytest.raises(InputError, match="out: this output is a folder"):
        write_text_atomic(Path(tmp_path / "out").mkdir() or tmp_path / "out", "x")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="cannot write here"):
        write_text_atomic(tmp_path / "file" / "inside.txt", "x")
    assert main(["object", "build", str(tmp_path / "missing.obj")]) == 2
    assert "missing.obj: mesh file not found" in capsys.readouterr().err


def test_a_builtin_object_goes_where_out_says(tmp_path):
    """`yoto object build --builtin tool --out FILE` writes FILE (the old code ignored --out and wrote into the
    workspace); `--builtin all` with one --out file is refused."""
    out = tmp_path / "models" / "tool.npz"
    workspace = tmp_path / "ws"
    assert (
        main(
            [
                "object",
                "build",
                "--builtin",
                "tool",
                "--points",
                "3000",
                "--out",
                str(out),
                "--workspace",
                str(workspace),
            ]
        )
        == 0
    )
    assert out.is_file() and not (workspace / "objects" / "tool.npz").exists()
    assert main(["object", "build", "--builtin", "all", "--out", str(out), "--workspace", str(workspace)]) == 2


def _tool_touch_at_ten_seconds(builtin_models, tmp_path: Path, rng) -> tuple[Path, Path, np.ndarray]:
    """The built-in tool's model file, a hand-written pair touched at t = 10 s, and its pose (written to pose.json)."""
    model_path = builtin_models["tool"].save(tmp_path / "tool.npz")
    touch = hand_written_pair(tmp_path, rng)
    payload = json.loads(touch.read_text())
    payload["timestamp"] = 10.0
    touch.write_text(json.dumps(payload))
    T_world_mesh = make_transform(np.eye(3), [0.05, 0.0, 0.03])
    (tmp_path / "pose.json").write_text(json.dumps({"T_world_object": T_world_mesh.tolist()}))
    return model_path, touch, T_world_mesh


def test_track_with_an_unreadable_truth_writes_nothing(builtin_models, tmp_path, rng, capsys):
    """`yoto track --truth BAD`: refused naming the file, and the tracked poses are not written (the old code wrote
    OUT.tum, then failed on the truth). Open loop from a given pose: hand-written touch, streams and pose result.
    The streams are at 10 Hz, slower than the 0.1 s dropout gap's floor: every time is tracked (the old code failed
    on a singular smoothing fit, then took the intervals a rounding over 0.1 s for dropouts and skipped them)."""
    model_path, touch, T_world_mesh = _tool_touch_at_ten_seconds(builtin_models, tmp_path, rng)
    for side, x in (("left", 0.0), ("right", 0.1)):
        lines = [f"{t:.2f} {x + 0.01 * (t - 10):.6f} 0 0 0 0 0 1" for t in np.arange(9.5, 11.0, 0.1)]
        (tmp_path / f"{side}.tum").write_text("\n".join(lines) + "\n")
    (tmp_path / "truth.tum").write_text("# timestamp x y z\n10.0 0.1 0.2 0.3\n")
    out = tmp_path / "object.tum"
    args = ["track", str(touch), "--left", str(tmp_path / "left.tum"), "--right", str(tmp_path / "right.tum")]
    args += ["--model", str(model_path), "--pose", str(tmp_path / "pose.json"), "--open-loop", "--out", str(out)]
    assert main([*args, "--truth", str(tmp_path / "truth.tum")]) == 2
    assert "truth.tum: line 2 has 4 values" in capsys.readouterr().err
    assert not out.exists()
    assert main(args) == 0
    tracked = np.loadtxt(out)
    # The object rides with both sensors: +1 cm in x per second from the touch on.
    np.testing.assert_allclose(tracked[:, 0], np.arange(10.0, 10.95, 0.1), atol=1e-9)
    np.testing.assert_allclose(tracked[:, 1], 0.05 + 0.01 * (tracked[:, 0] - 10), atol=1e-8)


def test_pose_results_that_would_overwrite_each_other_are_refused(tmp_path, rng, capsys):
    """`yoto pose a/ b/ --out res` with a pair_0000.json in each: refused naming both before anything is written (the
    old code wrote res/pair_0000.pose.json twice, the second over the first); a pair named twice (its file and its
    folder) is estimated once."""
    from yoto.pose.cli import _pairs_and_results

    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        hand_written_pair(tmp_path / folder, rng).rename(tmp_path / folder / "pair_0000.json")
    out = tmp_path / "res"
    assert main(["pose", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)]) == 2
    assert "a/pair_0000.json and " in capsys.readouterr().err and not out.exists()
    pairs = _pairs_and_results([tmp_path / "a" / "pair_0000.json", tmp_path / "a"], str(out))
    assert pairs == [(tmp_path / "a" / "pair_0000.json", out / "pair_0000.pose.json")]


def test_a_cloud_of_the_whole_pad_reads_as_its_contact(tmp_path, rng):
    """A reconstruction program may write a point per pixel: the contact and the untouched gel around it (z = 0 within
    a few micrometres of noise). Read as the contact alone, in pair files and tactile frame folders, so the poses
    are those of the contact-only cloud (the old reader took the flat gel for contact surface: the contact's centre
    moved to the pad's and all four poses of a simulated fruit set came out 90-176 deg wrong)."""
    from yoto.contacts import contact_in_sensor
    from yoto.tracking.streams import read_tactile_folder

    path = hand_written_pair(tmp_path, rng)
    contact = read_contact_pair(path).left.points_sensor
    pixel = 0.0634e-3
    columns, rows = np.meshgrid((np.arange(320) - 159.5) * pixel, (np.arange(240) - 119.5) * pixel)
    pad = np.column_stack([columns.ravel(), rows.ravel()])
    gel = pad[np.abs(pad).max(axis=1) > 0.0045]  # around the 8 mm contact square
    whole = np.vstack([np.column_stack([gel, rng.normal(0.0, 5e-6, len(gel))]), contact])
    foreign_ply(tmp_path / "left.ply", rng.permutation(whole), "binary_little_endian", "float")
    read_back = read_contact_pair(path).left.points_sensor
    np.testing.assert_allclose(np.sort(read_back, axis=0), np.sort(contact, axis=0), atol=1e-9)  # float32 file
    centre, normal = contact_in_sensor(read_back)
    expected_centre, expected_normal = contact_in_sensor(contact)
    np.testing.assert_allclose(centre, expected_centre, atol=1e-6)
    np.testing.assert_allclose(normal, expected_normal, atol=1e-4)
    frames = tmp_path / "frames"
    frames.mkdir()
    (tmp_path / "left.ply").rename(frames / "1700000000.25.ply")
    assert len(read_tactile_folder(frames).load(0)) == len(contact)


def test_a_column_major_matrix_is_refused_with_the_reason(tmp_path, rng):
    """A sensor pose written column-major (as Eigen or OpenGL store it): its translation lands in the last row, which
    is refused naming the likely cause."""
    path = hand_written_pair(tmp_path, rng)
    payload = json.loads(path.read_text())
    payload["right"]["T_world_sensor"] = np.asarray(payload["right"]["T_world_sensor"]).T.tolist()
    path.write_text(json.dumps(payload))
    with pytest.raises(InputError, match=r"pair.json: right.T_world_sensor has last row .* written column-major"):
        read_contact_pair(path)


def _motive_take(path: Path, times: np.ndarray, bodies: dict[str, np.ndarray]) -> Path:
    """A Motive 1.2x export of rigid bodies in millimetres (quaternion x y z w, then position), from its layout."""
    from yoto.geometry import rotation_to_quaternion_xyzw

    header = (
        "Format Version,1.23,Take Name,t,Capture Frame Rate,10.000000,Export Frame Rate,10.000000,"
        "Capture Start Time,2024-05-01 03.12.44.118 PM,Total Exported Frames,"
        f"{len(times)},Rotation Type,Quaternion,Length Units,Millimeters,Coordinate Space,Global"
    )
    names = [name for name in bodies for _ in range(7)]
    lines = [header, "", ",Type," + ",".join(["Rigid Body"] * len(names)), ",Name," + ",".join(names)]
    lines += [",ID," + ",".join(str(1 + k // 7) for k in range(len(names)))]
    lines += [",," + ",".join((["Rotation"] * 4 + ["Position"] * 3) * len(bodies))]
    lines += ["Frame,Time (Seconds)," + ",".join(["X", "Y", "Z", "W", "X", "Y", "Z"] * len(bodies))]
    for frame, t in enumerate(times):
        cells = []
        for poses in bodies.values():
            cells += [f"{v:.9f}" for v in rotation_to_quaternion_xyzw(poses[frame][:3, :3])]
            cells += [f"{v * 1000:.6f}" for v in poses[frame][:3, 3]]
        lines.append(f"{frame},{t:.6f}," + ",".join(cells))
    path.write_text("\r\n".join(lines) + "\r\n", encoding="utf-8-sig")
    return path


def test_track_from_rig_bodies_with_their_calibrations(builtin_models, tmp_path, rng, capsys):
    """`yoto track` on a Motive take of the two rigs' bodies and the object's: with the rig calibrations (--left-rig,
    --right-rig) and the object calibration (--truth-calibration) the same track, and errors, as from the GelSight
    and mesh poses themselves; without them, a warning that the streams are far from the pair's sensor poses at the
    touch (the body is not the GelSight), where the old code said nothing."""
    model_path, touch, T_world_mesh = _tool_touch_at_ten_seconds(builtin_models, tmp_path, rng)
    payload = json.loads(touch.read_text())
    times = np.arange(9.5, 11.0, 0.1)
    move = np.array(
        [make_transform(random_rotations(rng, 1)[0] if t > 10.2 else np.eye(3), [0.01 * t, 0, 0]) for t in times]
    )
    # Both sensors (and the object) move together; at the touch (10.0 s, sample 5) they are where the pair says.
    sensors = {
        side: np.linalg.inv(move[5]) @ move @ np.asarray(payload[side]["T_world_sensor"]) for side in ("left", "right")
    }
    T_rig_sensor = {side: make_transform(random_rotations(rng, 1)[0], rng.uniform(-0.05, 0.05, 3)) for side in sensors}
    T_objectbody_mesh = make_transform(random_rotations(rng, 1)[0], [0.01, -0.02, 0.03])
    truth_mesh = np.linalg.inv(move[5]) @ move @ T_world_mesh
    bodies = {f"Rig{side.title()}": sensors[side] @ np.linalg.inv(T_rig_sensor[side]) for side in sensors}
    bodies["Tool"] = truth_mesh @ np.linalg.inv(T_objectbody_mesh)
    take = _motive_take(tmp_path / "take.csv", times, bodies)
    for side in sensors:
        rig = {"format": "yoto-rig-calibration", "format_version": 1, "name": side, "rig_body": f"Rig{side.title()}"}
        (tmp_path / f"{side}.rig.json").write_text(json.dumps({**rig, "T_rig_sensor": T_rig_sensor[side].tolist()}))
        lines = [f"{t:.2f} " + " ".join(f"{v:.12f}" for v in _tum_row(T)) for t, T in zip(times, sensors[side])]
        (tmp_path / f"{side}.tum").write_text("\n".join(lines) + "\n")
    calibration = {"format": "yoto-object-calibration", "format_version": 1, "object": "tool", "object_body": "Tool"}
    calibration["T_objectbody_mesh"] = T_objectbody_mesh.tolist()
    (tmp_path / "tool.object.json").write_text(json.dumps(calibration))
    common = ["track", str(touch), "--model", str(model_path), "--pose", str(tmp_path / "pose.json"), "--open-loop"]
    assert (
        main(
            [
                *common,
                "--left",
                str(tmp_path / "left.tum"),
                "--right",
                str(tmp_path / "right.tum"),
                "--out",
                str(tmp_path / "tum.tum"),
            ]
        )
        == 0
    )
    mocap = ["--left", str(take), "--left-topic", "RigLeft", "--right", str(take), "--right-topic", "RigRight"]
    mocap += ["--truth", str(take), "--truth-topic", "Tool"]
    calibrated = [
        *mocap,
        "--left-rig",
        str(tmp_path / "left.rig.json"),
        "--right-rig",
        str(tmp_path / "right.rig.json"),
    ]
    report = tmp_path / "report.json"
    capsys.readouterr()
    assert (
        main(
            [
                *common,
                *calibrated,
                "--truth-calibration",
                str(tmp_path / "tool.object.json"),
                "--out",
                str(tmp_path / "mocap.tum"),
                "--report",
                str(report),
            ]
        )
        == 0
    )
    assert "from the pair file's sensor poses" not in capsys.readouterr().out
    ours, theirs = np.loadtxt(tmp_path / "tum.tum"), np.loadtxt(tmp_path / "mocap.tum")
    np.testing.assert_allclose(theirs, ours, atol=2e-6)  # millimetres with 6 decimals, quaternions with 9
    errors = json.loads(report.read_text())["errors"]["open_loop"]
    assert errors["motion_mean"]["mm"] < 0.01 and errors["motion_mean"]["deg"] < 0.01
    assert main([*common, *mocap, "--out", str(tmp_path / "bodies.tum")]) == 0
    assert "from the pair file's sensor poses" in capsys.readouterr().out


def _tum_row(T: np.ndarray) -> np.ndarray:
    from yoto.geometry import rotation_to_quaternion_xyzw

    return np.concatenate([T[:3, 3], rotation_to_quaternion_xyzw(T[:3, :3])])


def test_a_sensor_pose_in_millimetres_is_refused(tmp_path, rng):
    """A pair whose sensor poses are in millimetres (a mocap tool's default unit): refused naming the key and the
    likely unit, where the old reader passed them to the pose stage as metres."""
    path = hand_written_pair(tmp_path, rng)
    payload = json.loads(path.read_text())
    for side in ("left", "right"):
        T = np.asarray(payload[side]["T_world_sensor"])
        T[:3, 3] = [437.1, 58.4 + (side == "right") * 30.0, 1200.0]
        payload[side]["T_world_sensor"] = T.tolist()
    path.write_text(json.dumps(payload))
    with pytest.raises(InputError, match=r"pair.json: left.T_world_sensor is 1278 from the world origin.*millimetres"):
        read_contact_pair(path)


def test_a_tum_file_with_a_row_of_column_names(tmp_path):
    """A CSV-style export whose first row names the columns (no '#'): read (the old reader refused line 1 as not
    numeric); a non-numeric row among the poses is still refused naming its line."""
    from yoto.trajectory import read_tum

    rows = ["timestamp,tx,ty,tz,qx,qy,qz,qw", "1.0,0.1,0.2,0.3,0,0,0,1", "2.0,0.2,0.2,0.3,0,0,0.7071068,0.7071068"]
    (tmp_path / "named.tum").write_text("\n".join(rows) + "\n")
    stream = read_tum(tmp_path / "named.tum")
    np.testing.assert_array_equal(stream.timestamps_s, [1.0, 2.0])
    np.testing.assert_allclose(stream.T_world_frame[1, :3, 0], [0.0, 1.0, 0.0], atol=1e-7)
    (tmp_path / "bad.tum").write_text("\n".join([*rows, "3.0,x,0,0,0,0,0,1"]) + "\n")
    with pytest.raises(InputError, match="bad.tum: line 4 is not numeric"):
        read_tum(tmp_path / "bad.tum")
