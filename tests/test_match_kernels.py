"""The matched filter's compiled kernels (numba, the `fast` extra) against the numpy paths they replace."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL
from scipy import ndimage

import yoto.localize.match.contact as contact_module
import yoto.localize.match.localizer as localizer_module
import yoto.localize.match.scores as scores_module
import yoto.tactile_image as tactile_image_module
from yoto.geometry import make_transform, so3_exp, so3_log
from yoto.localize.match import MatchConfig, MatchLocalizer
from yoto.localize.match.kernels import KERNELS, _cholesky_solve, _rotation_exp, _rotation_log
from yoto.localize.match.lookup import parent_surface
from yoto.registration import point_to_plane_gauss_newton
from yoto.simulate.scenarios import PairSimulator
from yoto.tactile_image import binary_dilation, binary_erosion, tactile_height_image

pytestmark = pytest.mark.skipif(
    KERNELS is None, reason="no numba kernels (the `fast` extra not installed, or YOTO_NO_NUMBA set)"
)


@pytest.fixture(scope="module")
def fruit_clouds(builtin_models):
    """Four simulated contacts on the bumpy fruit, with their true sensor poses."""
    model = builtin_models["fruit"]
    simulator = PairSimulator(model)
    clouds = []
    for index in range(2):
        simulated = simulator.pair(seed=5, index=index)
        for side, contact in simulated.contacts.items():
            clouds.append((simulated.pair.contact(side).points_sensor, contact.press.T_object_sensor))
    return model, clouds


def _numpy_only(monkeypatch: pytest.MonkeyPatch) -> None:
    for module in (localizer_module, scores_module, contact_module):
        monkeypatch.setattr(module, "KERNELS", None)
    monkeypatch.setattr(tactile_image_module, "ENABLED", False)


def test_rotation_exp_log_and_solve_repeat_numpy(rng):
    """The compiled so3 exp / log (the branch near pi too) and the Cholesky solve give numpy's numbers."""
    vectors = rng.normal(size=(200, 3))
    angles = np.concatenate([rng.uniform(0, np.pi, 150), np.pi - rng.uniform(0, 0.09, 45), [0.0, 1e-12, 1e-8, 3.1, 0]])
    vectors = vectors / np.linalg.norm(vectors, axis=1, keepdims=True) * angles[:, None]
    rotations = so3_exp(vectors)
    out_r, out_v = np.empty((3, 3)), np.empty(3)
    for vector, rotation, expected_vector in zip(vectors, rotations, so3_log(rotations), strict=True):
        _rotation_exp(vector, out_r)
        assert np.abs(out_r - rotation).max() < TOL["float_round_trip"]
        _rotation_log(rotation, out_v)
        assert np.abs(out_v - expected_vector).max() < TOL["float_round_trip"]
    for _ in range(20):
        factor = rng.normal(size=(6, 6))
        system, right = factor @ factor.T + 0.1 * np.eye(6), rng.normal(size=6)
        solution = np.empty(6)
        _cholesky_solve(system.copy(), right.copy(), 6, solution)
        assert np.abs(solution - np.linalg.solve(system, right)).max() < TOL["float"] * np.abs(solution).max()


def test_the_compiled_candidate_icp_repeats_the_numpy_gauss_newton(fruit_clouds, rng):
    """From starts up to 4 mm / 10 deg off, the compiled ICP moves every pose where `point_to_plane_gauss_newton`
    moves it (the sums in another order: within 1e-9), with translation-only first iterations too."""
    from dataclasses import replace

    model, clouds = fruit_clouds
    points_sensor, T_object_sensor_true = clouds[0]
    localizer = MatchLocalizer()
    image = localizer.image(points_sensor, model)
    samples = localizer._samples(image, 120)
    starts = np.stack(
        [
            T_object_sensor_true
            @ make_transform(so3_exp(rng.normal(size=3) * np.radians(4.0)), rng.uniform(-0.004, 0.004, 3))
            for _ in range(12)
        ]
    )
    surface = parent_surface(model)
    for config in (MatchConfig().icp, replace(MatchConfig().icp, iterations=5, translation_only_iterations=2)):
        compiled = localizer_module.candidate_icp(surface, samples, starts, config, image)
        expected = point_to_plane_gauss_newton(
            surface, samples, starts, config, pivot_source=image.centre_sensor, facing_source=image.normal_sensor
        )
        assert np.abs(expected - starts).max() > 1e-4  # the poses moved
        assert np.abs(compiled - expected).max() < TOL["float"]


