"""The benchmark's measures: calibration of the confidence, the trusted threshold, errors modulo symmetry,
procedural objects, and the simulated re-touch fused into the pose."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import TOL

from yoto.evaluation.bench import reliability, symmetric_errors, trusted_threshold
from yoto.evaluation.calibrate import roc_auc
from yoto.evaluation.shapes import FAMILIES, procedural_mesh, procedural_names
from yoto.geometry import make_transform, random_rotations, rotation_about_axis
from yoto.objects.model import ObjectModelConfig, build_object_model


def test_reliability_and_expected_calibration_error(rng):
    confidence = rng.random(20000)
    calibrated = rng.random(20000) < confidence
    assert reliability(confidence, calibrated)["ece"] < 0.02
    overconfident = rng.random(20000) < confidence**3
    data = reliability(confidence, overconfident)
    assert data["ece"] > 0.15
    assert sum(b["pairs"] for b in data["bins"]) == 20000


def test_trusted_threshold_on_a_hand_made_example():
    confidence = np.array([0.99, 0.98, 0.97, 0.9, 0.9, 0.5, 0.2])
    right = np.array([True, True, True, True, False, True, False])
    trusted = trusted_threshold(confidence, right, precision=0.99)
    assert trusted["threshold"] == pytest.approx(0.97) and trusted["confident"] == pytest.approx(3 / 7)
    assert trusted["precision"] == 1.0
    # Ties are never split: at 0.9 both poses count (4 of 5 right).
    assert trusted_threshold(confidence, right, precision=0.8)["threshold"] == pytest.approx(0.5)
    assert trusted_threshold(confidence, ~right, precision=0.99)["confident"] == 0.0


def test_roc_auc():
    assert roc_auc(np.array([0.1, 0.2, 0.8, 0.9]), np.array([False, False, True, True])) == 1.0
    assert roc_auc(np.array([0.5, 0.5]), np.array([False, True])) == 0.5


def test_errors_modulo_symmetry_add_s_and_mssd(rng):
    model = build_object_model(
        trimesh.creation.box(extents=(0.1, 0.06, 0.03)), "box", ObjectModelConfig(num_points=30_000)
    )
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.4, 0.0, 0.2])
    T_world_mesh = T_world_object @ model.T_object_mesh
    flipped = T_world_object @ make_transform(model.symmetry.rotations[1], np.zeros(3)) @ model.T_object_mesh
    errors = symmetric_errors(model, flipped, T_world_mesh)
    assert errors["rotation_deg"] < 1e-4 and errors["translation_mm"] < TOL["pose_exact_m"] * 1e3
    assert errors["mssd_mm"] < 3.0  # the flip is a symmetry of the sampled box up to a degree (face normals)
    turned = T_world_object @ make_transform(rotation_about_axis(np.array([0, 0, 1.0]), np.radians(10)), np.zeros(3))
    errors = symmetric_errors(model, turned @ model.T_object_mesh, T_world_mesh)
    assert errors["rotation_deg"] == pytest.approx(10.0, abs=0.5)
    # MSSD is the largest vertex displacement: a 10 deg turn moves the box's far corners by ~10 mm.
    assert 8.0 < errors["mssd_mm"] < 11.0 and errors["add_s_mm"] < errors["mssd_mm"]


def test_procedural_objects_are_deterministic_and_closed():
    names = procedural_names(len(FAMILIES))
    assert [name.split("_")[1] for name in names] == list(FAMILIES)
    for name in names[:3]:
        first, again = procedural_mesh(name), procedural_mesh(name)
        assert first.is_watertight and np.array_equal(first.vertices, again.vertices)
    assert procedural_names(2, first=7) == ["proc_box_7", "proc_can_8"]
