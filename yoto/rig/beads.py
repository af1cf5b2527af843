"""The object's calibration (paper App. B.2 (ii)): the mesh frame in the object's rigid body, `T_objectbody_mesh`.

Beads (retro-reflective balls) are stuck on the object and form its rigid body. The user picks where each bead
sits on the mesh (points or vertex ids in a JSON file, mesh file's frame); each bead's centre is that surface point
offset by the bead radius along the outward normal there. Mocap gives the same centres; a closed-form SVD fit
(orthogonal Procrustes) aligns the two sets; the fit's residual per bead is reported (the paper: 1.52-2.23 mm).
Bead centres are averaged in the object body over a still capture, so the result is `T_objectbody_mesh`
directly and the object may be moved freely afterwards.

Picks file (`beads.json`):
    {"bead_radius_mm": 5.0, "units": "m",
     "beads": [{"name": "Object:Marker1", "vertex": 1234}, {"name": "Object:Marker2", "point": [0.01, 0.02, 0.03]}]}
`name` is the bead's marker (a PointStamped topic or name in a bag, a marker column of a Motive take);
`vertex` indexes the mesh file's vertices in the file's order, as a mesh viewer numbers them (PLY vertex element,
OBJ `v` lines, from 0; the built-in objects: their generated mesh); `point` is in `units`.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from yoto.errors import DegenerateGeometryError, InputError
from yoto.geometry import make_transform, normalize, procrustes_rotation, transform_points, validate_transform
from yoto.io import read_json, read_json_format, sha256_of_file, write_json_atomic
from yoto.raycast import MeshRaycaster
from yoto.rig.streams import Recording
from yoto.rig.timeline import static_segments

if TYPE_CHECKING:
    from yoto.objects.model import ObjectModel

FORMAT_NAME = "yoto-object-calibration"
FORMAT_VERSION = 1
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
MIN_SPREAD_M = 0.002  # beads closer than this to one line (collinear) or one plane (coplanar, 4+ beads) are refused
MISLABEL_RESIDUAL_M = 0.005  # a fit worse than this is checked against every other bead-to-marker assignment


@dataclass
class BeadPicks:
    """The user's picks: bead names, surface points (mesh frame, metres), the bead radius."""

    names: list[str]
    foot_mesh: np.ndarray  # (B, 3) picked surface points
    bead_radius_m: float
    source: Path | None = None


@dataclass
class ObjectCalibration:
    """The mesh frame in the object's rigid body and how well the beads agree."""

    object_name: str
    object_body: str  # topic or rigid-body name of the object
    T_objectbody_mesh: np.ndarray  # (4, 4)
    beads: list[dict[str, Any]] = field(default_factory=list)  # name, p_mesh, p_body, residual_mm
    residual_mm: dict[str, float] = field(default_factory=dict)  # mean, rms, max
    sources: dict[str, Any] = field(default_factory=dict)

    def save(self, path: str | Path) -> Path:
        return write_json_atomic(
            path,
            {
                "format": FORMAT_NAME,
                "format_version": FORMAT_VERSION,
                "object": self.object_name,
                "object_body": self.object_body,
                "T_objectbody_mesh": self.T_objectbody_mesh,
                "beads": self.beads,
                "residual_mm": self.residual_mm,
                "sources": self.sources,
            },
        )

    def summary(self) -> str:
        residuals = ", ".join(f"{b['name']} {b['residual_mm']:.2f}" for b in self.beads)
        r = self.residual_mm
        return (
            f"object '{self.object_name}' (body {self.object_body}): {len(self.beads)} beads, SVD residuals "
            f"{residuals} mm; mean {r['mean']:.2f}, max {r['max']:.2f} mm"
        )


def load_object_calibration(path: str | Path) -> ObjectCalibration:
    path = Path(path)
    payload = read_json_format(
        path,
        FORMAT_NAME,
        FORMAT_VERSION,
        "object calibration",
        ("object", "object_body", "T_objectbody_mesh"),
        "yoto rig calibrate-object",
    )
    return ObjectCalibration(
        str(payload["object"]),
        str(payload["object_body"]),
        validate_transform(payload["T_objectbody_mesh"], "T_objectbody_mesh", path),
        payload.get("beads", []),
        payload.get("residual_mm", {}),
        payload.get("sources", {}),
    )


