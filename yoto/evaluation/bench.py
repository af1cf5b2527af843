"""The benchmark (SPEC: "How we measure"): every method on the same simulated contacts, side by side.

For each object: N simulated dual contacts (fixed seed), then for each method (oracle, ICP, YOTO
variants) localization error, pose error and latency, measured in one process on the same contacts.
Results are cached per (object, method) so an interrupted run resumes; the report is written as
Markdown for people and JSON for machines, both stamped with commit, versions, device and seed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from yoto.contacts import SIDES
from yoto.errors import InputError, YotoError
from yoto.geometry import transform_points
from yoto.io import read_json, write_bytes_atomic, write_json_atomic, write_text_atomic
from yoto.metrics import pose_errors, summarize
from yoto.objects.build import build_object, load_object_model
from yoto.objects.mesh import MESH_SUFFIXES
from yoto.objects.model import ObjectModel
from yoto.pose.pipeline import PAPER, PoseConfig, localize_contacts, pose_from_candidates
from yoto.provenance import run_info

POSE_STAGES = {"full": PoseConfig(), "paper": PAPER}


def row_label(label: str, stage: str) -> str:
    """Table row of a method under a pose stage: the full stage keeps the method's label."""
    return label if stage == "full" else f"{label}, paper pose stage"


log = logging.getLogger("yoto")


@dataclass(frozen=True)
class MethodSpec:
    """One row group of the benchmark: a localizer, and optionally the object models it localizes on."""

    label: str  # row name, e.g. "YOTO fine-tuned"
    method: str  # "oracle", "icp" or "yoto"
    checkpoint: str | None = None  # for "yoto"
    model_suffix: str = ""  # localize on object model NAME+suffix (e.g. "_scan": trained on a scan-like mesh)
    via_images: bool = False  # the same pairs, each cloud reconstructed from its rendered GelSight image


@dataclass(frozen=True)
class BenchConfig:
    """What the benchmark runs."""

    num_pairs: int = 100  # dual contacts per object (SPEC: >= 100 for reported figures)
    seed: int = 7  # evaluation seed; training pairs must use other seeds
    warmup_pairs: int = 2  # pairs whose latency is excluded (first calls: caches, lazy imports)
    sensor_noise_mm: float = 0.0  # mean calibration error of each reported sensor position
    sensor_noise_deg: float = 0.0  # mean calibration error of each reported sensor orientation
    pose_stages: tuple[str, ...] = ("full", "paper")  # pose stages to report for every method (same localizations)
    image_calibration: str | None = None  # rows "via images": a calibration file or "shading[:SEED]" (image_route)
    image_variation: float = 0.0  # how much each rendered image's lighting, noise and gel stray from the sensor's


@dataclass
class MethodResult:
    """Per-pair measurements of one method on one object."""

    label: str
    object_name: str
    localization_top1_mm: list[float] = field(default_factory=list)  # per contact, localizer's first candidate
    localization_chosen_mm: list[float] = field(default_factory=list)  # per contact, after joint selection
    translation_mm: list[float] = field(default_factory=list)  # per pair
    rotation_deg: list[float] = field(default_factory=list)
    add_s_mm: list[float] = field(default_factory=list)
    confidence: list[float] = field(default_factory=list)
    contact_latency_ms: list[float] = field(default_factory=list)  # per contact, warm-up excluded
    pose_latency_ms: list[float] = field(default_factory=list)  # per pair, warm-up excluded
    failures: int = 0


def resolve_object(spec: str, workspace: str | Path | None) -> ObjectModel:
    """An object given as a workspace/built-in name, a model file, or a mesh file (built into the workspace)."""
    path = Path(spec)
    if path.suffix.lower() in MESH_SUFFIXES:
        if not path.is_file():
            raise InputError("mesh file not found", path)
        return load_object_model(build_object(path, path.stem, workspace=workspace))
    return load_object_model(spec, workspace)


def _make_localizer(spec: MethodSpec):
    from yoto.localize import make_localizer

    return make_localizer(spec.method, spec.checkpoint)


