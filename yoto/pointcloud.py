"""Point-cloud operations shared by the object model, the patch canonicalization and the solver."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from yoto.geometry import normalize


def covariance_eigh(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, ascending eigenvalues and eigenvectors (columns) of the covariance of (N, 3) points."""
    if weights is None:
        centroid = points.mean(axis=0)
        centred = points - centroid
        covariance = centred.T @ centred / len(points)
    else:
        weights = weights / weights.sum()
        centroid = weights @ points
        centred = points - centroid
        covariance = (centred * weights[:, None]).T @ centred
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    return centroid, eigenvalues, eigenvectors


def estimate_normals(
    points: np.ndarray, k: int, orientation_hint: np.ndarray, tree: cKDTree | None = None
) -> np.ndarray:
    """Unit normals from PCA of each point's k nearest neighbours, signed to agree with `orientation_hint`.

    `orientation_hint` is (3,) (one direction for all points, e.g. the sensor's outward axis) or (N, 3)
    (per point, e.g. mesh face normals). Returns (N, 3) float64.
    """
    points = np.asarray(points, dtype=np.float64)
    k = int(min(k, len(points)))
    if tree is None:
        tree = cKDTree(points)
    _, neighbours = tree.query(points, k=k)
    neighbourhoods = points[neighbours.reshape(len(points), k)]
    centred = neighbourhoods - neighbourhoods.mean(axis=1, keepdims=True)
    covariances = np.einsum("nki,nkj->nij", centred, centred)
    _, eigenvectors = np.linalg.eigh(covariances)
    normals = eigenvectors[:, :, 0]
    hint = np.broadcast_to(np.asarray(orientation_hint, dtype=np.float64), normals.shape)
    normals *= np.where(np.einsum("ni,ni->n", normals, hint) < 0.0, -1.0, 1.0)[:, None]
    return normalize(normals)


def voxel_downsample(points: np.ndarray, voxel_size: float, *extra: np.ndarray) -> tuple[np.ndarray, ...]:
    """Average the points (and any per-point arrays in `extra`) that fall in the same voxel.

    Returns the down-sampled points followed by the down-sampled extras, in first-occurrence order.
    """
    cells = np.floor(points / voxel_size).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, first, inverse, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # keep a stable, input-dependent order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    slots = rank[inverse]
    outputs = []
    for array in (points, *extra):
        summed = np.zeros((len(first),) + array.shape[1:], dtype=np.float64)
        np.add.at(summed, slots, array)
        outputs.append(summed / counts[order].reshape((-1,) + (1,) * (array.ndim - 1)))
    return tuple(outputs)