def pick_vertices_mesh(model: ObjectModel) -> np.ndarray:
    """What a picks file's `vertex` ids index (metres, mesh frame): the vertices of the mesh file the model was built
    from, in the file's order, or a built-in object's generated mesh. The model's own mesh is repaired (duplicate
    vertices merged, unused ones dropped), so its order is not the file's; a file that moved or changed since the
    build cannot resolve ids (InputError)."""
    from yoto.objects.mesh import mesh_file_vertices

    source = model.meta.get("source", {})
    if "mesh" not in source:
        return model.mesh_vertices_mesh
    mesh_path = Path(source["mesh"])
    if not mesh_path.is_file() or sha256_of_file(mesh_path) != source.get("sha256"):
        raise InputError(
            f"bead picks by 'vertex' index the vertices of the mesh file the model '{model.name}' was built from, "
            "which is no longer there unchanged: rebuild the model from the file, or give the picks as 'point's",
            mesh_path,
        )
    return mesh_file_vertices(mesh_path, float(source.get("scale_to_m", 1.0)))


def read_bead_picks(path: str | Path, vertices_mesh: np.ndarray | Callable[[], np.ndarray]) -> BeadPicks:
    """Read a picks file (module docstring); vertex ids index `vertices_mesh` (metres, mesh frame; a function giving
    them is called only when a bead is picked by vertex, e.g. `lambda: pick_vertices_mesh(model)`)."""
    path = Path(path)
    payload = read_json(path)
    if not isinstance(payload, dict) or not isinstance(payload.get("beads"), list):
        raise InputError(
            "a bead picks file holds {'bead_radius_mm': R, 'beads': [{'name', 'vertex' or 'point'}]}", path
        )
    units = payload.get("units", "m")
    if units not in UNITS:
        raise InputError(f"units must be one of {', '.join(UNITS)}, got '{units}'", path)
    radius_mm = payload.get("bead_radius_mm")
    if not isinstance(radius_mm, (int, float)) or not 0 < radius_mm < 50:
        raise InputError("bead_radius_mm must be the beads' radius in millimetres (e.g. 5.0)", path)
    names, feet = [], []
    for k, bead in enumerate(payload["beads"]):
        if not isinstance(bead, dict) or "name" not in bead:
            raise InputError(f"bead {k} needs a 'name' (its marker) and a 'vertex' or 'point'", path)
        if "vertex" in bead:
            if callable(vertices_mesh):
                vertices_mesh = vertices_mesh()
            vertex = bead["vertex"]
            if not isinstance(vertex, int) or not 0 <= vertex < len(vertices_mesh):
                raise InputError(
                    f"bead '{bead['name']}': vertex {vertex} is not in the mesh (0..{len(vertices_mesh) - 1})", path
                )
            feet.append(vertices_mesh[vertex])
        elif "point" in bead:
            point = np.asarray(bead["point"], dtype=np.float64)
            if point.shape != (3,) or not np.isfinite(point).all():
                raise InputError(f"bead '{bead['name']}': point must be 3 numbers", path)
            feet.append(point * UNITS[units])
        else:
            raise InputError(f"bead '{bead['name']}' needs a 'vertex' or a 'point'", path)
        names.append(str(bead["name"]))
    if len(set(names)) != len(names):
        raise InputError("two beads share a name", path)
    return BeadPicks(names, np.asarray(feet).reshape(-1, 3), float(radius_mm) * 1e-3, path)


