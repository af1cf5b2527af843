"""Dual-contact scenarios: ground truth chain, pair files, determinism, calibration noise, the CLI."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from yoto.cli import main
from yoto.contacts import SIDES, contact_in_sensor, read_contact_pair
from yoto.geometry import invert_transform, make_transform, rotation_about_axis, rotation_angle_rad, transform_points
from yoto.pose.solver import oracle_pose_errors
from yoto.simulate.gel import ReconstructionNoise
from yoto.simulate.press import PressConfig
from yoto.simulate.scenarios import (
    PairSimulator,
    ScenarioConfig,
    boxes_overlap,
    calibration_error,
    simulate_pairs,
    write_pairs,
)

pytest.importorskip("open3d")

NOISE_FREE = ScenarioConfig(press=PressConfig(noise=ReconstructionNoise.none()))
PAIRS_PER_OBJECT = 8


@pytest.fixture(scope="module")
def noise_free_pairs(builtin_models):
    """Eight noise-free pairs per built-in object (seed 0)."""
    return {
        name: simulate_pairs(model, PAIRS_PER_OBJECT, seed=0, config=NOISE_FREE)
        for name, model in builtin_models.items()
    }


def test_pairs_satisfy_the_scenario_constraints(builtin_models, noise_free_pairs):
    for name, pairs in noise_free_pairs.items():
        model = builtin_models[name]
        for simulated in pairs:
            p = simulated.p_object_true
            assert np.linalg.norm(p["right"] - p["left"]) >= NOISE_FREE.min_separation_m
            assert simulated.conditioning >= NOISE_FREE.min_conditioning
            assert all(contact.accepted for contact in simulated.contacts.values())
            position = simulated.T_world_object[:3, 3]
            assert np.all(position >= NOISE_FREE.workspace_min_m) and np.all(position <= NOISE_FREE.workspace_max_m)
            # Sensors press against the surface: the outward normal at the contact faces the sensor (-z).
            for side, contact in simulated.contacts.items():
                normal = model.aggregated_normal(contact.press.p_object)
                assert normal @ contact.press.T_object_sensor[:3, 2] < -0.7, (name, side)
            assert simulated.height_maps["left"].shape == (240, 320)


def test_ground_truth_chain_is_consistent(builtin_models, noise_free_pairs):
    """T_world_mesh_true @ p_mesh_true is where the sensor saw the contact; the solver's estimate agrees."""
    for name, pairs in noise_free_pairs.items():
        model = builtin_models[name]
        for simulated in pairs:
            pair = simulated.pair
            for side in SIDES:
                contact = simulated.contacts[side]
                p_world_truth = transform_points(pair.T_world_mesh_true, pair.p_mesh_true[side])
                p_world_sensor = transform_points(pair.contact(side).T_world_sensor, contact.press.p_sensor)
                assert np.linalg.norm(p_world_truth - p_world_sensor) < 1e-9
                # The ground truth in the mesh frame maps back to the canonical frame's contact.
                p_object = transform_points(model.T_object_mesh, pair.p_mesh_true[side])
                assert np.allclose(p_object, contact.press.p_object, atol=1e-12)
                # The solver's contact estimate on the noise-free cloud agrees to well under 0.5 mm.
                p_sensor, _ = contact_in_sensor(pair.contact(side).points_sensor)
                assert np.linalg.norm(p_sensor - contact.press.p_sensor) < 1e-4, (name, side)


def test_noise_free_oracle_recovers_the_pose(builtin_models, noise_free_pairs):
    """True contact locations + model normals + measured clouds -> solve_pose: the whole geometric chain.

    The remaining error is the difference between the model's aggregated normal (parent-cloud PCA over a few
    millimetres) and the normal the 2 mm plane fit measures on the tactile cloud, which grows on sharply
    curved features (the tool's chuck grooves): medians stay under 1 mm and 1 degree.
    """
    for name, pairs in noise_free_pairs.items():
        errors = np.array([oracle_pose_errors(builtin_models[name], simulated.pair) for simulated in pairs])
        assert np.median(errors[:, 0]) < 1e-3, name
        assert np.degrees(np.median(errors[:, 1])) < 1.0, name


