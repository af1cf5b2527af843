"""The candidate ICP's nearest-parent-point lookups, on pykdtree where it is installed (the `fast` extra).

A contact's Gauss-Newton passes and residual fits ask about 9,300 times for the parent point nearest a tactile
point (within a reach): about a quarter of its CPU time. pykdtree answers the same question as SciPy's
`cKDTree` with the same point (it is exact too: the candidates of 180 benchmark contacts are bitwise equal) in
less time: about 1.1 ms less CPU per contact (docs/journal/localization.md). Without it the model's own `cKDTree`
answers, with the same results.

pykdtree splits a query over OpenMP threads; the matched filter runs on one core (the other belongs to the pair's
second contact, `yoto.localize.helper`), and OpenMP threads that wait for a busy core spin: on a loaded 2-core
machine a contact's lookups took 61 ms of CPU on two threads against 4.2 ms on one. `one_openmp_thread` keeps
them on the calling thread.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass

import numpy as np
from threadpoolctl import ThreadpoolController

from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel
from yoto.registration import NearestPoints

try:
    from pykdtree.kdtree import KDTree

    HAVE_PYKDTREE = True
except ImportError:  # the `fast` extra is not installed: the model's cKDTree answers
    HAVE_PYKDTREE = False


@dataclass(frozen=True)
class ParentSurface:
    """A model's parent cloud as `yoto.registration.SurfaceCloud`, its lookups on pykdtree where installed."""

    points_object: np.ndarray  # (N, 3) the model's parent points
    normals_object: np.ndarray  # (N, 3) their outward unit normals
    kdtree: NearestPoints  # pykdtree's tree over the points (float64), or the model's cKDTree


def _build(model: ObjectModel, _: None) -> ParentSurface:
    points = model.points_object
    tree = KDTree(np.ascontiguousarray(points, dtype=np.float64)) if HAVE_PYKDTREE else model.kdtree
    return ParentSurface(points, model.normals_object, tree)


_CACHE: ModelCache[None, ParentSurface] = ModelCache(_build, size=4)


def parent_surface(model: ObjectModel) -> ParentSurface:
    """The model's parent cloud with the fastest exact nearest-point lookups installed (cached per model)."""
    return _CACHE.get(model, None)


def one_openmp_thread() -> contextlib.AbstractContextManager:
    """A context in which OpenMP (pykdtree's queries) runs on the calling thread alone (see the module docstring)."""
    if not HAVE_PYKDTREE:
        return contextlib.nullcontext()
    return _openmp_libraries().limit(limits=1)


@functools.cache
def _openmp_libraries() -> ThreadpoolController:
    """The OpenMP runtimes loaded once pykdtree is (found once, on first use)."""
    return ThreadpoolController().select(user_api="openmp")