def test_the_filter_stage_is_bitwise_the_numpy_path(fruit_clouds, monkeypatch):
    """The contact's roll maps, the plane costs' best rolls and the free-space penalty compiled: the filter's
    hypotheses (anchors, rolls, costs, poses) are the numpy path's, bit for bit."""
    model, clouds = fruit_clouds
    localizer = MatchLocalizer()
    compiled = [localizer.hypotheses(localizer.image(points, model), model) for points, _ in clouds]
    _numpy_only(monkeypatch)
    for (points, _), fast in zip(clouds, compiled, strict=True):
        slow = localizer.hypotheses(localizer.image(points, model), model)
        for name in ("anchors", "rolls", "filter_cost"):
            assert np.array_equal(getattr(fast, name), getattr(slow, name))
        # the image's local frame is a product in another order (heights within 1e-17 m): poses to 1e-15
        assert np.abs(fast.poses - slow.poses).max() < TOL["float_round_trip"]


def test_the_localizer_gives_the_numpy_paths_candidates(fruit_clouds, monkeypatch):
    """End to end: the same candidates in the same order, locations and beliefs within 1e-9 (compiled ICP and fits,
    free-space violation)."""
    model, clouds = fruit_clouds
    localizer = MatchLocalizer()
    compiled = [localizer.localize(points, model) for points, _ in clouds]
    _numpy_only(monkeypatch)
    for (points, _), fast in zip(clouds, compiled, strict=True):
        slow = localizer.localize(points, model)
        assert len(fast) == len(slow) > 1
        for a, b in zip(fast, slow, strict=True):
            assert a.details["match_anchor"] == b.details["match_anchor"]
            assert np.abs(a.p_object - b.p_object).max() < TOL["float"]
            assert abs(a.probability - b.probability) < TOL["float"]
            assert abs(a.details["match_residual_mm"] - b.details["match_residual_mm"]) < 1000 * TOL["float"]
            assert abs(a.details["match_free_space_mm"] - b.details["match_free_space_mm"]) < 1000 * TOL["float"]


def test_the_tactile_image_kernels_repeat_numpy_and_scipy(fruit_clouds, monkeypatch, rng):
    """The compiled binning gives the same masks and heights (to 1e-15 m); the cross dilation and erosion are
    scipy's, bit for bit, on random masks touching the border."""
    _, clouds = fruit_clouds
    compiled = [tactile_height_image(points, 0.0105, 0.0002, 1) for points, _ in clouds]
    masks = [rng.random((40, 30)) < p for p in (0.3, 0.6, 0.9)]
    for mask in masks:
        for iterations in (1, 3):
            assert np.array_equal(
                binary_dilation(mask, iterations), ndimage.binary_dilation(mask, iterations=iterations)
            )
            assert np.array_equal(binary_erosion(mask, iterations), ndimage.binary_erosion(mask, iterations=iterations))
    monkeypatch.setattr(tactile_image_module, "ENABLED", False)
    for (points, _), fast in zip(clouds, compiled, strict=True):
        slow = tactile_height_image(points, 0.0105, 0.0002, 1)
        assert np.array_equal(fast.filled, slow.filled) and np.array_equal(fast.mask, slow.mask)
        assert np.abs(fast.heights - slow.heights).max() < 1e-15


def test_the_contact_centre_is_bitwise_the_numpy_paths(fruit_clouds, monkeypatch):
    """`contact_in_sensor`'s compiled offsets and nearest point: numpy's centre and normal bit for bit, on float64
    clouds, a float32 copy (computed in float32, as numpy does) and a strided view."""
    import yoto.contacts as contacts_module

    _, clouds = fruit_clouds
    inputs = [points for points, _ in clouds] + [clouds[0][0].astype(np.float32), clouds[1][0][::3]]
    compiled = [contacts_module._contact_in_sensor(points) for points in inputs]
    monkeypatch.setattr(contacts_module, "ENABLED", False)
    for points, (centre, normal) in zip(inputs, compiled, strict=True):
        expected_centre, expected_normal = contacts_module._contact_in_sensor(points)
        assert centre.dtype == expected_centre.dtype
        assert centre.tobytes() == expected_centre.tobytes() and normal.tobytes() == expected_normal.tobytes()
