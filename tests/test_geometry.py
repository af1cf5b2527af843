"""Rigid-body geometry: properties over random inputs (round trips, group laws, proper rotations)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from conftest import TOL

from yoto.errors import InputError
from yoto.geometry import (
    invert_transform,
    make_transform,
    mean_rotation,
    procrustes_rotation,
    quaternion_xyzw_to_rotation,
    random_rotations,
    rotation_about_axis,
    rotation_angle_rad,
    rotation_between,
    rotation_to_quaternion_xyzw,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    tangent_basis,
    transform_points,
    validate_transform,
)

COUNT = 500


def random_rotation_vectors(rng, count, max_angle=np.pi):
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(0.0, max_angle, size=(count, 1))


def random_poses(rng, count):
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = random_rotations(rng, count)
    poses[:, :3, 3] = rng.uniform(-1.0, 1.0, size=(count, 3))
    return poses


def test_so3_exp_log_round_trip(rng):
    omega = random_rotation_vectors(rng, COUNT)
    assert np.abs(so3_log(so3_exp(omega)) - omega).max() < TOL["float_round_trip"]
    rotations = random_rotations(rng, COUNT)
    assert np.abs(so3_exp(so3_log(rotations)) - rotations).max() < TOL["float_round_trip"]


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, np.pi / 2, np.pi - 1e-3, np.pi - 1e-9, np.pi])
def test_so3_log_at_the_hard_angles(rng, angle):
    """Near 0 and near pi the textbook formula divides by sin(angle); the log must still invert exp."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rotation = so3_exp(axis * angle)
    recovered = so3_log(rotation)
    assert abs(np.linalg.norm(recovered) - angle) < TOL["float_round_trip"]
    assert np.abs(so3_exp(recovered) - rotation).max() < TOL["float_round_trip"]


def test_exp_is_a_proper_rotation_and_matches_rodrigues(rng):
    omega = random_rotation_vectors(rng, COUNT)
    rotations = so3_exp(omega)
    assert np.abs(rotations @ np.transpose(rotations, (0, 2, 1)) - np.eye(3)).max() < TOL["float"]
    assert np.abs(np.linalg.det(rotations) - 1.0).max() < TOL["float"]
    for w, rotation in zip(omega[:20], rotations[:20], strict=True):
        angle = np.linalg.norm(w)
        assert np.allclose(rotation_about_axis(w, angle), rotation, atol=TOL["float"])
        assert np.allclose(rotation @ w, w, atol=TOL["float"])  # the axis is fixed


def test_se3_exp_log_round_trip_and_group_law(rng):
    twists = np.concatenate([random_rotation_vectors(rng, COUNT, 3.0), rng.normal(size=(COUNT, 3))], axis=1)
    assert np.abs(se3_log(se3_exp(twists)) - twists).max() < TOL["float_round_trip"]
    poses = random_poses(rng, COUNT)
    assert np.abs(se3_exp(se3_log(poses)) - poses).max() < TOL["float_round_trip"]
    # exp of a pure rotation is that rotation; exp(t xi) exp(s xi) = exp((t + s) xi) along one twist
    assert np.allclose(se3_exp(np.r_[twists[0, :3], 0, 0, 0])[:3, :3], so3_exp(twists[0, :3]), atol=TOL["float"])
    xi = twists[1]
    assert np.allclose(se3_exp(0.3 * xi) @ se3_exp(0.5 * xi), se3_exp(0.8 * xi), atol=TOL["float_round_trip"])


@pytest.mark.parametrize("angle", [0.0, 1e-9, 2e-6, 1e-5, 0.0099, 0.0101, 0.5, np.pi - 1e-3])
def test_se3_exp_is_the_matrix_exponential_and_log_inverts_it(rng, angle):
    """exp and log are written out in closed form (per element, with series where a difference cancels): each
    must agree with the 4 x 4 matrix exponential of the twist, on both sides of every switch."""
    axis = rng.normal(size=3)
    xi = np.r_[axis / np.linalg.norm(axis) * angle, rng.normal(size=3)]
    generator = np.zeros((4, 4))
    generator[:3, :3] = [[0.0, -xi[2], xi[1]], [xi[2], 0.0, -xi[0]], [-xi[1], xi[0], 0.0]]
    generator[:3, 3] = xi[3:]
    assert np.abs(se3_exp(xi) - scipy.linalg.expm(generator)).max() < TOL["float_round_trip"]
    assert np.abs(se3_log(scipy.linalg.expm(generator)) - xi).max() < TOL["float_round_trip"]


def test_named_transforms_compose_and_invert(rng):
    """T_world_sensor = T_world_object @ T_object_sensor: adjacent subscripts cancel, inverses undo."""
    T_world_object, T_object_sensor = random_poses(rng, 2)
    p_sensor = rng.normal(size=(50, 3))
    T_world_sensor = T_world_object @ T_object_sensor
    assert np.allclose(
        transform_points(T_world_sensor, p_sensor),
        transform_points(T_world_object, transform_points(T_object_sensor, p_sensor)),
        atol=TOL["float"],
    )
    assert np.allclose(invert_transform(T_world_sensor) @ T_world_sensor, np.eye(4), atol=TOL["float"])
    assert np.allclose(invert_transform(T_world_sensor), np.linalg.inv(T_world_sensor), atol=TOL["float"])


