"""The dual-contact SVD solver: exact recovery, noise behaviour, degenerate input."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

from yoto.contacts import ContactEstimate, WorldContact, contact_in_sensor
from yoto.errors import DegenerateGeometryError
from yoto.geometry import (
    make_transform,
    normalize,
    random_rotations,
    rotate_vectors,
    rotation_about_axis,
    rotation_angle_rad,
    so3_log,
    transform_points,
)
from yoto.pose.solver import procrustes_quaternions, procrustes_rotations, quaternion_rotation_vectors, solve_pose


def _observe(T_world_object, p_object, n_object):
    p_world = transform_points(T_world_object, p_object)
    n_world = rotate_vectors(T_world_object, n_object)
    return WorldContact(p_sensor=np.zeros(3), n_sensor=np.zeros(3), p_world=p_world, n_world=n_world)


def _random_pose(rng):
    return make_transform(random_rotations(rng, 1)[0], rng.uniform(-0.5, 0.5, size=3))


def _random_contacts(rng):
    """Two contacts on a sphere-ish object with generic (non-coaxial) normals."""
    n_left, n_right = normalize(rng.normal(size=(2, 3)))
    return (ContactEstimate(n_left * 0.04, n_left), ContactEstimate(n_right * 0.05, n_right))


def test_random_poses_are_recovered_to_float_precision(rng):
    for _ in range(200):
        T_world_object = _random_pose(rng)
        left, right = _random_contacts(rng)
        solution = solve_pose(
            left,
            right,
            _observe(T_world_object, left.p_object, left.n_object),
            _observe(T_world_object, right.p_object, right.n_object),
        )
        assert np.abs(solution.T_world_object[:3, 3] - T_world_object[:3, 3]).max() < TOL["pose_exact_m"]
        assert rotation_angle_rad(solution.T_world_object, T_world_object) < TOL["pose_exact_rad"]
        assert np.allclose(solution.T_world_object[:3, :3], T_world_object[:3, :3], atol=TOL["pose_exact_rad"])
        assert solution.separation_error_m < TOL["pose_exact_m"]
        assert solution.alignment_residual_rad < TOL["arccos_rad"]


def test_result_is_a_proper_rotation_even_for_mirrored_input(rng):
    left, right = _random_contacts(rng)
    T = _random_pose(rng)
    world_left = _observe(T, left.p_object, left.n_object)
    world_right = _observe(T, right.p_object, right.n_object)
    # Mirror the world observations: no rotation fits, but the answer must stay in SO(3).
    for world in (world_left, world_right):
        world.p_world = world.p_world * np.array([1, 1, -1])
        world.n_world = world.n_world * np.array([1, 1, -1])
    rotation = solve_pose(left, right, world_left, world_right).T_world_object[:3, :3]
    assert np.allclose(rotation.T @ rotation, np.eye(3), atol=TOL["float_round_trip"])
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=TOL["float_round_trip"])


def test_error_grows_smoothly_with_normal_noise(rng):
    """Median rotation error rises monotonically with the noise on the measured normals, from zero."""
    medians = []
    for noise_rad in (0.0, 0.01, 0.03, 0.1):
        errors = []
        for _ in range(150):
            T = _random_pose(rng)
            left, right = _random_contacts(rng)
            worlds = []
            for c in (left, right):
                n_noisy = rotation_about_axis(rng.normal(size=3), rng.normal() * noise_rad) @ c.n_object
                worlds.append(_observe(T, c.p_object, n_noisy))
            solution = solve_pose(left, right, *worlds)
            errors.append(rotation_angle_rad(solution.T_world_object, T))
        medians.append(np.median(errors))
    assert medians[0] < TOL["arccos_rad"]
    assert medians[0] < medians[1] < medians[2] < medians[3]
    # Three directions averaging out the noise: the error stays on the order of the noise itself.
    assert medians[3] < 0.1


def test_coincident_contacts_raise(rng):
    n = normalize(rng.normal(size=3))
    left = ContactEstimate(np.array([0.01, 0.0, 0.0]), n)
    right = ContactEstimate(np.array([0.0105, 0.0, 0.0]), -n)
    T = _random_pose(rng)
    with pytest.raises(DegenerateGeometryError, match="mm apart on the object"):
        solve_pose(left, right, _observe(T, left.p_object, left.n_object), _observe(T, right.p_object, right.n_object))


def test_coaxial_grasp_is_flagged_not_silent(rng):
    """A parallel-gripper grasp of a cylinder: d and both normals on one line leave one rotation free."""
    axis = np.array([1.0, 0.0, 0.0])
    left = ContactEstimate(-0.02 * axis, -axis)
    right = ContactEstimate(0.02 * axis, axis)
    T = _random_pose(rng)
    solution = solve_pose(
        left, right, _observe(T, left.p_object, left.n_object), _observe(T, right.p_object, right.n_object)
    )
    assert not solution.well_conditioned
    assert solution.conditioning < TOL["float"]
    assert "near-coaxial" in solution.warnings[0]
    # A generic grasp is well conditioned.
    left, right = _random_contacts(rng)
    solution = solve_pose(
        left, right, _observe(T, left.p_object, left.n_object), _observe(T, right.p_object, right.n_object)
    )
    assert solution.well_conditioned and not solution.warnings


def test_contact_in_sensor_on_a_pressed_sphere():
    """A 10 mm sphere pressed 1 mm into the gel: contact at its deepest point, normal -z."""
    radius, depth = 0.010, 0.001
    xs, ys = np.meshgrid(np.linspace(-0.006, 0.006, 121), np.linspace(-0.006, 0.006, 121))
    centre = np.array([0.0012, -0.0008])
    r2 = (xs - centre[0]) ** 2 + (ys - centre[1]) ** 2
    z = radius - depth - np.sqrt(np.maximum(radius**2 - r2, 0.0))  # sphere surface seen from the gel
    inside = z < 0
    points = np.stack([xs[inside], ys[inside], z[inside]], axis=1)
    p_sensor, n_sensor = contact_in_sensor(points)
    assert np.allclose(p_sensor, [centre[0], centre[1], -depth], atol=2e-5)
    assert np.allclose(n_sensor, [0, 0, -1], atol=1e-3)


def test_contact_in_sensor_on_a_tilted_plane(rng):
    """A flat face pressed with a 10 degree tilt: the normal is the face's, not the sensor axis."""
    tilt = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(10))
    plane_normal = tilt @ np.array([0.0, 0.0, -1.0])
    xy = rng.uniform(-0.008, 0.008, size=(4000, 2))
    # Plane through (0, 0, -1 mm) with normal plane_normal: n . (p - p0) = 0.
    z = -0.001 - (plane_normal[0] * xy[:, 0] + plane_normal[1] * xy[:, 1]) / plane_normal[2]
    points = np.column_stack([xy, z])
    _, n_sensor = contact_in_sensor(points)
    assert np.allclose(n_sensor, plane_normal, atol=TOL["float32_unit"])


