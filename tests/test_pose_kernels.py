"""The compiled kernels (numba, the `fast` extra) against the numpy paths they replace."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

import yoto.pose.field as field_module
import yoto.pose.refine as refine_module
from yoto.geometry import se3_exp
from yoto.pose.field import SurfaceField
from yoto.pose.kernels import KERNELS
from yoto.pose.refine import RefineConfig

pytestmark = pytest.mark.skipif(KERNELS is None, reason="numba is not installed (the `fast` extra)")


def _sphere_field(radius: float = 0.02, cell: float = 0.001, band: float = 0.004) -> SurfaceField:
    """The signed distance of a sphere on a grid, clamped to the band like a built field."""
    axis = np.arange(-0.03, 0.03 + 1e-9, cell)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    values = np.clip(np.sqrt(x**2 + y**2 + z**2) - radius, -band, band).astype(np.float32)
    return SurfaceField(np.full(3, axis[0]), cell, values, band, 0.0)


def _numpy_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(field_module, "KERNELS", None)
    monkeypatch.setattr(refine_module, "KERNELS", None)


def test_field_read_is_bitwise_numpy(rng):
    field = _sphere_field()
    directions = rng.normal(size=(3000, 3))
    radii = rng.uniform(0.0, 0.05, 3000)  # near the surface, deep inside, beyond the band, outside the grid
    points = directions / np.linalg.norm(directions, axis=1, keepdims=True) * radii[:, None]
    points[:10] = [-1.0, 0.0, 0.0]  # far outside: +band, zero normal
    for with_gradient in (True, False):
        distance, normal = field.distance(points.reshape(30, 100, 3), with_gradient)
        expected, expected_normal = field._distance_numpy(points, (30, 100), with_gradient)
        assert distance.shape == (30, 100)
        assert np.array_equal(distance, expected)
        if with_gradient:
            assert normal is not None and expected_normal is not None
            assert np.array_equal(normal, expected_normal)
            assert np.all(normal[0, :10] == 0.0) and np.all(distance[0, :10] == field.band_m)
    # and the values are the sphere's: within the float32 storage near the surface (interpolation of a
    # smooth function on a 1 mm grid, second order)
    near = np.abs(radii - 0.02) < 0.002
    assert np.abs(field.distance(points[near], False)[0] - (radii[near] - 0.02)).max() < 5e-5


@pytest.mark.parametrize("scaled", [False, True])
def test_normal_equations_equal_numpy(rng, monkeypatch, scaled):
    field = _sphere_field()
    config = RefineConfig()
    # 60 points on a cap of the sphere (sensor frame: the pad at the sensor's origin, pressing along -z)
    directions = rng.normal(size=(60, 3)) * [0.2, 0.2, 0.0] + [0.0, 0.0, 1.0]
    on_sphere = 0.02 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    points_sensor = on_sphere - [0.0, 0.0, 0.02] + rng.normal(0.0, 5e-5, (60, 3))
    # K poses of the sensor at the sphere's top, each off by a small twist (some far enough to drop points)
    T_sensor = np.eye(4)
    T_sensor[2, 3] = 0.02
    twists = rng.normal(size=(25, 6)) * [0.05, 0.05, 0.05, 0.002, 0.002, 0.002]
    A = T_sensor @ se3_exp(twists)
    factor = rng.uniform(0.8, 1.2, 25) if scaled else None
    compiled = refine_module._contact_normal_equations(field, A, points_sensor, factor, config)
    _numpy_only(monkeypatch)
    expected = refine_module._contact_normal_equations(field, A, points_sensor, factor, config)
    for got, want in zip(compiled, expected):
        assert got.shape == want.shape
        assert np.abs(want).max() > 0.0 or (want.ndim == 2 and not scaled)  # no scale: zero rows
        np.testing.assert_allclose(got, want, rtol=TOL["float"], atol=TOL["float"] * np.abs(want).max())


def test_refinement_equal_numpy(rng, monkeypatch):
    """Whole refinements, both contacts of a pair on a sphere: the same poses and scores either way."""
    field = _sphere_field()
    config = RefineConfig()
    contacts = []
    for sensor, side in ((0, 1.0), (1, -1.0)):
        directions = rng.normal(size=(80, 3)) * [0.2, 0.2, 0.0] + [0.0, 0.0, 1.0]
        points = 0.02 * directions / np.linalg.norm(directions, axis=1, keepdims=True) - [0.0, 0.0, 0.02]
        T_world_sensor = np.diag([1.0, side, side, 1.0])  # the second sensor faces the first from below
        T_world_sensor[2, 3] = 0.02 * side
        free = np.zeros((0, 3))
        contacts.append(refine_module.ContactPoints(points, T_world_sensor, sensor, free, 0.05 * sensor))
    starts = se3_exp(rng.normal(size=(12, 6)) * [0.03, 0.03, 0.03, 0.001, 0.001, 0.001])
    prior = refine_module.CalibrationPrior()
    compiled = refine_module.refine_hypotheses(field, contacts, starts, prior, config)
    _numpy_only(monkeypatch)
    expected = refine_module.refine_hypotheses(field, contacts, starts, prior, config)
    for name in expected.__dataclass_fields__:
        want = getattr(expected, name)
        np.testing.assert_allclose(
            getattr(compiled, name), want, rtol=TOL["float"], atol=TOL["float"] * max(np.abs(want).max(), 1e-3)
        )
