"""The compiled kernels (numba, the `fast` extra) against the numpy paths they replace."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

import yoto.pose.field as field_module
import yoto.pose.refine as refine_module
import yoto.pose.search as search_module
from yoto.contacts import WorldContact
from yoto.geometry import se3_exp
from yoto.pose.executor import _counted_refine
from yoto.pose.field import SurfaceField
from yoto.pose.kernels import KERNELS
from yoto.pose.refine import RefineConfig

pytestmark = pytest.mark.skipif(
    KERNELS is None, reason="no numba kernels (the `fast` extra not installed, or YOTO_NO_NUMBA set)"
)


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


def test_select_is_the_sorted_order_statistic(rng):
    assert KERNELS is not None
    for count in (1, 2, 3, 8, 24, 119, 120):
        for values in (rng.normal(size=count), np.round(rng.normal(size=count), 1)):  # ties too
            ordered = np.sort(values)
            for rank in {0, (count - 1) // 2, count // 2, count - 1}:
                work = np.concatenate([values, [np.inf]])  # what lies beyond `count` is left alone
                assert KERNELS.select(work, count, rank) == ordered[rank]
                assert np.all(work[:rank] <= ordered[rank]) and np.array_equal(np.sort(work[:count]), ordered)
                assert work[count] == np.inf


@pytest.mark.parametrize("scaled", [False, True])
def test_normal_equations_equal_numpy(rng, monkeypatch, scaled):
    field = _sphere_field()
    config = RefineConfig()
    # 60 points on a cap of the sphere (sensor frame: the pad at the sensor's origin, pressing along -z), the
    # second sensor's contact (its correction's rows 12-17), its depth scale estimated when `scaled`
    directions = rng.normal(size=(60, 3)) * [0.2, 0.2, 0.0] + [0.0, 0.0, 1.0]
    on_sphere = 0.02 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    points_sensor = on_sphere - [0.0, 0.0, 0.02] + rng.normal(0.0, 5e-5, (60, 3))
    T_world_sensor = np.eye(4)
    T_world_sensor[2, 3] = 0.02
    contact = refine_module.ContactPoints(points_sensor, T_world_sensor, 1, np.zeros((0, 3)), 0.05 if scaled else 0.0)
    # K object poses and corrections, each off by a small twist (some far enough to drop points)
    poses = se3_exp(rng.normal(size=(25, 6)) * [0.05, 0.05, 0.05, 0.002, 0.002, 0.002])
    corrections = se3_exp(rng.normal(size=(25, 2, 6)) * 0.01)
    depth_scale = rng.uniform(0.8, 1.2, (25, 1)) if scaled else None
    size = 19 if scaled else 18
    results = []
    for compiled in (True, False):
        if not compiled:
            _numpy_only(monkeypatch)
        hessian, gradient = np.zeros((25, size, size)), np.zeros((25, size))
        refine_module._add_normal_equations(
            field, [contact], poses, corrections, config, hessian, gradient, depth_scale
        )
        results.append((hessian, gradient))
    (hessian, gradient), (expected_hessian, expected_gradient) = results
    assert np.all(expected_hessian[:, 6:12] == 0.0) and np.abs(expected_hessian[:, 12:18, :6]).max() > 0.0
    if scaled:
        assert np.abs(expected_hessian[:, 18, 12:18]).max() > 0.0
    for got, want in ((hessian, expected_hessian), (gradient, expected_gradient)):
        np.testing.assert_allclose(got, want, rtol=TOL["float"], atol=TOL["float"] * np.abs(want).max())


def _sphere_contacts(rng: np.random.Generator, count: int, free: int = 0) -> list[refine_module.ContactPoints]:
    """Both contacts of a pair on the sphere of `_sphere_field` (the second sensor facing the first from below,
    its depth scale estimated), each with `free` free-space points across its pad."""
    contacts = []
    for sensor, side in ((0, 1.0), (1, -1.0)):
        directions = rng.normal(size=(count, 3)) * [0.2, 0.2, 0.0] + [0.0, 0.0, 1.0]
        points = 0.02 * directions / np.linalg.norm(directions, axis=1, keepdims=True) - [0.0, 0.0, 0.02]
        T_world_sensor = np.diag([1.0, side, side, 1.0])
        T_world_sensor[2, 3] = 0.02 * side
        pad = np.column_stack([rng.uniform(-0.012, 0.012, (free, 2)), np.full(free, -2e-4)])
        contacts.append(refine_module.ContactPoints(points, T_world_sensor, sensor, pad, 0.05 * sensor))
    return contacts


def test_refinement_equal_numpy(rng, monkeypatch):
    """Whole refinements, both contacts of a pair on a sphere: the same poses and scores either way, and the same
    count of field reads with gradients."""
    field = _sphere_field()
    config = RefineConfig()
    contacts = _sphere_contacts(rng, 80)
    starts = se3_exp(rng.normal(size=(12, 6)) * [0.03, 0.03, 0.03, 0.001, 0.001, 0.001])
    prior = refine_module.CalibrationPrior()
    compiled, reads = _counted_refine(field, contacts, starts, prior, config)
    _numpy_only(monkeypatch)
    expected, expected_reads = _counted_refine(field, contacts, starts, prior, config)
    assert reads == expected_reads > 0  # the executor joins split batches by these counts
    for name in expected.__dataclass_fields__:
        want = getattr(expected, name)
        np.testing.assert_allclose(
            getattr(compiled, name), want, rtol=TOL["float"], atol=TOL["float"] * max(np.abs(want).max(), 1e-3)
        )


@pytest.mark.parametrize("angle_tolerance_deg", [0.01, 8.0, 200.0])
def test_key_test_finds_numpy_s_pairs_bitwise(rng, monkeypatch, angle_tolerance_deg):
    """The compiled key test keeps a superset of the pairs that fit and numpy's exact test decides: the same pairs
    in the same order with the same mismatches as the numpy path, for tolerances from a hair (0.01 deg: every
    pair lies near its limit) to beyond a half turn (every angle fits), blurred samples beside candidates, rows
    tested in two parts joined."""
    points = rng.normal(size=(2500, 3)) * 0.03
    normals = rng.normal(size=(2500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    candidate = np.arange(2500) % 7 == 0
    blur = np.where(candidate, 0.0, rng.uniform(0.0, 0.003, 2500))
    curvature = np.where(candidate, 0.0, rng.uniform(0.0, 300.0, 2500))
    left = search_module.Locations(points[:500], normals[:500], blur[:500], curvature[:500], candidate[:500])
    right = search_module.Locations(points[500:], normals[500:], blur[500:], curvature[500:], candidate[500:])
    # The measured pair: the key of a location pair, seen from a turned and shifted world
    T = se3_exp(np.array([0.4, -0.2, 0.7, 0.1, 0.0, -0.05]))
    world = {
        side: WorldContact(p, n, T[:3, :3] @ p + T[:3, 3], T[:3, :3] @ n)
        for side, p, n in (("left", points[3], normals[3]), ("right", points[600], normals[600]))
    }
    config = search_module.SearchConfig(angle_tolerance_rad=float(np.radians(angle_tolerance_deg)))
    test = search_module.key_test(left, right, world, config)
    assert test.chunk < test.rows  # several chunks
    compiled = search_module.key_matches(test)
    halves = zip(search_module.key_matches(test, 0, test.chunk), search_module.key_matches(test, test.chunk))
    monkeypatch.setattr(search_module, "SEARCH_KERNELS", None)
    exact = search_module.key_matches(test)
    assert 100 < len(exact[0]) < test.rows * test.right_columns.shape[1]
    assert (3, 100) in set(zip(exact[0].tolist(), exact[1].tolist()))  # the measured pair itself fits
    for a, b, (first, second) in zip(exact, compiled, halves):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        assert a.tobytes() == np.concatenate([first, second]).tobytes()


@pytest.mark.parametrize("truncated", [False, True])
def test_scores_equal_numpy(rng, monkeypatch, truncated):
    """The final fit (`evaluate_fit`, with corrections and depth scales) and the seeds' cheap score
    (`evaluate_offsets`, free space included) of poses near and far from the sphere, compiled and in numpy."""
    field = _sphere_field()
    config = RefineConfig(verify_points=40, verify_free_points=30, verify_capture_truncated=truncated)
    contacts = _sphere_contacts(rng, 60, free=50)
    size = np.geomspace(1e-4, 1.0, 40)[:, None]  # from on the sphere to far off it
    poses = se3_exp(rng.normal(size=(40, 6)) * [0.1, 0.1, 0.1, 0.003, 0.003, 0.003] * size)
    corrections = rng.normal(size=(40, 2, 6)) * 0.001
    depth_scale = rng.uniform(0.8, 1.2, (40, 2))
    prior = refine_module.CalibrationPrior()
    results = []
    for compiled in (True, False):
        if not compiled:
            _numpy_only(monkeypatch)
        fit = refine_module.evaluate_fit(field, contacts, poses, corrections, config, depth_scale)
        plain = refine_module.evaluate_fit(field, contacts, poses, None, config)
        results.append((*fit, *plain, refine_module.evaluate_offsets(field, contacts, poses, prior, config)))
    for got, want in zip(*results):
        np.testing.assert_allclose(got, want, rtol=TOL["float"], atol=TOL["float"] * np.abs(want).max())
    rms, inliers, free = results[1][3:6]
    # the cases are all there: clouds on and off the surface, free space inside the object and clear of it
    assert rms.min() < 1e-4 and rms.max() == pytest.approx(config.fit_tau_m)
    assert inliers.min() == 0.0 and inliers.max() > 0.5 and free.min() == 0.0 < free.max()
    assert np.ptp(results[1][-1]) > 10.0


def test_se3_exp_and_solve(rng):
    """The loop's pose update is `geometry.se3_exp`'s (small angles by the series too); its solve is numpy's, by
    Cholesky where positive definite, by pivoting where not, and says so where the system is singular."""
    assert KERNELS is not None
    twists = rng.normal(size=(30, 6)) * np.repeat([[1.0], [1e-3], [1e-7]], 10, axis=0)
    out = np.empty((4, 4))
    for twist, expected in zip(twists, se3_exp(twists)):
        KERNELS.se3_exp_into(twist, out)
        np.testing.assert_allclose(out, expected, rtol=0.0, atol=TOL["float_round_trip"])
    basis = rng.normal(size=(19, 19))
    indefinite = basis + basis.T  # symmetric, eigenvalues of both signs
    for matrix in (basis @ basis.T + np.eye(19), indefinite):
        rhs, solution, work = rng.normal(size=19), np.empty(19), np.empty((19, 19))
        kept = matrix.copy()
        assert KERNELS.solve_into(matrix, rhs, solution, work)
        np.testing.assert_allclose(solution, np.linalg.solve(matrix, rhs), rtol=TOL["float"], atol=TOL["float"])
        assert np.array_equal(matrix, kept)
    singular = np.zeros((19, 19))
    singular[:18, :18] = np.eye(18)
    assert not KERNELS.solve_into(singular, np.ones(19), np.empty(19), np.empty((19, 19)))
