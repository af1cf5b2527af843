"""Ground-truth contact labels from a recording (paper App. B.3-B.4), per trial.

For each rig, every mocap frame gives the GelSight's pose in the mesh frame (Eq. 3):
    T_mesh_sensor(t) = inv(T_world_objectbody(t) @ T_objectbody_mesh) @ T_world_rig(t) @ T_rig_sensor.
A **trial** is a stretch where the gel centre comes within `approach_m` of the mesh (approach, hold, withdrawal).
In each trial:
1. the GelSight frames are reconstructed (`yoto.sensor.reconstruct`); the frame of the steadiest deepest moment
   (slowest relative to the object, then deepest in the image) is the contact's tactile cloud;
2. the point labelled is the centroid of that frame's contact patch, `c_sensor` (SPEC: a contact's location is the
   surface point nearest its patch's centroid; the paper takes the gel centre, which is right only for contacts
   centred on the pad, and is reported beside it as `p_object_gel_centre`); the undeformed gel under it,
   `g_sensor = (c_x, c_y, 0)`, is mapped into the mesh frame at every mocap frame of the trial and its signed
   distance to the mesh found by ray casting;
3. frames with distance <= 0 are contact frames (the soft gel sinks into the rigid mesh); the closest mesh point of
   `T_mesh_sensor(t) @ c_sensor` in each is a per-frame estimate; estimates further than 3 sigma from their mean
   are rejected, and the mean of the rest, projected onto the mesh, is `p_object` (mesh file's frame);
4. the trial is refused (nothing written) when the images show no contact, mocap shows no contact frame, too few
   mocap frames remain, or a mocap dropout longer than `max_dropout_s` cuts the hold; it is flagged `slip` when
   the estimates drift during the hold by more than `slip_m`.
When trials of both rigs hold at the same time, they also form a dual contact (a contact-pair file).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import SIDES, TactileContact
from yoto.errors import InputError
from yoto.geometry import make_transform, procrustes_rotation, so3_log, transform_points
from yoto.io import png_bytes, write_bytes_atomic, write_json_atomic, write_ply_points
from yoto.objects.model import ObjectModel
from yoto.rig.beads import ObjectCalibration
from yoto.rig.calibration import RigCalibration
from yoto.rig.samples import LabelledContact, write_labelled_contact
from yoto.rig.streams import ImageStream, Recording
from yoto.rig.timeline import PoseStream
from yoto.sensor.calibration import SensorCalibration
from yoto.sensor.pair_images import in_rgb_order
from yoto.sensor.reconstruction import Reconstruction, reconstruct

log = logging.getLogger("yoto")


@dataclass(frozen=True)
class LabelConfig:
    """How trials are found and labelled."""

    approach_m: float = 0.005  # a trial: the gel centre comes this close to the mesh surface
    merge_gap_s: float = 1.0  # trial stretches closer in time than this are one trial (a dropout does not split one)
    pad_s: float = 0.1  # GelSight frames this long before and after a trial's stretch are searched too
    max_match_gap_s: float = 0.05  # rig and object poses are interpolated across gaps up to this
    max_dropout_s: float = 0.25  # a longer mocap dropout during a trial's contact refuses the trial
    min_contact_frames: int = 10  # fewer mocap contact frames refuse the trial
    outlier_sigma: float = 3.0  # per-frame estimates further than this many RMS deviations are rejected
    slip_m: float = 0.0015  # drift of the estimates between the first and last quarter of the hold: slip
    steady_window_s: float = 0.1  # speed relative to the object is measured, and poses averaged, over this window
    steady_speed_m_s: float = 0.005  # frames this slow (or within 1.5x of the slowest) count as steady
    pair_overlap_s: float = 0.1  # trials of both rigs in contact together this long form a dual contact
    max_object_motion_m: float = 0.0005  # the object may move this much between the two frames of a pair
    refine_min_contacts: int = 4  # fewer labelled contacts: no refinement
    refine_points_per_contact: int = 300  # each contact weighs the same in the refinement
    refine_reach_m: float = 0.004  # contact points further than this from the mesh are left out of the refinement


@dataclass
class RigSide:
    """One rig of a recording: its calibration, streams and GelSight calibration."""

    name: str  # "left" or "right"
    rig: RigCalibration
    images: str  # image topic (bag) or PNG folder (Motive take)
    gelsight: SensorCalibration
    rig_body: str | None = None  # rigid body (topic or name); default: the one the rig was calibrated with


@dataclass
class TrialResult:
    """One trial: where and when, what the label is, and why it is flagged or refused."""

    recording: str
    side: str
    index: int
    start_s: float
    end_s: float
    status: str = "labelled"  # "labelled" or "refused"
    reason: str = ""  # why refused
    flags: list[str] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    labelled: LabelledContact | None = None
    frame: np.ndarray | None = None  # the chosen GelSight frame (RGB)
    contact_span_s: tuple[float, float] = (0.0, 0.0)
    image_time_s: float = 0.0

    def row(self) -> dict[str, Any]:
        return {
            "recording": self.recording,
            "side": self.side,
            "trial": self.index,
            "start_s": self.start_s,
            "end_s": self.end_s,
            "status": self.status,
            "reason": self.reason,
            "flags": self.flags,
            **self.stats,
        }


@dataclass
class LabelReport:
    trials: list[TrialResult] = field(default_factory=list)
    pairs: list[dict[str, Any]] = field(default_factory=list)
    streams: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        lines = []
        for name, info in self.streams.items():
            lines.append(
                f"{name}: {info['samples']} samples at {info['rate_hz']:.0f} Hz, {info['dropped']} dropped frames"
            )
        for trial in self.trials:
            s = trial.stats
            text = f"{trial.recording} {trial.side} trial {trial.index} ({trial.start_s:.2f}-{trial.end_s:.2f} s): "
            if trial.status == "refused":
                text += f"REFUSED: {trial.reason}"
            else:
                text += (
                    f"{s['contact_frames']} contact frames, {s['rejected_frames']} rejected, spread "
                    f"{s['spread_mm']:.2f} mm, depth {s['image_depth_mm']:.2f} mm"
                )
                if trial.flags:
                    text += f"; FLAGGED: {', '.join(trial.flags)}"
            lines.append(text)
        labelled = sum(t.status == "labelled" for t in self.trials)
        lines.append(f"{labelled} of {len(self.trials)} trials labelled, {len(self.pairs)} dual contacts")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------------
# Geometry of a rig in the mesh frame


@dataclass
class SideStreams:
    """A rig's streams in the frames labelling needs, sampled at the rig's mocap frames."""

    rig: PoseStream  # T_world_rig as recorded
    world_sensor: PoseStream  # T_world_sensor = T_world_rig @ T_rig_sensor
    mesh_sensor: PoseStream  # T_mesh_sensor (Eq. 3), at the rig frames that have an object pose
    images: ImageStream


def side_streams(
    rig_stream: PoseStream,
    object_stream: PoseStream,
    images: ImageStream,
    rig: RigCalibration,
    T_objectbody_mesh: np.ndarray,
    max_gap_s: float,
) -> SideStreams:
    """Eq. 3 at every rig sample:
    T_mesh_sensor = inv(T_world_objectbody @ T_objectbody_mesh) @ T_world_rig @ T_rig_sensor."""
    T_world_body, ok = object_stream.at(rig_stream.timestamps_s, max_gap_s)
    T_world_sensor = rig_stream.T_world_body @ rig.T_rig_sensor
    T_mesh_sensor = np.linalg.inv(T_world_body[ok] @ T_objectbody_mesh) @ T_world_sensor[ok]

    def derived(name: str, times: np.ndarray, T: np.ndarray) -> PoseStream:
        return PoseStream(rig_stream.source, name, times, rig_stream.dropped, rig_stream.rate_hz, T)

    return SideStreams(
        rig_stream,
        derived(rig_stream.name, rig_stream.timestamps_s, T_world_sensor),
        derived(f"{rig_stream.name} in the mesh frame", rig_stream.timestamps_s[ok], T_mesh_sensor),
        images,
    )


class MeshQueries:
    """Signed distance and closest points on the object's mesh, in the mesh file's frame (ray casting)."""

    def __init__(self, model: ObjectModel):
        self.raycaster = model.raycaster  # object frame
        self.T_object_mesh = model.T_object_mesh
        self.T_mesh_object = model.T_mesh_object

    def signed_distance(self, p_mesh: np.ndarray) -> np.ndarray:
        return self.raycaster.signed_distance(transform_points(self.T_object_mesh, p_mesh))

    def closest(self, p_mesh: np.ndarray) -> np.ndarray:
        return transform_points(
            self.T_mesh_object, self.raycaster.closest_points(transform_points(self.T_object_mesh, p_mesh))
        )


def find_trials(times: np.ndarray, near: np.ndarray, config: LabelConfig) -> list[tuple[float, float]]:
    """(start, end) of the stretches where `near` holds, merged across short breaks."""
    stretches: list[list[float]] = []
    for t in times[near]:
        if stretches and t - stretches[-1][1] <= config.merge_gap_s:
            stretches[-1][1] = float(t)
        else:
            stretches.append([float(t), float(t)])
    return [(a, b) for a, b in stretches]


def longest_gap(times: np.ndarray, start: float, end: float) -> tuple[float, float]:
    """The longest interval without a sample within [start, end] (length, where it starts)."""
    inside = times[(times >= start) & (times <= end)]
    edges = np.concatenate([[start], inside, [end]])
    steps = np.diff(edges)
    k = int(np.argmax(steps))
    return float(steps[k]), float(edges[k])


# ---------------------------------------------------------------------------------------------------------
# Labelling one recording


def label_recording(
    recording: Recording,
    model: ObjectModel,
    object_calibration: ObjectCalibration,
    sides: list[RigSide],
    config: LabelConfig = LabelConfig(),
    object_body: str | None = None,
) -> LabelReport:
    """Find and label every trial of every rig in a recording (nothing is written; see `write_labels`)."""
    report = LabelReport()
    object_stream = recording.pose(object_body or object_calibration.object_body)
    report.streams["object"] = _stream_info(object_stream)
    queries = MeshQueries(model)
    T_objectbody_mesh = object_calibration.T_objectbody_mesh
    per_side: dict[str, list[TrialResult]] = {}
    streams: dict[str, SideStreams] = {}
    for side in sides:  # every stream is read and checked before any trial is labelled
        rig_stream = recording.pose(side.rig_body or side.rig.rig_body)
        report.streams[side.name] = _stream_info(rig_stream)
        images = recording.images(side.images)
        report.streams[f"{side.name} images"] = _stream_info(images)
        check_gelsight(images, side)
        streams[side.name] = side_streams(
            rig_stream, object_stream, images, side.rig, T_objectbody_mesh, config.max_match_gap_s
        )
    for side in sides:
        mesh_sensor = streams[side.name].mesh_sensor
        distance = queries.signed_distance(mesh_sensor.T_world_body[:, :3, 3])
        trials = find_trials(mesh_sensor.timestamps_s, distance < config.approach_m, config)
        results = []
        for index, (start, end) in enumerate(trials):
            trial = TrialResult(str(recording.path), side.name, index, start, end)
            try:
                label_trial(trial, side, streams[side.name], object_stream, T_objectbody_mesh, queries, model, config)
            except TrialRefused as exc:
                trial.status, trial.reason = "refused", str(exc)
                log.debug(  # the report lists it with its reason (`LabelReport.summary`): a warning printed it twice
                    "%s: %s trial %d (%.2f-%.2f s) refused: %s", recording.path, side.name, index, start, end, exc
                )
            results.append(trial)
        per_side[side.name] = results
        report.trials.extend(results)
    if all(name in per_side for name in SIDES):
        report.pairs = match_pairs(per_side["left"], per_side["right"], config)
    return report


class TrialRefused(Exception):
    """A trial that cannot be labelled; the message says why."""


def label_trial(
    trial: TrialResult,
    side: RigSide,
    streams: SideStreams,
    object_stream: PoseStream,
    T_objectbody_mesh: np.ndarray,
    queries: MeshQueries,
    model: ObjectModel,
    config: LabelConfig,
) -> None:
    """Label one trial in place (module docstring); raises TrialRefused with the reason."""
    images, mesh_sensor = streams.images, streams.mesh_sensor
    start, end = trial.start_s - config.pad_s, trial.end_s + config.pad_s
    where = f"{images.describe()} {start:.2f}-{end:.2f} s"
    frame_indices = np.flatnonzero((images.timestamps_s >= start) & (images.timestamps_s <= end))
    reconstructions: dict[int, Reconstruction] = {}
    frames: dict[int, np.ndarray] = {}
    # The recording's first frame passed `check_gelsight`; a frame refused later (a broad contact that changes
    # nearly the whole pad, a saturated flash) is skipped and counted, and only a trial with no usable frame is
    # refused for it.
    unusable: list[str] = []
    for index, frame in images.frames(frame_indices):
        source = f"{images.source} {images.name} frame {index}"
        frame = in_rgb_order(frame, side.gelsight.background, source, warn=False)  # warned by `check_gelsight`
        try:
            result = reconstruct(frame, side.gelsight, source=source)
        except InputError as exc:
            unusable.append(str(exc))
            continue
        if result.contact:
            reconstructions[index] = result
            frames[index] = frame
    if not reconstructions and unusable:
        raise TrialRefused(f"none of the {len(frame_indices)} GelSight frames of {where} is usable: {unusable[-1]}")
    if not reconstructions:
        raise TrialRefused(
            f"no contact in the GelSight frames ({len(frame_indices)} frames of {where}) although mocap puts the gel "
            f"within {config.approach_m * 1e3:g} mm of the mesh: a near miss, or the calibrations are off"
        )
    chosen, speeds = choose_frame(reconstructions, images, mesh_sensor, config)
    recon = reconstructions[chosen]
    c_sensor = recon.points_sensor.mean(axis=0)  # the patch centroid: SPEC's contact is the surface point nearest it
    g_sensor = np.array([c_sensor[0], c_sensor[1], 0.0])  # the undeformed gel under it, inside the object in contact
    t = mesh_sensor.timestamps_s
    window = (t >= start) & (t <= end)
    T_window = mesh_sensor.T_world_body[window]
    distance = queries.signed_distance(np.einsum("nij,j->ni", T_window[:, :3, :3], g_sensor) + T_window[:, :3, 3])
    q_mesh = np.einsum("nij,j->ni", T_window[:, :3, :3], c_sensor) + T_window[:, :3, 3]
    contact = distance <= 0.0
    count = int(contact.sum())
    if count == 0:
        raise TrialRefused(
            f"no contact frame: the GelSight shows contact at t = {images.timestamps_s[chosen]:.2f} s but mocap never "
            f"puts the gel inside the mesh (closest {distance.min() * 1e3:.2f} mm outside) in {where}: check the rig "
            "and object calibrations"
        )
    contact_times = t[window][contact]
    for stream in (streams.rig, object_stream):
        gap, gap_start = longest_gap(stream.timestamps_s, contact_times[0], contact_times[-1])
        if gap > config.max_dropout_s:
            raise TrialRefused(
                f"mocap dropout of {gap:.2f} s from t = {gap_start:.2f} s in '{stream.name}' during the contact "
                f"(limit {config.max_dropout_s:g} s): the rig or object was occluded"
            )
    if count < config.min_contact_frames:
        raise TrialRefused(
            f"too few mocap frames: {count} contact frames (at least {config.min_contact_frames} needed) in {where}"
        )
    estimates = queries.closest(q_mesh[contact])
    deviation = np.linalg.norm(estimates - estimates.mean(axis=0), axis=1)
    sigma = float(np.sqrt(np.mean(deviation**2)))
    keep = deviation <= config.outlier_sigma * max(sigma, 1e-9)
    kept = estimates[keep]
    p_mesh = queries.closest(kept.mean(axis=0)[None])[0]
    spread = float(np.sqrt(np.mean(np.sum((kept - kept.mean(axis=0)) ** 2, axis=1))))
    quarter = max(len(kept) // 4, 1)
    slip = float(np.linalg.norm(kept[:quarter].mean(axis=0) - kept[-quarter:].mean(axis=0)))
    # The paper's own label, for comparison: the closest points of the gel centre itself.
    gel_inside = queries.signed_distance(T_window[:, :3, 3]) <= 0
    p_gel_centre = (
        queries.closest(queries.closest(T_window[gel_inside, :3, 3]).mean(axis=0)[None])[0]
        if gel_inside.any()
        else np.full(3, np.nan)
    )
    image_time = float(images.timestamps_s[chosen])
    # Poses at the chosen frame, averaged over the steady window (the sensor) and the contact (the still object),
    # so the mocap's frame-to-frame jitter does not enter the sample.
    half = config.steady_window_s / 2
    T_world_sensor = mean_pose(streams.world_sensor, image_time - half, image_time + half)
    T_world_body = mean_pose(object_stream, float(contact_times[0]), float(contact_times[-1]))
    if T_world_sensor is None or T_world_body is None:
        raise TrialRefused(f"no mocap pose at the chosen GelSight frame (t = {image_time:.2f} s)")
    trial.flags = ["slip"] if slip > config.slip_m else []
    trial.stats = {
        "contact_frames": count,
        "rejected_frames": int((~keep).sum()),
        "spread_mm": spread * 1e3,
        "slip_mm": slip * 1e3,
        "image_depth_mm": recon.max_depth_m * 1e3,
        "image_speed_mm_s": float(speeds[chosen] * 1e3),
        "image_time_s": image_time,
        "contact_centre_sensor_mm": (g_sensor[:2] * 1e3).tolist(),
        "p_object": p_mesh.tolist(),
        "p_object_gel_centre": p_gel_centre.tolist(),
        "dropped_frames": _dropped_in(streams.rig, contact_times[0], contact_times[-1]),
        "unusable_gelsight_frames": len(unusable),
    }
    trial.contact_span_s = (float(contact_times[0]), float(contact_times[-1]))
    trial.image_time_s = image_time
    trial.frame = frames[chosen]
    trial.labelled = LabelledContact(
        object_name=model.name,
        contact=TactileContact(recon.points_sensor, T_world_sensor, depth_scale_sigma=recon.depth_scale_sigma),
        T_world_mesh=T_world_body @ T_objectbody_mesh,
        p_mesh=p_mesh,
        side=side.name,
    )


def mean_pose(stream: PoseStream, start: float, end: float) -> np.ndarray | None:
    """The mean of a stream's poses in [start, end] (chordal mean of the rotations), or None without samples."""
    inside = (stream.timestamps_s >= start) & (stream.timestamps_s <= end)
    if not inside.any():
        return None
    T = stream.T_world_body[inside]
    # The rotation nearest the sum of the rotations: Procrustes of their axes onto the identity's.
    rotation, _ = procrustes_rotation(np.hstack(list(T[:, :3, :3])), np.tile(np.eye(3), len(T)))
    return make_transform(rotation, T[:, :3, 3].mean(axis=0))


