"""Training objective of the localization network (paper Sec. 3.3, App. C.2).

    L = w_adapt * lambda_c * (L_cls + L_topK) + lambda_p * L_pos + lambda_s * L_select

- L_cls: cross-entropy of the coarse logits against the ground-truth block y.
- L_topK: [a_top - a_y + m1]_+ + [a_K - a_y + m2]_+, with a_top the best block other than y (the paper's
  highest-scoring block whenever the prediction is wrong, the runner-up when it is right, so the term keeps
  a margin instead of being the constant m1) and a_K the K-th highest logit (the last retained candidate).
  It applies to the samples whose true block is already among the top K, which is its purpose ("keep the
  correct block competitive during candidate selection"): applied to every sample, the hinge has a collapsed
  minimum (all features parallel, all logits equal, loss m1 + m2) that training fell into within 20 steps
  when most samples start outside the top K, and cosine logits get no gradient out of it (measured, see
  docs/network.md).
- L_pos: sum over candidates k of w_k * SmoothL1(p_k - p), where w_k favours candidates with a high combined
  score and a block centre near the truth: w = (softmax(score) + softmax(-|c_k - p| / d)) / 2, detached.
- L_select (not spelled out in the paper, which ranks candidates by coarse score + confidence but names no
  loss for the confidence): cross-entropy of the candidates' combined scores (coarse part detached) against
  the candidate whose prediction is nearest the truth. It is what teaches the confidence to rank.
- w_adapt: the classification weight rises when the batch's top-K block recall is low:
  1 + (max_factor - 1) * (1 - recall), so 1x at full recall and max_factor (2.5x) at zero.

Every term is a per-sample loss averaged with per-sample weights (real contacts weigh more in stage 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F


@dataclass(frozen=True)
class LossConfig:
    """Weights and shapes of the loss terms."""

    cls_weight: float = 1.0  # lambda_c, on L_cls and L_topK (paper App. C.2)
    pos_weight: float = 2.0  # lambda_p, on L_pos (paper App. C.2)
    select_weight: float = 1.0  # lambda_s, on L_select (ours; the paper names no loss for the confidence)
    margin_top: float = 0.5  # m1, logit units
    margin_k: float = 1.0  # m2, logit units
    topk: int = 9  # K of the top-K margin and recall (the candidate pool size)
    adaptive_max_factor: float = 2.5  # classification weight at zero top-K recall (paper: up to 2.5x)
    position_unit_m: float = 0.01  # L_pos measures errors in this unit (1 cm)
    smooth_l1_beta: float = 0.2  # SmoothL1 switches from quadratic to linear here, in position units (2 mm)
    weight_distance_m: float = 0.01  # d of the centre-distance part of w_k


def weighted_mean(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    return (values * weights).sum() / weights.sum().clamp_min(1e-12)


def block_cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-sample CE of (B, NB) logits (may hold -inf for other objects' blocks) -> (B,)."""
    return F.cross_entropy(logits, target, reduction="none")


def topk_margin(logits: torch.Tensor, target: torch.Tensor, k: int, margin_top: float, margin_k: float) -> torch.Tensor:
    """Per-sample [a_other_best - a_y + m1]_+ + [a_(K) - a_y + m2]_+ -> (B,)."""
    true_logit = logits.gather(1, target.unsqueeze(1)).squeeze(1)
    others = logits.scatter(1, target.unsqueeze(1), float("-inf"))
    best_other = others.amax(dim=1)
    k = min(k, logits.shape[1])
    kth = logits.topk(k, dim=1).values[:, -1]
    finite = torch.isfinite(best_other)  # an object with a single block has no competitor
    first = torch.where(finite, F.relu(best_other - true_logit + margin_top), torch.zeros_like(true_logit))
    return first + F.relu(kth - true_logit + margin_k)