def test_pair_files_round_trip(builtin_models, tmp_path):
    model = builtin_models["fruit"]
    config = dataclasses.replace(ScenarioConfig(), calibration_translation_m=0.001, calibration_rotation_rad=0.01)
    report = write_pairs(model, tmp_path, 2, seed=5, config=config)
    assert len(report.written) == 2 and report.attempts >= 4
    in_memory = simulate_pairs(model, 2, seed=5, config=config)
    for path, simulated in zip(report.written, in_memory, strict=True):
        pair = read_contact_pair(path)
        assert pair.object_name == "fruit" and pair.has_ground_truth
        assert np.allclose(pair.T_world_mesh_true, simulated.pair.T_world_mesh_true, atol=1e-12)
        record = pair.extra["simulation"]
        assert record["seed"] == 5 and record["index"] == simulated.index
        for side in SIDES:
            assert np.allclose(pair.p_mesh_true[side], simulated.pair.p_mesh_true[side], atol=1e-12)
            assert np.allclose(pair.contact(side).points_sensor, simulated.pair.contact(side).points_sensor, atol=1e-6)
            # The reported pose carries the calibration error; the true one is in the record.
            T_true = np.array(record[side]["T_world_sensor_true"])
            assert np.allclose(T_true, simulated.T_world_sensor_true[side], atol=1e-12)
            error_mm = np.linalg.norm(pair.contact(side).T_world_sensor[:3, 3] - T_true[:3, 3]) * 1e3
            assert error_mm == pytest.approx(record[side]["calibration_error_mm"], abs=1e-9)
            assert 0 < error_mm < 5
            # Ground truth and the true sensor pose agree on where the contact is.
            p_world = transform_points(pair.T_world_mesh_true, pair.p_mesh_true[side])
            p_sensor = transform_points(invert_transform(T_true), p_world)
            assert np.allclose(p_sensor, simulated.contacts[side].press.p_sensor, atol=1e-9)


def test_pair_i_depends_on_seed_and_index_only(builtin_models):
    model = builtin_models["fruit"]
    simulator = PairSimulator(model, ScenarioConfig())
    first_three = [simulator.pair(7, index) for index in range(3)]
    again = [PairSimulator(model, ScenarioConfig()).pair(7, index) for index in (2, 0)]
    for earlier, later in ((first_three[2], again[0]), (first_three[0], again[1])):
        assert np.array_equal(earlier.T_world_object, later.T_world_object)
        for side in SIDES:
            assert np.array_equal(earlier.pair.contact(side).points_sensor, later.pair.contact(side).points_sensor)
            assert np.array_equal(earlier.pair.contact(side).T_world_sensor, later.pair.contact(side).T_world_sensor)
    assert not np.array_equal(first_three[0].T_world_object, first_three[1].T_world_object)
    # Noise options leave the geometry alone: same poses and contacts, different clouds.
    noise_free = PairSimulator(model, NOISE_FREE).pair(7, 0)
    assert np.array_equal(noise_free.T_world_object, first_three[0].T_world_object)
    for side in SIDES:
        assert np.array_equal(noise_free.contacts[side].press.p_object, first_three[0].contacts[side].press.p_object)
        assert len(noise_free.pair.contact(side).points_sensor) != len(first_three[0].pair.contact(side).points_sensor)


def test_calibration_error_has_the_requested_mean_magnitude(rng):
    translations, angles = [], []
    for _ in range(4000):
        T = calibration_error(rng, 0.002, np.radians(1.5))
        translations.append(np.linalg.norm(T[:3, 3]))
        angles.append(rotation_angle_rad(T, np.eye(4)))
    assert np.mean(translations) == pytest.approx(0.002, rel=0.03)
    assert np.degrees(np.mean(angles)) == pytest.approx(1.5, rel=0.03)
    assert np.array_equal(calibration_error(rng, 0.0, 0.0), np.eye(4))