def test_quaternion_round_trip_and_convention(rng):
    rotations = random_rotations(rng, COUNT)
    quaternions = rotation_to_quaternion_xyzw(rotations)
    assert np.allclose(np.linalg.norm(quaternions, axis=1), 1.0, atol=TOL["float"])
    assert (quaternions[:, 3] >= 0).all()
    assert np.abs(quaternion_xyzw_to_rotation(quaternions) - rotations).max() < TOL["float_round_trip"]
    # (x, y, z, w) order: 90 degrees about z
    half = np.sqrt(0.5)
    assert np.allclose(quaternion_xyzw_to_rotation([0, 0, half, half]), rotation_about_axis([0, 0, 1], np.pi / 2))
    assert np.allclose(rotation_to_quaternion_xyzw(np.eye(3)), [0, 0, 0, 1])


def test_procrustes_returns_a_proper_rotation_for_any_input(rng):
    for weighted in (False, True):
        for _ in range(100):
            source = rng.normal(size=(3, 4))
            target = rng.normal(size=(3, 4))
            if rng.random() < 0.5:
                target[0] *= -1.0  # a mirrored target: the best orthogonal matrix would be a reflection
            weights = rng.uniform(0.1, 1.0, size=4) if weighted else None
            rotation, singular_values = procrustes_rotation(target, source, weights)
            assert abs(np.linalg.det(rotation) - 1.0) < TOL["float"]
            assert np.allclose(rotation.T @ rotation, np.eye(3), atol=TOL["float"])
            assert (np.diff(singular_values) <= 0).all()
    rotation = random_rotations(rng, 1)[0]
    source = rng.normal(size=(3, 3))
    recovered, _ = procrustes_rotation(rotation @ source, source)
    assert rotation_angle_rad(recovered, rotation) < TOL["pose_exact_rad"]


def test_mean_rotation_is_the_weighted_chordal_mean(rng):
    centre = random_rotations(rng, 1)[0]
    axis = rng.normal(size=3)
    # Turns both ways about one axis, equally weighted, average back to the centre ...
    turns = np.array([centre @ rotation_about_axis(axis, sign * 0.4) for sign in (-1.0, 1.0)])
    assert rotation_angle_rad(mean_rotation(turns), centre) < TOL["pose_exact_rad"]
    # ... and weighted w, 1 - w at angles 0 and phi, to the angle atan2((1 - w) sin phi, w + (1 - w) cos phi)
    # (the chordal mean: the projection of the weighted sum onto SO(3)), not the geodesic (1 - w) phi.
    phi, w = 1.2, 0.7
    turns = np.array([centre, centre @ rotation_about_axis(axis, phi)])
    expected = centre @ rotation_about_axis(axis, np.arctan2((1 - w) * np.sin(phi), w + (1 - w) * np.cos(phi)))
    mean = mean_rotation(turns, np.array([w, 1 - w]))
    assert rotation_angle_rad(mean, expected) < TOL["pose_exact_rad"]
    assert abs(rotation_angle_rad(mean, centre) - (1 - w) * phi) > 0.01
    # Any scattered set gives a proper rotation; poses' rotation parts are read as rotations.
    poses = random_poses(rng, 7)
    mean = mean_rotation(poses, rng.uniform(0.1, 1.0, size=7))
    assert abs(np.linalg.det(mean) - 1.0) < TOL["float"]
    assert np.allclose(mean.T @ mean, np.eye(3), atol=TOL["float"])


def test_rotation_angle_is_accurate_at_small_angles(rng):
    rotation = random_rotations(rng, 1)[0]
    for angle in (1e-12, 1e-8, 1e-3, 1.0, 3.0):
        turned = rotation @ rotation_about_axis(rng.normal(size=3), angle)
        assert abs(rotation_angle_rad(rotation, turned) - angle) < TOL["float_round_trip"] * (0.01 + angle)


def test_tangent_basis_is_right_handed_and_follows_the_reference(rng):
    axes = rng.normal(size=(COUNT, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for reference in (None, np.array([1.0, 0.0, 0.0])):
        u, v = tangent_basis(axes, reference)
        frames = np.stack([u, v, axes], axis=-1)
        assert np.abs(np.linalg.det(frames) - 1.0).max() < TOL["float"]
        assert np.abs(frames.transpose(0, 2, 1) @ frames - np.eye(3)).max() < TOL["float"]
    u, _ = tangent_basis(axes, np.array([1.0, 0.0, 0.0]))
    projected = np.array([1.0, 0.0, 0.0]) - axes[:, :1] * axes
    assert np.allclose(u, projected / np.linalg.norm(projected, axis=1, keepdims=True), atol=TOL["float"])


def test_rotation_between_maps_source_onto_target(rng):
    for _ in range(200):
        a, b = rng.normal(size=(2, 3))
        if rng.random() < 0.1:
            b = -a * 2.0  # antiparallel
        rotation = rotation_between(a, b)
        assert np.allclose(rotation @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=TOL["float"])
        assert abs(np.linalg.det(rotation) - 1.0) < TOL["float"]


def test_validate_transform_repairs_rounding_and_refuses_the_rest(rng):
    pose = random_poses(rng, 1)[0]
    rounded = np.round(pose, 6)
    repaired = validate_transform(rounded.tolist(), "T")
    assert np.allclose(repaired[:3, :3].T @ repaired[:3, :3], np.eye(3), atol=TOL["float"])
    mirrored = pose.copy()
    mirrored[:3, 0] *= -1.0
    with pytest.raises(InputError, match="not a rigid transform"):
        validate_transform(mirrored, "T", "poses.json")
    with pytest.raises(InputError, match="4x4"):
        validate_transform(make_transform(np.eye(3), np.zeros(3))[:3], "T")
