"""The benchmark (SPEC: "How we measure"): every method on the same simulated contacts, side by side.

For each object: N simulated dual contacts (fixed seed; by default under the standard condition, 1 mm / 1 deg of
calibration error per sensor), then for each method (oracle, ICP, matched filter, YOTO variants) localization
error, pose error (modulo the object's symmetries; ADD-S and BOP's MSSD beside it) and latency, measured in one
process on the same contacts, and what a robot needs to trust a pose:
- the share of right poses (within 5 mm and 5 deg), of pairs whose truth is among the hypotheses, of ambiguous
  pairs, and of right poses after the suggested re-touch (simulated: one sensor moves there, the other stays);
- why a truth is not among the hypotheses: the true pose, refined, explains the contacts better than the first
  hypothesis (the verification never reached it) or worse (the score prefers a wrong pose);
- the calibration of `confidence`: a reliability diagram, the expected calibration error, and the share of pairs
  reported confident at the threshold where 99% of confident poses are right.
Results are cached per (object, method) so an interrupted run resumes; the report is written as Markdown for
people and JSON for machines, both stamped with commit, versions, device and seed, plus two figures.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from yoto import __version__
from yoto.contacts import SIDES, TactileContact
from yoto.errors import InputError, YotoError
from yoto.evaluation.shapes import is_procedural, procedural_mesh
from yoto.geometry import transform_points
from yoto.io import read_json, write_bytes_atomic, write_json_atomic, write_text_atomic
from yoto.localize.helper import LocalizerProcess
from yoto.metrics import pose_errors, summarize
from yoto.objects.build import build_object, load_object_model
from yoto.objects.mesh import MESH_SUFFIXES
from yoto.objects.model import ObjectModel, build_object_model
from yoto.pose.executor import prepare_pose_helper
from yoto.pose.hypotheses import pose_distances
from yoto.pose.pipeline import (
    PAPER,
    PoseConfig,
    fuse_next_touch,
    localize_contacts,
    pose_from_candidates,
    refined_log_likelihood,
    true_corrections,
)
from yoto.pose.refine import CalibrationPrior
from yoto.provenance import git_commit, run_info
from yoto.workspace import object_model_path

if TYPE_CHECKING:
    from yoto.sensor.optical import ImagePath

RIGHT_MM, RIGHT_DEG = 5.0, 5.0  # a pose is right within 5 mm and 5 deg (SPEC)
TRUSTED_PRECISION = 0.99  # the benchmark's confidence threshold: 99% of the poses reported confident are right

log = logging.getLogger("yoto")


def row_label(label: str, stage: str) -> str:
    """Table row of a method under a pose stage: the full stage keeps the method's label."""
    return label if stage == "full" else f"{label}, paper pose stage"


@dataclass(frozen=True)
class MethodSpec:
    """One row group of the benchmark: a localizer, and optionally the object models it localizes on."""

    label: str  # row name, e.g. "YOTO fine-tuned"
    method: str  # "oracle", "icp", "match" or "yoto"
    checkpoint: str | None = None  # for "yoto"
    model_suffix: str = ""  # localize on object model NAME+suffix (e.g. "_scan": trained on a scan-like mesh)
    via_images: bool = False  # the same pairs, each cloud reconstructed from its rendered GelSight image


@dataclass(frozen=True)
class BenchConfig:
    """What the benchmark runs."""

    num_pairs: int = 100  # dual contacts per object (SPEC: >= 100 for reported figures)
    seed: int = 7  # evaluation seed; training pairs must use other seeds
    warmup_pairs: int = 2  # pairs whose latency is excluded (first calls: caches, lazy imports)
    sensor_noise_mm: float = 1.0  # mean calibration error of each reported sensor position (standard: 1 mm)
    sensor_noise_deg: float = 1.0  # mean calibration error of each reported sensor orientation (standard: 1 deg)
    prior_mm: float = 1.0  # the pose stage's calibration-error prior, position ...
    prior_deg: float = 1.0  # ... and orientation
    search: str = "auto"  # the pose stage's joint search: "auto", "always" or "never"
    retouch: bool = True  # simulate the suggested re-touch of ambiguous pairs and fuse it
    pose_stages: tuple[str, ...] = ("full", "paper")  # pose stages to report for every method (same localizations)
    image_calibration: str | None = None  # rows "via images": a calibration file, "shading[:SEED]" or
    # "table:FOLDER" (image_route)
    image_variation: float = 0.0  # how much each rendered image's lighting, noise and gel stray from the sensor's
    both_cores: bool = False  # localize each pair's right contact in a helper process while this one localizes
    # the left, and compute half of the pose stage's batches there (the same poses, bitwise): a pose's latency is
    # then both contacts at once plus the pose stage, as a robot with two free cores waits for it

    def pose_config(self, stage: str) -> PoseConfig:
        if stage == "paper":
            return PAPER
        prior = CalibrationPrior(self.prior_mm / 1000.0, float(np.radians(self.prior_deg)))
        return PoseConfig(calibration=prior, search=self.search, suggest_next_touch=self.retouch)


