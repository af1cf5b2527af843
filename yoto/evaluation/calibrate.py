"""Fitting the pose stage's confidence (`yoto calibrate-confidence`): simulated contacts of many objects in, the
logistic model's parameters out, checked on objects it never saw.

1. For each object (procedural shapes, built-in objects, meshes), N simulated dual contacts under the standard
   condition (1 mm / 1 deg of calibration error per sensor), localized by the matched filter and run through the
   pose stage; each pair gives the confidence features of its result and whether the pose is right (5 mm, 5 deg,
   modulo symmetry). Rows are cached per object, so an interrupted run resumes.
2. A logistic regression is fitted on the `fit` objects only.
3. On the `held_out` objects: the expected calibration error, the area under the ROC curve, and the share of
   pairs confident at the threshold where 99% of confident poses are right (that threshold chosen on the fit
   objects, as a user would).
The parameters are written as JSON (`yoto/pose/confidence.json` is the shipped file); the report beside them.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from yoto import __version__
from yoto.errors import YotoError
from yoto.evaluation.bench import (
    RIGHT_DEG,
    RIGHT_MM,
    BenchConfig,
    reliability,
    resolve_object,
    simulate_benchmark_pairs,
    symmetric_errors,
    trusted_threshold,
)
from yoto.io import read_json, write_json_atomic, write_text_atomic
from yoto.objects.model import ObjectModel
from yoto.pose.confidence import FEATURES, ConfidenceModel, fit_logistic
from yoto.pose.hypotheses import pose_distances
from yoto.pose.pipeline import PoseConfig, PoseEstimate, localize_contacts, pose_from_candidates
from yoto.provenance import git_commit, run_info

log = logging.getLogger("yoto")


@dataclass(frozen=True)
class CalibrationConfig:
    """How the confidence is fitted."""

    pairs_per_object: int = 40  # simulated dual contacts per object
    seed: int = 11  # simulation seed (not the benchmark's 7)
    sensor_noise_mm: float = 1.0  # the standard condition: calibration error of each sensor, position ...
    sensor_noise_deg: float = 1.0  # ... and orientation
    method: str = "match"  # the localizer
    l2: float = 0.001  # ridge penalty of the logistic regression (per pair, on standardised features; chosen by
    # leaving one object out at a time, docs/pose.md)
    features: tuple[str, ...] = FEATURES  # the features the model uses (rows keep them all)


FIT_ONLY = ("l2", "features")  # settings of the fit alone: rows do not depend on them


@dataclass
class Rows:
    """Confidence features and outcomes of one object's pairs."""

    object_name: str
    features: list[list[float]]  # per pair, in FEATURES order
    right: list[bool]
    confidence: list[float]  # the confidence the pose stage reported when the rows were collected
    hypotheses: list[list[list[float]]] = field(default_factory=list)  # per pair, per reported hypothesis:
    # probability, log-likelihood, distance from the first (mm, deg modulo symmetry), whether it is right; for
    # studying new features on the same rows without simulating them again


def rows_key(config: CalibrationConfig, fingerprint: str, localizer: object, pose_config: PoseConfig) -> str:
    """The cache key of an object's rows. Rows describe the localizer and the pose stage that made them: their
    settings (the localizer's dataclass configs, the pose stage's config) are part of the key, so a changed default
    (a cut in the localizer, say) never reuses rows made by the old one. So are YOTO's version and commit, as for
    `yoto bench`'s cache: a mended bug behind unchanged settings computes the rows again."""
    localizer_settings = [repr(value) for value in vars(localizer).values() if is_dataclass(value)]
    code = [__version__, git_commit()]
    simulated = {key: value for key, value in asdict(config).items() if key not in FIT_ONLY}
    settings = [simulated, fingerprint, FEATURES, localizer_settings, repr(pose_config), code]
    return hashlib.sha256(json.dumps(settings).encode()).hexdigest()[:12]


