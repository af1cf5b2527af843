"""The whole rig chain on a small simulated session: recording -> calibrations -> labels -> pair files and training
samples, against the simulator's truth; and the bad input of a real lab (wrong sensor, dropouts, no contact)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from yoto.errors import InputError
from yoto.geometry import rotation_angle_rad

pytest.importorskip("rosbags")


@pytest.fixture(scope="module")
def gelsight():
    """A GelSight calibration of the synthetic sensor of tests/test_sensor_pipeline.py (12 rendered presses)."""
    from test_sensor_pipeline import synthetic_calibration

    return synthetic_calibration(12)


@pytest.fixture(scope="module")
def session(tmp_path_factory, builtin_models, gelsight):
    """Two single contacts per rig, one dual contact, a near miss and a long dropout per rig; ROS1 and Motive."""
    from yoto.rig.bench import calibrate_session
    from yoto.rig.calibration import GelCalibrationConfig
    from yoto.rig.recording import MocapNoise, RecordingConfig, simulate_recording

    model = builtin_models["fruit"]
    out = tmp_path_factory.mktemp("session")
    config = RecordingConfig(
        mocap_rate_hz=100.0,
        camera_rate_hz=12.0,
        single_trials=2,
        dual_trials=1,
        miss_trials=1,
        dropout_trials=1,
        calibration_poses=5,
        plate_presses=3,
        noise=MocapNoise.mocap(),
        seed=1,
    )
    truth = simulate_recording(model, gelsight, out, config, formats=("ros1", "motive"))
    calibrations = {fmt: calibrate_session(out, fmt, model, GelCalibrationConfig()) for fmt in ("ros1", "motive")}
    return {
        "model": model,
        "out": out,
        "truth": json.loads((out / "truth.json").read_text()),
        "calibrations": calibrations,
        "config": config,
        "raw_truth": truth,
    }


def _label(session, gelsight, fmt="ros1", object_calibration=None, **overrides):
    from yoto.rig.labelling import RigSide, label_recording
    from yoto.rig.streams import open_recording

    info, files, rigs, bead_calibration = session["calibrations"][fmt]
    object_calibration = object_calibration or bead_calibration
    sides = [
        RigSide(side, rigs[side], info["images"][fmt][side], overrides.get(side, gelsight))
        for side in ("left", "right")
    ]
    return label_recording(open_recording(files["trials"]), session["model"], object_calibration, sides)


def test_calibrations_match_the_simulator(session):
    truth = session["truth"]
    for fmt in ("ros1", "motive"):
        _, _, rigs, object_calibration = session["calibrations"][fmt]
        for side in ("left", "right"):
            T_true = np.asarray(truth["T_rig_sensor"][side])
            T = rigs[side].T_rig_sensor
            assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 2e-4  # gel centre: 0.2 mm
            assert np.degrees(np.arccos(np.clip(T[:3, 2] @ T_true[:3, 2], -1, 1))) < 0.1  # sensor axis (plate)
            assert max(rigs[side].gel_ball["dispersion_mm"]) < 0.2
        assert object_calibration.residual_mm["max"] < 1.5
        T_true = np.asarray(truth["T_objectbody_mesh"])
        assert np.linalg.norm(object_calibration.T_objectbody_mesh[:3, 3] - T_true[:3, 3]) < 1e-3
        assert np.degrees(rotation_angle_rad(object_calibration.T_objectbody_mesh, T_true)) < 1.0


def test_the_simulators_own_object_calibration_loads_as_a_truth_calibration(session):
    from yoto.rig.beads import load_object_calibration

    true = load_object_calibration(session["out"] / "true.object.json")
    assert (true.object_name, true.object_body) == ("fruit", "Object")
    np.testing.assert_allclose(true.T_objectbody_mesh, session["truth"]["T_objectbody_mesh"], atol=1e-12)
    _, _, _, bead_fit = session["calibrations"]["ros1"]
    assert np.linalg.norm(true.T_objectbody_mesh[:3, 3] - bead_fit.T_objectbody_mesh[:3, 3]) > 1e-6  # not the fit's


def test_labels_against_the_truth_and_refused_trials(session, gelsight):
    from yoto.rig.bench import label_errors

    report = _label(session, gelsight)
    rows = label_errors(report, session["truth"], session["model"])
    kinds = {(row["side"], row["kind"]): row for row in rows}
    labelled = [row for row in rows if row["kind"] in ("single", "dual")]
    assert len(labelled) == 6 and all(row["status"] == "labelled" for row in labelled)
    errors = np.array([row["error_mm"] for row in labelled])
    assert errors.max() < 1.0, errors  # mocap noise, careful bead picks: sub-millimetre labels
    for side in ("left", "right"):
        assert kinds[(side, "miss")]["status"] == "refused"
        assert "no contact in the GelSight frames" in kinds[(side, "miss")]["reason"]
        assert kinds[(side, "dropout")]["status"] == "refused"
        assert "mocap dropout of 0.4" in kinds[(side, "dropout")]["reason"]
        assert "RigLeft" in kinds[("left", "dropout")]["reason"]
    assert len(report.pairs) == 1


def test_motive_take_gives_the_same_labels_as_the_bag(session, gelsight):
    bag = _label(session, gelsight, "ros1")
    take = _label(session, gelsight, "motive")
    p_bag = [t.labelled.p_mesh for t in bag.trials if t.labelled is not None]
    p_take = [t.labelled.p_mesh for t in take.trials if t.labelled is not None]
    assert len(p_bag) == len(p_take) == 6
    np.testing.assert_allclose(p_take, p_bag, atol=1e-4)  # same session, independent readers and calibrations


def test_written_labels_feed_pose_and_training(session, gelsight, tmp_path):
    from yoto.contacts import read_contact_pair
    from yoto.rig.labelling import write_labels
    from yoto.rig.samples import read_labelled_contact
    from yoto.training.data import contact_samples, load_labelled_contacts

    report = _label(session, gelsight)
    written = write_labels(report, tmp_path, "trials")
    assert len(written["contacts"]) == 6 and len(written["pairs"]) == 1
    pair = read_contact_pair(written["pairs"][0])
    assert pair.has_ground_truth
    T_true = np.asarray(session["truth"]["T_world_mesh"])
    assert np.linalg.norm(pair.T_world_mesh_true[:3, 3] - T_true[:3, 3]) < 2e-3
    contact = read_labelled_contact(written["contacts"][0])
    assert contact.object_name == "fruit" and (contact.contact.points_sensor[:, 2] <= 1e-9).all()
    contacts, files = load_labelled_contacts([tmp_path / "contacts"], {"fruit": session["model"]})
    assert len(files) == 6 and len(contact_samples(contacts["fruit"], session["model"])) == 6
    # Refused trials write nothing: 10 trials, 6 contacts on disk, each with its cloud and frame.
    assert len(list((tmp_path / "contacts").glob("*.ply"))) == 6


def test_a_calibration_for_another_sensor_is_refused(session, gelsight):
    other = dataclasses.replace(
        gelsight, background=np.clip(gelsight.background.astype(int) + 40, 0, 255).astype(np.uint8)
    )
    with pytest.raises(
        InputError, match=r"trials.bag: right GelSight frames on '/gelsight_right/image_raw' do not fit"
    ):
        _label(session, gelsight, right=other)


def test_missing_topic_is_named_with_what_exists(session, gelsight):
    from yoto.rig.labelling import RigSide, label_recording
    from yoto.rig.streams import open_recording

    info, files, rigs, object_calibration = session["calibrations"]["ros1"]
    sides = [RigSide("left", rigs["left"], "/gelsight_left/image_rect", gelsight)]
    with pytest.raises(InputError, match=r"no topic '/gelsight_left/image_rect'.*/gelsight_left/image_raw"):
        label_recording(open_recording(files["trials"]), session["model"], object_calibration, sides)


def test_recording_cli_and_inspect(session, capsys):
    from yoto.cli import main

    assert main(["rig", "inspect", str(session["out"] / "ros1" / "trials.bag")]) == 0
    text = capsys.readouterr().out
    assert "/vrpn_client_node/RigLeft/pose" in text and "sensor_msgs/msg/Image" in text and "320x240 rgb8" in text
    assert main(["rig", "inspect", str(session["out"] / "motive" / "beads.csv")]) == 0
    assert "Bead3" in capsys.readouterr().out


def test_contacts_refine_a_poor_bead_calibration(session, gelsight):
    """A bead fit off by 2 deg and 1.5 mm (poor picks) is pulled back towards the truth by the contacts."""
    from yoto.geometry import make_transform, so3_exp
    from yoto.rig.labelling import LabelConfig, refine_object_calibration

    _, _, _, object_calibration = session["calibrations"]["ros1"]
    T_true = np.asarray(session["truth"]["T_objectbody_mesh"])
    offset = make_transform(so3_exp(np.radians(2.0) * np.array([0.6, -0.8, 0.0])), np.array([0.0015, 0.0, -0.0005]))
    poor = dataclasses.replace(object_calibration, T_objectbody_mesh=object_calibration.T_objectbody_mesh @ offset)
    report = _label(session, gelsight, object_calibration=poor)
    labelled = sum(trial.labelled is not None for trial in report.trials)
    assert 4 <= labelled < 6  # the poor calibration puts some holds outside the mesh: refused
    refined, change = refine_object_calibration(report, session["model"], poor, LabelConfig())
    assert change["refined"] and change["contacts"] == labelled
    assert change["surface_rms_after_mm"] < 0.5 * change["surface_rms_before_mm"]
    centre = session["model"].T_mesh_object[:3, 3]

    def error_mm(T):
        return np.linalg.norm((T @ np.append(centre, 1))[:3] - (T_true @ np.append(centre, 1))[:3]) * 1e3

    assert error_mm(refined.T_objectbody_mesh) < 0.5 * error_mm(poor.T_objectbody_mesh)
    assert rotation_angle_rad(refined.T_objectbody_mesh, T_true) < 0.5 * rotation_angle_rad(
        poor.T_objectbody_mesh, T_true
    )
    relabelled = _label(session, gelsight, object_calibration=refined)
    assert sum(trial.labelled is not None for trial in relabelled.trials) == 6  # labelled again with the refined one


def test_label_cli_writes_labels_report_and_refined_calibration(session, gelsight, tmp_path, capsys, caplog):
    """... and names each refused trial once, in the report's list (a log warning printed it a second time, and a
    third and fourth with the refinement's first labelling)."""
    import logging

    from yoto.cli import main
    from yoto.rig.beads import load_object_calibration

    info, files, rigs, object_calibration = session["calibrations"]["ros1"]
    paths = {side: rigs[side].save(tmp_path / f"{side}.rig.json") for side in ("left", "right")}
    object_path = object_calibration.save(tmp_path / "fruit.object.json")
    gelsight_path = gelsight.save(tmp_path / "gelsight.npz")
    model_path = session["model"].save(tmp_path / "fruit.npz")
    out = tmp_path / "labelled"
    args = ["rig", "label", str(files["trials"]), "--object", str(model_path), "--object-calibration", str(object_path)]
    for side in ("left", "right"):
        args += [f"--{side}-rig", str(paths[side]), f"--{side}-images", info["images"]["ros1"][side]]
    args += [
        "--gelsight",
        str(gelsight_path),
        "--out",
        str(out),
        "--refine-object-calibration",
        str(tmp_path / "r.json"),
    ]
    with caplog.at_level(logging.DEBUG):
        assert main(args) == 0
    printed = capsys.readouterr()
    warned = [r for r in caplog.records if r.levelno >= logging.WARNING and "refused" in r.getMessage()]
    assert not warned and (printed.out + printed.err).count("REFUSED") == 4
    assert main([*args, "--strict"]) == 1  # the near miss and the dropout are refused
    rows = json.loads((out / "label_report.json").read_text())["trials"]
    assert [row["status"] for row in rows].count("labelled") == 6 and len(rows) == 10
    assert len(list((out / "pairs").glob("*.json"))) == 1
    refined = load_object_calibration(tmp_path / "r.json")
    assert refined.sources["refined_with_contacts"]["contacts"] == 6


