"""The sensor rig's calibration (paper App. B.2 (i)): where the gel centre is and how the GelSight is oriented
in the rig's rigid body, `T_rig_sensor`, and its file.

Gel centre: the multi-pose dual-ball procedure. A mocap ball rests at the centre of the gel, a reference ball is
fixed on the rig; the rig is held still in at least 5 distinct poses. In each pose both ball centres are mapped
into the rig body (`inv(T_world_rig) @ p_world`) and averaged; the gel-ball's position over the poses gives the
gel centre (its centre lies `ball_height_m` above the gel along the sensor's z) and its dispersion per axis; the
reference ball's dispersion checks the rig's rigidity.

Orientation: the rig's CAD rotation `R_rig_sensor` (given by the user: the GelSight's axes in the rig body), checked
and corrected by presses on a flat plate whose surface normal mocap knows. During a flat press the sensor's z is the
plate's inward normal, so each press measures z in the rig body; the CAD rotation is tilted (by the smallest
rotation) onto their mean, keeping the CAD's in-plane angle, which flat presses cannot observe. The residual is the
spread of the presses about that mean and the CAD's angle to it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError
from yoto.geometry import (
    make_transform,
    normalize,
    quaternion_xyzw_to_rotation,
    rotation_between,
    validate_transform,
)
from yoto.io import read_json, read_json_format, write_json_atomic
from yoto.rig.streams import Recording
from yoto.rig.timeline import PoseStream, static_segments

FORMAT_NAME = "yoto-rig-calibration"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class GelCalibrationConfig:
    """The dual-ball procedure and the plate presses."""

    ball_height_m: float = 0.0025  # gel ball's centre above the gel surface along the sensor's z (5 mm ball resting)
    min_poses: int = 5  # distinct still rig poses needed (paper: 5)
    distinct_rotation_deg: float = 10.0  # still segments closer than this in rotation ...
    distinct_translation_m: float = 0.02  # ... and in position are the same pose
    still_speed_m_s: float = 0.01  # a rig moving slower than this (and turning slower than below) is still
    still_turn_deg_s: float = 5.0
    min_still_s: float = 0.3  # shortest still segment used
    max_match_gap_s: float = 0.05  # marker and rig samples are matched across gaps up to this
    max_dispersion_m: float = 0.003  # a ball wandering more than this in the rig body is refused
    plate_normal_body: tuple[float, float, float] = (0.0, 0.0, 1.0)  # plate surface normal, plate body frame
    plate_surface_offset_m: float = 0.0  # plate surface along that normal from the plate body's origin
    plate_max_tilt_deg: float = 15.0  # a still rig whose CAD z is within this of the plate's inward normal ...
    plate_surface_tolerance_m: float = 0.01  # ... with its gel centre this close to the plate surface is a press
    min_plate_presses: int = 3


@dataclass
class RigCalibration:
    """A rig's calibration: the GelSight frame in the rig body and how well it is known."""

    name: str  # which rig ("left", "right", a serial number)
    rig_body: str  # the rig's rigid body: topic or name it was calibrated with
    T_rig_sensor: np.ndarray  # (4, 4) GelSight frame (origin: gel centre) in the rig body
    gel_ball: dict[str, Any] = field(default_factory=dict)  # poses, per-axis dispersion (mm)
    reference_ball: dict[str, Any] = field(default_factory=dict)
    orientation: dict[str, Any] = field(default_factory=dict)  # method, residuals (deg)
    sources: dict[str, Any] = field(default_factory=dict)  # recordings and settings

    @property
    def p_rig_gel(self) -> np.ndarray:
        return self.T_rig_sensor[:3, 3].copy()

    def save(self, path: str | Path) -> Path:
        payload = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "name": self.name,
            "rig_body": self.rig_body,
            "T_rig_sensor": self.T_rig_sensor,
            "gel_ball": self.gel_ball,
            "reference_ball": self.reference_ball,
            "orientation": self.orientation,
            "sources": self.sources,
        }
        return write_json_atomic(path, payload)

    def summary(self) -> str:
        dispersion = self.gel_ball.get("dispersion_mm", [float("nan")] * 3)
        lines = [
            f"rig '{self.name}' (body {self.rig_body}): gel centre in the rig body "
            + "["
            + ", ".join(f"{v * 1e3:.2f}" for v in self.p_rig_gel)
            + "] mm",
            f"  gel ball over {self.gel_ball.get('poses_used', 0)} poses: dispersion x/y/z "
            + "/".join(f"{v:.3f}" for v in dispersion)
            + f" mm (largest deviation {self.gel_ball.get('max_deviation_mm', float('nan')):.3f} mm)",
        ]
        if self.reference_ball:
            lines.append(
                "  reference ball: dispersion x/y/z "
                + "/".join(f"{v:.3f}" for v in self.reference_ball["dispersion_mm"])
                + " mm"
            )
        orientation = self.orientation
        text = f"  orientation: {orientation.get('method')}"
        if "plate" in orientation:
            plate = orientation["plate"]
            text += (
                f"; {plate['presses']} plate presses, residual {plate['residual_rms_deg']:.3f} deg RMS "
                f"(max {plate['residual_max_deg']:.3f}); CAD z off by {plate['cad_z_error_deg']:.3f} deg"
            )
        if "cad_gel_centre_error_mm" in orientation:
            text += f"; CAD gel centre off by {orientation['cad_gel_centre_error_mm']:.2f} mm"
        lines.append(text)
        return "\n".join(lines)


