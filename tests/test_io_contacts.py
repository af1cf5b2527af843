"""PLY and JSON files, atomic writes, and the contact-pair format (SPEC) with its bad-input errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import TOL

from yoto.contacts import ContactPair, TactileContact, find_pair_files, read_contact_pair, write_contact_pair
from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations
from yoto.io import atomic_open, read_ply_points, write_ply_points


def _cloud(rng, n=400):
    xy = rng.uniform(-0.005, 0.005, size=(n, 2))
    return np.column_stack([xy, -0.001 + 20 * (xy**2).sum(axis=1)])


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_reader_reads_every_flavour(tmp_path, rng, fmt):
    points = rng.normal(size=(50, 3))
    normals = rng.normal(size=(50, 3))
    header = f"ply\nformat {fmt} 1.0\nelement vertex 50\n"
    header += "property double x\nproperty double y\nproperty double z\nproperty uchar red\n"
    header += "property float nx\nproperty float ny\nproperty float nz\nelement face 0\n"
    header += "property list uchar int vertex_indices\nend_header\n"
    path = tmp_path / "cloud.ply"
    if fmt == "ascii":
        rows = "".join(" ".join(map(repr, [*map(float, p), 7, *map(float, n)])) + "\n" for p, n in zip(points, normals))
        path.write_bytes(header.encode() + rows.encode())
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([("p", order + "f8", 3), ("c", "u1"), ("n", order + "f4", 3)])
        records = np.zeros(50, dtype=dtype)
        records["p"], records["c"], records["n"] = points, 7, normals
        path.write_bytes(header.encode() + records.tobytes())
    read_points, read_normals = read_ply_points(path)
    assert np.allclose(read_points, points, atol=TOL["float"])
    assert np.allclose(read_normals, normals, atol=TOL["float32_unit"])


def test_ply_round_trip_and_errors(tmp_path, rng):
    points = rng.normal(size=(100, 3)) * 0.01
    path = write_ply_points(tmp_path / "a.ply", points)
    read, normals = read_ply_points(path)
    assert normals is None and np.allclose(read, points, atol=TOL["float"])

    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(InputError, match="truncated.ply: PLY file is truncated"):
        read_ply_points(truncated)
    not_ply = tmp_path / "not.ply"
    not_ply.write_text("solid x\n")
    with pytest.raises(InputError, match="not a PLY file"):
        read_ply_points(not_ply)
    no_z = tmp_path / "noz.ply"
    no_z.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n")
    with pytest.raises(InputError, match="no 'z' property"):
        read_ply_points(no_z)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_open(target) as handle:
        handle.write(b"half")
        raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old"
    assert list(tmp_path.iterdir()) == [target]


def _pair(rng) -> ContactPair:
    poses = [make_transform(r, rng.uniform(-0.5, 0.5, 3)) for r in random_rotations(rng, 3)]
    return ContactPair(
        object_name="fruit",
        left=TactileContact(_cloud(rng), poses[0]),
        right=TactileContact(_cloud(rng), poses[1]),
        T_world_mesh_true=poses[2],
        p_mesh_true={"left": rng.normal(size=3), "right": rng.normal(size=3)},
        extra={"note": "kept"},
    )


def test_pair_round_trip(tmp_path, rng):
    pair = _pair(rng)
    path = write_contact_pair(tmp_path / "pair_0007.json", pair)
    payload = json.loads(path.read_text())
    assert payload["left"]["points"] == "pair_0007_left.ply" and payload["note"] == "kept"
    assert set(payload["ground_truth"]) == {"T_world_object", "left_p_object", "right_p_object"}
    read = read_contact_pair(path)
    assert read.object_name == "fruit" and read.extra == {"note": "kept"}
    for side in ("left", "right"):
        assert np.allclose(read.contact(side).points_sensor, pair.contact(side).points_sensor, atol=TOL["ply_text_m"])
        assert np.allclose(read.contact(side).T_world_sensor, pair.contact(side).T_world_sensor, atol=TOL["float"])
        assert np.allclose(read.p_mesh_true[side], pair.p_mesh_true[side])
    assert np.allclose(read.T_world_mesh_true, pair.T_world_mesh_true, atol=TOL["float"])
    assert read.has_ground_truth
    # Pose results next to the pairs are not mistaken for pairs.
    (tmp_path / "pair_0007.pose.json").write_text("{}")
    (tmp_path / "simulation.json").write_text("{}")  # the simulator's folder settings
    assert find_pair_files([tmp_path]) == [path]


def test_a_reconstructed_cloud_keeps_its_depth_scale_prior_when_rewritten(tmp_path, rng):
    """A cloud reconstructed from a GelSight image is known only up to a depth scale: written as a PLY and read back,
    the pair still says so (before, the prior was lost and the pose stage took the heights as exact)."""
    pair = _pair(rng)
    pair.left.depth_scale_sigma = 0.05
    path = write_contact_pair(tmp_path / "pair_0001.json", pair)
    payload = json.loads(path.read_text())
    assert payload["left"]["depth_scale_sigma"] == 0.05 and "depth_scale_sigma" not in payload["right"]
    read = read_contact_pair(path)
    assert read.left.depth_scale_sigma == 0.05 and read.right.depth_scale_sigma == 0.0
    payload["left"]["depth_scale_sigma"] = -0.1
    path.write_text(json.dumps(payload))
    with pytest.raises(InputError, match=r"pair_0001.json.*left.depth_scale_sigma must be a number in \[0, 1\)"):
        read_contact_pair(path)


def _write_payload(tmp_path, rng, mutate) -> object:
    path = write_contact_pair(tmp_path / "p.json", _pair(rng))
    payload = json.loads(path.read_text())
    mutate(payload)
    path.write_text(json.dumps(payload))
    return path


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda p: p.pop("right"), "missing key 'right'"),
        (lambda p: p["left"].pop("T_world_sensor"), "missing key 'T_world_sensor' in left"),
        (lambda p: p["left"].update(T_world_sensor=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "must be a 4x4 matrix"),
        (
            lambda p: p["left"].update(T_world_sensor=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
            "not a rigid",
        ),
        (
            lambda p: p["right"].update(
                T_world_sensor=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, float("nan")], [0, 0, 0, 1]]
            ),
            "NaN",
        ),
        (lambda p: p["left"].update(points="missing.ply"), "missing.ply: point cloud file not found"),
        (lambda p: p["ground_truth"].update(left_p_object=[1, 2]), "list of 3 finite numbers"),
        (lambda p: p.update(object=""), "'object' must be"),
    ],
)
def test_bad_pair_files_name_the_file_and_the_problem(tmp_path, rng, mutate, message):
    path = _write_payload(tmp_path, rng, mutate)
    with pytest.raises(InputError, match=message):
        read_contact_pair(path)


def test_bad_clouds_and_sensor_geometry(tmp_path, rng):
    pair = _pair(rng)
    pair.left.points_sensor = pair.left.points_sensor[:10]
    path = write_contact_pair(tmp_path / "few.json", pair)
    with pytest.raises(InputError, match="few_left.ply: tactile cloud has only 10 points"):
        read_contact_pair(path)

    pair = _pair(rng)
    pair.right.points_sensor = pair.right.points_sensor * 1000.0  # written in millimetres
    with pytest.raises(InputError, match="is it in metres"):
        read_contact_pair(write_contact_pair(tmp_path / "mm.json", pair))

    pair = _pair(rng)
    kept = pair.right.points_sensor.copy()
    pair.right.points_sensor[[3, 8]] = np.nan  # an organised cloud's pixels without data: dropped
    read = read_contact_pair(write_contact_pair(tmp_path / "organised.json", pair))
    assert np.allclose(read.right.points_sensor, np.delete(kept, [3, 8], axis=0), atol=TOL["ply_text_m"])
    pair.right.points_sensor[5, 2] = np.nan  # one coordinate missing: not a pixel without data
    with pytest.raises(InputError, match="nan_right.ply: tactile cloud has 1 points with some coordinates NaN"):
        read_contact_pair(write_contact_pair(tmp_path / "nan.json", pair))

    pair = _pair(rng)
    pair.right.T_world_sensor = pair.left.T_world_sensor.copy()
    with pytest.raises(InputError, match="two sensors are 0.0 mm apart"):
        read_contact_pair(write_contact_pair(tmp_path / "same.json", pair))

    wrong = tmp_path / "wrong.json"
    wrong.write_text("[1, 2, 3]")
    with pytest.raises(InputError, match="wrong.json: a contact pair file must hold a JSON object"):
        read_contact_pair(wrong)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(InputError, match="broken.json: not a valid JSON"):
        read_contact_pair(broken)
