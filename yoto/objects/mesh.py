"""Loading object meshes (CAD or scan) in any common format and unit, and repairing what scans break."""

from __future__ import annotations

import io
import logging
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import cast

import numpy as np
import trimesh

from yoto.errors import InputError
from yoto.pointcloud import covariance_eigh

log = logging.getLogger("yoto")

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".glb", ".gltf", ".off")
UNIT_SCALES_TO_M = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "in": 0.0254}

# A GelSight-graspable object is larger than a few millimetres and smaller than a couple of metres.
PLAUSIBLE_EXTENT_M = (0.01, 1.0)
IMPOSSIBLE_EXTENT_M = (0.002, 2.0)
# Thinner than this fraction of its size along its thinnest principal axis, a mesh is flat (to float precision).
FLAT_THICKNESS_FRACTION = 1e-6


@dataclass
class RepairReport:
    """What `repair_mesh` changed, for the user and for the object model's metadata."""

    merged_duplicate_vertices: int = 0
    removed_degenerate_faces: int = 0
    removed_duplicate_faces: int = 0
    removed_small_components: int = 0
    fixed_winding: bool = False
    flipped_inside_out: bool = False
    filled_holes: bool = False
    non_manifold_edges: int = 0
    watertight: bool = False

    def summary(self) -> str:
        parts = []
        if self.merged_duplicate_vertices:
            parts.append(f"merged {self.merged_duplicate_vertices} duplicate vertices")
        if self.removed_degenerate_faces:
            parts.append(f"removed {self.removed_degenerate_faces} degenerate (sliver) faces")
        if self.removed_duplicate_faces:
            parts.append(f"removed {self.removed_duplicate_faces} duplicate faces")
        if self.removed_small_components:
            parts.append(f"removed {self.removed_small_components} tiny disconnected pieces")
        if self.fixed_winding:
            parts.append("made face winding consistent")
        if self.flipped_inside_out:
            parts.append("turned the inside-out mesh outward")
        if self.filled_holes:
            parts.append("filled small holes")
        if self.non_manifold_edges:
            parts.append(f"{self.non_manifold_edges} non-manifold edges remain")
        if not self.watertight:
            parts.append("the mesh is not watertight (open scan?): inside/outside tests use winding order")
        return "; ".join(parts) if parts else "nothing to repair"

    def to_dict(self) -> dict:
        return asdict(self)