def bead_centres_mesh(picks: BeadPicks, vertices_mesh: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Bead centres on the mesh: each pick snapped to the surface and offset by the bead radius along the outward
    normal (the area-weighted normal of the faces within one bead radius)."""
    raycaster = MeshRaycaster(vertices_mesh, faces, "bead centres on the mesh")
    foot = raycaster.closest_points(picks.foot_mesh)
    triangles = vertices_mesh[faces]
    face_normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])  # 2 x area
    centroids = triangles.mean(axis=1)
    centres = []
    for point in foot:
        distance = np.linalg.norm(centroids - point, axis=1)
        near = distance <= picks.bead_radius_m
        if near.sum() < 3:  # a coarse mesh: the few faces nearest the pick
            near = np.argsort(distance)[:3]
        centres.append(point + picks.bead_radius_m * normalize(face_normals[near].sum(axis=0)))
    return np.asarray(centres)


def check_bead_geometry(p_mesh: np.ndarray, source: Path | None) -> None:
    """Refuse fewer than 3 beads, collinear beads, and 4 or more coplanar ones (the rotation is then unreliable)."""
    count = len(p_mesh)
    if count < 3:
        raise InputError(
            f"{count} beads: the mesh frame needs at least 3 (the paper uses 4 to 5, not coplanar)", source
        )
    centred = p_mesh - p_mesh.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False) / np.sqrt(count)  # RMS spread along the principal axes
    if singular[1] < MIN_SPREAD_M:
        raise InputError(
            f"the {count} beads are collinear (they lie within {singular[1] * 1e3:.1f} mm RMS of one line): the "
            "rotation about that line is undetermined; place them around the object",
            source,
        )
    if count >= 4 and singular[2] < MIN_SPREAD_M:
        raise InputError(
            f"the {count} beads are coplanar (within {singular[2] * 1e3:.1f} mm RMS of one plane): place at least one "
            f"off the plane of the others (more than {MIN_SPREAD_M * 1e3:g} mm)",
            source,
        )


def rigid_fit(p_target: np.ndarray, p_source: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T minimising sum |p_target - T p_source|^2 (closed-form SVD, proper rotation) and the residual per point."""
    centre_t, centre_s = p_target.mean(axis=0), p_source.mean(axis=0)
    rotation, _ = procrustes_rotation((p_target - centre_t).T, (p_source - centre_s).T)
    T = make_transform(rotation, centre_t - rotation @ centre_s)
    return T, np.linalg.norm(p_target - transform_points(T, p_source), axis=1)


def beads_in_body(recording: Recording, object_body: str, names: list[str], max_gap_s: float = 0.05) -> np.ndarray:
    """Each bead marker's mean position in the object body over the capture's longest still stretch, (B, 3)."""
    body = recording.pose(object_body)
    segments = static_segments(body, min_duration_s=0.2) or [body.span_s]
    start, end = max(segments, key=lambda s: s[1] - s[0])
    means = []
    for name in names:
        stream = recording.point(name)
        inside = (stream.timestamps_s >= start) & (stream.timestamps_s <= end)
        T_world_body, ok = body.at(stream.timestamps_s[inside], max_gap_s)
        if not ok.any():
            raise InputError(
                f"bead marker '{name}' was not seen while the object stood still ({start:.2f} to {end:.2f} s)",
                recording.path,
            )
        p_world = stream.p_world[inside][ok]
        means.append(np.einsum("nji,nj->ni", T_world_body[ok, :3, :3], p_world - T_world_body[ok, :3, 3]).mean(axis=0))
    return np.asarray(means)


def calibrate_object(
    recording: Recording,
    picks: BeadPicks,
    vertices_mesh: np.ndarray,
    faces: np.ndarray,
    *,
    object_name: str,
    object_body: str,
) -> ObjectCalibration:
    """Fit `T_objectbody_mesh` from the picked beads and a still capture of the object's beads."""
    p_mesh = bead_centres_mesh(picks, vertices_mesh, faces)
    check_bead_geometry(p_mesh, picks.source)
    p_body = beads_in_body(recording, object_body, picks.names)
    T, residuals = rigid_fit(p_body, p_mesh)
    if residuals.max() > MISLABEL_RESIDUAL_M and len(p_mesh) <= 7:
        best = min(
            itertools.permutations(range(len(p_mesh))),
            key=lambda order: rigid_fit(p_body[list(order)], p_mesh)[1].max(),
        )
        best_residual = rigid_fit(p_body[list(best)], p_mesh)[1].max()
        if best_residual < 0.5 * residuals.max():
            pairs = ", ".join(
                f"pick '{picks.names[i]}' -> marker '{picks.names[j]}'" for i, j in enumerate(best) if i != j
            )
            raise InputError(
                f"the beads look mislabelled: the fit leaves up to {residuals.max() * 1e3:.1f} mm, but {pairs} leaves "
                f"{best_residual * 1e3:.1f} mm; fix the names in the picks file",
                picks.source,
            )
    if not np.isfinite(T).all():
        raise DegenerateGeometryError("the bead fit did not converge")
    beads = [
        {"name": name, "p_mesh": pm.tolist(), "p_body": pb.tolist(), "residual_mm": float(r * 1e3)}
        for name, pm, pb, r in zip(picks.names, p_mesh, p_body, residuals)
    ]
    residual_mm = {
        "mean": float(residuals.mean() * 1e3),
        "rms": float(np.sqrt(np.mean(residuals**2)) * 1e3),
        "max": float(residuals.max() * 1e3),
    }
    sources = {"recording": str(recording.path), "picks": str(picks.source), "bead_radius_m": picks.bead_radius_m}
    return ObjectCalibration(object_name, object_body, T, beads, residual_mm, sources)