def topk_recall(logits: torch.Tensor, target: torch.Tensor, k: int) -> torch.Tensor:
    """(B,) bool: is the true block among the k highest logits."""
    k = min(k, logits.shape[1])
    return (logits.topk(k, dim=1).indices == target.unsqueeze(1)).any(dim=1)


def candidate_weights(
    scores: torch.Tensor, candidate_centres: torch.Tensor, p_true: torch.Tensor, distance_m: float
) -> torch.Tensor:
    """w (B, K): half softmax of the combined scores, half softmax of -|c_k - p| / d; no gradient."""
    distance = torch.linalg.vector_norm(candidate_centres - p_true.unsqueeze(1), dim=-1)
    weights = 0.5 * F.softmax(scores.detach(), dim=1) + 0.5 * F.softmax(-distance / distance_m, dim=1)
    return weights.detach()


def position_loss(
    positions: torch.Tensor, p_true: torch.Tensor, weights: torch.Tensor, unit_m: float, beta: float
) -> torch.Tensor:
    """Per-sample sum_k w_k SmoothL1(p_k - p) (summed over x, y, z, in `unit_m` units) -> (B,)."""
    error = (positions - p_true.unsqueeze(1)) / unit_m
    per_candidate = F.smooth_l1_loss(error, torch.zeros_like(error), beta=beta, reduction="none").sum(-1)
    return (weights * per_candidate).sum(dim=1)


def selection_loss(
    coarse_logits: torch.Tensor,
    candidates: torch.Tensor,
    confidence: torch.Tensor,
    positions: torch.Tensor,
    p_true: torch.Tensor,
) -> torch.Tensor:
    """Per-sample CE of (detached coarse + confidence) against the candidate nearest the truth -> (B,)."""
    scores = coarse_logits.detach().gather(1, candidates) + confidence
    nearest = torch.linalg.vector_norm(positions.detach() - p_true.unsqueeze(1), dim=-1).argmin(dim=1)
    return F.cross_entropy(scores, nearest, reduction="none")


def localization_loss(
    outputs: dict[str, torch.Tensor],
    block_target: torch.Tensor,
    p_true: torch.Tensor,
    block_centres: torch.Tensor,
    sample_weight: torch.Tensor,
    config: LossConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The total loss of a batch and its parts (floats, for the log).

    outputs: the network's forward outputs; block_target (B,) ground-truth block; p_true (B, 3) object frame;
    block_centres (NB, 3); sample_weight (B,) per-sample loss weight.
    """
    logits = outputs["coarse_logits"]
    cls = block_cross_entropy(logits, block_target)
    recall = topk_recall(logits.detach(), block_target, config.topk).float()
    margin = topk_margin(logits, block_target, config.topk, config.margin_top, config.margin_k) * recall
    adaptive = 1.0 + (config.adaptive_max_factor - 1.0) * (1.0 - weighted_mean(recall, sample_weight))
    weights = candidate_weights(
        outputs["scores"], block_centres[outputs["candidates"]], p_true, config.weight_distance_m
    )
    pos = position_loss(outputs["positions"], p_true, weights, config.position_unit_m, config.smooth_l1_beta)
    select = selection_loss(logits, outputs["candidates"], outputs["confidence"], outputs["positions"], p_true)
    coarse = weighted_mean(cls + margin, sample_weight)
    total = (
        adaptive.detach() * config.cls_weight * coarse
        + config.pos_weight * weighted_mean(pos, sample_weight)
        + config.select_weight * weighted_mean(select, sample_weight)
    )
    parts = {
        "loss": float(total.detach()),
        "cls": float(weighted_mean(cls, sample_weight).detach()),
        "topk_margin": float(weighted_mean(margin, sample_weight).detach()),
        "pos": float(weighted_mean(pos, sample_weight).detach()),
        "select": float(weighted_mean(select, sample_weight).detach()),
        "adaptive": float(adaptive),
        "topk_recall": float(recall.mean()),
    }
    return total, parts