def test_box_overlap_against_a_sampling_reference(rng):
    """The separating-axis test never misses an overlap that dense sampling finds, and agrees on easy cases."""
    half = np.array([0.5, 0.5, 0.5])
    assert boxes_overlap(np.eye(4), np.zeros(3), half, make_transform(np.eye(3), [0.99, 0, 0]), np.zeros(3), half)
    assert not boxes_overlap(np.eye(4), np.zeros(3), half, make_transform(np.eye(3), [1.01, 0, 0]), np.zeros(3), half)
    turned = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.pi / 4)  # a corner 0.707 from the centre along x
    for gap, expected in ((-0.02, True), (0.02, False)):
        T = make_transform(turned, [0.5 + np.sqrt(0.5) + gap, 0.0, 0.0])
        assert boxes_overlap(np.eye(4), np.zeros(3), half, T, np.zeros(3), half) == expected
    grid = np.stack(np.meshgrid(*[np.linspace(-1, 1, 9)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    found = 0
    for _ in range(300):
        halves = rng.uniform(0.1, 0.6, size=(2, 3))
        poses = [
            make_transform(rotation_about_axis(rng.normal(size=3), rng.uniform(0, np.pi)), rng.uniform(-1, 1, 3))
            for _ in range(2)
        ]
        inside = False
        for a, b in ((0, 1), (1, 0)):
            samples = transform_points(poses[a], grid * halves[a])
            local = transform_points(invert_transform(poses[b]), samples)
            inside |= bool(np.any(np.all(np.abs(local) <= halves[b], axis=1)))
        result = boxes_overlap(poses[0], np.zeros(3), halves[0], poses[1], np.zeros(3), halves[1])
        if inside:
            assert result
            found += 1
    assert found > 30


def test_facing_sensors_collide(builtin_models):
    simulator = PairSimulator(builtin_models["fruit"], NOISE_FREE)
    flipped = rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.pi)
    # Facing each other: gels 1 mm into each other collide, 3 mm apart they do not.
    assert simulator.sensors_collide(np.eye(4), make_transform(flipped, [0.0, 0.0, -0.001]))
    assert not simulator.sensors_collide(np.eye(4), make_transform(flipped, [0.0, 0.0, 0.003]))
    # Side by side: the 32 mm wide housings overlap at 30 mm, clear at 33 mm.
    assert simulator.sensors_collide(np.eye(4), make_transform(np.eye(3), [0.03, 0.0, 0.0]))
    assert not simulator.sensors_collide(np.eye(4), make_transform(np.eye(3), [0.033, 0.0, 0.0]))


def test_cli_writes_resumes_and_refuses_mixed_settings(builtin_models, tmp_path, capsys):
    model_path = builtin_models["fruit"].save(tmp_path / "fruit.npz")
    out = tmp_path / "pairs"
    args = ["-q", "simulate", "pairs", "--object", str(model_path), "--out", str(out), "--seed", "3"]
    assert main([*args, "-n", "2"]) == 0
    first = (out / "pair_0000.json").read_bytes()
    assert main([*args, "-n", "3"]) == 0
    printed = capsys.readouterr().out
    assert "1 pairs written, 2 kept" in printed and "oracle" in printed
    assert (out / "pair_0000.json").read_bytes() == first
    assert sorted(p.name for p in out.glob("pair_*.json")) == ["pair_0000.json", "pair_0001.json", "pair_0002.json"]
    settings = json.loads((out / "simulation.json").read_text())
    assert settings["seed"] == 3 and settings["object"] == "fruit"
    # Another seed into the same folder would mix two scenario sets: refused, unless --overwrite.
    assert main([*args[:-1], "4", "-n", "3"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert main([*args[:-1], "4", "-n", "1", "--overwrite", "--sensor-noise-mm", "1"]) == 0
    assert (out / "pair_0000.json").read_bytes() != first
    # The earlier run's other pairs are gone with it: one folder, one scenario set.
    assert sorted(p.name for p in out.iterdir()) == [
        "pair_0000.json",
        "pair_0000_left.ply",
        "pair_0000_right.ply",
        "simulation.json",
    ]