@dataclass
class MethodResult:
    """Per-pair measurements of one method under one pose stage on one object."""

    label: str
    object_name: str
    localization_top1_mm: list[float] = field(default_factory=list)  # per contact, localizer's first candidate
    localization_chosen_mm: list[float] = field(default_factory=list)  # per contact, under the chosen pose
    translation_mm: list[float] = field(default_factory=list)  # per pair, object centroid
    rotation_deg: list[float] = field(default_factory=list)  # per pair, modulo the object's symmetries
    add_s_mm: list[float] = field(default_factory=list)
    mssd_mm: list[float] = field(default_factory=list)  # BOP's maximum symmetry-aware surface distance
    confidence: list[float] = field(default_factory=list)
    ambiguous: list[bool] = field(default_factory=list)
    hypotheses: list[int] = field(default_factory=list)  # reported hypotheses per pair
    truth_in_hypotheses: list[bool] = field(default_factory=list)  # a hypothesis within 5 mm and 5 deg
    missed_truth_better: list[bool] = field(default_factory=list)  # per pair whose truth is not among them: the
    # truth, refined, explains the contacts better than the first hypothesis (the verification never reached it)
    retouch: list[str] = field(default_factory=list)  # "-" (not ambiguous / no suggestion), "ok", or the rejection
    right_after_retouch: list[bool] = field(default_factory=list)  # the pose right after the re-touch (or without)
    right_after_two: list[bool] = field(default_factory=list)  # ... after a second re-touch where still ambiguous
    contact_latency_ms: list[float] = field(default_factory=list)  # per contact, warm-up excluded
    pose_latency_ms: list[float] = field(default_factory=list)  # per pair: both localizations (at once with
    # `both_cores`) + the pose stage
    pose_stage_ms: list[float] = field(default_factory=list)  # per pair: the pose stage alone (no next_touch)
    next_touch_ms: list[float] = field(default_factory=list)  # per ambiguous pair
    failures: int = 0

    @property
    def right(self) -> np.ndarray:
        return (np.asarray(self.translation_mm) < RIGHT_MM) & (np.asarray(self.rotation_deg) < RIGHT_DEG)


def resolve_object(spec: str, workspace: str | Path | None) -> ObjectModel:
    """An object given as a workspace/built-in name, a model file, a mesh file (built into the workspace), or a
    procedural shape's name (`proc_<family>_<index>`, built into the workspace on first use)."""
    path = Path(spec)
    if path.suffix.lower() in MESH_SUFFIXES:
        if not path.is_file():
            raise InputError("mesh file not found", path)
        return load_object_model(build_object(path, path.stem, workspace=workspace))
    if is_procedural(spec) and not object_model_path(spec, workspace).exists():
        model = build_object_model(procedural_mesh(spec), spec, source={"procedural": spec})
        model.save(object_model_path(spec, workspace))
        return model
    return load_object_model(spec, workspace)


def _make_localizer(spec: MethodSpec):
    from yoto.localize import make_localizer

    return make_localizer(spec.method, spec.checkpoint)


