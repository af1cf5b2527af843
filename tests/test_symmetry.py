"""Rotational symmetries found at model build time, and pose distances modulo them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import TOL

from yoto.geometry import random_rotations, rotation_about_axis
from yoto.objects.model import ObjectModel, ObjectModelConfig, build_object_model
from yoto.objects.symmetry import Symmetry, close_group, detect_symmetry

SMALL = ObjectModelConfig(num_points=30_000)


@pytest.fixture(scope="module")
def shapes():
    return {
        "box": build_object_model(trimesh.creation.box(extents=(0.10, 0.06, 0.03)), "box", SMALL),
        "cylinder": build_object_model(trimesh.creation.cylinder(0.03, 0.1, sections=128), "cylinder", SMALL),
        "hexagon": build_object_model(trimesh.creation.cylinder(0.03, 0.1, sections=6), "hexagon", SMALL),
        "cone": build_object_model(trimesh.creation.cone(0.03, 0.08, sections=128), "cone", SMALL),
    }


def test_symmetries_of_primitive_shapes(shapes, builtin_models):
    box, cylinder, hexagon, cone = (shapes[name].symmetry for name in ("box", "cylinder", "hexagon", "cone"))
    assert box.axis_object is None and len(box.rotations) == 4  # three 2-fold turns and the identity
    assert cylinder.axis_object is not None and abs(cylinder.axis_object[0]) > 0.999  # the long axis is x
    assert len(cylinder.rotations) == 2  # turning it over
    assert hexagon.axis_object is None and len(hexagon.rotations) == 12  # 6-fold turns and their flips
    assert cone.axis_object is not None and len(cone.rotations) == 1  # no flip: the apex is on one side
    for name in ("tool", "fruit", "figurine"):
        assert builtin_models[name].symmetry.is_trivial, name
    # Every group element maps the surface onto itself, and the set is closed under composition.
    for group in (box.rotations, hexagon.rotations):
        for a in group:
            for b in group:
                assert min(np.abs(a @ b - g).max() for g in group) < 0.05


def test_rotation_error_modulo_symmetry(shapes, rng):
    box, cylinder = shapes["box"].symmetry, shapes["cylinder"].symmetry
    trivial = Symmetry()
    R = random_rotations(rng, 1)[0]
    flip = box.rotations[1]  # a 2-fold turn (about a face normal, as found on the sampled surface)
    small = rotation_about_axis(np.array([0.2, 0.5, -0.3]), 0.1)
    assert box.rotation_error_rad(R, R @ flip) < TOL["arccos_rad"]
    assert trivial.rotation_error_rad(R, R @ flip) == pytest.approx(np.pi)
    assert box.rotation_error_rad(R, R @ flip @ small) == pytest.approx(0.1, abs=1e-6)
    # Any twist about a continuous axis is free; a tilt of the axis is not.
    axis = cylinder.axis_object
    twist = rotation_about_axis(axis, 1.234)
    tilt = rotation_about_axis(np.cross(axis, [0.0, 0.0, 1.0]), 0.2)
    assert cylinder.rotation_error_rad(R, R @ twist) < TOL["arccos_rad"]
    assert cylinder.rotation_error_rad(R, R @ twist @ tilt) == pytest.approx(0.2, abs=1e-6)


def test_symmetry_is_stored_in_the_model_and_detected_for_old_files(shapes, tmp_path):
    model = shapes["box"]
    loaded = ObjectModel.load(model.save(tmp_path / "box.npz"))
    assert np.allclose(loaded.symmetry.rotations, model.symmetry.rotations)
    assert "2-fold" in loaded.symmetry.describe()
    del loaded.meta["symmetry"]  # a model file written before symmetry detection existed
    old = ObjectModel.load(loaded.save(tmp_path / "old.npz"))
    assert len(old.symmetry.rotations) == 4


def test_group_closure_and_a_tolerance_that_rejects(shapes):
    quarter = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    assert len(close_group([quarter])) == 4
    strict = detect_symmetry(
        shapes["box"].points_object, shapes["box"].normals_object, type(SMALL.symmetry)(tolerance_m=1e-7)
    )
    assert strict.is_trivial
