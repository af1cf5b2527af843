"""Error measures shared by `yoto pose` summaries, training validation and the benchmark."""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree

from yoto.geometry import rotation_angle_rad, transform_points


class ModelPoints(Protocol):
    """What an error measure needs of an object model (an `ObjectModel` has it)."""

    @property
    def T_mesh_object(self) -> np.ndarray: ...

    @property
    def points_object(self) -> np.ndarray: ...


def pose_errors(
    T_world_mesh_estimate: np.ndarray, T_world_mesh_true: np.ndarray, model: ModelPoints
) -> dict[str, float]:
    """Translation error (mm) of the object's centroid, rotation error (deg), ADD and ADD-S (mm).

    Translation is measured at the object's centroid (the origin of YOTO's object frame) rather than at the
    mesh file's origin, which may lie far from the object and would mix rotation error into translation.
    ADD is the mean distance between model points under the two poses; ADD-S the mean distance from each
    point under the estimate to the nearest point under the truth (symmetric objects).
    """
    centroid_mesh = model.T_mesh_object[:3, 3]
    points_mesh = transform_points(
        model.T_mesh_object, model.points_object[:: max(1, len(model.points_object) // 2000)]
    )
    estimate_world = transform_points(T_world_mesh_estimate, points_mesh)
    true_world = transform_points(T_world_mesh_true, points_mesh)
    add_s = cKDTree(true_world).query(estimate_world)[0].mean()
    return {
        "translation_mm": 1000.0
        * float(
            np.linalg.norm(
                transform_points(T_world_mesh_estimate, centroid_mesh)
                - transform_points(T_world_mesh_true, centroid_mesh)
            )
        ),
        "rotation_deg": float(np.degrees(rotation_angle_rad(T_world_mesh_estimate, T_world_mesh_true))),
        "add_mm": 1000.0 * float(np.linalg.norm(estimate_world - true_world, axis=1).mean()),
        "add_s_mm": 1000.0 * float(add_s),
    }


def summarize(values: list[float] | np.ndarray) -> dict[str, float]:
    """mean, std, median, p90, max of a list of errors (NaN-free)."""
    array = np.asarray(values, dtype=np.float64)
    if len(array) == 0:
        return {key: float("nan") for key in ("mean", "std", "median", "p90", "max")}
    return {
        "mean": float(array.mean()),
        "std": float(array.std()),
        "median": float(np.median(array)),
        "p90": float(np.percentile(array, 90)),
        "max": float(array.max()),
    }
