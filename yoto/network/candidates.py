"""From network outputs to ranked contact candidates, shared by validation and the localizer.

The paper's answer is the best candidate (coarse score + confidence) in the pool of the top coarse block.
A single contact can be ambiguous (self-similar surfaces), so we also keep the best candidate of the pools
of the next few coarse blocks ("hypotheses"); the pose stage then picks the pair of candidates that agrees
with the two sensors' geometry. Candidate beliefs are a softmax of the combined scores over the returned
candidates, at a temperature fitted on validation data after training, with candidates that land within a
few millimetres of each other merged (their beliefs added).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from yoto.network.model import ContactLocalizationNet


@torch.no_grad()
def rank_hypotheses(
    net: ContactLocalizationNet,
    patch_features: torch.Tensor,
    block_features: torch.Tensor,
    blocks: dict[str, torch.Tensor],
    hypotheses: int,
) -> dict[str, np.ndarray]:
    """Score the candidate pools of the top `hypotheses` coarse blocks of each patch.

    patch_features (B, D), or (B, R, D) for R in-plane rotations of each patch (test-time augmentation: coarse
    logits, fine positions and confidences are averaged over the rotations); block_features (NB, D); `blocks`
    holds block_centres, block_rotations and block_neighbours as in the network's input. Returns numpy arrays
    (H hypotheses, K candidates per pool):
        logits (B, NB), top_blocks (B, H), pools (B, H, K), positions (B, H, K, 3), confidence (B, H, K),
        scores (B, H, K) = coarse logit + confidence, best (B, H): index of each pool's best candidate.
    """
    if patch_features.dim() == 2:
        patch_features = patch_features.unsqueeze(1)
    batch, rotations, dim = patch_features.shape
    flat_features = patch_features.reshape(batch * rotations, dim)
    logits = net.coarse_logits(flat_features, block_features).reshape(batch, rotations, -1).mean(dim=1)
    count = min(hypotheses, logits.shape[1])
    top_blocks = logits.topk(count, dim=1).indices  # (B, H)
    pools = blocks["block_neighbours"][top_blocks]  # (B, H, K)
    k = pools.shape[2]
    flat = pools.reshape(batch, count * k)
    positions, _, confidence = net.fine_predictions(
        flat_features,
        block_features,
        flat.repeat_interleave(rotations, dim=0),
        blocks["block_centres"],
        blocks["block_rotations"],
    )
    positions = positions.reshape(batch, rotations, count * k, 3).mean(dim=1)
    confidence = confidence.reshape(batch, rotations, count * k).mean(dim=1)
    scores = logits.gather(1, flat) + confidence
    scores = scores.reshape(batch, count, k)
    return {
        "logits": logits.float().cpu().numpy(),
        "top_blocks": top_blocks.cpu().numpy(),
        "pools": pools.cpu().numpy(),
        "positions": positions.reshape(batch, count, k, 3).double().cpu().numpy(),
        "confidence": confidence.reshape(batch, count, k).float().cpu().numpy(),
        "scores": scores.float().cpu().numpy(),
        "best": scores.argmax(dim=2).cpu().numpy(),
    }


def rotated_copies(points: np.ndarray, normals: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` copies of a canonical patch (N, 3) rotated about +z by 2 pi i / count -> (count, N, 3) each."""
    angles = 2.0 * np.pi * np.arange(count) / count
    c, s = np.cos(angles), np.sin(angles)
    rotations = np.zeros((count, 3, 3), dtype=np.float32)
    rotations[:, 0, 0], rotations[:, 0, 1], rotations[:, 1, 0], rotations[:, 1, 1] = c, -s, s, c
    rotations[:, 2, 2] = 1.0
    return (
        np.einsum("rij,nj->rni", rotations, points).astype(np.float32),
        np.einsum("rij,nj->rni", rotations, normals).astype(np.float32),
    )


@dataclass
class Candidate:
    """One ranked contact hypothesis of one patch."""

    p_object: np.ndarray  # (3,) object frame
    block: int
    score: float  # coarse logit + confidence
    coarse: float  # the block's coarse logit
    confidence: float  # the fine head's confidence
    hypothesis: int  # rank of the coarse block whose pool produced it (0: the paper's answer)
    probability: float = 0.0


def merge_close(candidates: list[Candidate], beliefs: np.ndarray, radius_m: float) -> list[Candidate]:
    """Greedy merge in the given order: a candidate within `radius_m` of a kept one adds its belief to it."""
    kept: list[Candidate] = []
    for candidate, belief in zip(candidates, beliefs, strict=True):
        for other in kept:
            if np.linalg.norm(other.p_object - candidate.p_object) <= radius_m:
                other.probability += float(belief)
                break
        else:
            candidate.probability = float(belief)
            kept.append(candidate)
    return kept


def softmax(values: np.ndarray, temperature: float) -> np.ndarray:
    scaled = np.asarray(values, dtype=np.float64) / max(temperature, 1e-6)
    scaled -= scaled.max()
    weights = np.exp(scaled)
    return weights / weights.sum()


def candidates_of(
    ranking: dict[str, np.ndarray], index: int, temperature: float, merge_radius_m: float, paper_first: bool = True
) -> list[Candidate]:
    """The ranked candidates of patch `index`: each hypothesis' best, one per block, close ones merged.

    Order: the paper's answer (best of the top coarse block's pool) first when `paper_first`, then the
    others by score. Probabilities sum to 1 over the returned candidates.
    """
    found: dict[int, Candidate] = {}
    for h, k in enumerate(ranking["best"][index]):
        block = int(ranking["pools"][index, h, k])
        if block in found:
            continue
        found[block] = Candidate(
            p_object=ranking["positions"][index, h, k],
            block=block,
            score=float(ranking["scores"][index, h, k]),
            coarse=float(ranking["logits"][index, block]),
            confidence=float(ranking["confidence"][index, h, k]),
            hypothesis=h,
        )
    ordered = sorted(found.values(), key=lambda c: (not (paper_first and c.hypothesis == 0), -c.score))
    return merge_close(ordered, softmax(np.array([c.score for c in ordered]), temperature), merge_radius_m)


def fit_temperature(score_lists: list[np.ndarray], correct_lists: list[np.ndarray]) -> float:
    """Softmax temperature that best predicts which candidate is right (negative log-likelihood on a grid).

    score_lists[i] holds the candidates' scores of sample i, correct_lists[i] a bool per candidate (the
    candidates within tolerance of the truth). Samples with no correct candidate contribute the belief that
    is left for "none of them" only through the others; they are skipped.
    """
    grid = np.exp(np.linspace(np.log(0.05), np.log(50.0), 121))
    best, best_nll = 1.0, np.inf
    usable = [(s, c) for s, c in zip(score_lists, correct_lists, strict=True) if c.any() and len(s) > 1]
    if not usable:
        return 1.0
    for temperature in grid:
        nll = 0.0
        for scores, correct in usable:
            nll -= np.log(max(softmax(scores, temperature)[correct].sum(), 1e-12))
        if nll < best_nll:
            best, best_nll = float(temperature), nll
    return best