def load_rig_calibration(path: str | Path) -> RigCalibration:
    """Read a rig calibration file; errors name the file."""
    path = Path(path)
    payload = read_json_format(
        path,
        FORMAT_NAME,
        FORMAT_VERSION,
        "rig calibration",
        ("name", "rig_body", "T_rig_sensor"),
        "yoto rig calibrate-rig",
    )
    return RigCalibration(
        name=str(payload["name"]),
        rig_body=str(payload["rig_body"]),
        T_rig_sensor=validate_transform(payload["T_rig_sensor"], "T_rig_sensor", path),
        gel_ball=payload.get("gel_ball", {}),
        reference_ball=payload.get("reference_ball", {}),
        orientation=payload.get("orientation", {}),
        sources=payload.get("sources", {}),
    )


def read_cad_rotation(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The sensor's rotation in the rig body from the rig's CAD: a JSON with `T_rig_sensor` (4x4; its translation,
    the CAD's gel centre, is then checked against the measured one), `R_rig_sensor` (3x3) or `quaternion_xyzw`.
    Returns (R_rig_sensor, p_rig_gel from the CAD or None)."""
    path = Path(path)
    payload = read_json(path)
    if not isinstance(payload, dict):
        raise InputError("the CAD rotation file must hold a JSON object", path)
    if "T_rig_sensor" in payload:
        T = validate_transform(payload["T_rig_sensor"], "T_rig_sensor", path)
        return T[:3, :3], T[:3, 3]
    if "R_rig_sensor" in payload:
        R = np.asarray(payload["R_rig_sensor"], dtype=np.float64)
        T = validate_transform(make_transform(R, np.zeros(3)) if R.shape == (3, 3) else R, "R_rig_sensor", path)
        return T[:3, :3], None
    if "quaternion_xyzw" in payload:
        q = np.asarray(payload["quaternion_xyzw"], dtype=np.float64)
        if q.shape != (4,) or not np.isfinite(q).all() or abs(np.linalg.norm(q) - 1) > 1e-3:
            raise InputError("quaternion_xyzw must be 4 numbers of a unit quaternion (x, y, z, w)", path)
        return quaternion_xyzw_to_rotation(q), None
    raise InputError("the CAD file needs 'T_rig_sensor' (4x4), 'R_rig_sensor' (3x3) or 'quaternion_xyzw'", path)


# ---------------------------------------------------------------------------------------------------------
# Still poses


def distinct_poses(rig: PoseStream, config: GelCalibrationConfig) -> list[list[tuple[float, float]]]:
    """Still segments of the rig grouped into distinct poses (segments of one pose interrupted by jitter merge)."""
    segments = static_segments(rig, config.still_speed_m_s, np.radians(config.still_turn_deg_s), config.min_still_s)
    poses: list[list[tuple[float, float]]] = []
    representatives: list[np.ndarray] = []
    for start, end in segments:
        middle, _ = rig.at(np.array([(start + end) / 2]), max_gap_s=np.inf)
        T = middle[0]
        for k, other in enumerate(representatives):
            turned = np.degrees(np.arccos(np.clip((np.trace(other[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1)))
            if (
                turned < config.distinct_rotation_deg
                and np.linalg.norm(other[:3, 3] - T[:3, 3]) < config.distinct_translation_m
            ):
                poses[k].append((start, end))
                break
        else:
            poses.append([(start, end)])
            representatives.append(T)
    return poses


def ball_in_rig(
    recording: Recording,
    rig: PoseStream,
    marker: str,
    poses: list[list[tuple[float, float]]],
    config: GelCalibrationConfig,
) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """The marker's mean position in the rig body in each pose, (P, 3), and a table row per pose."""
    stream = recording.point(marker)
    means, rows = [], []
    for index, segments in enumerate(poses):
        samples = []
        for start, end in segments:
            inside = (stream.timestamps_s >= start) & (stream.timestamps_s <= end)
            T_world_rig, ok = rig.at(stream.timestamps_s[inside], config.max_match_gap_s)
            if ok.any():
                p_world = stream.p_world[inside][ok]
                samples.append(np.einsum("nji,nj->ni", T_world_rig[ok, :3, :3], p_world - T_world_rig[ok, :3, 3]))
        if not samples:
            rows.append({"pose": index, "frames": 0})
            continue
        points = np.concatenate(samples)
        means.append(points.mean(axis=0))
        row: dict[str, Any] = {
            "pose": index,
            "start_s": segments[0][0],
            "end_s": segments[-1][1],
            "frames": len(points),
            "p_rig_mm": (points.mean(axis=0) * 1e3).round(4).tolist(),
            "jitter_mm": float(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))) * 1e3),
        }
        rows.append(row)
    if not means:
        raise InputError(f"marker '{marker}' was never seen while the rig stood still", recording.path)
    return np.asarray(means), rows


