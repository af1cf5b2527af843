"""Simulated phone scans: degrade a clean (CAD-like) mesh the way consumer photogrammetry does.

The paper trains on object models from consumer-grade scans (Sec. 4) and SPEC's benchmark compares models
built from a CAD mesh with models built from a phone scan. Without a phone, `degrade_mesh` makes the scan:

1. Sampling. Points are drawn uniformly over the surface, about `resolution_m / 2` apart, with the mesh's
   outward normals (what a photogrammetry pipeline has before meshing: a dense, oriented point cloud).
2. Surface noise. Each point moves along its normal by a smooth random field (random Fourier features of
   a Gaussian-covariance field, correlation length `noise_length_m`: the low-frequency waviness of a scan)
   plus a white component; `noise_std_m` is the standard deviation of the sum.
3. Holes. `holes` random discs of radius `hole_radius_m` lose their points (occluded or textureless
   regions); the surface reconstruction bridges them smoothly, flattening what was there.
4. Meshing. Screened Poisson reconstruction (Open3D) at an octree depth whose cells are about
   `resolution_m`: detail finer than that is smoothed away and the triangulation is new.
5. Scale. Everything is scaled by exactly `1 + scale_error` about the source mesh's centroid (the
   metric-scale error of a scan; negative values shrink).

The result records what was done in `mesh.metadata["yoto_scan"]`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from yoto.errors import InputError, require_open3d


@dataclass(frozen=True)
class ScanConfig:
    """How much a simulated phone scan departs from the true surface."""

    resolution_m: float = 0.0015  # finest detail the scan keeps (Poisson cell size)
    noise_std_m: float = 0.0003  # surface noise along the normal, standard deviation
    noise_length_m: float = 0.004  # correlation length of the smooth part of the noise
    white_noise_fraction: float = 0.3  # share of the noise variance that is uncorrelated per point
    holes: int = 4  # holes cut in the sampled surface, then bridged by the reconstruction
    hole_radius_m: float = 0.004  # radius of each hole
    scale_error: float = 0.007  # relative metric scale error (applied exactly: 0.007 -> 0.7 % larger)
    smoothing_iterations: int = 2  # Taubin smoothing passes after meshing (0: none)


def degrade_mesh(mesh: trimesh.Trimesh, config: ScanConfig = ScanConfig(), rng: np.random.Generator | None = None):
    """A simulated phone scan of `mesh` (metres). Deterministic for a given `rng` state.

    Returns a new trimesh.Trimesh whose `metadata["yoto_scan"]` holds the config, the scale centre and the
    number of points sampled and removed.
    """
    o3d = require_open3d("simulating a phone scan")
    if rng is None:
        rng = np.random.default_rng(0)
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise InputError("cannot scan a mesh without surface")
    if config.resolution_m <= 0:
        raise InputError(f"scan resolution must be positive, got {config.resolution_m}")

    # 1. Dense oriented samples.
    spacing = config.resolution_m / 2
    count = int(np.clip(mesh.area / spacing**2, 20_000, 2_000_000))
    points, faces = _sample_surface(mesh, count, rng)
    normals = np.asarray(mesh.face_normals)[faces]

    # 2. Noise along the normals: smooth waviness plus a white part.
    smooth_std = config.noise_std_m * np.sqrt(1.0 - config.white_noise_fraction)
    white_std = config.noise_std_m * np.sqrt(config.white_noise_fraction)
    offsets = smooth_std * _smooth_field(points, config.noise_length_m, rng) + white_std * rng.normal(size=count)
    offsets -= offsets.mean()  # waves as long as the object would otherwise add a net inflation: a scale error
    points = points + offsets[:, None] * normals

    # 3. Holes.
    removed = 0
    if config.holes > 0 and config.hole_radius_m > 0:
        centres = points[rng.integers(0, count, size=config.holes)]
        keep = np.ones(count, dtype=bool)
        for centre in centres:
            keep &= np.linalg.norm(points - centre, axis=1) > config.hole_radius_m
        removed = int((~keep).sum())
        points, normals = points[keep], normals[keep]

    # 4. Screened Poisson at a depth whose octree cell is about the resolution.
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    extent = float(np.ptp(points, axis=0).max()) * 1.1
    depth = int(np.clip(np.ceil(np.log2(extent / config.resolution_m)), 5, 11))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        surface, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=depth, scale=1.1, linear_fit=True, n_threads=1
        )
    vertices = np.asarray(surface.vertices)
    triangles = np.asarray(surface.triangles)
    # Poisson closes the surface far from the samples too; drop what lies well away from any sample.
    distance = np.asarray(cloud.compute_point_cloud_distance(o3d.geometry.PointCloud(surface.vertices)))
    del densities
    far = distance > max(3 * config.resolution_m, 2 * config.hole_radius_m)
    if far.any():
        keep_faces = ~far[triangles].any(axis=1)
        triangles = triangles[keep_faces]
    scan = trimesh.Trimesh(vertices=vertices, faces=triangles, process=True)
    scan.remove_unreferenced_vertices()
    if config.smoothing_iterations > 0:
        trimesh.smoothing.filter_taubin(scan, iterations=config.smoothing_iterations)
    # Poisson meshing inflates or deflates a surface by a fraction of a cell; remove that mean offset so the
    # scan's only size error is the configured one.
    _, nearest = cKDTree(points).query(scan.vertices)
    offset = float(np.mean(np.einsum("ij,ij->i", scan.vertices - points[nearest], normals[nearest])))
    scan.vertices = scan.vertices - offset * scan.vertex_normals

    # 5. Metric scale error about the source's centroid.
    centre = np.asarray(mesh.center_mass if mesh.is_watertight else mesh.centroid, dtype=np.float64)
    scan.vertices = centre + (1.0 + config.scale_error) * (scan.vertices - centre)
    scan.metadata["yoto_scan"] = {
        "config": asdict(config),
        "scale_centre_m": centre.tolist(),
        "sampled_points": count,
        "hole_points_removed": removed,
        "poisson_depth": depth,
        "poisson_offset_removed_m": offset,
    }
    return scan


def _sample_surface(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface points and the face each lies on."""
    cdf = np.cumsum(mesh.area_faces)
    faces = np.minimum(np.searchsorted(cdf, rng.random(count) * cdf[-1], side="right"), len(cdf) - 1)
    u, v = rng.random(count), rng.random(count)
    outside = u + v > 1.0
    u[outside], v[outside] = 1.0 - u[outside], 1.0 - v[outside]
    corners = mesh.triangles[faces]
    points = corners[:, 0] + u[:, None] * (corners[:, 1] - corners[:, 0]) + v[:, None] * (corners[:, 2] - corners[:, 0])
    return points, faces


def _smooth_field(points: np.ndarray, length_m: float, rng: np.random.Generator, features: int = 64) -> np.ndarray:
    """Unit-variance smooth random field at 3-D points (random Fourier features, Gaussian covariance)."""
    waves = rng.normal(scale=1.0 / length_m, size=(features, 3))
    phases = rng.uniform(0.0, 2.0 * np.pi, size=features)
    field = np.zeros(len(points))
    for wave, phase in zip(waves, phases, strict=True):
        field += np.cos(points[:, 0] * wave[0] + points[:, 1] * wave[1] + points[:, 2] * wave[2] + phase)
    return field * np.sqrt(2.0 / features)