def evaluate_method(
    spec: MethodSpec, model: ObjectModel, pairs: list, config: BenchConfig, workspace: str | Path | None
) -> dict[str, MethodResult]:
    """Run one method over the simulated pairs of one object: localize once, then each pose stage."""
    localizer = _make_localizer(spec)
    localize_model = load_object_model(model.name + spec.model_suffix, workspace) if spec.model_suffix else model
    results = {
        stage: MethodResult(label=row_label(spec.label, stage), object_name=model.name) for stage in config.pose_stages
    }
    for number, simulated in enumerate(tqdm(pairs, desc=f"{model.name}: {spec.label}", unit="pair", leave=False)):
        pair = simulated.pair
        for stage, result in results.items():
            try:
                if stage == config.pose_stages[0]:
                    candidates, world, latency = localize_contacts(pair, localize_model, localizer)
                estimate = pose_from_candidates(
                    pair, localize_model, candidates, world, POSE_STAGES[stage], spec.method
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
            errors = pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model)
            result.translation_mm.append(errors["translation_mm"])
            result.rotation_deg.append(errors["rotation_deg"])
            result.add_s_mm.append(errors["add_s_mm"])
            result.confidence.append(estimate.confidence)
            if number >= config.warmup_pairs:
                result.contact_latency_ms += [latency["localize_left"], latency["localize_right"]]
                result.pose_latency_ms.append(
                    latency["localize_left"] + latency["localize_right"] + estimate.latency_ms["solve"]
                )
    return results


def simulate_benchmark_pairs(model: ObjectModel, config: BenchConfig) -> list:
    from yoto.simulate.scenarios import PairSimulator, ScenarioConfig

    scenario = ScenarioConfig(
        calibration_translation_m=config.sensor_noise_mm / 1000.0,
        calibration_rotation_rad=np.radians(config.sensor_noise_deg),
    )
    simulator = PairSimulator(model, scenario)
    return [
        simulator.pair(config.seed, index)
        for index in tqdm(range(config.num_pairs), desc=f"{model.name}: simulating", unit="pair", leave=False)
    ]


def pairs_via_images(pairs: list, config: BenchConfig) -> list:
    """The same simulated pairs (same poses, same truth), each tactile cloud replaced by the reconstruction of the
    GelSight image its noise-free gel height map renders to (`yoto.sensor.optical.image_route`); a frame the
    reconstruction finds no contact in gives an empty cloud, which the methods count as a failure."""
    from dataclasses import replace

    from yoto.sensor.optical import image_route

    assert config.image_calibration is not None
    to_cloud = image_route(config.image_calibration, config.image_variation)
    out = []
    for simulated in tqdm(pairs, desc="rendering and reconstructing images", unit="pair", leave=False):
        sides = {
            side: replace(simulated.pair.contact(side), points_sensor=to_cloud(simulated.height_maps[side]))
            for side in SIDES
        }
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
    """Run every method on every object; write bench.md, bench.json and bench.png into `out_dir`."""
    out_dir = Path(out_dir)
    partial_dir = out_dir / "partial"
    labels = [m.label for m in methods]
    if len(set(labels)) != len(labels):
        raise InputError(f"benchmark method labels must be unique, got {labels}")
    run_key = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode()).hexdigest()[:12]
    started = time.perf_counter()
    results: dict[str, dict[str, MethodResult]] = {}
    for spec_string in objects:
        model = resolve_object(spec_string, workspace)
        results[model.name] = {}
        pairs: list | None = None
        image_pairs: list | None = None
        for spec in methods:
            cache = partial_dir / f"{model.name}__{spec.label.replace(' ', '_')}__{run_key}.json"
            fingerprint = {"model": model.fingerprint, "spec": asdict(spec)}
            if cache.exists() and not overwrite:
                stored = read_json(cache)
                if stored.get("fingerprint") == fingerprint:
                    for stage_result in stored["results"]:
                        results[model.name][stage_result["label"]] = MethodResult(**stage_result)
                    continue
            if pairs is None:
                pairs = simulate_benchmark_pairs(model, config)
            if spec.via_images and image_pairs is None:
                image_pairs = pairs_via_images(pairs, config)
            method_pairs = image_pairs if spec.via_images and image_pairs is not None else pairs
            by_stage = evaluate_method(spec, model, method_pairs, config, workspace)
            write_json_atomic(cache, {"fingerprint": fingerprint, "results": [asdict(r) for r in by_stage.values()]})
            for result in by_stage.values():
                results[model.name][result.label] = result
    report = build_report(results, rows_of(methods, config))
    report["run"] = {
        **run_info(),
        "seed": config.seed,
        "config": asdict(config),
        "wall_time_s": time.perf_counter() - started,
    }
    write_json_atomic(out_dir / "bench.json", report)
    write_text_atomic(out_dir / "bench.md", format_markdown(report))
    plot_report(results, rows_of(methods, config), out_dir / "bench.png")
    return report


