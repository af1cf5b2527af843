"""Point-to-plane registration: the truncated fit against a slow reference, and the batched Gauss-Newton."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from conftest import TOL
from scipy.spatial import cKDTree

from yoto.geometry import make_transform, normalize, rotation_about_axis, rotation_angle_rad, transform_points
from yoto.registration import (
    GaussNewtonConfig,
    point_to_plane_gauss_newton,
    truncated_plane_fit,
    weighted_normal_equations,
)


@dataclass
class Surface:
    points_object: np.ndarray
    normals_object: np.ndarray

    def __post_init__(self):
        self.kdtree = cKDTree(self.points_object)


def saddle_surface(curvature_x: float = 40.0, curvature_y: float = -25.0, half_m: float = 0.012, step_m=2e-4):
    """Samples of z = (kx x^2 + ky y^2) / 2 (a saddle: it pins all six degrees of freedom) with unit normals."""
    axis = np.arange(-half_m, half_m + 1e-12, step_m)
    x, y = [a.ravel() for a in np.meshgrid(axis, axis)]
    z = 0.5 * (curvature_x * x**2 + curvature_y * y**2)
    normals = normalize(np.stack([-curvature_x * x, -curvature_y * y, np.ones_like(x)], axis=1))
    return Surface(np.stack([x, y, z], axis=1), normals)


def flat_surface(half_m: float = 0.02, step_m=4e-4):
    axis = np.arange(-half_m, half_m + 1e-12, step_m)
    x, y = [a.ravel() for a in np.meshgrid(axis, axis)]
    return Surface(np.stack([x, y, np.zeros_like(x)], axis=1), np.tile([0.0, 0.0, 1.0], (len(x), 1)))


def patch_of(surface: Surface, rng, count=300, radius_m=0.005):
    """Surface points near the origin, expressed in a random 'sensor' frame; returns them and T_surface_sensor."""
    near = np.flatnonzero(np.linalg.norm(surface.points_object[:, :2], axis=1) < radius_m)
    chosen = surface.points_object[rng.choice(near, count, replace=False)]
    T_surface_sensor = make_transform(rotation_about_axis(rng.normal(size=3), 0.4), rng.normal(size=3) * 0.01)
    return transform_points(np.linalg.inv(T_surface_sensor), chosen), T_surface_sensor


def perturbed(rng, T, translation_m, rotation_rad, count):
    out = []
    for _ in range(count):
        delta = make_transform(rotation_about_axis(rng.normal(size=3), rotation_rad), normalize(rng.normal(size=3)))
        delta[:3, 3] *= translation_m
        out.append(delta @ T)
    return np.array(out)


def test_truncated_fit_matches_a_slow_reference(rng):
    surface = saddle_surface()
    points = surface.points_object[rng.choice(len(surface.points_object), 200)] + rng.normal(scale=3e-4, size=(200, 3))
    tau, reach = 4e-4, 1e-3
    facing = np.array([0.0, 0.2, 1.0])
    fit = truncated_plane_fit(surface, points[None], tau, reach_m=reach, facing_surface=facing[None, None])
    residuals, matched = [], []
    for p in points:  # brute force: nearest sample, its plane, the checks
        distances = np.linalg.norm(surface.points_object - p, axis=1)
        j = int(np.argmin(distances))
        ok = distances[j] <= reach and surface.normals_object[j] @ normalize(facing) * np.linalg.norm(facing) > 0.5
        plane = abs((p - surface.points_object[j]) @ surface.normals_object[j])
        residuals.append(min(plane, tau) if ok else tau)
        matched.append(ok and plane < tau)
    assert fit.rms_m[0] == pytest.approx(np.sqrt(np.mean(np.square(residuals))), rel=TOL["float_round_trip"])
    assert fit.inlier_fraction[0] == pytest.approx(np.mean(matched), abs=TOL["float_round_trip"])
    assert 0.0 < fit.inlier_fraction[0] < 1.0  # the test exercises both branches


def test_gauss_newton_recovers_a_perturbed_pose_on_a_curved_patch(rng):
    surface = saddle_surface()
    points_sensor, T_true = patch_of(surface, rng)
    starts = perturbed(rng, T_true, translation_m=5e-4, rotation_rad=np.radians(3.0), count=6)
    config = GaussNewtonConfig(iterations=30, prior_rotation_rad=1.0, prior_translation_m=1.0)
    pivot = points_sensor.mean(axis=0)
    refined = point_to_plane_gauss_newton(surface, points_sensor, starts, config, pivot_source=pivot)

    def pivot_error(T):  # where the patch's centre lands, against the truth
        return np.linalg.norm(transform_points(T, pivot) - transform_points(T_true, pivot))

    # Sliding along the surface shows only through its curvature, and nearest-sample planes stop seeing it within
    # a fraction of the 0.2 mm sample spacing: some hundredths of a millimetre of slide remain.
    for T in refined:
        assert pivot_error(T) < 1e-4
        assert np.degrees(rotation_angle_rad(T, T_true)) < 0.15
    assert min(pivot_error(T) for T in starts) > 3e-4  # the starts really were off


def test_the_prior_holds_what_the_surface_leaves_free(rng):
    """On a plane, sliding and spinning cost nothing: the pose stays at its start there and only the offset and
    tilt move onto the plane."""
    surface = flat_surface()
    points_sensor, T_true = patch_of(surface, rng)
    start = make_transform(rotation_about_axis([1.0, 0.0, 0.0], 0.02), [0.003, -0.002, 0.0008]) @ T_true
    refined = point_to_plane_gauss_newton(surface, points_sensor, start[None], GaussNewtonConfig(iterations=20))[0]
    on_plane = transform_points(refined, points_sensor)
    assert np.abs(on_plane[:, 2]).max() < 1e-5  # the points lie on the plane
    slide_start = transform_points(start, points_sensor.mean(axis=0))[:2]
    slide_end = transform_points(refined, points_sensor.mean(axis=0))[:2]
    assert np.linalg.norm(slide_end - slide_start) < 2e-4  # in-plane position kept (up to the tilt's lever)


@pytest.mark.parametrize("pivot", [None, "centroid"])
@pytest.mark.parametrize("tolerance", [0.0, 1e-3])
def test_batched_refinement_agrees_with_one_candidate_at_a_time(rng, pivot, tolerance):
    """Batching changes nothing, also when poses converge at different iterations: each stops on its own. (The
    first start is nearly right: with the loose tolerance it stops after its first, tiny, translation step; had it
    kept iterating while the others moved, its later rotation steps would move it away from its lone result.)"""
    surface = saddle_surface()
    points_sensor, T_true = patch_of(surface, rng)
    starts = perturbed(rng, T_true, translation_m=8e-4, rotation_rad=np.radians(4.0), count=5)
    starts[0] = perturbed(rng, T_true, translation_m=2e-5, rotation_rad=np.radians(0.05), count=1)[0]
    pivot_source = None if pivot is None else points_sensor.mean(axis=0)
    facing = T_true[:3, :3].T @ np.array([0.0, 0.0, 1.0])  # the saddle's normal at the patch, in the sensor frame
    config = GaussNewtonConfig(
        iterations=6, translation_only_iterations=2, step_tolerance_m=tolerance, step_tolerance_rad=tolerance
    )
    batched = point_to_plane_gauss_newton(surface, points_sensor, starts, config, pivot_source, facing)
    assert np.abs(batched - starts).max() > 1e-3  # the poses moved
    for start, T in zip(starts, batched, strict=True):
        single = point_to_plane_gauss_newton(surface, points_sensor, start[None], config, pivot_source, facing)
        assert np.abs(single[0] - T).max() < TOL["float"]


def test_points_of_two_contacts_keep_to_their_own_side_of_a_thin_wall():
    """A box's two opposite walls, 1 mm thick: the contacts' points, given 0.6 mm off along the walls' normal,
    lie nearer the inner face of one wall. With each point's expected outward normal (its contact's) they match
    only the outer faces and the fit removes the offset; without it one contact pulls towards the inner face."""
    axis = np.arange(-0.01, 0.01 + 1e-12, 4e-4)
    y, z = [a.ravel() for a in np.meshgrid(axis, axis)]
    faces = [(-0.020, -1.0), (-0.019, 1.0), (0.019, -1.0), (0.020, 1.0)]  # (x, normal's x): outer, inner, inner, outer
    surface = Surface(
        np.vstack([np.stack([np.full_like(y, x), y, z], axis=1) for x, _ in faces]),
        np.vstack([np.tile([sign, 0.0, 0.0], (len(y), 1)) for _, sign in faces]),
    )
    near = y**2 + z**2 < 0.005**2
    left, right = (np.stack([np.full(near.sum(), x), y[near], z[near]], axis=1) for x in (-0.020, 0.020))
    points = np.vstack([left, right]) + [6e-4, 0.0, 0.0]
    facing = np.vstack([np.tile([-1.0, 0.0, 0.0], (len(left), 1)), np.tile([1.0, 0.0, 0.0], (len(right), 1))])
    config = GaussNewtonConfig()
    fit = point_to_plane_gauss_newton(surface, points, np.eye(4)[None], config, facing_source=facing)[0]
    assert fit[0, 3] == pytest.approx(-6e-4, abs=1e-6)
    blind = point_to_plane_gauss_newton(surface, points, np.eye(4)[None], config)[0]
    assert abs(blind[0, 3] + 6e-4) > 2e-4  # the left contact's points matched to its wall's inner face


def test_the_normal_equations_weigh_each_set_of_residuals_on_its_own_robust_scale(rng):
    """Five residuals with their Jacobians (7 columns: the twist's and one more), noise 0.1 mm: three within it
    count whole, one at 1 mm (ten times the scale) a tenth, an unused one nothing; batched with a set whose
    residuals all lie at 1 mm (its robust scale then 1.5 mm: every one whole), each set's equations are its own."""
    noise = 1e-4
    jacobian = rng.normal(size=(5, 7))
    distance = np.array([1e-5, -2e-5, 3e-5, 1e-3, 0.5])
    use = np.array([True, True, True, True, False])
    weights = np.array([1.0, 1.0, 1.0, 0.1, 0.0]) / noise**2
    normal, gradient = weighted_normal_equations(jacobian, distance, use, noise)
    np.testing.assert_allclose(normal, jacobian.T @ (weights[:, None] * jacobian), rtol=1e-12)
    np.testing.assert_allclose(gradient, jacobian.T @ (weights * distance), rtol=1e-12)

    far = np.full(5, 1e-3)
    normals, gradients = weighted_normal_equations(
        np.stack([jacobian, jacobian]), np.stack([distance, far]), np.stack([use, use]), noise
    )
    np.testing.assert_allclose(normals[0], normal, rtol=1e-12)
    np.testing.assert_allclose(gradients[0], gradient, rtol=1e-12)
    whole = use / noise**2
    np.testing.assert_allclose(normals[1], jacobian.T @ (whole[:, None] * jacobian), rtol=1e-12)
    np.testing.assert_allclose(gradients[1], jacobian.T @ (whole * far), rtol=1e-12)
