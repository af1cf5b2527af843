"""Ray casting on a triangle mesh (Open3D's RaycastingScene): the one place every stage casts rays.

Used by the matched filter (the height map a sensor pressed at an anchor would see), the contact simulator
(what the gel meets, whether the sensor body collides) and anything that needs the closest surface point
or which side of the surface a point lies on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.errors import InputError, require_open3d

_RAYS_PER_BATCH = 1_000_000  # rays cast at once by `height_maps` (memory, not speed, sets it)


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

    def height_maps(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        u: np.ndarray,
        v: np.ndarray,
        cells: np.ndarray,
        start_m: float,
        reach_m: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(A, C) float32 heights of the surface along -n at in-plane offsets `cells` (C, 2) of each of A frames
        (point, outward normal, tangents u and v, each (A, 3)), and their validity (bool).

        A ray starts `start_m` in front of the tangent plane and travels along -n; its first hit is the surface a
        sensor pressed there would meet. A back-face hit means the ray started inside the object (the surface rises
        above the start): height -start_m. No hit, or one deeper than `reach_m`: no surface.
        """
        heights = np.zeros((len(points), len(cells)), dtype=np.float32)
        valid = np.zeros((len(points), len(cells)), dtype=bool)
        chunk = max(1, _RAYS_PER_BATCH // len(cells))
        for first in range(0, len(points), chunk):
            last = min(first + chunk, len(points))
            origins = (
                points[first:last, None]
                + cells[None, :, 0, None] * u[first:last, None]
                + cells[None, :, 1, None] * v[first:last, None]
                + start_m * normals[first:last, None]
            ).reshape(-1, 3)
            directions = np.broadcast_to(-normals[first:last, None], (last - first, len(cells), 3)).reshape(-1, 3)
            hits = self.cast(origins, directions)
            h = np.where(hits.back_face, -start_m, hits.t_hit - start_m)
            ok = hits.hit & (h <= reach_m)
            heights[first:last] = np.where(ok, h, 0.0).reshape(last - first, len(cells))
            valid[first:last] = ok.reshape(last - first, len(cells))
        return heights, valid

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