def _confidence_bins(confidence: list[float], translation: list[float], rotation: list[float]) -> list[dict]:
    """Pose error by confidence quartile, most confident first: how a user sets a re-touch threshold."""
    if len(confidence) < 8:
        return []
    order = np.argsort(confidence)[::-1]
    bins = []
    for chunk in np.array_split(order, 4):
        bins.append(
            {
                "confidence_min": float(np.min(np.asarray(confidence)[chunk])),
                "translation_mm_median": float(np.median(np.asarray(translation)[chunk])),
                "rotation_deg_median": float(np.median(np.asarray(rotation)[chunk])),
                "pairs": len(chunk),
            }
        )
    return bins


@dataclass(frozen=True)
class Row:
    """One row of the report: a method under a pose stage."""

    label: str
    method: str
    stage: str


def rows_of(methods: list[MethodSpec], config: BenchConfig) -> list[Row]:
    return [Row(row_label(spec.label, stage), spec.method, stage) for stage in config.pose_stages for spec in methods]


def build_report(results: dict[str, dict[str, MethodResult]], methods: list[Row]) -> dict[str, Any]:
    """Statistics per object and over all objects, per method."""
    report: dict[str, Any] = {"objects": {}, "all": {}}

    def stats(items: list[MethodResult]) -> dict[str, Any]:
        gather = lambda name: [v for item in items for v in getattr(item, name)]  # noqa: E731
        return {
            "localization_mm": summarize(gather("localization_top1_mm")),
            "localization_chosen_mm": summarize(gather("localization_chosen_mm")),
            "translation_mm": summarize(gather("translation_mm")),
            "rotation_deg": summarize(gather("rotation_deg")),
            "add_s_mm": summarize(gather("add_s_mm")),
            "contact_latency_ms": summarize(gather("contact_latency_ms")),
            "pose_latency_ms": summarize(gather("pose_latency_ms")),
            "confidence_bins": _confidence_bins(gather("confidence"), gather("translation_mm"), gather("rotation_deg")),
            "pairs": len(gather("translation_mm")),
            "failures": sum(item.failures for item in items),
            "right_share": right_share(gather("translation_mm"), gather("rotation_deg"), items),
        }

    for object_name, by_label in results.items():
        report["objects"][object_name] = {label: stats([result]) for label, result in by_label.items()}
    for spec in methods:
        report["all"][spec.label] = stats(
            [by_label[spec.label] for by_label in results.values() if spec.label in by_label]
        )
    report["methods"] = [asdict(spec) for spec in methods]
    return report


RIGHT_MM, RIGHT_DEG = 5.0, 5.0  # SPEC: a pose counts as right within 5 mm and 5 deg of the truth


def right_share(translation_mm: list[float], rotation_deg: list[float], items: list[MethodResult]) -> float:
    """Share of all attempted pairs (failures count as wrong) whose pose is right (SPEC: 5 mm and 5 deg)."""
    attempted = len(translation_mm) + sum(item.failures for item in items)
    right = sum(t <= RIGHT_MM and r <= RIGHT_DEG for t, r in zip(translation_mm, rotation_deg, strict=True))
    return right / attempted if attempted else float("nan")