def _dropped_in(stream: PoseStream, start: float, end: float) -> int:
    if stream.rate_hz <= 0:
        return 0
    inside = int(((stream.timestamps_s >= start) & (stream.timestamps_s <= end)).sum())
    return max(int(round((end - start) * stream.rate_hz)) + 1 - inside, 0)


def choose_frame(
    reconstructions: dict[int, Reconstruction], images: ImageStream, mesh_sensor: PoseStream, config: LabelConfig
) -> tuple[int, dict[int, float]]:
    """The frame of the steadiest deepest moment: among the frames moving (relative to the object) no faster than
    `steady_speed_m_s` or 1.5x the slowest, the deepest reconstruction. Returns it and each frame's speed."""
    indices = np.array(sorted(reconstructions))
    times = images.timestamps_s[indices]
    half = config.steady_window_s / 2
    before, ok_before = mesh_sensor.at(times - half, config.max_match_gap_s)
    after, ok_after = mesh_sensor.at(times + half, config.max_match_gap_s)
    moved = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1) / config.steady_window_s
    speed = np.where(ok_before & ok_after, moved, np.inf)
    speeds = {int(i): float(v) for i, v in zip(indices, speed)}
    limit = max(config.steady_speed_m_s, 1.5 * float(speed.min()))
    steady = [int(i) for i, v in zip(indices, speed) if v <= limit] or [int(i) for i in indices]
    return max(steady, key=lambda i: reconstructions[i].max_depth_m), speeds