def dispersion(means: np.ndarray) -> dict[str, Any]:
    centre = means.mean(axis=0)
    deviation = np.linalg.norm(means - centre, axis=1)
    return {
        "p_rig": centre.tolist(),
        "dispersion_mm": (means.std(axis=0, ddof=1) * 1e3).tolist() if len(means) > 1 else [0.0, 0.0, 0.0],
        "max_deviation_mm": float(deviation.max() * 1e3),
        "poses_used": len(means),
    }


# ---------------------------------------------------------------------------------------------------------
# The whole rig


def calibrate_rig(
    recording: Recording,
    *,
    name: str,
    rig_body: str,
    gel_ball: str,
    R_rig_sensor_cad: np.ndarray,
    reference_ball: str | None = None,
    p_rig_gel_cad: np.ndarray | None = None,
    plate_recording: Recording | None = None,
    plate_body: str | None = None,
    config: GelCalibrationConfig = GelCalibrationConfig(),
) -> RigCalibration:
    """Gel centre by the dual-ball procedure, orientation from the CAD (tilted onto plate presses when given)."""
    rig = recording.pose(rig_body)
    poses = distinct_poses(rig, config)
    if len(poses) < config.min_poses:
        raise InputError(
            f"the rig '{rig_body}' stood still in {len(poses)} distinct poses; the dual-ball procedure needs at least "
            f"{config.min_poses} (hold each for {config.min_still_s:g} s or more, turned by "
            f"{config.distinct_rotation_deg:g} deg or moved by {config.distinct_translation_m * 1e3:g} mm from the "
            "others)",
            recording.path,
        )
    ball_means, ball_rows = ball_in_rig(recording, rig, gel_ball, poses, config)
    gel = dispersion(ball_means)
    gel["poses"] = ball_rows
    gel["height_above_gel_m"] = config.ball_height_m
    if gel["max_deviation_mm"] > config.max_dispersion_m * 1e3:
        raise InputError(
            f"the gel ball '{gel_ball}' moves by up to {gel['max_deviation_mm']:.1f} mm in the rig body between poses "
            f"(limit {config.max_dispersion_m * 1e3:g} mm): it slid on the gel, the marker is mislabelled, or "
            f"'{rig_body}' is not this rig",
            recording.path,
        )
    if len(ball_means) < config.min_poses:
        raise InputError(
            f"the gel ball '{gel_ball}' was seen in {len(ball_means)} of the {len(poses)} still poses; at least "
            f"{config.min_poses} are needed",
            recording.path,
        )
    reference: dict[str, Any] = {}
    if reference_ball:
        reference_means, reference_rows = ball_in_rig(recording, rig, reference_ball, poses, config)
        reference = dispersion(reference_means)
        reference["poses"] = reference_rows
        if reference["max_deviation_mm"] > config.max_dispersion_m * 1e3:
            raise InputError(
                f"the reference ball '{reference_ball}' moves by {reference['max_deviation_mm']:.1f} mm in the rig "
                "body between poses: the rig is not rigid, or the marker is mislabelled",
                recording.path,
            )
    R_cad = np.asarray(R_rig_sensor_cad, dtype=np.float64)
    orientation: dict[str, Any] = {"method": "cad", "R_rig_sensor_cad": R_cad.tolist()}
    rotation = R_cad
    p_ball = np.asarray(gel["p_rig"])
    p_gel = p_ball - config.ball_height_m * rotation[:, 2]
    if plate_recording is not None:
        if not plate_body:
            raise InputError("plate presses need the plate's rigid body (--plate-body)", plate_recording.path)
        plate = plate_presses(plate_recording, rig_body, plate_body, p_gel, R_cad, config)
        rotation = rotation_between(R_cad[:, 2], np.asarray(plate["z_rig"])) @ R_cad
        p_gel = p_ball - config.ball_height_m * rotation[:, 2]
        orientation = {**orientation, "method": "cad+plate", "plate": plate}
    if p_rig_gel_cad is not None:
        orientation["cad_gel_centre_error_mm"] = float(np.linalg.norm(p_rig_gel_cad - p_gel) * 1e3)
    sources = {
        "recording": str(recording.path),
        "gel_ball": gel_ball,
        "reference_ball": reference_ball,
        "plate_recording": str(plate_recording.path) if plate_recording else None,
        "plate_body": plate_body,
        "config": asdict(config),
    }
    return RigCalibration(name, rig_body, make_transform(rotation, p_gel), gel, reference, orientation, sources)


