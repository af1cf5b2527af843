"""Patch canonicalization: the one function that puts virtual and real tactile patches in the same form.

Paper Sec. 3.1 / App. A.3 step 4: centre the patch at its centroid, estimate its concave direction as
the smallest-variance PCA axis, sign it by comparing the centre's height with the rim's, and rotate
(smallest rotation, Rodrigues) so that direction becomes +z. The in-plane orientation is left as it came;
the network is trained to be indifferent to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.errors import DegenerateGeometryError
from yoto.geometry import rotation_between
from yoto.pointcloud import covariance_eigh, estimate_normals, voxel_downsample

Z_AXIS = np.array([0.0, 0.0, 1.0])
CENTRE_FRACTION = 0.3  # points within this fraction of the patch radius form the "centre"; beyond 0.7 the "rim"
FLAT_PATCH_SAG = 0.02  # |centre - rim| height below this fraction of the radius: sign from the normals instead
MIN_CONCAVE_Z = 0.99  # paper's degeneracy test on the rotated concave direction
TACTILE_NORMAL_NEIGHBOURS = 30  # k of the PCA normals of tactile clouds, as for the parent cloud


@dataclass
class CanonicalPatch:
    """A patch in canonical form, and the transform that put it there: p_canonical = R (p_source - c)."""

    points: np.ndarray  # (N, 3) canonical coordinates, centroid at the origin, concave direction +z
    normals: np.ndarray  # (N, 3) outward normals in the canonical frame
    rotation_canonical_source: np.ndarray  # (3, 3) R
    centroid_source: np.ndarray  # (3,) c, the patch centroid in the source frame
    concave_direction_source: np.ndarray  # (3,) the direction that became +z


def concave_direction(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and concave direction of a patch: PCA normal signed so the centre lies below the rim.

    For a bump (convex surface) the concave direction points into the object. Nearly flat patches,
    whose centre-vs-rim sign would be noise, take the sign that points against the mean outward normal.
    """
    centroid, _, eigenvectors = covariance_eigh(points)
    direction = eigenvectors[:, 0]
    centred = points - centroid
    heights = centred @ direction
    radial = np.linalg.norm(centred - heights[:, None] * direction, axis=1)
    radius = radial.max()
    centre, rim = radial <= CENTRE_FRACTION * radius, radial >= (1.0 - CENTRE_FRACTION) * radius
    sag = heights[rim].mean() - heights[centre].mean() if centre.any() and rim.any() else 0.0
    if abs(sag) > FLAT_PATCH_SAG * radius:
        sign = 1.0 if sag > 0 else -1.0  # rim above centre along +direction: the patch opens toward +direction
    else:
        sign = -1.0 if normals.sum(axis=0) @ direction > 0 else 1.0
    return centroid, sign * direction


def canonicalize_patch(points: np.ndarray, normals: np.ndarray) -> CanonicalPatch:
    """Canonical form of a patch given its points and outward normals in any frame (object or sensor).

    Raises DegenerateGeometryError when the concave direction is degenerate (paper App. A.3).
    """
    centroid, direction = concave_direction(points, normals)
    rotation = rotation_between(direction, Z_AXIS)
    if (rotation @ direction)[2] < MIN_CONCAVE_Z:
        raise DegenerateGeometryError("patch has a degenerate concave direction")
    return CanonicalPatch(
        points=(points - centroid) @ rotation.T,
        normals=normals @ rotation.T,
        rotation_canonical_source=rotation,
        centroid_source=centroid,
        concave_direction_source=direction,
    )


def prepare_tactile_cloud(points_sensor: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Bring a tactile cloud to the parent cloud's density and give it outward normals.

    Real and simulated tactile clouds are far denser than the parent cloud (a pixel is 0.063 mm); averaging
    them on a voxel grid of the parent's point spacing makes the normals' neighbourhoods, and the point
    density the network sees, match those of virtual patches. Normals point out of the object, which is
    toward the sensor (-z in the sensor frame).
    """
    (points,) = voxel_downsample(points_sensor, spacing_m)
    if len(points) < 3:
        raise DegenerateGeometryError("tactile cloud collapses to fewer than 3 points at the model's spacing")
    normals = estimate_normals(points, TACTILE_NORMAL_NEIGHBOURS, orientation_hint=-Z_AXIS)
    return points, normals