def check_gelsight(images: ImageStream, side: RigSide) -> None:
    """The first frame must be one the GelSight calibration can reconstruct (same sensor, same lighting)."""
    first = in_rgb_order(images.frame(0), side.gelsight.background, f"{images.source} {images.name}")
    try:
        reconstruct(first, side.gelsight)
    except InputError as exc:
        raise InputError(
            f"{side.name} GelSight frames on '{images.name}' do not fit the GelSight calibration given for the "
            f"{side.name} rig ({exc.problem}): a calibration for another sensor?",
            images.source,
        ) from exc


def _stream_info(stream) -> dict[str, Any]:
    return {
        "name": stream.name,
        "samples": len(stream.timestamps_s),
        "rate_hz": stream.rate_hz,
        "dropped": stream.dropped,
        "span_s": list(stream.span_s),
    }


def match_pairs(left: list[TrialResult], right: list[TrialResult], config: LabelConfig) -> list[dict[str, Any]]:
    """Dual contacts: labelled trials of the two rigs whose contacts overlap in time."""
    pairs = []
    for a in left:
        for b in right:
            if a.labelled is None or b.labelled is None:
                continue
            overlap = min(a.contact_span_s[1], b.contact_span_s[1]) - max(a.contact_span_s[0], b.contact_span_s[0])
            if overlap < config.pair_overlap_s:
                continue
            motion = float(np.linalg.norm(a.labelled.T_world_mesh[:3, 3] - b.labelled.T_world_mesh[:3, 3]))
            if motion > config.max_object_motion_m:
                log.warning(
                    "trials %d/%d: the object moved %.2f mm between the two frames; no pair",
                    a.index,
                    b.index,
                    motion * 1e3,
                )
                continue
            pairs.append({"left": a, "right": b, "overlap_s": overlap, "object_motion_mm": motion * 1e3})
    return pairs


