"""Per-step patch augmentations (paper App. C.2) and sensor-like crops, on numpy arrays in the canonical frame.

The paper's four: in-plane rotation about the canonical z axis, Gaussian jitter, point dropout and voxel
down-sampling. The paper gives jitter as sigma 0.01 clipped at 0.05 without a unit; on patches measured in
centimetres (our network's input unit) that is 0.1 mm clipped at 0.5 mm, which is what we use: the same
numbers in metres would be a 1 cm jitter, larger than the geometry a patch holds.

Sensor-like crops (ours, `crop_prob` > 0): a GelSight press sees only the part of the surface within the
indentation depth of its deepest point, often smaller than a virtual ball patch on curved surfaces. The
crop keeps the points within a random depth of the patch's extreme point along its outward normal, and
optionally a random disc; the training sample is then re-canonicalized and relabelled (data.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AugmentConfig:
    """Which augmentations run, and how strong they are."""

    rotation_prob: float = 0.75  # probability of a random in-plane rotation (paper: 0.75)
    rotation_max_rad: float = 1.0  # angle drawn uniformly in [-max, max] (paper: 1 rad; pi = any roll)
    jitter_sigma_m: float = 1e-4  # Gaussian jitter per coordinate (paper: 0.01 in cm units)
    jitter_clip_m: float = 5e-4  # jitter clipped at this (paper: 0.05 in cm units)
    dropout_prob: float = 0.5  # probability that a patch loses points (paper: 50% of patches)
    dropout_ratio: float = 0.1  # fraction of points dropped (paper: 0.1)
    voxel_size_m: float = 2e-4  # voxel down-sampling grid (paper: 0.2 mm); 0 disables
    crop_prob: float = 0.0  # probability of a sensor-like depth crop of a virtual patch (0: the paper's setup)
    crop_depth_m: tuple[float, float] = (0.0005, 0.002)  # indentation depth range of the crop
    crop_disc_prob: float = 0.5  # probability that a crop is also limited to a disc around a random point
    crop_disc_fraction: tuple[float, float] = (0.5, 1.0)  # disc radius as a fraction of the patch radius
    crop_min_fraction: float = 0.25  # a crop keeping fewer of the patch's points than this is not applied
    normal_noise_rad: float = 0.0  # std of random tilts added to normals (0: none)


def rotation_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_in_plane_rotation(
    points: np.ndarray, normals: np.ndarray, rng: np.random.Generator, prob: float, max_rad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rotate about the canonical z axis by U(-max, max) with probability `prob`."""
    if prob <= 0 or rng.random() >= prob:
        return points, normals
    rotation = rotation_z(rng.uniform(-max_rad, max_rad)).astype(points.dtype)
    return points @ rotation.T, normals @ rotation.T


def jitter(points: np.ndarray, rng: np.random.Generator, sigma: float, clip: float) -> np.ndarray:
    if sigma <= 0:
        return points
    return points + np.clip(rng.normal(0.0, sigma, size=points.shape), -clip, clip).astype(points.dtype)


def perturb_normals(normals: np.ndarray, rng: np.random.Generator, sigma_rad: float) -> np.ndarray:
    """Tilt unit normals by small random angles (std `sigma_rad` per tangent direction) and renormalise."""
    if sigma_rad <= 0:
        return normals
    noisy = normals + rng.normal(0.0, sigma_rad, size=normals.shape).astype(normals.dtype)
    return noisy / np.linalg.norm(noisy, axis=1, keepdims=True)


def voxel_keep_first(points: np.ndarray, size_m: float) -> np.ndarray:
    """Indices of one point per occupied voxel of side `size_m` (the first one), in input order."""
    if size_m <= 0:
        return np.arange(len(points))
    cells = np.floor(points / size_m).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, first = np.unique(keys, return_index=True)
    return np.sort(first)


def point_dropout(indices: np.ndarray, rng: np.random.Generator, prob: float, ratio: float) -> np.ndarray:
    """With probability `prob`, replace a `ratio` of the sampled indices by repeats of the kept ones."""
    if prob <= 0 or ratio <= 0 or rng.random() >= prob:
        return indices
    dropped = rng.random(len(indices)) < ratio
    if dropped.all() or not dropped.any():
        return indices
    kept = indices[~dropped]
    out = indices.copy()
    out[dropped] = kept[rng.integers(0, len(kept), size=int(dropped.sum()))]
    return out


def depth_crop_mask(
    points: np.ndarray, normals: np.ndarray, rng: np.random.Generator, config: AugmentConfig
) -> np.ndarray | None:
    """A sensor-like crop of a canonical patch: points within a random depth of its extreme point along the
    mean outward normal, optionally within a random disc (in the plane normal to it). None: no crop."""
    outward = normals.sum(axis=0)
    norm = np.linalg.norm(outward)
    if norm < 1e-9:
        return None
    outward = outward / norm
    height = points @ outward  # larger = nearer the sensor
    depth = rng.uniform(*config.crop_depth_m)
    keep = height >= height.max() - depth
    if rng.random() < config.crop_disc_prob:
        lateral = points - np.outer(height, outward)
        radius = np.linalg.norm(lateral, axis=1).max()
        centre = lateral[rng.integers(len(points))] * rng.uniform(0.0, 0.5)
        keep &= np.linalg.norm(lateral - centre, axis=1) <= rng.uniform(*config.crop_disc_fraction) * radius
    if keep.sum() < config.crop_min_fraction * len(points) or keep.all():
        return None
    return keep
