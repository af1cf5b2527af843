"""The object-model stage: mesh file (or built-in object) -> object model file in the workspace."""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np

from yoto.errors import InputError
from yoto.io import sha256_of_file
from yoto.objects.builtin import BUILTIN_OBJECTS, builtin_mesh
from yoto.objects.mesh import load_mesh
from yoto.objects.model import ObjectModel, ObjectModelConfig, build_object_model
from yoto.workspace import object_model_path

log = logging.getLogger("yoto")


def _as_json(value: dict) -> dict:
    """The dict as it reads back from JSON (tuples become lists), for comparisons with stored metadata."""
    return json.loads(json.dumps(value))


def build_object(
    mesh_path: str | Path | None,
    name: str,
    config: ObjectModelConfig = ObjectModelConfig(),
    units: str = "m",
    workspace: str | Path | None = None,
    out: str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Build and save the object model of a mesh file, or of the built-in object `name` if no mesh is given.

    Skips the work if the output exists and was built from the same source with the same config,
    unless `overwrite`. Returns the model's path.
    """
    out_path = Path(out) if out else object_model_path(name, workspace)
    source: dict[str, str | float]  # what the model is built from, kept in its metadata
    if mesh_path is None:
        if name not in BUILTIN_OBJECTS:
            raise InputError(f"no mesh given and {name!r} is not a built-in object ({', '.join(BUILTIN_OBJECTS)})")
        source = {"builtin": name, "description": BUILTIN_OBJECTS[name][3]}
    else:
        if not Path(mesh_path).is_file():
            raise InputError("mesh file not found", mesh_path)
        source = {"mesh": str(Path(mesh_path).resolve()), "sha256": sha256_of_file(mesh_path), "units": units}

    if out_path.exists() and not overwrite:
        try:
            existing = ObjectModel.load(out_path)
            stored_source = existing.meta.get("source", {})
            if existing.meta.get("build_config") == _as_json(asdict(config)) and all(
                stored_source.get(key) == value for key, value in source.items()
            ):
                log.info("%s: up to date, kept (pass --overwrite to rebuild)", out_path)
                return out_path
        except InputError:
            pass
        log.info("%s: exists but was built from another source or config; rebuilding", out_path)

    if mesh_path is None:
        mesh, report = builtin_mesh(name), None
    else:
        mesh, report, scale = load_mesh(mesh_path, units)
        source["scale_to_m"] = scale
        log.info("%s: %s", mesh_path, report.summary())
        if report.non_manifold_edges:
            log.warning(
                "%s: %d non-manifold edges (more than two faces on one edge): the surface is sampled as given, "
                "but check the mesh if contacts there look wrong",
                mesh_path,
                report.non_manifold_edges,
            )
    model = build_object_model(mesh, name, config, source=source, repair_report=report)
    model.save(out_path)
    log.info(
        "%s: %d parent points, %d/%d valid blocks, bbox %s mm, symmetry: %s -> %s",
        name,
        len(model.points_object),
        model.num_blocks,
        int(np.prod(config.grid_shape)),
        " x ".join(f"{v * 1000:.1f}" for v in model.meta["bbox_object_m"]),
        model.symmetry.describe(),
        out_path,
    )
    return out_path


def load_object_model(name_or_path: str | Path, workspace: str | Path | None = None) -> ObjectModel:
    """Load an object model given a model file path or an object name in the workspace.

    A built-in object's model is built on first use.
    """
    candidate = Path(name_or_path)
    if candidate.suffix == ".npz" or candidate.is_file():
        return ObjectModel.load(candidate)
    path = object_model_path(str(name_or_path), workspace)
    if path.exists():
        return ObjectModel.load(path)
    if str(name_or_path) in BUILTIN_OBJECTS:
        return ObjectModel.load(build_object(None, str(name_or_path), workspace=workspace))
    raise InputError(
        f"no object model named {str(name_or_path)!r} in {path.parent} (build one with `yoto object build MESH "
        f"--name {name_or_path}`; built-in objects: {', '.join(BUILTIN_OBJECTS)})"
    )