# ---------------------------------------------------------------------------------------------------------
# Files


def write_labels(report: LabelReport, out_dir: str | Path, prefix: str) -> dict[str, list[Path]]:
    """Write each labelled trial as a labelled contact (OUT/contacts/) and each dual contact as a contact-pair file
    with ground truth (OUT/pairs/); refused trials write nothing. The JSON of a contact or pair is written last,
    after its clouds and frames, so an interrupted run never leaves a record whose files are missing."""
    out_dir = Path(out_dir)
    written: dict[str, list[Path]] = {"contacts": [], "pairs": []}
    names: dict[int, tuple[str, str]] = {}
    for trial in report.trials:
        if trial.labelled is None or trial.frame is None:
            continue
        stem = f"{prefix}_{trial.side}_{trial.index:03d}"
        folder = out_dir / "contacts"
        write_ply_points(folder / f"{stem}.ply", trial.labelled.contact.points_sensor)
        write_bytes_atomic(folder / f"{stem}.png", png_bytes(trial.frame))
        trial.labelled.extra = {
            "label": {"flags": trial.flags, **trial.stats},
            "source": {"recording": trial.recording, "trial": trial.index, "window_s": [trial.start_s, trial.end_s]},
        }
        written["contacts"].append(
            write_labelled_contact(folder / f"{stem}.json", trial.labelled, f"{stem}.ply", f"{stem}.png")
        )
        names[id(trial)] = (stem, "contacts")
    for k, pair in enumerate(report.pairs):
        stem = f"{prefix}_pair_{k:03d}"
        folder = out_dir / "pairs"
        payload: dict[str, Any] = {"object": pair["left"].labelled.object_name}
        truth: dict[str, Any] = {}
        for side in SIDES:
            trial = pair[side]
            labelled = trial.labelled
            write_ply_points(folder / f"{stem}_{side}.ply", labelled.contact.points_sensor)
            write_bytes_atomic(folder / f"{stem}_{side}.png", png_bytes(trial.frame))
            payload[side] = {
                "points": f"{stem}_{side}.ply",
                "image": f"{stem}_{side}.png",
                "T_world_sensor": labelled.contact.T_world_sensor,
            }
            truth[f"{side}_p_object"] = labelled.p_mesh
        truth = {"T_world_object": pair["left"].labelled.T_world_mesh, **truth}
        payload["ground_truth"] = truth
        payload["label"] = {
            "left_trial": names[id(pair["left"])][0],
            "right_trial": names[id(pair["right"])][0],
            "overlap_s": pair["overlap_s"],
            "object_motion_mm": pair["object_motion_mm"],
        }
        written["pairs"].append(write_json_atomic(folder / f"{stem}.json", payload))
    return written


