"""`yoto rig bench`: the whole rig chain on simulated recordings, against the simulator's truth.

For each object: `simulate_recording` (every format asked for), then per format the rig calibrations (dual-ball +
CAD + plate), the object calibration (beads), labelling of the trials, and `yoto pose` on the labelled dual
contacts (the pose function is passed in by the command line, which sits above the pose stage). Reported:
- label error: the labelled `p_object` against SPEC's truth for the labelled contact (the mesh point nearest the
  labelled tactile cloud's centroid, placed by the true sensor pose), and the paper's gel-centre label beside it;
- gel-centre dispersion per axis, the calibrated gel centre's and sensor axis' errors, bead residuals, the object
  calibration's error; refused and flagged trials;
- pose error of the labelled dual contacts, against the simulator's true object pose.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from yoto.geometry import invert_transform, rotation_angle_rad, transform_points
from yoto.io import read_json, write_json_atomic, write_text_atomic
from yoto.metrics import summarize
from yoto.objects.model import ObjectModel
from yoto.raycast import MeshRaycaster
from yoto.rig.beads import calibrate_object, pick_vertices_mesh, read_bead_picks
from yoto.rig.calibration import GelCalibrationConfig, calibrate_rig, read_cad_rotation
from yoto.rig.labelling import LabelConfig, RigSide, label_recording, refine_object_calibration, write_labels
from yoto.rig.recording import FORMATS, SIDES, RecordingConfig, simulate_recording
from yoto.rig.streams import open_recording
from yoto.sensor.calibration import SensorCalibration

log = logging.getLogger("yoto")

# pose_fn(pair files, model) -> one dict per pair: {"T_world_mesh": 4x4 estimate or None, "confidence", "error"}
PoseFunction = Callable[[list[Path], ObjectModel], list[dict[str, Any]]]


def calibrate_session(recording_dir: Path, fmt: str, model: ObjectModel, gel_config: GelCalibrationConfig):
    """Rig and object calibrations from a simulated session's calibration recordings (names from session.json)."""
    session = read_json(recording_dir / "session.json")
    files = {name: recording_dir / path for name, path in session["recordings"][fmt].items()}
    gel_config = dataclasses.replace(gel_config, ball_height_m=session["ball_height_mm"] * 1e-3)
    rigs = {}
    for side in SIDES:
        R_cad, p_cad = read_cad_rotation(recording_dir / f"cad_{side}.json")
        rigs[side] = calibrate_rig(
            open_recording(files[f"gel_{side}"]),
            name=side,
            rig_body=session["rig_bodies"][side],
            gel_ball=session["gel_ball"],
            reference_ball=session["reference_ball"],
            R_rig_sensor_cad=R_cad,
            p_rig_gel_cad=p_cad,
            plate_recording=open_recording(files[f"plate_{side}"]),
            plate_body=session["plate_body"],
            config=gel_config,
        )
    picks = read_bead_picks(recording_dir / "beads.json", lambda: pick_vertices_mesh(model))
    object_calibration = calibrate_object(
        open_recording(files["beads"]),
        picks,
        model.mesh_vertices_mesh,
        model.mesh_faces,
        object_name=model.name,
        object_body=session["object_body"],
    )
    return session, files, rigs, object_calibration


def label_errors(report, truth: dict[str, Any], model: ObjectModel, clock: str = "hold_s") -> list[dict[str, Any]]:
    """Each labelled trial against the truth of the trial it belongs to (`clock`: "hold_s" for ROS stamps,
    "hold_take_s" for a Motive take's time)."""
    raycaster = MeshRaycaster(model.mesh_vertices_mesh, model.mesh_faces, "label errors")
    rows = []
    for trial in report.trials:
        match = [
            t
            for t in truth["trials"]
            if t["side"] == trial.side and t[clock][0] - 1.5 <= trial.start_s <= t[clock][1] + 0.5
        ]
        row = {"side": trial.side, "trial": trial.index, "status": trial.status, "flags": trial.flags}
        row["kind"] = match[0]["kind"] if match else "none"
        row["reason"] = trial.reason
        if trial.labelled is not None and match:
            T_mesh_sensor = np.asarray(match[0]["T_mesh_sensor"])
            centroid = transform_points(T_mesh_sensor, trial.labelled.contact.points_sensor.mean(axis=0))
            p_true = raycaster.closest_points(centroid[None])[0]
            row["error_mm"] = float(np.linalg.norm(trial.labelled.p_mesh - p_true) * 1e3)
            row["paper_error_mm"] = float(np.linalg.norm(np.asarray(trial.stats["p_object_gel_centre"]) - p_true) * 1e3)
            row["press_truth_error_mm"] = float(
                np.linalg.norm(trial.labelled.p_mesh - np.asarray(match[0]["p_object"])) * 1e3
            )
            row["spread_mm"] = trial.stats["spread_mm"]
            row["contact_frames"] = trial.stats["contact_frames"]
        rows.append(row)
    return rows


