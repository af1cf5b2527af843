"""Errors that YOTO raises for bad input.

Every error about a file names the file and the problem, so a user can act on the message alone.
"""

from __future__ import annotations

from pathlib import Path


class YotoError(Exception):
    """Base class for every error YOTO raises on purpose."""


class InputError(YotoError):
    """Input data (a file, an array, a parameter) is unusable; the message says why."""

    def __init__(self, problem: str, path: str | Path | None = None):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)

    def __reduce__(self):
        # Pickled across processes: keep the path and the problem apart, as raised.
        return type(self), (self.problem, self.path)


class NoContactError(InputError):
    """The tactile input shows no contact: a cloud with no indentation, or an image in which nothing touches the gel."""


class DegenerateGeometryError(YotoError):
    """The geometry cannot determine the requested quantity (coincident contacts, parallel normals...)."""


class MissingDependencyError(YotoError):
    """An optional dependency is not installed; the message names the extra to install."""

    def __init__(self, module: str, extra: str, purpose: str):
        self.module, self.extra, self.purpose = module, extra, purpose
        super().__init__(
            f"{purpose} needs the Python package '{module}'. Install it with "
            f"`pip install 'yoto[{extra}]'`"
            + (" (for a CPU-only install: `pip install torch==2.13.0`)." if module == "torch" else ".")
        )

    def __reduce__(self):
        # Raised in a worker process, it crosses back pickled: rebuild it from its own arguments.
        return type(self), (self.module, self.extra, self.purpose)


def require_open3d(purpose: str):
    """Import Open3D or raise a MissingDependencyError that says how to install it."""
    try:
        import open3d
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError("open3d", "geometry", purpose) from exc
    return open3d


def require_torch(purpose: str):
    """Import torch or raise a MissingDependencyError that says how to install it."""
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError("torch", "learn", purpose) from exc
    return torch