def load_mesh(path: str | Path, units: str = "m") -> tuple[trimesh.Trimesh, RepairReport, float]:
    """Read a mesh file, convert it to metres and repair it.

    `units` is "m", "cm", "mm", "in" (inches) or "auto" (millimetres if the mesh is larger than a metre, else
    metres).
    Returns the repaired mesh in metres (in the file's own frame), the repair report and the scale
    that was applied. Raises InputError naming the file for unreadable, empty, flat or implausibly sized meshes.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"unsupported mesh format '{path.suffix}' (use one of {', '.join(MESH_SUFFIXES)})", path)
    try:
        relative = _obj_with_absolute_indices(path) if path.suffix.lower() == ".obj" else None
        if relative is not None:
            loaded = trimesh.load(io.StringIO(relative), file_type="obj", force="mesh", process=False)
        else:
            loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many unrelated types for broken files
        raise InputError(f"could not read the mesh ({type(exc).__name__}: {exc})", path) from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise InputError("the file holds no triangles (empty mesh, or a point cloud rather than a mesh)", path)
    faces = np.asarray(loaded.faces)
    if faces.min() < 0 or faces.max() >= len(loaded.vertices):
        raise InputError(f"mesh faces index vertices that do not exist ({len(loaded.vertices)} vertices)", path)
    # Vertices no face uses (an exporter's leftovers, a scan's stray points) take no part: not in the size check,
    # not in the model.
    used = np.unique(faces)
    vertices = np.asarray(loaded.vertices, dtype=np.float64)[used]
    faces = np.searchsorted(used, faces)
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"mesh has {int((~np.isfinite(vertices)).any(axis=1).sum())} vertices with NaN or inf", path)
    scale = _unit_scale(path, float(np.ptp(vertices, axis=0).max()), units)
    require_thickness(vertices * scale, path)
    mesh = trimesh.Trimesh(vertices=vertices * scale, faces=faces, process=False)
    mesh, report = repair_mesh(mesh, path)
    return mesh, report, scale


def _obj_with_absolute_indices(path: Path) -> str | None:
    """An OBJ file's text with its relative face indices (`f -4 -3 -2 -1`: counted back from the vertices defined so
    far, as the OBJ format says) made absolute, or None when it has none. trimesh counts them from the file's last
    vertex instead, which silently scrambles a file that defines vertices between faces."""
    text = path.read_text(encoding="utf-8", errors="replace")
    if not re.search(r"^[ \t]*[fl][ \t].*[ \t/]-\d", text, re.MULTILINE):
        return None
    defined = {"v": 0, "vt": 0, "vn": 0}
    lines = []
    for line in text.splitlines():
        words = line.split()
        if words and words[0] in defined:
            defined[words[0]] += 1
        elif words and words[0] in ("f", "l"):
            references = []
            for reference in words[1:]:
                parts = reference.split("/")
                for k, (part, kind) in enumerate(zip(parts, ("v", "vt", "vn"))):
                    if part.startswith("-"):
                        parts[k] = str(defined[kind] + 1 + int(part))
                references.append("/".join(parts))
            line = " ".join([words[0], *references])
        lines.append(line)
    return "\n".join(lines) + "\n"


def mesh_file_vertices(path: str | Path, scale_to_m: float = 1.0) -> np.ndarray:
    """The vertices of a mesh file in the file's own order (what a mesh viewer's vertex index counts), metres.

    PLY: its vertex element; OBJ: its `v` lines; OFF, GLB, glTF: as trimesh reads them unprocessed. The object
    model's mesh is repaired (duplicate vertices merged, unused ones dropped), so its vertex order is not the file's.
    An STL file lists each triangle's corners rather than shared vertices: it has no vertex ids (InputError).
    """
    from yoto.io import read_ply_points

    path = Path(path)
    if not path.is_file():
        raise InputError("mesh file not found", path)
    suffix = path.suffix.lower()
    if suffix == ".stl":
        raise InputError("an STL file has no vertex ids (it lists triangle corners): give points, not vertices", path)
    if suffix == ".ply":
        vertices, _ = read_ply_points(path)
    elif suffix == ".obj":
        rows = []
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
            words = line.split()
            if words and words[0] == "v":
                try:
                    rows.append([float(value) for value in words[1:4]])
                except ValueError as exc:
                    raise InputError(f"line {number}: vertex is not numeric ({exc})", path) from exc
                if len(rows[-1]) != 3:
                    raise InputError(f"line {number}: a vertex needs x y z", path)
        vertices = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
    else:
        try:
            loaded = cast(trimesh.Trimesh, trimesh.load(path, force="mesh", process=False))  # force="mesh": a mesh
            vertices = np.asarray(loaded.vertices, dtype=np.float64)
        except Exception as exc:  # trimesh raises many unrelated types for broken files
            raise InputError(f"could not read the mesh ({type(exc).__name__}: {exc})", path) from exc
    return vertices * scale_to_m


def _unit_scale(path: Path, extent: float, units: str) -> float:
    if units == "auto":
        units = "mm" if extent > 1.0 else "m"
    if units not in UNIT_SCALES_TO_M:
        raise InputError(f"unknown unit '{units}' (use {', '.join(UNIT_SCALES_TO_M)} or auto)")
    scale = UNIT_SCALES_TO_M[units]
    extent_m = extent * scale
    if extent_m <= 0.0:
        raise InputError("mesh has zero extent (all vertices coincide)", path)
    hint = _unit_hint(extent, units)
    if not IMPOSSIBLE_EXTENT_M[0] <= extent_m <= IMPOSSIBLE_EXTENT_M[1]:
        raise InputError(
            f"read in {units}, the mesh is {extent_m * 1000:.4g} mm across, which no GelSight-graspable object "
            f"is{hint}",
            path,
        )
    if not PLAUSIBLE_EXTENT_M[0] <= extent_m <= PLAUSIBLE_EXTENT_M[1]:
        log.warning("%s: read in %s, the mesh is %.4g mm across%s", path, units, extent_m * 1000, hint)
    return scale


def _unit_hint(extent: float, units: str) -> str:
    """The other units in which the mesh has a plausible size, most plausible first, as a message tail.

    Most plausible: the size nearest (by ratio) the middle of PLAUSIBLE_EXTENT_M, 10 cm, a typical object.
    """
    typical_m = float(np.sqrt(PLAUSIBLE_EXTENT_M[0] * PLAUSIBLE_EXTENT_M[1]))
    sizes = {other: extent * scale for other, scale in UNIT_SCALES_TO_M.items() if other != units}
    plausible = sorted(
        (unit for unit, size in sizes.items() if PLAUSIBLE_EXTENT_M[0] <= size <= PLAUSIBLE_EXTENT_M[1]),
        key=lambda unit: abs(np.log(sizes[unit] / typical_m)),
    )
    if not plausible:
        return ""
    best, *others = plausible
    hint = f"; with --units {best} it is {sizes[best] * 1000:.4g} mm across"
    if others:
        hint += " (" + ", ".join(f"--units {unit}: {sizes[unit] * 1000:.4g} mm" for unit in others) + ")"
    return hint


def require_thickness(vertices_m: np.ndarray, path: str | Path | None = None, what: str = "the mesh") -> None:
    """Raise InputError naming `path` (or `what`) when the vertices (metres) lie in one plane.

    A flat mesh has no extent along its thinnest principal axis, which the object model divides into blocks,
    and its two sides coincide, so no contact has an outward normal.
    """
    vertices_m = np.asarray(vertices_m, dtype=np.float64)
    _, _, axes = covariance_eigh(vertices_m)
    extents = np.ptp(vertices_m @ axes, axis=0)  # along the principal axes, thinnest first
    if extents[0] <= FLAT_THICKNESS_FRACTION * extents[2]:
        raise InputError(
            f"{what} is flat: all its vertices lie in one plane ({extents[2] * 1000:.4g} x {extents[1] * 1000:.4g} "
            "mm, no thickness). An object model needs a solid (its thinnest axis is divided into blocks, and a "
            "contact needs an outside): export the object's closed surface, not a single face",
            path,
        )


def repair_mesh(mesh: trimesh.Trimesh, path: str | Path | None = None, min_component_area_fraction: float = 0.01):
    """Fix what scans typically break; returns the repaired mesh and a RepairReport."""
    report = RepairReport()
    vertex_count = len(mesh.vertices)
    mesh.merge_vertices()
    report.merged_duplicate_vertices = vertex_count - len(mesh.vertices)

    face_count = len(mesh.faces)
    mesh.update_faces(mesh.nondegenerate_faces(height=1e-9))
    report.removed_degenerate_faces = face_count - len(mesh.faces)
    face_count = len(mesh.faces)
    mesh.update_faces(mesh.unique_faces())
    report.removed_duplicate_faces = face_count - len(mesh.faces)
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise InputError("every face of the mesh is degenerate (zero area)", path)

    components = mesh.split(only_watertight=False)
    if len(components) > 1:
        total_area = sum(component.area for component in components)
        kept = [c for c in components if c.area >= min_component_area_fraction * total_area]
        report.removed_small_components = len(components) - len(kept)
        if report.removed_small_components:
            mesh = cast(trimesh.Trimesh, trimesh.util.concatenate(kept))  # meshes concatenate to a mesh

    faces_before = mesh.faces.copy()
    trimesh.repair.fix_winding(mesh)
    report.fixed_winding = bool(len(faces_before) == len(mesh.faces) and np.any(faces_before != mesh.faces))
    if not mesh.is_watertight:
        report.filled_holes = bool(trimesh.repair.fill_holes(mesh)) and mesh.is_watertight
    # An outward mesh has positive signed volume; for open meshes the volume is still a useful vote.
    if mesh.volume < 0:
        mesh.invert()
        report.flipped_inside_out = True

    edges = np.sort(mesh.edges, axis=1).astype(np.int64)
    _, edge_use = np.unique(edges[:, 0] * len(mesh.vertices) + edges[:, 1], return_counts=True)
    report.non_manifold_edges = int((edge_use > 2).sum())
    report.watertight = bool(mesh.is_watertight)
    return mesh, report
