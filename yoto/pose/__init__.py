"""The pose stage: a contact pair and an object model in, T_world_object out."""

from __future__ import annotations

from typing import Any

__all__ = ["PoseEstimate", "estimate_pose"]


def __getattr__(name: str) -> Any:
    # Lazy, so `yoto --help` (which imports yoto.pose.cli) does not load numpy/scipy/trimesh.
    if name in __all__:
        from yoto.pose import pipeline

        return getattr(pipeline, name)
    raise AttributeError(name)