def bench_object(
    model: ObjectModel,
    gelsight: SensorCalibration,
    out_dir: Path,
    config: RecordingConfig,
    formats: tuple[str, ...],
    pose_fn: PoseFunction | None,
    label_config: LabelConfig = LabelConfig(),
    gel_config: GelCalibrationConfig = GelCalibrationConfig(),
) -> dict[str, Any]:
    """Simulate (or reuse) one object's session and run the chain on every format."""
    recording_dir = out_dir / "recordings" / model.name
    settings = {"config": dataclasses.asdict(config), "formats": list(formats), "gelsight": gelsight.background_sha256}
    done = recording_dir / "bench_settings.json"
    if not (done.is_file() and read_json(done) == read_json_roundtrip(settings)):
        log.info("%s: simulating the session", model.name)
        simulate_recording(model, gelsight, recording_dir, config, formats)
        write_json_atomic(done, settings)
    truth = read_json(recording_dir / "truth.json")
    results: dict[str, Any] = {"object": model.name, "formats": {}}
    for fmt in formats:
        session, files, rigs, object_calibration = calibrate_session(recording_dir, fmt, model, gel_config)
        sides = [RigSide(side, rigs[side], session["images"][fmt][side], gelsight) for side in SIDES]
        recording = open_recording(files["trials"])
        report = label_recording(recording, model, object_calibration, sides, label_config)
        written = write_labels(report, out_dir / "labels" / model.name / fmt.replace("-", "_"), "trials")
        clock = "hold_take_s" if fmt == "motive" else "hold_s"
        rows = label_errors(report, truth, model, clock)
        refined, refinement = refine_object_calibration(report, model, object_calibration, label_config)
        if refinement["refined"]:
            refined_rows = label_errors(
                label_recording(recording, model, refined, sides, label_config), truth, model, clock
            )
            refinement["label_error_mm"] = [row["error_mm"] for row in refined_rows if "error_mm" in row]
        rig_rows = {}
        for side in SIDES:
            T_true = np.asarray(truth["T_rig_sensor"][side])
            T_cal = rigs[side].T_rig_sensor
            rig_rows[side] = {
                "gel_centre_error_mm": float(np.linalg.norm(T_cal[:3, 3] - T_true[:3, 3]) * 1e3),
                "z_axis_error_deg": float(np.degrees(np.arccos(np.clip(T_cal[:3, 2] @ T_true[:3, 2], -1, 1)))),
                "rotation_error_deg": float(np.degrees(rotation_angle_rad(T_cal, T_true))),
                "dispersion_mm": rigs[side].gel_ball["dispersion_mm"],
                "plate_residual_deg": rigs[side].orientation["plate"]["residual_rms_deg"],
            }
        T_true_body_mesh = np.asarray(truth["T_objectbody_mesh"])
        centre_mesh = model.T_mesh_object[:3, 3]
        object_error = np.linalg.norm(
            transform_points(invert_transform(T_true_body_mesh) @ object_calibration.T_objectbody_mesh, centre_mesh)
            - centre_mesh
        )
        poses = pose_fn(written["pairs"], model) if pose_fn and written["pairs"] else []
        T_world_mesh_true = np.asarray(truth["T_world_mesh"])
        for pose in poses:
            if pose.get("T_world_mesh") is not None:
                T = np.asarray(pose["T_world_mesh"])
                pose["translation_mm"] = float(
                    np.linalg.norm(transform_points(T, centre_mesh) - transform_points(T_world_mesh_true, centre_mesh))
                    * 1e3
                )
                pose["rotation_deg"] = float(np.degrees(rotation_angle_rad(T, T_world_mesh_true)))
                pose.pop("T_world_mesh")
        results["formats"][fmt] = {
            "trials": rows,
            "rigs": rig_rows,
            "bead_residuals_mm": [bead["residual_mm"] for bead in object_calibration.beads],
            "object_calibration_error_mm": float(object_error * 1e3),
            "pairs": len(written["pairs"]),
            "refinement": refinement,
            "poses": poses,
            "streams": report.streams,
        }
    return results


