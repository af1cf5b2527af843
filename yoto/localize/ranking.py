"""From scored registrations to ranked, distinct contact candidates with beliefs (geometric localizers).

The matched filter and the ICP baseline both end with K registrations of the tactile cloud on the object, each
with a truncated point-to-plane residual. Both rank them the same way:

- distinct: registrations whose contact locations lie within `dedup_radius_m` of a better one are the same
  candidate (several starts or anchors converging on one place);
- beliefs: each distinct candidate gets weight exp(-(r / T)^2 / 2) with T = `temperature_m`, next to a "none of
  these" weight at the residual `null_residual_m`; `probability` is a weight over their sum. Candidates that fit
  equally well share the belief (a flat face or a cylinder spreads it thin), probabilities sum to less than one,
  and a poor best fit keeps a low probability. The pose stage multiplies them into its joint choice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.errors import InputError


@dataclass(frozen=True)
class BeliefConfig:
    """How registrations become ranked candidates with beliefs."""

    temperature_m: float = 1e-4  # T of the belief: residual differences well below T do not separate candidates
    null_residual_m: float = 3e-4  # residual of the "none of these" hypothesis
    dedup_radius_m: float = 0.003  # registrations whose contacts lie closer than this are one candidate
    num_candidates: int = 10  # candidates returned

    def __post_init__(self):
        if self.temperature_m <= 0 or self.num_candidates < 1:
            raise InputError("temperature_m must be positive and num_candidates at least 1")


def distinct_candidates(p_object: np.ndarray, order: np.ndarray, radius_m: float) -> list[int]:
    """Indices, in `order` (best first), of the locations (K, 3) not within `radius_m` of a better kept one."""
    near = np.linalg.norm(p_object[:, None, :] - p_object[None, :, :], axis=2) < radius_m
    kept: list[int] = []
    for i in order:
        if not near[i, kept].any():
            kept.append(int(i))
    return kept


def residual_beliefs(residuals_m: np.ndarray, config: BeliefConfig) -> np.ndarray:
    """Probability of each distinct candidate from its residual, beside a "none of these" hypothesis."""
    residuals = np.append(np.asarray(residuals_m, dtype=np.float64), config.null_residual_m)
    exponents = -0.5 * (residuals / config.temperature_m) ** 2
    # Subtract the largest exponent before exponentiating, so that small weights do not all underflow to 0.
    weights = np.exp(exponents - exponents.max())
    return weights[:-1] / weights.sum()


@dataclass
class Ranking:
    """The returned candidates of a ranking."""

    indices: list[int]  # the best `num_candidates` distinct registrations, best first
    probabilities: np.ndarray  # their beliefs
    distinct: int  # how many distinct registrations there were in all


def rank_registrations(p_object: np.ndarray, residuals_m: np.ndarray, config: BeliefConfig) -> Ranking:
    """The best distinct registrations of (K, 3) contact locations with (K,) residuals, and their beliefs.

    Beliefs are normalised over every distinct registration, not only those returned: a contact that matches
    twenty places equally well gives each a twentieth even when only ten are returned.
    """
    residuals_m = np.asarray(residuals_m, dtype=np.float64)
    order = np.argsort(residuals_m, kind="stable")
    kept = distinct_candidates(np.asarray(p_object, dtype=np.float64), order, config.dedup_radius_m)
    probabilities = residual_beliefs(residuals_m[kept], config)
    return Ranking(kept[: config.num_candidates], probabilities[: config.num_candidates], len(kept))
