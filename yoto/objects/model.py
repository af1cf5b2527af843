"""The object model: parent surface cloud, PCA canonical frame and surface blocks (paper Sec. 3.1, App. A.1-A.2).

Frames: `object` is YOTO's canonical frame (PCA of the parent cloud, origin at its centroid); `mesh` is
the frame of the mesh file the user gave. `T_mesh_object` maps object-frame points into the mesh frame.
Everything stored per point or per block is in the object frame unless its name says otherwise.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from yoto.errors import InputError
from yoto.geometry import (
    invert_transform,
    make_transform,
    normalize,
    rotation_between,
    tangent_basis,
    transform_points,
)
from yoto.io import load_npz, save_npz_atomic
from yoto.objects.mesh import RepairReport, require_thickness
from yoto.objects.symmetry import Symmetry, SymmetryConfig, detect_symmetry
from yoto.pointcloud import covariance_eigh, estimate_normals, voxel_downsample
from yoto.raycast import MeshRaycaster

log = logging.getLogger("yoto")

FORMAT_VERSION = 1
FORMAT_NAME = "yoto-object-model"


@dataclass(frozen=True)
class ObjectModelConfig:
    """How an object model is built from a mesh."""

    num_points: int | None = None  # parent cloud size; None: points_per_cm2 x surface area, clipped below
    points_per_cm2: float = 500.0  # surface density when num_points is None (paper's avocado: 72k points)
    min_points: int = 20_000  # lower clip of the density-derived size
    max_points: int = 300_000  # upper clip of the density-derived size
    normal_neighbours: int = 30  # k of the PCA normal estimate (paper App. A.1)
    grid_shape: tuple[int, int, int] = (6, 3, 3)  # blocks along the object's x (longest), y, z (shortest) axes
    min_block_points: int = 10  # blocks holding fewer parent points are dropped (paper App. A.2)
    seed: int = 0  # surface sampling seed
    symmetry: SymmetryConfig = SymmetryConfig()  # how the object's rotational symmetries are detected


@dataclass
class ObjectModel:
    """Parent cloud, canonical frame and surface blocks of one object."""

    name: str
    points_object: np.ndarray  # (N, 3) float32, parent cloud, metres
    normals_object: np.ndarray  # (N, 3) float32, outward unit normals
    point_block: np.ndarray  # (N,) int32, index into the block arrays, -1 for points of dropped cells
    T_mesh_object: np.ndarray  # (4, 4) float64, object (canonical) frame -> mesh file frame
    block_cells: np.ndarray  # (B, 3) int32, grid cell (ix, iy, iz) of each valid block
    block_centres_object: np.ndarray  # (B, 3) float64, centroid of each block's points
    block_normals_object: np.ndarray  # (B, 3) float64, mean outward normal (away from the object centre)
    block_rotations: np.ndarray  # (B, 3, 3) float64, R_i with R_i @ (-normal_i) = +z (the concave direction)
    grid_min_object: np.ndarray  # (3,) lower corner of the block grid
    grid_cell_size: np.ndarray  # (3,) cell size of the block grid
    mesh_vertices_mesh: np.ndarray  # (V, 3) float64, the repaired mesh in the mesh file's frame, metres
    mesh_faces: np.ndarray  # (F, 3) int32
    meta: dict[str, Any] = field(default_factory=dict)  # format, build config, source hash, repair report

    # ------------------------------------------------------------------------------------------ queries
    @property
    def num_blocks(self) -> int:
        return len(self.block_centres_object)

    @property
    def T_object_mesh(self) -> np.ndarray:
        return invert_transform(self.T_mesh_object)

    @cached_property
    def kdtree(self) -> cKDTree:
        """KD-tree over the parent cloud (object frame), built on first use."""
        return cKDTree(self.points_object)

    @cached_property
    def mesh_object(self) -> trimesh.Trimesh:
        """The repaired mesh expressed in the object frame."""
        vertices = transform_points(self.T_object_mesh, self.mesh_vertices_mesh)
        return trimesh.Trimesh(vertices=vertices, faces=self.mesh_faces, process=False)

    @cached_property
    def raycaster(self) -> MeshRaycaster:
        """Ray casting on the repaired mesh, object frame (needs Open3D), built on first use."""
        return MeshRaycaster(self.mesh_object.vertices, self.mesh_object.faces)

    @cached_property
    def point_spacing_m(self) -> float:
        """Typical distance between neighbouring parent points: sqrt(surface area / point count)."""
        return float(np.sqrt(self.meta["surface_area_m2"] / len(self.points_object)))

    @cached_property
    def fingerprint(self) -> str:
        """Hash of the parent cloud and blocks: datasets and checkpoints record which model they belong to."""
        digest = hashlib.sha256()
        for array in (self.points_object, self.point_block, self.block_centres_object):
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()[:16]

    @cached_property
    def symmetry(self) -> Symmetry:
        """The object's rotational symmetries (object frame), found at build time; models built before symmetry
        detection existed get them detected on first use (about a second)."""
        if "symmetry" in self.meta:
            return Symmetry.from_json(self.meta["symmetry"])
        log.info("%s: the model file predates symmetry detection; detecting it now", self.name)
        return detect_symmetry(self.points_object, self.normals_object)

    @cached_property
    def mesh_scale_m(self) -> float:
        """Largest extent of the parent cloud (metres): the object's size, for tolerances."""
        return float(np.ptp(self.points_object, axis=0).max())

    def block_points(self, block: int) -> tuple[np.ndarray, np.ndarray]:
        """Points and normals (object frame) of one valid block."""
        members = self.point_block == block
        return self.points_object[members], self.normals_object[members]

    def aggregated_normal(self, p_object: np.ndarray, k: int = 20) -> np.ndarray:
        """Outward normal at a surface location: the mean of the k nearest parent normals (paper Sec. 3.2).

        Accepts (3,) or (M, 3) points; returns unit normals of the same shape.
        """
        p_object = np.asarray(p_object, dtype=np.float64)
        _, neighbours = self.kdtree.query(p_object.reshape(-1, 3), k=k)
        normals = normalize(self.normals_object[neighbours.reshape(-1, k)].astype(np.float64).sum(axis=1))
        return normals.reshape(p_object.shape)

    def anchor_frames(
        self, spacing_m: float, normal_neighbours: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Anchors about every `spacing_m` on the surface (the parent point nearest each voxel's centre) with their
        outward normals (`aggregated_normal` over `normal_neighbours` points) and tangents u, v: (A, 3) each, (u, v,
        -n) right-handed, the frame of a sensor pressing along -n."""
        parent = self.points_object.astype(np.float64)
        (centres,) = voxel_downsample(parent, spacing_m)
        _, nearest = self.kdtree.query(centres)
        points = parent[np.unique(nearest)]
        normals = self.aggregated_normal(points, normal_neighbours)
        u, v = tangent_basis(-normals)
        return points, normals, u, v

    def nearest_surface_point(self, p_object: np.ndarray) -> np.ndarray:
        """The parent point nearest each query point (object frame)."""
        _, index = self.kdtree.query(np.asarray(p_object).reshape(-1, 3))
        return self.points_object[index].astype(np.float64).reshape(np.shape(p_object))

    def block_of_points(self, p_object: np.ndarray) -> np.ndarray:
        """Block index of each query point's nearest parent point (-1 where that cell was dropped)."""
        _, index = self.kdtree.query(np.asarray(p_object).reshape(-1, 3))
        return self.point_block[index]

    # ------------------------------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        arrays = {
            "points_object": self.points_object.astype(np.float32),
            "normals_object": self.normals_object.astype(np.float32),
            "point_block": self.point_block.astype(np.int32),
            "T_mesh_object": self.T_mesh_object,
            "block_cells": self.block_cells.astype(np.int32),
            "block_centres_object": self.block_centres_object,
            "block_normals_object": self.block_normals_object,
            "block_rotations": self.block_rotations,
            "grid_min_object": self.grid_min_object,
            "grid_cell_size": self.grid_cell_size,
            "mesh_vertices_mesh": self.mesh_vertices_mesh,
            "mesh_faces": self.mesh_faces.astype(np.int32),
        }
        meta = {**self.meta, "format": FORMAT_NAME, "format_version": FORMAT_VERSION, "name": self.name}
        return save_npz_atomic(path, arrays, meta)

    @classmethod
    def load(cls, path: str | Path) -> ObjectModel:
        arrays, meta = load_npz(path, "object model")
        if meta.get("format") != FORMAT_NAME:
            raise InputError(f"not a YOTO object model (format is {meta.get('format')!r})", path)
        if meta.get("format_version") != FORMAT_VERSION:
            raise InputError(
                f"object model format version {meta.get('format_version')} is not supported by this YOTO "
                f"(expects {FORMAT_VERSION}); rebuild it with `yoto object build`",
                path,
            )
        missing = [name for name in cls.__dataclass_fields__ if name not in ("name", "meta") and name not in arrays]
        if missing:
            raise InputError(f"object model is missing arrays {missing}", path)
        fields = {name: arrays[name] for name in cls.__dataclass_fields__ if name not in ("name", "meta")}
        return cls(name=meta["name"], meta=meta, **fields)


# ------------------------------------------------------------------------------------------------ building
def parent_cloud_size(area_m2: float, config: ObjectModelConfig) -> int:
    if config.num_points is not None:
        return int(config.num_points)
    by_density = int(round(area_m2 * 1e4 * config.points_per_cm2))
    return int(np.clip(by_density, config.min_points, config.max_points))


def sample_parent_cloud(mesh: trimesh.Trimesh, count: int, config: ObjectModelConfig) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface samples and PCA normals signed to agree with the sampled faces' normals."""
    rng = np.random.default_rng(config.seed)
    face_areas = mesh.area_faces
    faces = rng.choice(len(face_areas), size=count, p=face_areas / face_areas.sum())
    # Uniform barycentric coordinates by reflecting the unit square onto the triangle.
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    triangles = mesh.triangles[faces]
    points = (
        triangles[:, 0]
        + u[:, None] * (triangles[:, 1] - triangles[:, 0])
        + v[:, None] * (triangles[:, 2] - triangles[:, 0])
    )
    normals = estimate_normals(points, config.normal_neighbours, orientation_hint=mesh.face_normals[faces])
    return points, normals


def canonical_frame(points_mesh: np.ndarray) -> np.ndarray:
    """T_mesh_object of the PCA canonical frame (paper App. A.2).

    Origin at the centroid; z = smallest-variance axis signed toward the mesh's +z; x = largest-variance
    axis signed toward the mesh's +x; y = z cross x. Ties in sign (an axis perpendicular to the mesh axis it
    is signed against) are broken by the axis's largest component, so the frame is deterministic.
    """
    centroid, _, eigenvectors = covariance_eigh(points_mesh)

    def signed(axis: np.ndarray, reference: int) -> np.ndarray:
        component = axis[reference] if abs(axis[reference]) > 1e-9 else axis[np.argmax(np.abs(axis))]
        return axis if component >= 0 else -axis

    e_z = signed(eigenvectors[:, 0], 2)
    e_x = signed(eigenvectors[:, 2], 0)
    e_y = np.cross(e_z, e_x)
    return make_transform(np.stack([e_x, e_y, e_z], axis=1), centroid)


def build_blocks(
    points_object: np.ndarray, normals_object: np.ndarray, config: ObjectModelConfig
) -> dict[str, np.ndarray]:
    """Partition the parent cloud on the canonical grid; drop sparse cells; per-block centre, normal, rotation."""
    grid_shape = np.asarray(config.grid_shape)
    low, high = points_object.min(axis=0), points_object.max(axis=0)
    cell_size = (high - low) / grid_shape
    cells = np.clip(np.floor((points_object - low) / cell_size).astype(np.int64), 0, grid_shape - 1)
    flat = np.ravel_multi_index(cells.T, grid_shape)
    counts = np.bincount(flat, minlength=int(grid_shape.prod()))
    valid_flat = np.flatnonzero(counts >= config.min_block_points)
    block_of_flat = np.full(int(grid_shape.prod()), -1, dtype=np.int32)
    block_of_flat[valid_flat] = np.arange(len(valid_flat), dtype=np.int32)
    point_block = block_of_flat[flat]

    centres, block_normals, rotations = [], [], []
    for block in range(len(valid_flat)):
        members = point_block == block
        centre = points_object[members].mean(axis=0)
        mean_normal = normals_object[members].sum(axis=0)
        # The mean normal can cancel out (a cell holding both sides of a thin part); fall back to the radial one.
        if np.linalg.norm(mean_normal) < 1e-6 * members.sum():
            mean_normal = centre
        normal = mean_normal / np.linalg.norm(mean_normal)
        if normal @ centre < 0:  # point away from the object centre (the origin of the object frame)
            normal = -normal
        centres.append(centre)
        block_normals.append(normal)
        rotations.append(rotation_between(-normal, np.array([0.0, 0.0, 1.0])))
    return {
        "point_block": point_block,
        "block_cells": np.stack(np.unravel_index(valid_flat, grid_shape), axis=1).astype(np.int32),
        "block_centres_object": np.array(centres),
        "block_normals_object": np.array(block_normals),
        "block_rotations": np.array(rotations),
        "grid_min_object": low,
        "grid_cell_size": cell_size,
    }


def build_object_model(
    mesh_mesh: trimesh.Trimesh,
    name: str,
    config: ObjectModelConfig = ObjectModelConfig(),
    source: dict[str, Any] | None = None,
    repair_report: RepairReport | None = None,
) -> ObjectModel:
    """Build the object model of a (repaired, metre-scale) mesh given in its own file frame."""
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise InputError(f"object name {name!r} must be letters, digits, '-' or '_'")
    require_thickness(mesh_mesh.vertices, what=f"the mesh of object {name!r}")
    count = parent_cloud_size(mesh_mesh.area, config)
    points_mesh, normals_mesh = sample_parent_cloud(mesh_mesh, count, config)
    T_mesh_object = canonical_frame(points_mesh)
    T_object_mesh = invert_transform(T_mesh_object)
    points_object = transform_points(T_object_mesh, points_mesh)
    normals_object = normals_mesh @ T_object_mesh[:3, :3].T
    blocks = build_blocks(points_object, normals_object, config)
    meta = {
        "build_config": asdict(config),
        "source": source or {},
        "repair": repair_report.to_dict() if repair_report else None,
        "num_points": count,
        "num_blocks": len(blocks["block_centres_object"]),
        "bbox_object_m": np.ptp(points_object, axis=0).tolist(),
        "surface_area_m2": float(mesh_mesh.area),
        "watertight": bool(mesh_mesh.is_watertight),
        "symmetry": detect_symmetry(points_object, normals_object, config.symmetry).to_json(),
    }
    return ObjectModel(
        name=name,
        points_object=points_object.astype(np.float32),
        normals_object=normals_object.astype(np.float32),
        T_mesh_object=T_mesh_object,
        mesh_vertices_mesh=np.asarray(mesh_mesh.vertices, dtype=np.float64),
        mesh_faces=np.asarray(mesh_mesh.faces, dtype=np.int32),
        meta=meta,
        **blocks,
    )