def read_json_roundtrip(payload: Any) -> Any:
    """`payload` as it reads back from a JSON file (tuples become lists)."""
    import json

    return json.loads(json.dumps(payload))


def summary_tables(results: list[dict[str, Any]], header: str) -> str:
    lines = [header, ""]
    lines += [
        "| object | format | labelled / trials | label error mm mean / median / max (n) |"
        " paper's gel-centre label mm mean | gel-centre dispersion mm (x/y/z, worst rig) | gel centre error mm |"
        " sensor z error deg | bead residuals mm mean / max | object calibration error mm |"
        " label error after contact refinement mm mean | pose error mm / deg, median (n) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for result in results:
        for fmt, r in result["formats"].items():
            labelled = [row for row in r["trials"] if "error_mm" in row and row["kind"] in ("single", "dual")]
            errors = summarize([row["error_mm"] for row in labelled])
            paper = summarize([row["paper_error_mm"] for row in labelled if np.isfinite(row["paper_error_mm"])])
            worst = max(SIDES, key=lambda side: max(r["rigs"][side]["dispersion_mm"]))
            beads = r["bead_residuals_mm"]
            poses = [p for p in r["poses"] if "translation_mm" in p]
            pose_text = "-"
            if poses:
                translation = np.median([p["translation_mm"] for p in poses])
                pose_text = f"{translation:.2f} / {np.median([p['rotation_deg'] for p in poses]):.2f} ({len(poses)})"
            refined_errors = r["refinement"].get("label_error_mm")
            refined_text = f"{np.mean(refined_errors):.2f}" if refined_errors else "-"
            lines.append(
                f"| {result['object']} | {fmt} | {sum(row['status'] == 'labelled' for row in r['trials'])} / "
                f"{len(r['trials'])} | {errors['mean']:.2f} / {errors['median']:.2f} / {errors['max']:.2f} "
                f"({len(labelled)}) | "
                f"{paper['mean']:.2f} | {'/'.join(f'{v:.3f}' for v in r['rigs'][worst]['dispersion_mm'])} | "
                f"{max(r['rigs'][s]['gel_centre_error_mm'] for s in SIDES):.3f} | "
                f"{max(r['rigs'][s]['z_axis_error_deg'] for s in SIDES):.3f} | "
                f"{np.mean(beads):.2f} / {np.max(beads):.2f} | {r['object_calibration_error_mm']:.2f} | "
                f"{refined_text} | "
                f"{pose_text} |"
            )
    refused = [
        f"{result['object']} {fmt} {row['side']} trial {row['trial']} ({row['kind']}): "
        f"{row['reason'] or ', '.join(row['flags'])}"
        for result in results
        for fmt, r in result["formats"].items()
        for row in r["trials"]
        if row["status"] == "refused" or row["flags"]
    ]
    if refused:
        lines += ["", "Refused or flagged trials:", ""] + [f"- {text}" for text in refused]
    return "\n".join(lines) + "\n"


def run_rig_benchmark(
    models: list[ObjectModel],
    gelsight: SensorCalibration,
    out_dir: str | Path,
    config: RecordingConfig = RecordingConfig(),
    formats: tuple[str, ...] = FORMATS,
    pose_fn: PoseFunction | None = None,
) -> tuple[str, dict[str, Any]]:
    """Benchmark every object; writes OUT/rig_bench.md and .json. Returns the Markdown and the results."""
    from yoto.provenance import run_info

    out_dir = Path(out_dir)
    results = [bench_object(model, gelsight, out_dir, config, formats, pose_fn) for model in models]
    info = run_info()
    header = (
        f"# Rig benchmark (commit {info['commit']}, {info['device']}, seed {config.seed})\n\n"
        f"Simulated sessions: {config.single_trials} single contacts per rig, {config.dual_trials} dual contacts, "
        f"mocap {config.mocap_rate_hz:g} Hz, GelSight {config.camera_rate_hz:g} Hz, "
        f"noise {dataclasses.asdict(config.noise)}."
    )
    markdown = summary_tables(results, header)
    write_text_atomic(out_dir / "rig_bench.md", markdown)
    write_json_atomic(
        out_dir / "rig_bench.json", {"run": info, "config": dataclasses.asdict(config), "results": results}
    )
    return markdown, {"run": info, "results": results}
