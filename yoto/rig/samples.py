"""Labelled single contacts: the training samples `yoto rig label` writes and `yoto train --real-pairs` reads.

One JSON file per contact (`format: yoto-labelled-contact`), its tactile cloud (PLY, sensor frame) and GelSight
frame (PNG) beside it, keyed like a side of a contact-pair file (SPEC "Dual contact"):

    {"format": "yoto-labelled-contact", "format_version": 1, "object": "drill", "side": "left",
     "contact": {"points": "c_0003.ply", "image": "c_0003.png", "T_world_sensor": 4x4},
     "ground_truth": {"T_world_object": 4x4, "p_object": [x, y, z]},
     "label": {...how the label was made...}, "source": {...recording, topic, time...}}

`ground_truth` is in the mesh file's frame, like a pair file's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import TactileContact, validate_tactile_points
from yoto.errors import InputError
from yoto.geometry import validate_transform
from yoto.io import read_json, read_json_format, read_ply_points, write_json_atomic

FORMAT_NAME = "yoto-labelled-contact"
FORMAT_VERSION = 1


@dataclass
class LabelledContact:
    """One contact with its ground truth: what a training sample needs."""

    object_name: str
    contact: TactileContact  # tactile cloud (sensor frame) and the sensor's pose at that moment
    T_world_mesh: np.ndarray  # (4, 4) the object's pose (mesh file's frame) at that moment, from mocap
    p_mesh: np.ndarray  # (3,) contact location, mesh file's frame
    side: str = ""
    extra: dict[str, Any] = field(default_factory=dict)  # label statistics, source


def is_labelled_contact_file(path: str | Path) -> bool:
    """Whether a JSON file is a labelled single contact (cheap: reads the file's JSON)."""
    try:
        payload = read_json(path)
    except InputError:
        return False
    return isinstance(payload, dict) and payload.get("format") == FORMAT_NAME


def write_labelled_contact(
    path: str | Path,
    labelled: LabelledContact,
    points_name: str,
    image_name: str | None = None,
) -> Path:
    """Write the JSON of a labelled contact whose PLY (and PNG) were written beside it under these names."""
    contact: dict[str, Any] = {"points": points_name}
    if image_name:
        contact["image"] = image_name
    contact["T_world_sensor"] = labelled.contact.T_world_sensor
    payload = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "object": labelled.object_name,
        "side": labelled.side,
        "contact": contact,
        "ground_truth": {"T_world_object": labelled.T_world_mesh, "p_object": labelled.p_mesh},
        **labelled.extra,
    }
    return write_json_atomic(path, payload)


def read_labelled_contact(path: str | Path) -> LabelledContact:
    """Read a labelled contact and its tactile cloud; errors name the file."""
    path = Path(path)
    payload = read_json_format(path, FORMAT_NAME, FORMAT_VERSION, "labelled contact", how_to_make="yoto rig label")
    contact, truth = payload.get("contact"), payload.get("ground_truth")
    if not isinstance(contact, dict) or "points" not in contact or not isinstance(truth, dict):
        raise InputError("a labelled contact needs 'contact' (points, T_world_sensor) and 'ground_truth'", path)
    cloud_path = path.parent / str(contact["points"])
    points, _ = read_ply_points(cloud_path)
    p_mesh = np.asarray(truth.get("p_object"), dtype=np.float64)
    if p_mesh.shape != (3,) or not np.isfinite(p_mesh).all():
        raise InputError("ground_truth.p_object must be 3 finite numbers", path)
    return LabelledContact(
        object_name=str(payload.get("object", "")),
        contact=TactileContact(
            validate_tactile_points(points, cloud_path),
            validate_transform(contact.get("T_world_sensor"), "contact.T_world_sensor", path),
            cloud_path,
        ),
        T_world_mesh=validate_transform(truth.get("T_world_object"), "ground_truth.T_world_object", path),
        p_mesh=p_mesh,
        side=str(payload.get("side", "")),
        extra={key: payload[key] for key in ("label", "source") if key in payload},
    )