def test_a_near_miss_backs_off_as_an_arm_moves():
    """The miss's extra back-off (press depth + 3 mm) ramps in and out with the moves from and to the parking sphere:
    no mocap step or change of speed of the miss is larger than an ordinary trial's own (a step of the whole 3.5 mm in
    one frame was read as a mis-fitted body)."""
    from yoto.rig.recording import RecordingConfig, Trial, _backoff

    config = RecordingConfig()

    def backoff(tau, extra_m):  # the press itself does not enter the back-off
        return _backoff(Trial("left", "miss", None, np.eye(4), extra_backoff_m=extra_m), config, tau, 0.15)  # type: ignore[arg-type]

    _, _, _, d = Trial("left", "miss", None, np.eye(4)).timings(config)  # type: ignore[arg-type]
    tau = np.arange(0.0, d + config.move_s, 1.0 / config.mocap_rate_hz)
    plain, miss = backoff(tau, 0.0), backoff(tau, 0.0035)
    assert np.all(miss >= plain) and miss.max() - plain.max() < 1e-12  # parks where it did, stays 3.5 mm short
    assert np.all(miss[(tau >= config.move_s) & (tau < d)] - plain[(tau >= config.move_s) & (tau < d)] > 0.0035 - 1e-12)
    step = np.abs(np.diff(miss)).max()
    assert step <= np.abs(np.diff(plain)).max()  # 3.6 mm a frame at most (0.15 m parking): the move's own peak
    change = np.abs(np.diff(miss, 2)).max()  # 0.19 mm a frame per frame (2.7 m/s^2 at 120 Hz)
    assert change <= 1.05 * np.abs(np.diff(plain, 2)).max()


def test_the_near_miss_keeps_every_rig_sample(session):
    """The tracker's mocap check (`implausible_samples`) keeps all of each rig's trial stream, the near miss's too."""
    from yoto.tracking.fusion import implausible_samples, stream_jitter
    from yoto.tracking.streams import read_sensor_stream

    _, files, _, _ = session["calibrations"]["ros1"]
    for body in ("RigLeft", "RigRight"):
        stream = read_sensor_stream(files["trials"], body, body)
        assert implausible_samples(stream, stream_jitter(stream)).sum() == 0, body
