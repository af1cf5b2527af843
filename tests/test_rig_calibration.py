"""The calibration chain on synthetic mocap takes: gel centre (dual-ball), sensor axis (plate), mesh frame (beads)."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
from conftest import TOL

from yoto.errors import InputError
from yoto.geometry import make_transform, random_rotations, rotation_about_axis, rotation_angle_rad, transform_points
from yoto.rig.beads import BeadPicks, check_bead_geometry, rigid_fit
from yoto.rig.calibration import calibrate_rig, load_rig_calibration
from yoto.rig.motive import write_motive_csv
from yoto.rig.recording import still_hops
from yoto.rig.streams import open_recording

CSV_M = 2e-6  # positions through a Motive CSV in millimetres with 6 decimals, rotations with 6 decimals
START = dt.datetime(2024, 3, 1, 14, 0, 0)


def _rig_take(tmp_path, rng, T_rig_sensor, poses=6, noise_m=0.0, ball_height_m=0.0025):
    T_poses = [make_transform(R, rng.uniform(-0.2, 0.2, 3)) for R in random_rotations(rng, poses)]
    times = np.arange(0, poses * 1.3, 0.01)
    T_world_rig = still_hops(rng, T_poses, times, 0.8, 0.5)
    gel_ball = T_rig_sensor[:3, 3] + ball_height_m * T_rig_sensor[:3, 2]
    reference = np.array([0.02, 0.03, 0.01])
    markers = {
        "GelBall": transform_points_batch(T_world_rig, gel_ball) + rng.normal(size=(len(times), 3)) * noise_m,
        "RefBall": transform_points_batch(T_world_rig, reference) + rng.normal(size=(len(times), 3)) * noise_m,
    }
    return write_motive_csv(
        tmp_path / "gel.csv", times, {"Rig": T_world_rig}, markers, capture_start=START, frame_rate_hz=100.0
    )


def transform_points_batch(T, p):
    return np.einsum("nij,j->ni", T[:, :3, :3], p) + T[:, :3, 3]


def _plate_take(tmp_path, rng, T_rig_sensor, presses=4):
    T_world_plate = make_transform(rotation_about_axis(np.array([1.0, 0.2, 0.0]), 0.1), np.array([0.3, 0.1, 0.0]))
    poses = []
    for k in range(presses):
        in_plane = rotation_about_axis(np.array([0.0, 0.0, 1.0]), 1.5 * k)
        flip = rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.pi)  # sensor z = -plate z
        T_world_sensor = T_world_plate @ make_transform(in_plane @ flip, np.array([0.02 * k, -0.01 * k, -0.0005]))
        poses.append(T_world_sensor @ np.linalg.inv(T_rig_sensor))
        poses.append(T_world_sensor @ make_transform(np.eye(3), [0, 0, -0.05]) @ np.linalg.inv(T_rig_sensor))
    times = np.arange(0, len(poses) * 1.4, 0.01)
    bodies = {"Rig": still_hops(rng, poses, times, 0.8, 0.6), "Plate": np.tile(T_world_plate, (len(times), 1, 1))}
    return write_motive_csv(tmp_path / "plate.csv", times, bodies, {}, capture_start=START, frame_rate_hz=100.0)


def test_dual_ball_and_plate_recover_the_sensor_frame(tmp_path, rng):
    """Noise-free: the gel centre to CSV precision; the CAD's tilt (2 deg) corrected by the plate, its in-plane
    angle (which flat presses cannot see) kept."""
    T_true = make_transform(random_rotations(rng, 1)[0], np.array([0.09, 0.01, -0.02]))
    tilt = rotation_about_axis(np.cross(T_true[:3, 2], [1.0, 0, 0]), np.radians(2.0))
    R_cad = tilt @ T_true[:3, :3]
    calibration = calibrate_rig(
        open_recording(_rig_take(tmp_path, rng, T_true)),
        name="left",
        rig_body="Rig",
        gel_ball="GelBall",
        reference_ball="RefBall",
        R_rig_sensor_cad=R_cad,
        plate_recording=open_recording(_plate_take(tmp_path, rng, T_true)),
        plate_body="Plate",
    )
    np.testing.assert_allclose(calibration.T_rig_sensor[:3, 3], T_true[:3, 3], atol=CSV_M)
    assert np.degrees(np.arccos(calibration.T_rig_sensor[:3, 2] @ T_true[:3, 2])) < 1e-3
    assert np.degrees(rotation_angle_rad(R_cad, T_true)) == pytest.approx(2.0, abs=1e-9)
    assert calibration.orientation["plate"]["cad_z_error_deg"] == pytest.approx(2.0, abs=1e-3)
    assert calibration.orientation["plate"]["presses"] == 4
    assert max(calibration.gel_ball["dispersion_mm"]) < 1e-2
    path = calibration.save(tmp_path / "left.rig.json")
    np.testing.assert_allclose(load_rig_calibration(path).T_rig_sensor, calibration.T_rig_sensor, atol=TOL["float"])


def test_dispersion_is_reported_per_axis_with_marker_noise(tmp_path, rng):
    T_true = make_transform(random_rotations(rng, 1)[0], np.array([0.09, 0.0, -0.02]))
    calibration = calibrate_rig(
        open_recording(_rig_take(tmp_path, rng, T_true, noise_m=0.0005)),
        name="left",
        rig_body="Rig",
        gel_ball="GelBall",
        R_rig_sensor_cad=T_true[:3, :3],
    )
    dispersion = np.asarray(calibration.gel_ball["dispersion_mm"])
    # 80 samples per pose: the pose means scatter by about 0.5 / sqrt(80) = 0.056 mm per axis
    assert np.all((dispersion > 0.02) & (dispersion < 0.12)), dispersion
    assert np.linalg.norm(calibration.T_rig_sensor[:3, 3] - T_true[:3, 3]) < 1e-4


def test_too_few_poses_and_a_wandering_ball_are_refused(tmp_path, rng):
    T_true = make_transform(np.eye(3), np.array([0.09, 0.0, -0.02]))
    with pytest.raises(InputError, match=r"gel.csv: the rig 'Rig' stood still in 3 distinct poses.*at least 5"):
        calibrate_rig(
            open_recording(_rig_take(tmp_path, rng, T_true, poses=3)),
            name="left",
            rig_body="Rig",
            gel_ball="GelBall",
            R_rig_sensor_cad=np.eye(3),
        )
    # A ball lying on the table, not on the rig: it wanders in the rig body.
    T_poses = [make_transform(R, rng.uniform(-0.2, 0.2, 3)) for R in random_rotations(rng, 6)]
    times = np.arange(0, 6 * 1.3, 0.01)
    path = write_motive_csv(
        tmp_path / "loose.csv",
        times,
        {"Rig": still_hops(rng, T_poses, times, 0.8, 0.5)},
        {"GelBall": np.tile([0.1, 0.2, 0.0], (len(times), 1))},
        capture_start=START,
        frame_rate_hz=100.0,
    )
    with pytest.raises(InputError, match=r"loose.csv: the gel ball 'GelBall' moves by up to .* mm in the rig body"):
        calibrate_rig(open_recording(path), name="left", rig_body="Rig", gel_ball="GelBall", R_rig_sensor_cad=np.eye(3))
    with pytest.raises(InputError, match="no marker 'GelBal'"):
        calibrate_rig(open_recording(path), name="left", rig_body="Rig", gel_ball="GelBal", R_rig_sensor_cad=np.eye(3))


def test_rigid_fit_recovers_random_poses_exactly(rng):
    for count in (3, 4, 5, 8):
        p_mesh = rng.uniform(-0.05, 0.05, size=(count, 3))
        T = make_transform(random_rotations(rng, 1)[0], rng.normal(size=3))
        fitted, residuals = rigid_fit(transform_points(T, p_mesh), p_mesh)
        np.testing.assert_allclose(fitted, T, atol=1e-12)
        assert residuals.max() < 1e-12


def test_bead_geometry_checks():
    with pytest.raises(InputError, match="2 beads: the mesh frame needs at least 3"):
        check_bead_geometry(np.array([[0, 0, 0], [0.05, 0, 0.0]]), None)
    with pytest.raises(InputError, match="collinear"):
        check_bead_geometry(np.array([[0, 0, 0], [0.05, 0, 0.0], [0.1, 0.0003, 0.0]]), None)
    with pytest.raises(InputError, match="coplanar"):
        check_bead_geometry(np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0.05, 0.05, 0.001]]), None)
    check_bead_geometry(np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]]), None)  # three beads define a frame
    check_bead_geometry(np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0.02, 0.02, 0.03]]), None)


def test_object_calibration_from_beads(tmp_path, rng, builtin_models):
    """Beads picked exactly on the mesh: T_objectbody_mesh to CSV precision; the picks file's names and vertex ids."""
    from yoto.rig.beads import bead_centres_mesh, calibrate_object, read_bead_picks

    model = builtin_models["figurine"]
    vertices, faces = model.mesh_vertices_mesh, model.mesh_faces
    chosen = [int(i) for i in rng.choice(len(vertices), 5, replace=False)]
    picks_file = tmp_path / "beads.json"
    import json

    picks_file.write_text(
        json.dumps({"bead_radius_mm": 5, "beads": [{"name": f"B{k}", "vertex": v} for k, v in enumerate(chosen)]})
    )
    picks = read_bead_picks(picks_file, vertices)
    centres = bead_centres_mesh(picks, vertices, faces)
    assert np.all(np.abs(np.linalg.norm(centres - vertices[chosen], axis=1) - 0.005) < 1e-6)
    T_world_mesh = make_transform(random_rotations(rng, 1)[0], np.array([0.4, 0.1, 0.2]))
    T_world_body = make_transform(np.eye(3), transform_points(T_world_mesh, centres).mean(axis=0))
    times = np.arange(0, 1, 0.01)
    markers = {f"B{k}": np.tile(transform_points(T_world_mesh, c), (len(times), 1)) for k, c in enumerate(centres)}
    take = write_motive_csv(
        tmp_path / "beads.csv",
        times,
        {"Object": np.tile(T_world_body, (len(times), 1, 1))},
        markers,
        capture_start=START,
        frame_rate_hz=100.0,
    )
    calibration = calibrate_object(
        open_recording(take), picks, vertices, faces, object_name="figurine", object_body="Object"
    )
    np.testing.assert_allclose(calibration.T_objectbody_mesh, np.linalg.inv(T_world_body) @ T_world_mesh, atol=CSV_M)
    assert calibration.residual_mm["max"] < 0.01
    # Two beads' names swapped in the picks: refused, saying which.
    swapped = BeadPicks(["B1", "B0", "B2", "B3", "B4"], picks.foot_mesh, picks.bead_radius_m, picks_file)
    with pytest.raises(InputError, match="beads look mislabelled.*pick 'B1' -> marker 'B0'"):
        calibrate_object(open_recording(take), swapped, vertices, faces, object_name="figurine", object_body="Object")
    few = BeadPicks(["B0", "B1"], picks.foot_mesh[:2], picks.bead_radius_m, picks_file)
    with pytest.raises(InputError, match=r"beads.json: 2 beads"):
        calibrate_object(open_recording(take), few, vertices, faces, object_name="figurine", object_body="Object")


def test_calibration_files_of_another_kind_or_version_are_refused_naming_the_file(tmp_path):
    from yoto.rig.beads import load_object_calibration

    path = tmp_path / "rig.json"
    path.write_text('{"format": "yoto-object-calibration", "format_version": 1}')
    with pytest.raises(InputError, match=r"rig.json.*not a rig calibration.*make one with `yoto rig calibrate-rig`"):
        load_rig_calibration(path)
    with pytest.raises(InputError, match="object calibration has no 'object'"):
        load_object_calibration(path)
    path.write_text('{"format": "yoto-rig-calibration", "format_version": 7}')
    with pytest.raises(InputError, match="rig calibration version 7 is not supported"):
        load_rig_calibration(path)
