"""Validation during training, and the candidate-belief temperature fitted on it after training.

Each object has fixed validation sets, one per kind of sample: held-out virtual (ball) patches, held-out
press-shaped patches, and held-out real contacts (`--val-pairs`). They are scored as the localizer scores a
contact (yoto.network.candidates), so the metrics say what the localizer will do.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

from yoto.metrics import summarize
from yoto.network.candidates import candidates_of, fit_temperature, rank_hypotheses, rotated_copies
from yoto.network.inputs import inference_points
from yoto.network.model import ContactLocalizationNet
from yoto.training.config import TrainConfig
from yoto.training.data import ContactSample, ObjectData

CALIBRATION_TOLERANCE_M = 0.010  # a candidate counts as right within this distance (temperature fit)
KINDS = ("virtual", "press", "real")


@dataclass
class EvalSet:
    """Fixed validation inputs of one object and one kind (virtual, press or real)."""

    points: np.ndarray  # (n, N, 3)
    normals: np.ndarray  # (n, N, 3)
    p_object: np.ndarray  # (n, 3)
    block: np.ndarray  # (n,)


def make_eval_set(
    data: ObjectData, kind: str, num_points: int, real: list[ContactSample] | None = None
) -> EvalSet | None:
    """The validation set of one object and kind (`real`: its contacts), None when it has no samples."""
    items: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
    if kind in ("virtual", "press"):
        indices = data.virtual_val if kind == "virtual" else data.press_val
        if len(indices):
            dataset = data.dataset(kind)
            for index in indices:
                points, normals = dataset.patch(int(index))
                items.append((points, normals, dataset.p_object[index], int(dataset.block[index])))
    else:
        items = [(s.points, s.normals, s.p_object, s.block) for s in (real or [])]
    if not items:
        return None
    sampled = [inference_points(points, normals, num_points) for points, normals, _, _ in items]
    return EvalSet(
        points=np.stack([s[0] for s in sampled]),
        normals=np.stack([s[1] for s in sampled]),
        p_object=np.stack([item[2] for item in items]).astype(np.float64),
        block=np.array([item[3] for item in items], dtype=np.int64),
    )


def make_eval_sets(data: list[ObjectData], num_points: int) -> dict[tuple[int, str], EvalSet]:
    """Every object's validation sets, keyed by (object index, kind)."""
    return {
        (i, kind): s
        for i, obj in enumerate(data)
        for kind in KINDS
        if (s := make_eval_set(obj, kind, num_points, obj.real_val)) is not None
    }


