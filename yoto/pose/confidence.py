"""Calibrated confidence: the probability that a pose is within 5 mm and 5 deg of the truth (SPEC "Pose result").

The pose stage describes its result by a few numbers (`confidence_features`): how much of the probability the
first hypothesis holds and by what margin, how far the others lie from it (near neighbours along a family of
poses, or poses elsewhere; modulo the object's symmetries), how well the clouds fit under it and how large the
sensor corrections had to be, how well the two contacts' directions condition the rotation, how far the clouds
leave the first pose free (its standard deviations), whether the contacts have features of their own, what the
localizers believed. A logistic model maps them to the probability of being
right. It is fitted on simulated contacts of many objects under realistic calibration error (`yoto
calibrate-confidence`, see docs/pose.md), held-out objects check it, and its parameters ship with YOTO
(`confidence.json`), so a threshold means the same on every object. A reliability diagram in the benchmark shows
how well it holds.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import SIDES, ContactEstimate
from yoto.errors import InputError
from yoto.io import write_json_atomic
from yoto.objects.symmetry import Symmetry
from yoto.pose.hypotheses import Hypotheses, spread
from yoto.pose.refine import Refined
from yoto.pose.search import LocalShape
from yoto.pose.solver import PoseSolution

FORMAT_NAME = "yoto-pose-confidence"
FORMAT_VERSION = 1
SHIPPED = Path(__file__).with_name("confidence.json")
FIT_NOISE_M = 3e-5  # residuals are expressed in units of this (the residual of a right pose)

FEATURES = (
    "log_odds_first",  # log odds of the first hypothesis's probability (clipped at +-12)
    "log_likelihood_margin",  # log-likelihood of the first hypothesis minus the second's (capped at 30)
    "log_hypotheses",  # log of the number of hypotheses above 1e-3
    "fit_residual",  # log(1 + larger side's residual RMS / 30 um)
    "correction",  # sqrt of the sensor corrections' Mahalanobis square under the calibration prior
    "conditioning",  # sigma_2 / sigma_1 of [d, nL, nR]
    "featureless",  # how many of the two contacts are featureless (a quadric fits them within 30 um)
    "belief",  # log10 of the product of the localizers' beliefs at the chosen contacts (floored at 1e-4)
    "searched",  # whether the joint search ran (the localizers did not settle it)
    "spread",  # log(1 + probability-weighted distance of the hypotheses from the first, in 5 mm / 5 deg, capped at 4)
    "rotation_std",  # log of the first pose's rotation standard deviation (largest axis) over 5 deg, from the
    # refinement's information there (the corrections marginalised)
    "translation_std",  # log of its translation standard deviation (largest axis) over 5 mm
)
SPREAD_SCALE_M, SPREAD_SCALE_RAD = 0.005, float(np.radians(5.0))  # the unit of `spread`: what "right" allows ...
SPREAD_CAP = 4.0  # ... and the distance at which a hypothesis counts as elsewhere


def featureless(shape: LocalShape) -> bool:
    """A contact whose local quadric fits within the residual of a right pose: a flat, cylindrical or spherical
    patch, which fits many places of the object equally well."""
    return bool(shape.rms_m[0] <= FIT_NOISE_M)


def confidence_features(
    hypotheses: Hypotheses,
    refined: Refined,
    solution: PoseSolution,
    contacts: dict[str, ContactEstimate],
    shapes: dict[str, LocalShape],
    searched: bool,
    symmetry: Symmetry,
    covariance: np.ndarray,
) -> dict[str, float]:
    """The numbers the confidence is computed from (see FEATURES); `covariance` (6, 6) is the first hypothesis's
    pose covariance (`refine.pose_covariance`)."""
    best = int(hypotheses.member[0])
    first = float(np.clip(hypotheses.probability[0], 1e-12, 1.0))
    # the largest standard deviation of the rotation (its first three rows) and of the translation (the last three)
    rotation_std, translation_std = (
        float(np.sqrt(np.linalg.eigvalsh(covariance[k : k + 3, k : k + 3])[-1])) for k in (0, 3)
    )
    margin = (
        30.0 if len(hypotheses) < 2 else min(30.0, float(hypotheses.log_likelihood[0] - hypotheses.log_likelihood[1]))
    )
    belief = max(1e-4, float(np.prod([contacts[side].probability for side in SIDES])))
    return {
        "log_odds_first": float(np.clip(np.log(first) - np.log1p(-min(first, 1 - 1e-12)), -12.0, 12.0)),
        "log_likelihood_margin": margin,
        "log_hypotheses": float(np.log(max(1, int(np.sum(hypotheses.probability >= 1e-3))))),
        "fit_residual": float(np.log1p(refined.fit_rms_m[best].max() / FIT_NOISE_M)),
        "correction": float(np.sqrt(refined.correction_cost[best])),
        "conditioning": float(solution.conditioning),
        "featureless": float(sum(featureless(shapes[side]) for side in SIDES)),
        "belief": float(np.log10(belief)),
        "searched": float(searched),
        "spread": float(np.log1p(spread(hypotheses, symmetry, SPREAD_SCALE_M, SPREAD_SCALE_RAD, SPREAD_CAP))),
        "rotation_std": float(np.log(rotation_std / SPREAD_SCALE_RAD)),
        "translation_std": float(np.log(translation_std / SPREAD_SCALE_M)),
    }


@dataclass
class ConfidenceModel:
    """Logistic model: P(right) = sigmoid(bias + weights . (features - mean) / scale)."""

    mean: np.ndarray  # (F,)
    scale: np.ndarray  # (F,)
    weights: np.ndarray  # (F,)
    bias: float
    features: tuple[str, ...] = FEATURES
    info: dict[str, Any] = field(default_factory=dict)  # how and on what it was fitted

    def predict(self, features: dict[str, float]) -> float:
        return float(self.predict_many(np.array([[features[name] for name in self.features]]))[0])

    def predict_many(self, matrix: np.ndarray) -> np.ndarray:
        """P(right) of (N, F) feature rows (columns in `features` order)."""
        z = self.bias + ((np.asarray(matrix, dtype=np.float64) - self.mean) / self.scale) @ self.weights
        return 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "features": list(self.features),
            "mean": self.mean.tolist(),
            "scale": self.scale.tolist(),
            "weights": self.weights.tolist(),
            "bias": float(self.bias),
            "info": self.info,
        }

    def save(self, path: str | Path) -> Path:
        return write_json_atomic(Path(path), self.to_json())


def fit_logistic(
    matrix: np.ndarray,
    right: np.ndarray,
    l2: float = 1e-2,
    iterations: int = 50,
    info: dict | None = None,
    features: tuple[str, ...] = FEATURES,
) -> ConfidenceModel:
    """Fit P(right | features) by L2-regularised logistic regression (Newton's method on standardised features);
    `matrix` (N, F) has a column per name in `features`."""
    x = np.asarray(matrix, dtype=np.float64)
    y = np.asarray(right, dtype=np.float64)
    mean, scale = x.mean(axis=0), x.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    z = np.hstack([np.ones((len(x), 1)), (x - mean) / scale])
    theta = np.zeros(z.shape[1])
    penalty = l2 * len(x) * np.diag([0.0] + [1.0] * x.shape[1])
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-np.clip(z @ theta, -50.0, 50.0)))
        gradient = z.T @ (p - y) + penalty @ theta
        hessian = (z * (p * (1 - p))[:, None]).T @ z + penalty + 1e-9 * np.eye(len(theta))
        step = np.linalg.solve(hessian, gradient)
        theta -= step
        if np.abs(step).max() < 1e-8:
            break
    return ConfidenceModel(mean, scale, theta[1:], float(theta[0]), tuple(features), info or {})


def read_confidence_model(path: str | Path) -> ConfidenceModel:
    """A confidence model file (written by `ConfidenceModel.save`); errors name the file."""
    path = Path(path)
    try:
        payload = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read the confidence model: {exc}", path) from exc
    if payload.get("format") != FORMAT_NAME or payload.get("format_version") != FORMAT_VERSION:
        raise InputError(
            f"not a YOTO confidence model of version {FORMAT_VERSION} (format {payload.get('format')!r}, "
            f"version {payload.get('format_version')!r}); refit it with `yoto calibrate-confidence`",
            path,
        )
    features = tuple(payload["features"])
    unknown = [name for name in features if name not in FEATURES]
    if unknown:
        raise InputError(f"the confidence model uses features this YOTO does not compute: {unknown}", path)
    return ConfidenceModel(
        np.asarray(payload["mean"], dtype=np.float64),
        np.asarray(payload["scale"], dtype=np.float64),
        np.asarray(payload["weights"], dtype=np.float64),
        float(payload["bias"]),
        features,
        payload.get("info", {}),
    )


@lru_cache(maxsize=8)
def load_confidence_model(path: str | None = None) -> ConfidenceModel:
    """The confidence model at `path`, or the one shipped with YOTO (cached)."""
    return read_confidence_model(path or SHIPPED)
