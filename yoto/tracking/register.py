"""How far a tactile frame's registration is biased by a reconstruction's smooth depth errors.

A GelSight reconstruction's depths carry smooth errors that repeat from frame to frame: a depth scale error of a
few percent (the gradient calibration) and a low-frequency bias field (lighting, integration drift). Where the
contact's shape pins the object they hardly matter, but along a direction the shape barely constrains (turning
about the normal of a nearly flat contact, rolling on a gently curved one) a few hundredths of a millimetre of
smooth depth error look like a pose change of degrees: a point-to-plane fit of frames taken at the true pose
settles degrees away from it, frame after frame the same way (figurine: 4 deg, where the white-noise information
of the same frames promises 0.6 deg). Such an offset is a bias of the measurement, not noise: the tracker's filter
estimates it beside the pose, with the covariance `systematic_covariance` gives it, so only changes the bias
cannot explain correct the pose, and directions the bias dominates keep the open loop's prediction.

Frames: points in the object frame (YOTO's canonical frame), rotations about its origin (the centroid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.objects.model import ObjectModel
from yoto.registration import plane_distances


@dataclass(frozen=True)
class DepthErrorModel:
    """The smooth depth errors of a reconstruction that repeat from frame to frame."""

    field_std_m: float = 2e-5  # 1-sigma of the smooth bias field ...
    field_length_m: float = 0.003  # ... and its correlation length
    scale_std: float = 0.03  # 1-sigma relative depth scale error


@dataclass
class ContactGeometry:
    """One contact's registered points and what the registration knows from them."""

    normal_matrix: np.ndarray  # (6, 6) J^T J over the matched points (rotation about the origin, translation)
    push: np.ndarray  # (6, 7) J^T (n . z) E: how the depth error terms E push the fit (before H^-1); the
    # covariance they cause comes from all contacts registered together (`joint_systematic_covariance`)


def contact_geometry(
    model: ObjectModel,
    points_object: np.ndarray,
    points_sensor: np.ndarray,
    axis_object: np.ndarray,
    reach_m: float,
    errors: DepthErrorModel,
) -> ContactGeometry:
    """The normal matrix of a contact's registered points (object frame) and how its depth errors push the fit.

    `points_sensor`: the same points in the sensor frame (where the depth errors live), `axis_object`: the
    sensor's z axis in the object frame. The depth errors on the patch: the bias field's offset, two slopes and
    three curvatures (each `field_std_m` over one `field_length_m`), and the scale error times the depth.
    """
    _, matched, _, normals = plane_distances(model, points_object, reach_m)
    jacobian = np.concatenate([np.cross(points_object, normals), normals], axis=1)[matched]
    sensor = points_sensor[matched]
    along = normals[matched] @ axis_object  # a depth error moves a point along the sensor axis: its normal share
    xy = (sensor[:, :2] - sensor[:, :2].mean(axis=0)) / errors.field_length_m if len(sensor) else sensor[:, :2]
    x, y = xy[:, 0], xy[:, 1]
    field = errors.field_std_m * np.stack([np.ones_like(x), x, y, 0.5 * x * x, x * y, 0.5 * y * y], axis=1)
    terms = np.hstack([field, errors.scale_std * sensor[:, 2:3]])  # (N, 7) depth errors, one column per term
    return ContactGeometry(jacobian.T @ jacobian, jacobian.T @ (along[:, None] * terms))


def joint_systematic_covariance(contacts: list[ContactGeometry], prior_normal: np.ndarray) -> np.ndarray:
    """Covariance (6, 6) of a joint fit's twist caused by the contacts' depth errors (independent per contact):
    the response `H^-1 J^T (n . z) delta_h` of the point-to-plane fit, H the summed normal matrices plus
    `prior_normal` (the fit's prior, in the same units: J^T J per unit surface noise)."""
    hessian = sum((c.normal_matrix for c in contacts), prior_normal)
    response = np.linalg.solve(hessian, np.hstack([c.push for c in contacts]))
    return response @ response.T
