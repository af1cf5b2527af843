"""The confidence's features that describe how well the contacts fix the pose (`refine.pose_covariance`)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from yoto.geometry import invert_transform, make_transform, random_rotations, rotation_about_axis, transform_points
from yoto.objects.model import ObjectModelConfig, build_object_model
from yoto.pose.field import surface_field
from yoto.pose.refine import CalibrationPrior, ContactPoints, RefineConfig, pose_covariance, refine_hypotheses
from yoto.registration import transform_batch


@pytest.fixture(scope="module")
def box():
    return build_object_model(
        trimesh.creation.box(extents=(0.12, 0.08, 0.05)), "box", ObjectModelConfig(num_points=20_000)
    )


def _face_contacts(box, T_world_object: np.ndarray, centres, normals) -> list[ContactPoints]:
    """A contact on each given face of the box (centre and outward normal in the mesh frame), away from its edges."""
    contacts = []
    for sensor, (centre, normal) in enumerate(zip(transform_points(box.T_object_mesh, np.array(centres)), normals)):
        patch = box.points_object[np.linalg.norm(box.points_object - centre, axis=1) < 0.005][:60]
        T_object_sensor = make_transform(rotation_about_axis(np.array(normal, dtype=float), 0.7 + sensor), centre)
        points_sensor = transform_batch(invert_transform(T_object_sensor)[None], patch)[0]
        contacts.append(ContactPoints(points_sensor, T_world_object @ T_object_sensor, sensor, np.zeros((0, 3))))
    return contacts


def test_pose_covariance_is_large_only_where_the_contacts_leave_the_pose_free(box, rng):
    """Two faces at right angles (top, +x) fix everything but a slide along y: there the standard deviation is the
    refinement's weak prior on the starting pose (10 mm), elsewhere the calibration error's size (~1 mm / ~1 deg per
    sensor) or less. Opposite faces (+x, -x) leave the slides along y and z and the turn about x free."""
    field = surface_field(box)
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.4, -0.1, 0.3])
    prior, config = CalibrationPrior(), RefineConfig()
    corner = _face_contacts(box, T_world_object, [[0.01, 0.005, 0.025], [0.06, -0.01, 0.0]], [[0, 0, 1], [1, 0, 0]])
    refined = refine_hypotheses(field, corner, T_world_object[None], prior, config)
    covariance = pose_covariance(field, corner, refined, 0, prior, config)
    assert np.allclose(covariance, covariance.T)
    y_axis = box.T_object_mesh[:3, :3] @ np.array([0.0, 1.0, 0.0])  # the free slide, in the object frame
    translation_std = np.sqrt(np.linalg.eigvalsh(covariance[3:, 3:]))
    assert translation_std[-1] == pytest.approx(config.prior_translation_m, rel=0.05)
    assert np.sqrt(y_axis @ covariance[3:, 3:] @ y_axis) == pytest.approx(config.prior_translation_m, rel=0.05)
    assert translation_std[1] < 0.002 and np.sqrt(np.linalg.eigvalsh(covariance[:3, :3])[-1]) < np.radians(2.0)
    opposite = _face_contacts(box, T_world_object, [[0.06, 0.01, 0.0], [-0.06, -0.01, 0.005]], [[1, 0, 0], [-1, 0, 0]])
    refined = refine_hypotheses(field, opposite, T_world_object[None], prior, config)
    covariance = pose_covariance(field, opposite, refined, 0, prior, config)
    translation_std = np.sqrt(np.linalg.eigvalsh(covariance[3:, 3:]))
    assert translation_std[1] > 0.5 * config.prior_translation_m and translation_std[0] < 0.002
    assert np.sqrt(np.linalg.eigvalsh(covariance[:3, :3])[-1]) > 0.5 * config.prior_rotation_rad