def plate_presses(
    recording: Recording,
    rig_body: str,
    plate_body: str,
    p_rig_gel: np.ndarray,
    R_rig_sensor_cad: np.ndarray,
    config: GelCalibrationConfig,
) -> dict[str, Any]:
    """The sensor's z in the rig body from flat presses on a plate: one still press after another."""
    rig = recording.pose(rig_body)
    plate = recording.pose(plate_body)
    normal_plate = normalize(np.asarray(config.plate_normal_body, dtype=np.float64))
    presses = []
    for start, end in static_segments(
        rig, config.still_speed_m_s, np.radians(config.still_turn_deg_s), config.min_still_s
    ):
        inside = (rig.timestamps_s >= start) & (rig.timestamps_s <= end)
        times = rig.timestamps_s[inside]
        T_world_plate, ok = plate.at(times, config.max_match_gap_s)
        if ok.sum() < 3:
            continue
        T_world_rig = rig.T_world_body[inside][ok]
        n_world = np.einsum("nij,j->ni", T_world_plate[ok, :3, :3], normal_plate)
        origin_world = T_world_plate[ok, :3, 3] + n_world * config.plate_surface_offset_m
        gel_world = np.einsum("nij,j->ni", T_world_rig[:, :3, :3], p_rig_gel) + T_world_rig[:, :3, 3]
        height = np.einsum("ni,ni->n", gel_world - origin_world, n_world)
        z_cad_world = np.einsum("nij,j->ni", T_world_rig[:, :3, :3], R_rig_sensor_cad[:, 2])
        tilt = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", z_cad_world, -n_world), -1, 1)))
        if np.median(np.abs(height)) > config.plate_surface_tolerance_m or np.median(tilt) > config.plate_max_tilt_deg:
            continue
        z_rig = normalize(np.einsum("nji,nj->ni", T_world_rig[:, :3, :3], -n_world).mean(axis=0))
        presses.append({"start_s": start, "end_s": end, "frames": int(ok.sum()), "z_rig": z_rig})
    if len(presses) < config.min_plate_presses:
        raise InputError(
            f"found {len(presses)} flat presses of '{rig_body}' on the plate '{plate_body}' (need "
            f"{config.min_plate_presses}): a press is the rig held still with the gel on the plate, its CAD z within "
            f"{config.plate_max_tilt_deg:g} deg of the plate's normal {list(config.plate_normal_body)} (plate body "
            "frame; --plate-normal)",
            recording.path,
        )
    directions = np.array([p["z_rig"] for p in presses])
    z_mean = normalize(directions.mean(axis=0))
    residuals = np.degrees(np.arccos(np.clip(directions @ z_mean, -1, 1)))
    for press, direction, residual in zip(presses, directions, residuals):
        press["z_rig"] = direction.tolist()
        press["residual_deg"] = float(residual)
    return {
        "recording": str(recording.path),
        "presses": len(presses),
        "z_rig": z_mean.tolist(),
        "residual_rms_deg": float(np.sqrt(np.mean(residuals**2))),
        "residual_max_deg": float(residuals.max()),
        "cad_z_error_deg": float(np.degrees(np.arccos(np.clip(R_rig_sensor_cad[:, 2] @ z_mean, -1, 1)))),
        "table": presses,
    }


def T_world_sensor_of(calibration: RigCalibration, T_world_rig: np.ndarray) -> np.ndarray:
    """The GelSight's pose(s) in the world from the rig's mocap pose(s): T_world_rig @ T_rig_sensor."""
    return np.asarray(T_world_rig) @ calibration.T_rig_sensor