@dataclass
class SetEvaluation:
    """Metrics of one validation set, and each sample's candidates for the temperature fit."""

    count: int  # samples
    top1: float  # share whose top coarse block is the true block
    topk: float  # share whose true block is among the K candidate blocks
    error_mm: dict[str, float]  # localization error of the answer (yoto.metrics.summarize)
    within_5mm: float  # share of answers within 5 mm
    best_of_candidates_error_mm: dict[str, float]  # error of the best returned candidate
    scores: list[np.ndarray]  # per sample, the returned candidates' scores
    correct: list[np.ndarray]  # per sample, which of them lie within CALIBRATION_TOLERANCE_M of the truth

    def metrics(self) -> dict[str, Any]:
        """The record for the log: every field but the per-sample candidates."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("scores", "correct")}


def evaluate_set(
    net: ContactLocalizationNet,
    eval_set: EvalSet,
    block_tensors: dict[str, torch.Tensor],
    block_features: torch.Tensor,
    config: TrainConfig,
    rotations: int | None = None,
) -> SetEvaluation:
    """Score one validation set as the localizer would (`rotations`: default config.test_rotations)."""
    rankings = []
    rotations = max(1, rotations if rotations is not None else config.test_rotations)
    chunk = max(1, 256 // rotations)
    with torch.no_grad():
        for start in range(0, len(eval_set.points), chunk):
            points, normals = eval_set.points[start : start + chunk], eval_set.normals[start : start + chunk]
            if rotations > 1:
                copies = [rotated_copies(p, n, rotations) for p, n in zip(points, normals, strict=True)]
                points = np.concatenate([c[0] for c in copies])
                normals = np.concatenate([c[1] for c in copies])
            device = block_features.device
            features = net.encode(torch.from_numpy(points).to(device), torch.from_numpy(normals).to(device))
            features = features.reshape(-1, rotations, features.shape[-1])
            rankings.append(rank_hypotheses(net, features, block_features, block_tensors, config.hypotheses))
    ranking = {key: np.concatenate([r[key] for r in rankings]) for key in rankings[0]}
    k = min(config.network.candidates, ranking["logits"].shape[1])
    order = np.argsort(-ranking["logits"], axis=1)
    top1 = order[:, 0] == eval_set.block
    topk = (order[:, :k] == eval_set.block[:, None]).any(axis=1)
    answer_errors, best_errors, score_lists, correct_lists = [], [], [], []
    for i in range(len(eval_set.block)):
        candidates = candidates_of(ranking, i, 1.0, config.merge_radius_m)
        errors = np.array([np.linalg.norm(c.p_object - eval_set.p_object[i]) for c in candidates])
        answer_errors.append(errors[0])
        best_errors.append(errors.min())
        score_lists.append(np.array([c.score for c in candidates]))
        correct_lists.append(errors <= CALIBRATION_TOLERANCE_M)
    answer_mm = 1000.0 * np.array(answer_errors)
    return SetEvaluation(
        count=len(eval_set.block),
        top1=float(top1.mean()),
        topk=float(topk.mean()),
        error_mm=summarize(answer_mm),
        within_5mm=float((answer_mm <= 5.0).mean()),
        best_of_candidates_error_mm=summarize(1000.0 * np.array(best_errors)),
        scores=score_lists,
        correct=correct_lists,
    )


def pooled(results: list[SetEvaluation]) -> dict[str, float]:
    """Sample-weighted mean of per-object metrics (errors pooled by their means)."""
    total = sum(r.count for r in results)
    out: dict[str, float] = {"count": total}
    for key in ("top1", "topk", "within_5mm"):
        out[key] = sum(getattr(r, key) * r.count for r in results) / total
    out["error_mean_mm"] = sum(r.error_mm["mean"] * r.count for r in results) / total
    return out


def validate(
    net: ContactLocalizationNet,
    data: list[ObjectData],
    block_tensors: list[dict[str, torch.Tensor]],
    eval_sets: dict[tuple[int, str], EvalSet],
    config: TrainConfig,
) -> dict[str, Any]:
    """The epoch's validation record: val_{kind}_{object} metrics, and val_{kind}_{metric} pooled over objects."""
    net.eval()
    record: dict[str, Any] = {}
    per_kind: dict[str, list[SetEvaluation]] = {kind: [] for kind in KINDS}
    with torch.no_grad():
        features = [net.encode(b["block_points"], b["block_normals"], b["block_knn"]) for b in block_tensors]
        for (obj_index, kind), eval_set in eval_sets.items():
            result = evaluate_set(net, eval_set, block_tensors[obj_index], features[obj_index], config)
            record[f"val_{kind}_{data[obj_index].name}"] = result.metrics()
            per_kind[kind].append(result)
    for kind, results in per_kind.items():
        if results:
            for key, value in pooled(results).items():
                record[f"val_{kind}_{key}"] = value
    net.train()
    return record


def calibrate(
    net: ContactLocalizationNet,
    block_tensors: list[dict[str, torch.Tensor]],
    eval_sets: dict[tuple[int, str], EvalSet],
    config: TrainConfig,
) -> float:
    """Fit the candidate-belief temperature on the real validation contacts, or the virtual ones if none."""
    kind = "real" if any(k == "real" for _, k in eval_sets) else "virtual"
    scores: list[np.ndarray] = []
    correct: list[np.ndarray] = []
    net.eval()
    with torch.no_grad():
        for (obj_index, set_kind), eval_set in eval_sets.items():
            if set_kind != kind:
                continue
            b = block_tensors[obj_index]
            features = net.encode(b["block_points"], b["block_normals"], b["block_knn"])
            result = evaluate_set(net, eval_set, b, features, config)
            scores += result.scores
            correct += result.correct
    return fit_temperature(scores, correct)
