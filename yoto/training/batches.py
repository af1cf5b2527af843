"""An epoch's batches: which samples of which object each step draws, and their tensors."""

from __future__ import annotations

import math

import numpy as np
import torch

from yoto.training.config import StageConfig
from yoto.training.data import ObjectData, Patch

# A batch entry: the kind of sample ("virtual", "press" or "real") and its index in the object's pool of that kind.
Entry = tuple[str, int]


def plan_epoch(
    objects: list[ObjectData], stage: StageConfig, batch_size: int, rng: np.random.Generator, use_real: bool
) -> list[tuple[int, list[Entry]]]:
    """The epoch's batches: (object index, [(kind, sample index), ...]), objects interleaved at random.

    The number of batches depends only on the pool sizes, not on the draw (the schedule needs it up front).
    """
    batches: list[tuple[int, list[Entry]]] = []
    for obj_index, data in enumerate(objects):
        pool = []
        for kind, indices in (("virtual", data.virtual_train), ("press", data.press_train)):
            if stage.virtual_fraction < 1.0 and len(indices):
                count = max(1, int(round(stage.virtual_fraction * len(indices))))
                indices = rng.choice(indices, size=count, replace=False)
            pool += [(kind, int(i)) for i in indices]
        if use_real:
            pool += [("real", j) for j in range(len(data.real_train))] * stage.real_oversample
        if not pool:
            continue
        order = rng.permutation(len(pool))
        chunks = max(1, math.ceil(len(pool) / batch_size))
        for chunk in np.array_split(order, chunks):
            batches.append((obj_index, [pool[i] for i in chunk]))
    order = rng.permutation(len(batches))
    return [batches[i] for i in order]


def epoch_batch_count(objects: list[ObjectData], stage: StageConfig, batch_size: int, use_real: bool) -> int:
    """len(plan_epoch(...)) without drawing it."""
    total = 0
    for data in objects:
        count = 0
        for indices in (data.virtual_train, data.press_train):
            if stage.virtual_fraction < 1.0 and len(indices):
                count += max(1, int(round(stage.virtual_fraction * len(indices))))
            else:
                count += len(indices)
        if use_real:
            count += len(data.real_train) * stage.real_oversample
        total += max(1, math.ceil(count / batch_size)) if count else 0
    return total


def collate(patches: list[Patch], real_weight: float) -> dict[str, torch.Tensor]:
    """The batch's tensors: patch_points, patch_normals (B, N, 3), p_object (B, 3), block (B,), and each
    sample's loss weight (B,): `real_weight` for real contacts, 1 for virtual patches."""
    return {
        "patch_points": torch.from_numpy(np.stack([p.points for p in patches])),
        "patch_normals": torch.from_numpy(np.stack([p.normals for p in patches])),
        "p_object": torch.from_numpy(np.stack([p.p_object for p in patches]).astype(np.float32)),
        "block": torch.tensor([p.block for p in patches], dtype=torch.int64),
        "weight": torch.tensor([real_weight if p.real else 1.0 for p in patches], dtype=torch.float32),
    }
