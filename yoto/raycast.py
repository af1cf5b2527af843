"""Ray casting on a triangle mesh (Open3D's RaycastingScene): the one place every stage casts rays.

Used by the matched filter (the height map a sensor pressed at an anchor would see), the contact simulator
(what the gel meets, whether the sensor body collides) and anything that needs the closest surface point
or which side of the surface a point lies on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.errors import InputError, require_open3d


@dataclass
class RayHits:
    """What each ray met first."""

    t_hit: np.ndarray  # (N,) float64 distance along the (unit) direction to the first hit; +inf: no hit
    back_face: np.ndarray  # (N,) bool: the first hit is a back face (the ray and the face normal agree): the ray
    # started inside a closed surface, or the mesh is open there

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.t_hit)


class MeshRaycaster:
    """A triangle mesh ready for ray queries. Build once per mesh (milliseconds to a second); queries are batched."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, purpose: str = "ray casting on the object mesh"):
        o3d = require_open3d(purpose)
        vertices = np.asarray(vertices, dtype=np.float32)
        faces = np.asarray(faces)
        if len(faces) == 0:
            raise InputError("cannot cast rays on a mesh without faces")
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))

    def cast_rays(self, rays: np.ndarray) -> RayHits:
        """Rays as an (N, 6) array of origin and unit direction (float32 is passed through without a copy)."""
        rays = np.ascontiguousarray(rays, dtype=np.float32)
        hits = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        t_hit = hits["t_hit"].numpy().astype(np.float64)
        normals = hits["primitive_normals"].numpy()
        # Elementwise products, not a BLAS dot: numpy's threaded matmul can stall on a busy machine.
        facing = normals[:, 0] * rays[:, 3] + normals[:, 1] * rays[:, 4] + normals[:, 2] * rays[:, 5]
        return RayHits(t_hit=t_hit, back_face=(facing > 0.0) & np.isfinite(t_hit))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Rays from (N, 3) origins along (N, 3) (or one (3,)) unit directions."""
        origins = np.asarray(origins, dtype=np.float32).reshape(-1, 3)
        rays = np.empty((len(origins), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = np.asarray(directions, dtype=np.float32)
        return self.cast_rays(rays)

    def closest_points(self, points: np.ndarray) -> np.ndarray:
        """The nearest point on the mesh surface to each query point, same shape as `points` (float64)."""
        query = self._o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        closest = self.scene.compute_closest_points(query)["points"].numpy().astype(np.float64)
        return closest.reshape(np.shape(points))

    def closest_points_and_normals(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest surface point to each (N, 3) query point and the normal of the triangle it lies on (N, 3)."""
        query = self._o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        closest = self.scene.compute_closest_points(query)
        return closest["points"].numpy().astype(np.float64), closest["primitive_normals"].numpy().astype(np.float64)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Distance to the surface of each (..., 3) point, negative inside the object (a closed mesh is assumed).

        Inside or outside is decided by the parity of crossings along a ray (Open3D); on an open mesh points near
        the hole can be misclassified.
        """
        query = self._o3d.core.Tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3))
        distance = self.scene.compute_signed_distance(query).numpy().astype(np.float64)
        return distance.reshape(np.shape(points)[:-1])
