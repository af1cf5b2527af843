"""Tactile clouds at the edges of what a sensor reports: no contact at all, and contacts on a sharp tip and a thin
edge, too small for the matched filter's default cells."""

from __future__ import annotations

import numpy as np
import pytest

from yoto.contacts import ContactPair, TactileContact, read_gel, validate_tactile_points, write_contact_pair
from yoto.errors import DegenerateGeometryError, NoContactError


def _grid(z: float | np.ndarray, count: int = 60) -> np.ndarray:
    x, y = np.meshgrid(np.linspace(-0.008, 0.008, count), np.linspace(-0.006, 0.006, count))
    return np.stack([x.ravel(), y.ravel(), np.broadcast_to(z, x.shape).ravel()], axis=1)


def test_a_cloud_not_pressed_into_the_gel_is_no_contact(rng):
    """Flat on the gel plane (exactly, or with noise) is no contact; flipped z gets a hint; a flat face pressed
    0.3 mm deep, or a small dent in an otherwise flat dense height map, is a contact."""
    for flat in (_grid(0.0), _grid(rng.normal(0.0, 2e-5, (60, 60)))):
        with pytest.raises(NoContactError, match="no contact: the tactile cloud is not pressed into the gel"):
            validate_tactile_points(flat, "flat.ply")
    dent = np.hypot(*_grid(0.0)[:, :2].T) < 0.001
    flipped = _grid(0.0)
    flipped[dent, 2] = 0.5e-3
    with pytest.raises(NoContactError, match="flipped"):
        validate_tactile_points(flipped, None)
    validate_tactile_points(_grid(-0.3e-3), None)
    dense = _grid(rng.normal(0.0, 1e-5, (60, 60)))
    dense[dent, 2] -= 0.4e-3
    gel = read_gel(dense)
    assert gel.depth_m > 0.3e-3 > gel.floor_m and len(validate_tactile_points(dense, None)) == len(dense)


def test_pose_says_a_pair_with_a_flat_side_has_no_contact(builtin_models, tmp_path, capsys):
    from yoto.cli import main

    model_path = builtin_models["fruit"].save(tmp_path / "fruit.npz")
    xy = _grid(0.0)[:, :2]
    dent = np.column_stack([xy, -1e-3 + 5 * (xy**2).sum(axis=1)])
    pair = ContactPair(
        "fruit",
        TactileContact(dent, np.eye(4)),
        TactileContact(_grid(0.0), np.array([[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])),
    )
    path = write_contact_pair(tmp_path / "pair.json", pair)
    assert main(["pose", str(path), "--model", str(model_path)]) == 1
    printed = capsys.readouterr().out
    assert "no pose, a sensor shows no contact" in printed and "pair_right.ply: no contact" in printed


# ------------------------------------------------------------------------------------------------ small contacts
@pytest.fixture(scope="module")
def cat():
    """A body with a conical ear (a sharp tip) and a 1 mm thin fin (a thin edge), and a simulator that keeps
    contacts of any size; contacts are the noise-free patches the gel touches."""
    trimesh = pytest.importorskip("trimesh")
    pytest.importorskip("manifold3d")
    from yoto.objects.model import ObjectModelConfig, build_object_model
    from yoto.simulate.gel import ReconstructionNoise
    from yoto.simulate.press import PressConfig, PressSimulator

    body = trimesh.creation.icosphere(subdivisions=4, radius=0.02)
    body.apply_scale([1.3, 1.0, 0.8])
    ear = trimesh.creation.cone(0.006, 0.014, sections=48)
    ear.apply_translation([0.01, 0.0, 0.012])
    fin = trimesh.creation.box((0.02, 0.001, 0.01))
    fin.apply_translation([-0.03, 0.0, 0.0])
    model = build_object_model(trimesh.boolean.union([body, ear, fin]), "cat", ObjectModelConfig(num_points=40_000))
    config = PressConfig(min_contact_pixels=20, min_crossing_width_m=0.0, noise=ReconstructionNoise.none())
    return model, PressSimulator(model.mesh_object, config, model.raycaster)


def _press(cat, p_mesh, direction_mesh, depth_m):
    from yoto.geometry import make_transform, rotation_about_axis, rotation_between, transform_points
    from yoto.simulate.press import SimulatedContact, finish_contact

    model, simulator = cat
    p_object = transform_points(model.T_object_mesh, np.asarray(p_mesh))
    approach = model.T_object_mesh[:3, :3] @ np.asarray(direction_mesh, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    rotation = rotation_between(z, approach) @ rotation_about_axis(z, 0.3)
    press = simulator.press(make_transform(rotation, p_object - 0.002 * approach), depth_m, target_object=p_object)
    assert press.accepted, press.rejection
    contact = finish_contact(simulator, SimulatedContact(p_object, {}, press), np.random.default_rng(0))
    return contact


@pytest.mark.parametrize(
    "where, p_mesh, direction, depth_m, most_cells",
    [
        ("sharp tip", [0.01, 0.0, 0.026], [0.0, 0.0, -1.0], 0.6e-3, 0.2),
        ("thin edge", [-0.04, 0.0, 0.0], [1.0, 0.0, 0.0], 0.4e-3, 0.75),
    ],
)
def test_small_contacts_are_localized_with_finer_cells_not_refused(cat, where, p_mesh, direction, depth_m, most_cells):
    """A tip's contact (0.3 mm^2) is too small for the default cells (1.5 mm) to match at all, a thin edge's (a
    1 mm x 10 mm strip) too small to match well: both are matched with finer cells, and their beliefs are low (a
    small patch says little about where it is)."""
    from yoto.localize import make_localizer
    from yoto.localize.match import MatchLocalizer

    model, _ = cat
    contact = _press(cat, p_mesh, direction, depth_m)
    assert contact.press.contact_pixels < 3000  # at most ~12 mm^2
    if where == "sharp tip":
        with pytest.raises(DegenerateGeometryError, match="too small to match"):
            MatchLocalizer().localize(contact.points_sensor, model)
    candidates = make_localizer("match").localize(contact.points_sensor, model)
    assert len(candidates) >= 3
    assert candidates[0].details["match_cell_mm"] <= most_cells
    assert candidates[0].probability < 0.5
    for candidate in candidates:  # every candidate lies on the object's surface
        assert abs(model.raycaster.signed_distance(candidate.p_object[None])[0]) < 1e-3
