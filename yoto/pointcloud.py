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


def smallest_eigenvectors(matrices: np.ndarray) -> np.ndarray:
    """Unit eigenvector of the smallest eigenvalue of each symmetric 3x3 matrix, (..., 3, 3) -> (..., 3).

    Closed form (trigonometric eigenvalues, then the eigenvector as the largest cross product of two rows of
    A - lambda I): about ten times faster than batched `np.linalg.eigh`, which remains the fallback for
    matrices whose two smallest eigenvalues nearly coincide (there the direction is ill-defined anyway).
    """
    a = np.asarray(matrices, dtype=np.float64).reshape(-1, 3, 3)
    q = np.trace(a, axis1=1, axis2=2) / 3.0
    p1 = a[:, 0, 1] ** 2 + a[:, 0, 2] ** 2 + a[:, 1, 2] ** 2
    p2 = (a[:, 0, 0] - q) ** 2 + (a[:, 1, 1] - q) ** 2 + (a[:, 2, 2] - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    b = (a - q[:, None, None] * np.eye(3)) / np.maximum(p, 1e-300)[:, None, None]
    r = np.clip(np.linalg.det(b) / 2.0, -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    rows = a - smallest[:, None, None] * np.eye(3)
    crosses = np.stack(
        [np.cross(rows[:, 0], rows[:, 1]), np.cross(rows[:, 0], rows[:, 2]), np.cross(rows[:, 1], rows[:, 2])], axis=1
    )
    norms = np.linalg.norm(crosses, axis=2)
    best = np.argmax(norms, axis=1)
    vectors = crosses[np.arange(len(a)), best] / np.maximum(norms[np.arange(len(a)), best], 1e-300)[:, None]
    # Ill-conditioned cases: a repeated smallest eigenvalue, or an (almost) isotropic matrix.
    scale = np.maximum(np.abs(q), 1e-300)
    shaky = (norms.max(axis=1) < 1e-10 * scale**2) | (p < 1e-9 * scale)
    if shaky.any():
        vectors[shaky] = np.linalg.eigh(a[shaky])[1][:, :, 0]
    return vectors.reshape(np.shape(matrices)[:-1])


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
    normals = smallest_eigenvectors(np.matmul(centred.transpose(0, 2, 1), centred))
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
    counts = counts[order].astype(np.float64)
    outputs = []
    for array in (points, *extra):
        flat = np.asarray(array, dtype=np.float64).reshape(len(points), -1)
        summed = np.stack(
            [np.bincount(slots, weights=flat[:, j], minlength=len(first)) for j in range(flat.shape[1])], axis=1
        )
        outputs.append((summed / counts[:, None]).reshape((len(first),) + np.shape(array)[1:]))
    return tuple(outputs)