def format_markdown(report: dict[str, Any]) -> str:
    """The report as Markdown tables (millimetres and degrees)."""
    run = report["run"]
    objects = list(report["objects"])
    labels = [m["label"] for m in report["methods"]]
    full_labels = [m["label"] for m in report["methods"] if m["stage"] == "full"]
    lines = [
        "# YOTO benchmark",
        "",
        f"commit {run['commit']} | yoto {run['yoto']} | torch {run.get('torch', '-')} "
        f"| open3d {run.get('open3d', '-')} "
        f"| {run['device']} | seed {run['seed']} | {report['all'][labels[0]]['pairs']} pairs | "
        f"sensor noise {run['config']['sensor_noise_mm']} mm / {run['config']['sensor_noise_deg']} deg",
        "",
        "## Contact localization error (mm): mean +- std (median / p90 / max), localizer's top candidate",
        "",
        "| Method | " + " | ".join(objects) + " | All |",
        "|---|" + "---|" * (len(objects) + 1),
    ]

    def cell(s: dict[str, float]) -> str:
        return f"{s['mean']:.2f} +- {s['std']:.2f} ({s['median']:.2f} / {s['p90']:.2f} / {s['max']:.1f})"

    for label in full_labels:
        row = [
            cell(report["objects"][o][label]["localization_mm"]) if label in report["objects"][o] else "-"
            for o in objects
        ]
        lines.append(f"| {label} | " + " | ".join(row) + f" | {cell(report['all'][label]['localization_mm'])} |")
    lines += [
        "",
        "## Pose error: translation mm / rotation deg, median (mean); ADD-S mm median",
        "",
        "| Method | " + " | ".join(objects) + " | All |",
        "|---|" + "---|" * (len(objects) + 1),
    ]

    def pose_cell(s: dict[str, Any]) -> str:
        t, r, a = s["translation_mm"], s["rotation_deg"], s["add_s_mm"]
        fail = f", {s['failures']} failed" if s["failures"] else ""
        return f"{t['median']:.2f} / {r['median']:.2f} ({t['mean']:.2f} / {r['mean']:.2f}); {a['median']:.2f}{fail}"

    for label in labels:
        row = [pose_cell(report["objects"][o][label]) if label in report["objects"][o] else "-" for o in objects]
        lines.append(f"| {label} | " + " | ".join(row) + f" | {pose_cell(report['all'][label])} |")
    lines += [
        "",
        f"## Poses right (within {RIGHT_MM:g} mm and {RIGHT_DEG:g} deg; failures count as wrong)",
        "",
        "| Method | " + " | ".join(objects) + " | All |",
        "|---|" + "---|" * (len(objects) + 1),
    ]
    for label in labels:
        row = [
            f"{report['objects'][o][label]['right_share']:.0%}" if label in report["objects"][o] else "-"
            for o in objects
        ]
        lines.append(f"| {label} | " + " | ".join(row) + f" | {report['all'][label]['right_share']:.0%} |")
    lines += [
        "",
        "## Latency (ms, warm-up excluded): per contact median / p90; per pose median",
        "",
        "| Method | " + " | ".join(objects) + " | All |",
        "|---|" + "---|" * (len(objects) + 1),
    ]

    def latency_cell(s: dict[str, Any]) -> str:
        c, p = s["contact_latency_ms"], s["pose_latency_ms"]
        return f"{c['median']:.1f} / {c['p90']:.1f}; {p['median']:.1f}"

    for label in full_labels:
        row = [latency_cell(report["objects"][o][label]) if label in report["objects"][o] else "-" for o in objects]
        lines.append(f"| {label} | " + " | ".join(row) + f" | {latency_cell(report['all'][label])} |")
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
    for label in full_labels:
        bins = report["all"][label]["confidence_bins"]
        method = next(m for m in report["methods"] if m["label"] == label)
        if bins and method["method"] in ("yoto", "match"):
            lines += [
                "",
                f"## {label}: pose error by confidence quartile (all objects)",
                "",
                "| confidence >= | pairs | translation mm (median) | rotation deg (median) |",
                "|---:|---:|---:|---:|",
            ]
            lines += [
                f"| {b['confidence_min']:.3g} | {b['pairs']} | {b['translation_mm_median']:.2f} "
                f"| {b['rotation_deg_median']:.2f} |"
                for b in bins
            ]
    lines.append(f"\nWall time {run['wall_time_s']:.0f} s.")
    return "\n".join(lines) + "\n"


def plot_report(results: dict[str, dict[str, MethodResult]], methods: list[Row], path: Path) -> Path:
    """Localization and pose error CDFs per method (all objects), and pose error against confidence."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    panels = (
        ("localization_top1_mm", "contact localization error (mm)"),
        ("translation_mm", "pose translation error (mm)"),
        ("rotation_deg", "pose rotation error (deg)"),
    )
    colours = {spec.label: f"C{i}" for i, spec in enumerate(methods)}
    for axis, (key, title) in zip(axes[:3], panels):
        for spec in methods:
            values = np.sort(
                [
                    v
                    for by_label in results.values()
                    if spec.label in by_label
                    for v in getattr(by_label[spec.label], key)
                ]
            )
            localization = key == "localization_top1_mm"
            if len(values) and not (localization and (spec.method == "oracle" or spec.stage != "full")):
                axis.plot(values, np.arange(1, len(values) + 1) / len(values), label=spec.label, c=colours[spec.label])
        axis.set_xscale("symlog", linthresh=1.0)
        axis.set_xlabel(title)
        axis.set_ylabel("fraction of contacts" if key.startswith("local") else "fraction of pairs")
        axis.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    for spec in methods:
        if spec.method != "yoto" or spec.stage != "full":
            continue
        confidence = [
            v for by_label in results.values() if spec.label in by_label for v in by_label[spec.label].confidence
        ]
        translation = [
            v for by_label in results.values() if spec.label in by_label for v in by_label[spec.label].translation_mm
        ]
        axes[3].scatter(confidence, translation, s=8, alpha=0.6, label=spec.label, c=colours[spec.label])
    axes[3].set_yscale("log")
    axes[3].set_xlabel("YOTO confidence")
    axes[3].set_ylabel("pose translation error (mm)")
    axes[3].set_title("re-touch below a confidence threshold")
    axes[3].grid(alpha=0.3)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90)
    plt.close(figure)
    return write_bytes_atomic(path, buffer.getvalue())