# ---------------------------------------------------------------------------------------------------------
# Refining the object calibration with the contacts


def refine_object_calibration(
    report: LabelReport, model: ObjectModel, object_calibration: ObjectCalibration, config: LabelConfig
) -> tuple[ObjectCalibration, dict[str, Any]]:
    """Refine `T_objectbody_mesh` so that the labelled contacts' tactile clouds lie on the mesh.

    The bead fit is only as good as the picks on the mesh (the paper's residuals: 1.5-2.2 mm), and that error goes
    straight into every label. A held contact is a few thousand points of the object's surface, measured by the
    GelSight and placed by mocap and the rig calibration (sub-millimetre): all contacts of a session, mapped into
    the object's rigid body, are registered onto the mesh by point-to-plane Gauss-Newton (`yoto.registration`),
    with the bead calibration as the prior (its residuals set the prior's width), so directions the contacts do not
    constrain stay where the beads put them. Slipping contacts are left out. Returns the refined calibration and
    what changed.
    """
    from yoto.registration import GaussNewtonConfig, plane_distances, point_to_plane_gauss_newton

    used = [t for t in report.trials if t.labelled is not None and not t.flags]
    if len(used) < config.refine_min_contacts:
        return object_calibration, {
            "refined": False,
            "reason": f"{len(used)} unflagged contacts (need {config.refine_min_contacts})",
        }
    T_body_mesh = object_calibration.T_objectbody_mesh
    rng = np.random.default_rng(0)
    clouds = []
    for trial in used:
        labelled = trial.labelled
        assert labelled is not None  # `used` holds labelled trials only
        T_body_sensor = T_body_mesh @ np.linalg.inv(labelled.T_world_mesh) @ labelled.contact.T_world_sensor
        points = labelled.contact.points_sensor
        keep = rng.choice(len(points), min(config.refine_points_per_contact, len(points)), replace=False)
        clouds.append(transform_points(T_body_sensor, points[keep]))
    points_body = np.concatenate(clouds)
    T_object_body = model.T_object_mesh @ np.linalg.inv(T_body_mesh)
    residual_m = max(object_calibration.residual_mm.get("rms", 1.0), 1.0) * 1e-3
    spread_m = float(np.sqrt(np.mean(np.sum((points_body - points_body.mean(0)) ** 2, axis=1))))
    gauss_newton = GaussNewtonConfig(
        iterations=30,
        max_distance_m=config.refine_reach_m,
        surface_noise_m=1e-4,
        prior_rotation_rad=max(residual_m / max(spread_m, 1e-3), np.radians(0.5)),
        prior_translation_m=residual_m,
    )

    def rms(T: np.ndarray) -> float:
        distance, matched, _, _ = plane_distances(model, transform_points(T, points_body), config.refine_reach_m)
        return float(np.sqrt(np.mean(distance[matched] ** 2))) if matched.any() else float("nan")

    pivot = points_body.mean(axis=0)
    refined = point_to_plane_gauss_newton(model, points_body, T_object_body[None], gauss_newton, pivot_source=pivot)[0]
    T_body_mesh_refined = np.linalg.inv(refined) @ model.T_object_mesh
    centre = model.T_mesh_object[:3, 3]
    change = {
        "refined": True,
        "contacts": len(used),
        "surface_rms_before_mm": rms(T_object_body) * 1e3,
        "surface_rms_after_mm": rms(refined) * 1e3,
        "moved_at_centre_mm": float(
            np.linalg.norm(transform_points(T_body_mesh_refined, centre) - transform_points(T_body_mesh, centre)) * 1e3
        ),
        "rotated_deg": float(np.degrees(np.linalg.norm(so3_log(T_body_mesh_refined[:3, :3] @ T_body_mesh[:3, :3].T)))),
    }
    refined_calibration = ObjectCalibration(
        object_calibration.object_name,
        object_calibration.object_body,
        T_body_mesh_refined,
        object_calibration.beads,
        object_calibration.residual_mm,
        {**object_calibration.sources, "refined_with_contacts": change},
    )
    return refined_calibration, change