def collect_rows(spec: str, config: CalibrationConfig, cache_dir: Path, workspace: str | Path | None) -> Rows:
    """The rows of one object (cached in `cache_dir`)."""
    from yoto.localize import make_localizer

    model = resolve_object(spec, workspace)
    localizer = make_localizer(config.method)
    bench = BenchConfig(
        num_pairs=config.pairs_per_object,
        seed=config.seed,
        sensor_noise_mm=config.sensor_noise_mm,
        sensor_noise_deg=config.sensor_noise_deg,
        retouch=False,
    )
    pose_config = bench.pose_config("full")
    cache = cache_dir / f"{model.name}__{rows_key(config, model.fingerprint, localizer, pose_config)}.json"
    if cache.exists():
        return Rows(**read_json(cache))
    pairs = simulate_benchmark_pairs(model, bench)
    rows = Rows(model.name, [], [], [])
    for simulated in tqdm(pairs, desc=f"{model.name}: pose features", unit="pair", leave=False):
        pair = simulated.pair
        try:
            candidates, world, _ = localize_contacts(pair, model, localizer)
            estimate = pose_from_candidates(pair, model, candidates, world, pose_config, config.method)
        except YotoError as exc:
            log.warning("%s pair %d: %s", model.name, simulated.index, exc)
            continue
        if not estimate.features:
            continue  # the closed-form fallback: no verified hypothesis
        errors = symmetric_errors(model, estimate.T_world_mesh, pair.T_world_mesh_true)
        rows.features.append([estimate.features[name] for name in FEATURES])
        rows.right.append(bool(errors["translation_mm"] < RIGHT_MM and errors["rotation_deg"] < RIGHT_DEG))
        rows.confidence.append(float(estimate.confidence))
        rows.hypotheses.append(hypothesis_rows(model, estimate, pair.T_world_mesh_true))
    write_json_atomic(cache, asdict(rows))
    return rows


def hypothesis_rows(model: ObjectModel, estimate: PoseEstimate, T_world_mesh_true: np.ndarray) -> list[list[float]]:
    """Per reported hypothesis: probability, log-likelihood, translation (mm) and rotation (deg, modulo symmetry)
    from the first, and whether it is right (1.0) or not (0.0)."""
    poses = estimate.hypotheses.T_world_object
    translation, rotation = pose_distances(poses, poses[0], model.symmetry)
    truth_translation, truth_rotation = pose_distances(poses, T_world_mesh_true @ model.T_mesh_object, model.symmetry)
    right = (1000.0 * truth_translation < RIGHT_MM) & (np.degrees(truth_rotation) < RIGHT_DEG)
    return np.column_stack(
        [
            estimate.hypotheses.probability,
            estimate.hypotheses.log_likelihood,
            1000.0 * translation,
            np.degrees(rotation),
            right.astype(np.float64),
        ]
    ).tolist()


def feature_matrix(rows: list[Rows], features: tuple[str, ...]) -> np.ndarray:
    """(N, F) the rows' values of `features` (rows keep FEATURES, in that order)."""
    columns = [FEATURES.index(name) for name in features]
    matrix = np.array([f for r in rows for f in r.features], dtype=np.float64).reshape(-1, len(FEATURES))
    return matrix[:, columns]


