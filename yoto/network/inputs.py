"""How clouds become network inputs: fixed-size point samples of patches and of surface blocks.

Used alike by training, validation and the localizer, so the network sees at inference exactly the kind
of input it was trained and validated on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from yoto.network.presets import NetworkConfig
from yoto.objects.model import ObjectModel


def subsample_indices(count: int, target: int, rng: np.random.Generator) -> np.ndarray:
    """`target` indices into `count` points in random order: without repeats when possible, else every point
    once and random repeats to fill (the paper's repeat-padding)."""
    if count >= target:
        return rng.permutation(count)[:target]
    extra = rng.integers(0, count, size=target - count)
    return rng.permutation(np.concatenate([np.arange(count), extra]))


def inference_points(
    points: np.ndarray, normals: np.ndarray, num_points: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """The fixed (seeded) sub-sample of a canonical patch that the network sees at inference and validation."""
    chosen = subsample_indices(len(points), num_points, np.random.default_rng(seed))
    return np.ascontiguousarray(points[chosen], dtype=np.float32), np.ascontiguousarray(
        normals[chosen], dtype=np.float32
    )


@dataclass
class BlockSet:
    """One object's blocks as the network sees them: fixed point samples in each block's standardised frame."""

    points: np.ndarray  # (NB, M, 3) float32, R_i (x - c_i), metres
    normals: np.ndarray  # (NB, M, 3) float32, R_i n
    centres: np.ndarray  # (NB, 3) float32, c_i, object frame
    rotations: np.ndarray  # (NB, 3, 3) float32, R_i
    neighbours: np.ndarray  # (NB, K) int64, each block's nearest blocks by centre distance, itself first

    @property
    def num_blocks(self) -> int:
        return len(self.centres)

    def tensors(self) -> dict[str, torch.Tensor]:
        """The block entries of the network's input dict (see ContactLocalizationNet.forward)."""
        return {
            "block_points": torch.from_numpy(self.points),
            "block_normals": torch.from_numpy(self.normals),
            "block_centres": torch.from_numpy(self.centres),
            "block_rotations": torch.from_numpy(self.rotations),
            "block_neighbours": torch.from_numpy(self.neighbours),
        }


def make_block_set(model: ObjectModel, config: NetworkConfig) -> BlockSet:
    """Blocks of `model` for the network. Deterministic: the same model always gives the same samples."""
    points, normals = [], []
    for block in range(model.num_blocks):
        block_points, block_normals = model.block_points(block)
        rng = np.random.default_rng([block, len(block_points)])
        chosen = subsample_indices(len(block_points), config.points_per_block, rng)
        rotation = model.block_rotations[block]
        points.append((block_points[chosen] - model.block_centres_object[block]) @ rotation.T)
        normals.append(block_normals[chosen] @ rotation.T)
    return BlockSet(
        points=np.asarray(points, dtype=np.float32),
        normals=np.asarray(normals, dtype=np.float32),
        centres=model.block_centres_object.astype(np.float32),
        rotations=model.block_rotations.astype(np.float32),
        neighbours=block_neighbours(model.block_centres_object, config.candidates),
    )


def block_neighbours(centres: np.ndarray, count: int) -> np.ndarray:
    """(NB, min(count, NB)) int64 indices of each block's nearest block centres (NB, 3), itself first, ties by
    index: the candidate pools of the fine stage."""
    distances = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(distances, -1.0)  # itself first
    return np.argsort(distances, axis=1, kind="stable")[:, :count].astype(np.int64)