def symmetric_errors(model: ObjectModel, T_world_mesh_estimate: np.ndarray, T_world_mesh_true: np.ndarray) -> dict:
    """Pose errors modulo the object's symmetries: translation (centroid, mm), rotation (deg), ADD-S and MSSD (mm).

    MSSD (BOP): the largest distance of a mesh vertex between the two poses, minimised over the symmetries (a
    continuous axis is discretised every 5 degrees).
    """
    T_estimate = T_world_mesh_estimate @ model.T_mesh_object
    T_true = T_world_mesh_true @ model.T_mesh_object
    translation, rotation = pose_distances(T_estimate[None], T_true, model.symmetry)
    vertices_object = transform_points(model.T_object_mesh, model.mesh_vertices_mesh)
    vertices_object = vertices_object[:: max(1, len(vertices_object) // 3000)]
    estimate = transform_points(T_estimate, vertices_object)
    symmetric = np.einsum("gij,vj->gvi", model.symmetry.equivalent_rotations(), vertices_object)
    truth = np.einsum("ij,gvj->gvi", T_true[:3, :3], symmetric) + T_true[:3, 3]
    mssd = float(np.min(np.max(np.linalg.norm(truth - estimate[None], axis=2), axis=1)))
    add_s = pose_errors(T_world_mesh_estimate, T_world_mesh_true, model)["add_s_mm"]
    return {
        "translation_mm": 1000.0 * float(translation[0]),
        "rotation_deg": float(np.degrees(rotation[0])),
        "add_s_mm": add_s,
        "mssd_mm": 1000.0 * mssd,
    }


def evaluate_method(
    spec: MethodSpec,
    model: ObjectModel,
    simulated_pairs: list,
    simulator,
    config: BenchConfig,
    workspace,
    image_path: ImagePath | None = None,
) -> dict[str, MethodResult]:
    """Run one method over the simulated pairs of one object: localize once, then each pose stage (with
    `config.both_cores`, in this process and a helper). `simulator` presses the suggested re-touches (None: none),
    through `image_path`'s GelSight images where the pairs came through them."""
    localizer = _make_localizer(spec)
    localize_model = load_object_model(model.name + spec.model_suffix, workspace) if spec.model_suffix else model
    with LocalizerProcess(localizer) if config.both_cores else nullcontext() as helper:
        if helper is not None:  # the helper's per-model data and surface field, before the first pair
            helper.prepare_object(localize_model)
            prepare_pose_helper(helper, localize_model, config.pose_config("full").field_config).result()
        return _evaluate_pairs(
            spec, model, localize_model, localizer, simulated_pairs, simulator, config, helper, image_path
        )


def _evaluate_pairs(
    spec: MethodSpec,
    model: ObjectModel,
    localize_model: ObjectModel,
    localizer,
    simulated_pairs: list,
    simulator,
    config: BenchConfig,
    helper: LocalizerProcess | None,
    image_path: ImagePath | None,
) -> dict[str, MethodResult]:
    """`evaluate_method`'s pairs, with its localizer and its helper (or none)."""
    results = {
        stage: MethodResult(label=row_label(spec.label, stage), object_name=model.name) for stage in config.pose_stages
    }
    for number, simulated in enumerate(tqdm(simulated_pairs, desc=f"{model.name}: {spec.label}", unit="pair")):
        pair = simulated.pair
        for stage, result in results.items():
            # Pairs through images search with the image contacts' budget (`PoseConfig.for_pair`); the pose stage
            # (first estimate and re-touch) applies it by itself, so this only keeps the recorded config the one run.
            pose_config = config.pose_config(stage).for_pair(pair)
            try:
                if stage == config.pose_stages[0]:
                    candidates, world, latency = localize_contacts(pair, localize_model, localizer, helper)
                estimate = pose_from_candidates(
                    pair, localize_model, candidates, world, pose_config, spec.method, helper=helper
                )
            except YotoError as exc:
                log.warning("%s pair %d: %s failed: %s", model.name, simulated.index, result.label, exc)
                result.failures += 1
                continue
            # Localization error in the mesh file's frame, which every object model of this object shares.
            for side in SIDES:
                truth_mesh = pair.p_mesh_true[side]
                for store, estimate_contact in (
                    (result.localization_top1_mm, estimate.candidates[side][0]),
                    (result.localization_chosen_mm, estimate.contacts[side]),
                ):
                    p_mesh = transform_points(localize_model.T_mesh_object, estimate_contact.p_object)
                    store.append(1000.0 * float(np.linalg.norm(p_mesh - truth_mesh)))
            errors = symmetric_errors(model, estimate.T_world_mesh, pair.T_world_mesh_true)
            for key in ("translation_mm", "rotation_deg", "add_s_mm", "mssd_mm"):
                getattr(result, key).append(errors[key])
            right = errors["translation_mm"] < RIGHT_MM and errors["rotation_deg"] < RIGHT_DEG
            result.confidence.append(float(estimate.confidence))
            result.ambiguous.append(bool(estimate.ambiguous))
            result.hypotheses.append(len(estimate.hypotheses))
            T_true = pair.T_world_mesh_true @ model.T_mesh_object
            T_hypotheses = estimate.hypotheses_mesh(localize_model) @ model.T_mesh_object
            translation, rotation = pose_distances(T_hypotheses, T_true, model.symmetry)
            result.truth_in_hypotheses.append(
                bool(np.any((translation < RIGHT_MM / 1000.0) & (rotation < np.radians(RIGHT_DEG))))
            )
            if pose_config.verify and not result.truth_in_hypotheses[-1]:
                T_true_localize = pair.T_world_mesh_true @ localize_model.T_mesh_object
                truth = refined_log_likelihood(
                    pair,
                    localize_model,
                    T_true_localize,
                    pose_config,
                    true_corrections(pair, simulated.T_world_sensor_true),
                )
                result.missed_truth_better.append(truth > float(estimate.hypotheses.log_likelihood[0]))
            status, after = "-", [right, right]
            if estimate.next_touch is not None and simulator is not None:
                status, after = _retouch(
                    simulator, simulated, estimate, localize_model, model, pose_config, localizer, image_path
                )
            result.retouch.append(status)
            result.right_after_retouch.append(bool(after[0]))
            result.right_after_two.append(bool(after[1]))
            if number >= config.warmup_pairs:
                result.contact_latency_ms += [latency["localize_left"], latency["localize_right"]]
                result.pose_stage_ms.append(estimate.latency_ms["pose"])
                both = (
                    latency["localize_left"] + latency["localize_right"] if helper is None else latency["localize_pair"]
                )
                result.pose_latency_ms.append(both + result.pose_stage_ms[-1])
                if "next_touch" in estimate.latency_ms:
                    result.next_touch_ms.append(estimate.latency_ms["next_touch"])
    return results


def _retouch(
    simulator, simulated, estimate, localize_model, model, pose_config, localizer, image_path, touches: int = 2
) -> tuple[str, list[bool]]:
    """Simulate the suggested re-touches (up to `touches`, the next one only while the fused pose is still
    ambiguous and suggests one), fuse each, and say whether the pose is right after each: the first touch's outcome
    ("ok" or the simulator's rejection) and, per touch, right or not (a failed or unsuggested touch keeps the pose
    as it was)."""
    from yoto.evaluation.retouch import simulate_retouch

    def is_right(current) -> bool:
        errors = symmetric_errors(model, current.T_world_mesh, simulated.pair.T_world_mesh_true)
        return errors["translation_mm"] < RIGHT_MM and errors["rotation_deg"] < RIGHT_DEG

    earlier: tuple[tuple[TactileContact, str], ...] = ()
    current, status, right = estimate, "-", []
    for number in range(touches):
        suggestion = current.next_touch
        outcome = None if suggestion is None else simulate_retouch(simulator, simulated, suggestion, number, image_path)
        if number == 0 and outcome is not None:
            status = "ok" if outcome.touch is not None else str(outcome.rejection)
        if outcome is not None and outcome.touch is not None:
            current = fuse_next_touch(
                simulated.pair,
                localize_model,
                current,
                outcome.touch,
                suggestion.sensor,
                pose_config,
                localizer=localizer,
                earlier=earlier,
            )
            earlier = (*earlier, (outcome.touch, suggestion.sensor))
        right.append(is_right(current))
    return status, right


def benchmark_simulator(model: ObjectModel, config: BenchConfig):
    """The contact simulator of the benchmark's condition (it also presses the simulated re-touches)."""
    from yoto.simulate.scenarios import PairSimulator, ScenarioConfig

    scenario = ScenarioConfig(
        calibration_translation_m=config.sensor_noise_mm / 1000.0,
        calibration_rotation_rad=np.radians(config.sensor_noise_deg),
    )
    return PairSimulator(model, scenario)


def simulate_benchmark_pairs(model: ObjectModel, config: BenchConfig, simulator=None) -> list:
    """The object's N simulated pairs under the benchmark's condition (with `simulator`, that one's)."""
    simulator = simulator or benchmark_simulator(model, config)
    return [
        simulator.pair(config.seed, index)
        for index in tqdm(range(config.num_pairs), desc=f"{model.name}: simulating", unit="pair", leave=False)
    ]


def pairs_via_images(pairs: list, config: BenchConfig, to_cloud: ImagePath | None = None) -> list:
    """The same simulated pairs (same poses, same truth), each tactile cloud replaced by the reconstruction of the
    GelSight image its noise-free gel height map renders to (`to_cloud`, else the config's
    `yoto.sensor.optical.image_route`), with the reconstruction's depth-scale prior
    (`TactileContact.depth_scale_sigma`); a frame the reconstruction finds no contact in gives an empty cloud, which
    the methods count as a failure."""
    from dataclasses import replace

    from yoto.sensor.optical import image_route

    assert config.image_calibration is not None
    to_cloud = to_cloud or image_route(config.image_calibration, config.image_variation)
    out = []
    for simulated in tqdm(pairs, desc="rendering and reconstructing images", unit="pair", leave=False):
        sides = {}
        for side in SIDES:
            result = to_cloud.reconstruction(simulated.height_maps[side])
            points, sigma = (
                (np.zeros((0, 3)), 0.0) if result is None else (result.points_sensor, result.depth_scale_sigma)
            )
            sides[side] = replace(simulated.pair.contact(side), points_sensor=points, depth_scale_sigma=sigma)
        out.append(replace(simulated, pair=replace(simulated.pair, **sides)))
    return out


def run_benchmark(
    objects: list[str],
    methods: list[MethodSpec],
    config: BenchConfig = BenchConfig(),
    out_dir: str | Path = "bench_out",
    workspace: str | Path | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Run every method on every object; write bench.md, bench.json, bench.png and reliability.png into `out_dir`."""
    out_dir = Path(out_dir)
    partial_dir = out_dir / "partial"
    labels = [m.label for m in methods]
    if len(set(labels)) != len(labels):
        raise InputError(f"benchmark method labels must be unique, got {labels}")
    run_key = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode()).hexdigest()[:12]
    # Cached results are reused only by the code that made them: another version or commit (a changed default,
    # a mended bug) computes them again rather than mixing old rows into a new report.
    code = {"yoto": __version__, "commit": git_commit()}
    started = time.perf_counter()
    results: dict[str, dict[str, MethodResult]] = {}
    image_path: ImagePath | None = None  # the rows via images' renderer and reconstruction, made once
    for spec_string in objects:
        model = resolve_object(spec_string, workspace)
        results[model.name] = {}
        pairs, simulator = None, None
        image_pairs: list | None = None
        for spec in methods:
            cache = partial_dir / f"{model.name}__{spec.label.replace(' ', '_')}__{run_key}.json"
            fingerprint = {"model": model.fingerprint, "spec": asdict(spec), "code": code}
            if cache.exists() and not overwrite:
                stored = read_json(cache)
                if stored.get("fingerprint") == fingerprint:
                    for stage_result in stored["results"]:
                        results[model.name][stage_result["label"]] = MethodResult(**stage_result)
                    continue
            if pairs is None:
                simulator = benchmark_simulator(model, config)
                pairs = simulate_benchmark_pairs(model, config, simulator)
            if spec.via_images and image_path is None:
                from yoto.sensor.optical import image_route

                assert config.image_calibration is not None
                image_path = image_route(config.image_calibration, config.image_variation)
            if spec.via_images and image_pairs is None:
                image_pairs = pairs_via_images(pairs, config, image_path)
            method_pairs = image_pairs if spec.via_images and image_pairs is not None else pairs
            # Rows via images are re-touched through images too (the re-touch's press rendered and reconstructed)
            by_stage = evaluate_method(
                spec,
                model,
                method_pairs,
                simulator if config.retouch else None,
                config,
                workspace,
                image_path if spec.via_images else None,
            )
            write_json_atomic(cache, {"fingerprint": fingerprint, "results": [asdict(r) for r in by_stage.values()]})
            for result in by_stage.values():
                results[model.name][result.label] = result
    rows = rows_of(methods, config)
    report = build_report(results, rows)
    report["run"] = {
        **run_info(),
        "seed": config.seed,
        "config": asdict(config),
        "wall_time_s": time.perf_counter() - started,
    }
    write_json_atomic(out_dir / "bench.json", report)
    write_text_atomic(out_dir / "bench.md", format_markdown(report))
    plot_report(results, rows, out_dir / "bench.png")
    plot_reliability(results, rows, out_dir / "reliability.png")
    return report


# ------------------------------------------------------------------------------------------------ statistics
@dataclass(frozen=True)
class Row:
    """One row of the report: a method under a pose stage."""

    label: str
    method: str
    stage: str


def rows_of(methods: list[MethodSpec], config: BenchConfig) -> list[Row]:
    return [Row(row_label(spec.label, stage), spec.method, stage) for stage in config.pose_stages for spec in methods]


def reliability(confidence: np.ndarray, right: np.ndarray, bins: int = 10) -> dict[str, Any]:
    """Reliability diagram data and expected calibration error (equal-width confidence bins)."""
    confidence, right = np.asarray(confidence, dtype=np.float64), np.asarray(right, dtype=bool)
    edges = np.linspace(0.0, 1.0, bins + 1)
    index = np.clip(np.digitize(confidence, edges[1:-1]), 0, bins - 1)
    table = []
    ece = 0.0
    for b in range(bins):
        members = index == b
        if not members.any():
            continue
        mean_confidence, accuracy = float(confidence[members].mean()), float(right[members].mean())
        ece += members.mean() * abs(mean_confidence - accuracy)
        table.append(
            {
                "low": float(edges[b]),
                "high": float(edges[b + 1]),
                "pairs": int(members.sum()),
                "confidence": mean_confidence,
                "right": accuracy,
            }
        )
    return {"bins": table, "ece": float(ece) if len(confidence) else float("nan")}


def trusted_threshold(confidence: np.ndarray, right: np.ndarray, precision: float = TRUSTED_PRECISION) -> dict:
    """The lowest confidence threshold at which at least `precision` of the poses at or above it are right, and the
    share of pairs it keeps (0 kept when no threshold reaches the precision)."""
    confidence, right = np.asarray(confidence, dtype=np.float64), np.asarray(right, dtype=bool)
    if not len(confidence):
        return {"threshold": float("nan"), "confident": 0.0, "precision": float("nan"), "pairs": 0}
    order = np.argsort(-confidence, kind="stable")
    hits = np.cumsum(right[order])
    kept = np.arange(1, len(order) + 1)
    ok = np.flatnonzero(hits / kept >= precision)
    # Thresholds must not split ties: the last index of each run of equal confidences.
    values = confidence[order]
    ok = ok[(ok == len(order) - 1) | (values[np.minimum(ok + 1, len(order) - 1)] < values[ok])]
    if not len(ok):
        return {"threshold": float("nan"), "confident": 0.0, "precision": float("nan"), "pairs": len(confidence)}
    last = int(ok.max())
    return {
        "threshold": float(values[last]),
        "confident": float(kept[last] / len(order)),
        "precision": float(hits[last] / kept[last]),
        "pairs": len(confidence),
    }


def build_report(results: dict[str, dict[str, MethodResult]], rows: list[Row]) -> dict[str, Any]:
    """Statistics per object and over all objects, per row."""
    report: dict[str, Any] = {"objects": {}, "all": {}}

    def stats(items: list[MethodResult]) -> dict[str, Any]:
        def gather(name: str) -> list:
            return [v for item in items for v in getattr(item, name)]

        right = np.concatenate([item.right for item in items]) if items else np.zeros(0, bool)
        confidence = np.asarray(gather("confidence"))
        ambiguous = np.asarray(gather("ambiguous"), dtype=bool)
        stage = np.asarray(gather("pose_stage_ms"))
        retouch = gather("retouch")
        return {
            "localization_mm": summarize(gather("localization_top1_mm")),
            "localization_chosen_mm": summarize(gather("localization_chosen_mm")),
            "translation_mm": summarize(gather("translation_mm")),
            "rotation_deg": summarize(gather("rotation_deg")),
            "add_s_mm": summarize(gather("add_s_mm")),
            "mssd_mm": summarize(gather("mssd_mm")),
            "right": float(right.mean()) if len(right) else float("nan"),
            "truth_in_hypotheses": float(np.mean(gather("truth_in_hypotheses"))) if len(right) else float("nan"),
            "truth_missed": int(np.sum(~np.asarray(gather("truth_in_hypotheses"), dtype=bool))),
            "truth_missed_not_reached": int(np.sum(gather("missed_truth_better"))),
            "ambiguous": float(ambiguous.mean()) if len(right) else float("nan"),
            "hypotheses_median": float(np.median(gather("hypotheses"))) if len(right) else float("nan"),
            "retouched": float(np.mean([r == "ok" for r in retouch])) if retouch else 0.0,
            "retouch_failed": float(np.mean([r not in ("-", "ok") for r in retouch])) if retouch else 0.0,
            "right_after_retouch": float(np.mean(gather("right_after_retouch"))) if len(right) else float("nan"),
            "right_after_two": float(np.mean(gather("right_after_two"))) if len(right) else float("nan"),
            "reliability": reliability(confidence, right),
            "trusted": trusted_threshold(confidence, right),
            "contact_latency_ms": summarize(gather("contact_latency_ms")),
            "pose_latency_ms": summarize(gather("pose_latency_ms")),
            "pose_stage_ms": summarize(stage),
            "next_touch_ms": summarize(gather("next_touch_ms")),
            "pairs": len(right),
            "failures": sum(item.failures for item in items),
            "right_share": right_share(gather("translation_mm"), gather("rotation_deg"), items),
        }

    for object_name, by_label in results.items():
        report["objects"][object_name] = {label: stats([result]) for label, result in by_label.items()}
    for row in rows:
        report["all"][row.label] = stats(
            [by_label[row.label] for by_label in results.values() if row.label in by_label]
        )
        # Every object at the threshold chosen on all of them: what a user who sets it once would see per object.
        threshold = report["all"][row.label]["trusted"]["threshold"]
        for object_name, by_label in results.items():
            if row.label in by_label:
                result = by_label[row.label]
                confident = np.asarray(result.confidence) >= threshold
                report["objects"][object_name][row.label]["at_common_threshold"] = {
                    "confident": float(confident.mean()) if len(confident) else float("nan"),
                    "precision": float(result.right[confident].mean()) if confident.any() else float("nan"),
                }
    report["methods"] = [asdict(row) for row in rows]
    return report


def right_share(translation_mm: list[float], rotation_deg: list[float], items: list[MethodResult]) -> float:
    """Share of all attempted pairs (failures count as wrong) whose pose is right (SPEC: 5 mm and 5 deg)."""
    attempted = len(translation_mm) + sum(item.failures for item in items)
    right = sum(t < RIGHT_MM and r < RIGHT_DEG for t, r in zip(translation_mm, rotation_deg, strict=True))
    return right / attempted if attempted else float("nan")


# ------------------------------------------------------------------------------------------------ report
def _percent(value: float) -> str:
    return "-" if value != value else f"{100.0 * value:.0f}%"


def format_markdown(report: dict[str, Any]) -> str:
    """The report as Markdown tables (millimetres and degrees)."""
    run = report["run"]
    objects = list(report["objects"])
    labels = [m["label"] for m in report["methods"]]
    full_labels = [m["label"] for m in report["methods"] if m["stage"] == "full"]
    header = "| Method | " + " | ".join(objects) + " | All |"
    rule = "|---|" + "---|" * (len(objects) + 1)
    config = run["config"]
    lines = [
        "# YOTO benchmark",
        "",
        f"commit {run['commit']} | yoto {run['yoto']} | torch {run.get('torch', '-')} "
        f"| open3d {run.get('open3d', '-')} "
        f"| {run['device']} | seed {run['seed']} | {report['all'][labels[0]]['pairs']} pairs | "
        f"sensor calibration error {config['sensor_noise_mm']} mm / {config['sensor_noise_deg']} deg "
        f"(prior {config['prior_mm']} mm / {config['prior_deg']} deg) | search {config['search']}",
        "",
        "A pose is right within 5 mm (object centroid) and 5 deg, modulo the object's symmetries.",
        "",
        "## Contact localization error (mm): mean +- std (median / p90 / max), localizer's top candidate",
        "",
        header,
        rule,
    ]

    def table(row_labels: list[str], cell, key: str | None = None) -> list[str]:
        out = []
        for label in row_labels:
            row = [cell(report["objects"][o][label]) if label in report["objects"][o] else "-" for o in objects]
            out.append(f"| {label} | " + " | ".join(row) + f" | {cell(report['all'][label])} |")
        return out

    def localization(key: str):
        def cell(s: dict[str, Any]) -> str:
            m = s[key]
            return f"{m['mean']:.2f} +- {m['std']:.2f} ({m['median']:.2f} / {m['p90']:.2f} / {m['max']:.1f})"

        return cell

    lines += table(full_labels, localization("localization_mm"))
    lines += [
        "",
        "## Contact localization error through the pose stage (mm): the contact's place on the object under the "
        "chosen pose, mean +- std (median / p90 / max)",
        "",
        header,
        rule,
    ]
    lines += table(full_labels, localization("localization_chosen_mm"))
    lines += [
        "",
        "## Pose error: translation mm / rotation deg, median (mean); ADD-S / MSSD mm median; right",
        "",
        header,
        rule,
    ]

    def pose(s: dict[str, Any]) -> str:
        t, r = s["translation_mm"], s["rotation_deg"]
        fail = f", {s['failures']} failed" if s["failures"] else ""
        return (
            f"{t['median']:.2f} / {r['median']:.2f} ({t['mean']:.1f} / {r['mean']:.1f}); "
            f"{s['add_s_mm']['median']:.2f} / {s['mssd_mm']['median']:.2f}; {_percent(s['right'])}{fail}"
        )

    lines += table(labels, pose)
    lines += [
        "",
        f"## Poses right (within {RIGHT_MM:g} mm and {RIGHT_DEG:g} deg; failures count as wrong)",
        "",
        header,
        rule,
    ]
    lines += table(labels, lambda s: _percent(s["right_share"]))
    lines += [
        "",
        "## Trust: right / truth among hypotheses / ambiguous / right after one suggested re-touch / after two / "
        "confident at the common 99% threshold (its precision)",
        "",
        header,
        rule,
    ]

    def trust(s: dict[str, Any]) -> str:
        common = s.get(
            "at_common_threshold", {"confident": s["trusted"]["confident"], "precision": s["trusted"]["precision"]}
        )
        return (
            f"{_percent(s['right'])} / {_percent(s['truth_in_hypotheses'])} / {_percent(s['ambiguous'])} / "
            f"{_percent(s['right_after_retouch'])} / {_percent(s['right_after_two'])} / "
            f"{_percent(common['confident'])} ({_percent(common['precision'])})"
        )

    lines += table(full_labels, trust)
    lines += [
        "",
        "Truth not among the hypotheses, why: the true pose, refined as a hypothesis would be (its sensor corrections "
        "starting from the true ones), explains the contacts "
        "better than the first hypothesis (the verification never reached it) / worse (the score prefers a wrong "
        "pose: model and contacts disagree there).",
        "",
    ]

    def why(s: dict[str, Any]) -> str:
        better = s["truth_missed_not_reached"]
        return f"{s['truth_missed']} ({better} / {s['truth_missed'] - better})"

    for label in full_labels:
        per_object = [
            f"{name} {why(by_label[label])}"
            for name, by_label in report["objects"].items()
            if label in by_label and by_label[label].get("truth_missed")
        ]
        lines.append(f"- {label}: {why(report['all'][label])} pairs (better / worse); " + ", ".join(per_object))
    lines += ["", "## Confidence calibration (all objects)", ""]
    lines += ["| Method | ECE | threshold for 99% right | confident at it | its precision | re-touched (failed) |"]
    lines += ["|---|---:|---:|---:|---:|---:|"]
    for label in full_labels:
        s = report["all"][label]
        trusted = s["trusted"]
        lines.append(
            f"| {label} | {s['reliability']['ece']:.3f} | {trusted['threshold']:.3g} "
            f"| {_percent(trusted['confident'])} | {_percent(trusted['precision'])} "
            f"| {_percent(s['retouched'])} ({_percent(s['retouch_failed'])}) |"
        )
    lines += ["", "Reliability diagram: `reliability.png`.", ""]
    lines += [
        "## Latency (ms, warm-up excluded): per contact median / p90; pose stage alone median / p90; "
        "per pose median; next_touch median"
        + (
            " (both cores: both contacts at once, half of the pose stage's batches in a helper process)"
            if run["config"].get("both_cores")
            else ""
        ),
        "",
        header,
        rule,
    ]

    def latency(s: dict[str, Any]) -> str:
        c, p, a, n = s["contact_latency_ms"], s["pose_stage_ms"], s["pose_latency_ms"], s["next_touch_ms"]
        touch = "-" if n["median"] != n["median"] else f"{n['median']:.0f}"
        return f"{c['median']:.0f} / {c['p90']:.0f}; {p['median']:.0f} / {p['p90']:.0f}; {a['median']:.0f}; {touch}"

    lines += table(full_labels, latency)
    icp = next((m["label"] for m in report["methods"] if m["method"] == "icp"), None)
    if icp:
        for label in full_labels:
            method = next(m for m in report["methods"] if m["label"] == label)
            if method["method"] in ("yoto", "match"):
                ratio = (
                    report["all"][icp]["contact_latency_ms"]["median"]
                    / report["all"][label]["contact_latency_ms"]["median"]
                )
                lines.append(
                    f"\n{label} is {ratio:.1f}x faster than ICP per contact (median, same process, same contacts)."
                )
    lines.append(f"\nWall time {run['wall_time_s']:.0f} s.")
    return "\n".join(lines) + "\n"


def _figure_bytes(figure) -> bytes:
    import io

    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90)
    plt.close(figure)
    return buffer.getvalue()


def plot_report(results: dict[str, dict[str, MethodResult]], rows: list[Row], path: Path) -> Path:
    """Localization and pose error CDFs per method (all objects)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    panels = (
        ("localization_top1_mm", "contact localization error (mm)"),
        ("translation_mm", "pose translation error (mm)"),
        ("rotation_deg", "pose rotation error (deg, modulo symmetry)"),
    )
    colours = {row.label: f"C{i}" for i, row in enumerate(rows)}
    for axis, (key, title) in zip(axes, panels):
        for row in rows:
            values = np.sort(
                [v for by_label in results.values() if row.label in by_label for v in getattr(by_label[row.label], key)]
            )
            localization = key == "localization_top1_mm"
            if len(values) and not (localization and (row.method == "oracle" or row.stage != "full")):
                axis.plot(values, np.arange(1, len(values) + 1) / len(values), label=row.label, c=colours[row.label])
        axis.set_xscale("symlog", linthresh=1.0)
        axis.set_xlabel(title)
        axis.set_ylabel("fraction of contacts" if key.startswith("local") else "fraction of pairs")
        axis.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    figure.tight_layout()
    return write_bytes_atomic(path, _figure_bytes(figure))


def plot_reliability(results: dict[str, dict[str, MethodResult]], rows: list[Row], path: Path) -> Path:
    """Reliability diagram of `confidence` per method (full pose stage, all objects): right share per bin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (axis, counts) = plt.subplots(2, 1, figsize=(6, 7), gridspec_kw={"height_ratios": [3, 1]}, sharex=True)
    axis.plot([0, 1], [0, 1], "k:", lw=1, label="perfect calibration")
    for i, row in enumerate(r for r in rows if r.stage == "full" and r.method != "oracle"):
        items = [by_label[row.label] for by_label in results.values() if row.label in by_label]
        confidence = np.array([v for item in items for v in item.confidence])
        right = np.concatenate([item.right for item in items]) if items else np.zeros(0, bool)
        data = reliability(confidence, right)
        centres = [(b["low"] + b["high"]) / 2 for b in data["bins"]]
        axis.plot(
            [b["confidence"] for b in data["bins"]],
            [b["right"] for b in data["bins"]],
            "o-",
            c=f"C{i}",
            label=f"{row.label} (ECE {data['ece']:.3f})",
        )
        counts.bar(np.array(centres) + 0.02 * i, [b["pairs"] for b in data["bins"]], width=0.02, color=f"C{i}")
    axis.set_ylabel("share of right poses (5 mm, 5 deg)")
    axis.set_title("confidence reliability (all objects)")
    axis.legend(fontsize=8, loc="upper left")
    axis.grid(alpha=0.3)
    counts.set_xlabel("reported confidence")
    counts.set_ylabel("pairs")
    counts.set_yscale("log")
    figure.tight_layout()
    return write_bytes_atomic(path, _figure_bytes(figure))