def roc_auc(score: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve (the probability that a right pose scores above a wrong one; ties count half)."""
    score, positive = np.asarray(score, dtype=np.float64), np.asarray(positive, dtype=bool)
    if positive.all() or not positive.any():
        return float("nan")
    ranks = np.empty(len(score))
    order = np.argsort(score, kind="stable")
    ranks[order] = np.arange(1, len(score) + 1)
    for value in np.unique(score):  # average ranks of ties
        tied = score == value
        ranks[tied] = ranks[tied].mean()
    count = positive.sum()
    return float((ranks[positive].sum() - count * (count + 1) / 2) / (count * (len(score) - count)))


def summary(model: ConfidenceModel, rows: list[Rows], threshold: float | None = None) -> dict[str, Any]:
    """How the model does on a set of objects: ECE, AUC, and the share confident at `threshold` (default: the
    99%-right threshold chosen on these rows themselves)."""
    right = np.array([v for r in rows for v in r.right], dtype=bool)
    confidence = model.predict_many(feature_matrix(rows, model.features))
    trusted = trusted_threshold(confidence, right)
    chosen = trusted["threshold"] if threshold is None else threshold
    confident = confidence >= chosen
    return {
        "pairs": int(len(right)),
        "right": float(right.mean()) if len(right) else float("nan"),
        "ece": reliability(confidence, right)["ece"],
        "auc": roc_auc(confidence, right),
        "threshold": float(chosen),
        "confident": float(confident.mean()) if len(right) else float("nan"),
        "precision": float(right[confident].mean()) if confident.any() else float("nan"),
        "objects": {
            r.object_name: {
                "pairs": len(r.right),
                "right": float(np.mean(r.right)) if r.right else float("nan"),
                "confident": float(np.mean(model.predict_many(feature_matrix([r], model.features)) >= chosen))
                if r.right
                else 0.0,
            }
            for r in rows
        },
    }


def calibrate_confidence(
    fit_objects: list[str],
    held_out: list[str],
    config: CalibrationConfig = CalibrationConfig(),
    out: str | Path = "confidence.json",
    work_dir: str | Path = "calibration_out",
    workspace: str | Path | None = None,
) -> dict[str, Any]:
    """Collect rows, fit on `fit_objects`, check on `held_out`; write the model to `out` and a report next to it."""
    started = time.perf_counter()
    cache_dir = Path(work_dir) / "rows"
    fit_rows = [collect_rows(spec, config, cache_dir, workspace) for spec in fit_objects]
    held_rows = [collect_rows(spec, config, cache_dir, workspace) for spec in held_out]
    features = feature_matrix(fit_rows, config.features)
    right = np.array([v for r in fit_rows for v in r.right], dtype=bool)
    info = {
        "fitted_on": [r.object_name for r in fit_rows],
        "held_out": [r.object_name for r in held_rows],
        "pairs": int(len(right)),
        "condition": f"{config.sensor_noise_mm} mm / {config.sensor_noise_deg} deg calibration error per sensor",
        "config": asdict(config),
        **{key: value for key, value in run_info().items() if key in ("commit", "yoto", "device")},
    }
    model = fit_logistic(features, right, l2=config.l2, info=info, features=config.features)
    fit_summary = summary(model, fit_rows)
    report = {
        "fit": fit_summary,
        "held_out": summary(model, held_rows, fit_summary["threshold"]) if held_rows else None,
        "weights": dict(zip(model.features, model.weights.tolist())),
        "wall_time_s": time.perf_counter() - started,
    }
    model.info["report"] = {key: report[key] for key in ("fit", "held_out")}
    model.save(out)
    write_json_atomic(Path(work_dir) / "calibration.json", report)
    write_text_atomic(Path(work_dir) / "calibration.md", format_report(report, out))
    return report


def format_report(report: dict[str, Any], out: str | Path) -> str:
    lines = ["# Confidence calibration", "", f"Model written to `{out}`.", ""]
    lines += ["| set | pairs | right | ECE | AUC | threshold (99% right on fit) | confident | precision |"]
    lines += ["|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in ("fit", "held_out"):
        s = report.get(name)
        if s:
            lines.append(
                f"| {name} | {s['pairs']} | {100 * s['right']:.0f}% | {s['ece']:.3f} | {s['auc']:.3f} "
                f"| {s['threshold']:.3g} | {100 * s['confident']:.0f}% | {100 * s['precision']:.1f}% |"
            )
    for name in ("fit", "held_out"):
        s = report.get(name)
        if s:
            lines += ["", f"## {name}: per object (right / confident at the threshold)", ""]
            lines += [
                f"- {obj}: {v['pairs']} pairs, {100 * v['right']:.0f}% right, {100 * v['confident']:.0f}% confident"
                for obj, v in s["objects"].items()
            ]
    lines += ["", "## Weights (standardised features)", ""]
    lines += [f"- {name}: {value:+.3f}" for name, value in report["weights"].items()]
    return "\n".join(lines) + "\n"