def test_quaternion_procrustes_matches_the_svd_and_handles_degenerate_input(rng):
    """Horn's quaternion method gives the SVD's proper rotation (reflections included), a rotation for rank-one and
    zero cross-covariances, and rotation vectors equal to so3_log's."""
    H = rng.normal(size=(500, 3, 3))  # about half with det < 0: the proper rotation needs the reflection fix
    u, _, vt = np.linalg.svd(H)
    u[:, :, 2] *= np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)[:, None]
    quaternions = procrustes_quaternions(H)
    assert np.all(quaternions[:, 3] >= 0.0) and np.allclose(np.linalg.norm(quaternions, axis=1), 1.0)
    assert np.allclose(procrustes_rotations(H), u @ vt, atol=TOL["float"])
    assert np.allclose(quaternion_rotation_vectors(quaternions), so3_log(procrustes_rotations(H)), atol=TOL["float"])
    # Rank one (three parallel directions): any rotation taking the axis onto its image is optimal.
    axis, R = normalize(rng.normal(size=3)), random_rotations(rng, 1)[0]
    rotation = procrustes_rotations(np.outer(R @ axis, axis)[None])[0]
    assert np.allclose(rotation @ axis, R @ axis, atol=1e-6) and np.isclose(np.linalg.det(rotation), 1.0)
    assert np.allclose(procrustes_rotations(np.zeros((1, 3, 3)))[0], np.eye(3))
