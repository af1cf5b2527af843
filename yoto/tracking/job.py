"""`yoto track` as a function: files in (a touch, two sensor streams, tactile frames, ground truth), files out.

The touch's pose comes from the pose stage (`yoto.pose.estimate_pose` on the contact pair) or from a pose result
file `yoto pose` wrote. Tracked poses are written as a TUM file of `T_world_object` in the mesh file's frame, at
every timestamp of the sensor streams from the touch on (SPEC). With ground truth, the errors of the tracked poses
(and of the open loop beside them) are summarised as the paper's Table 3 and plotted like its Fig. 4.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import SIDES, ContactPair, read_contact_pair
from yoto.errors import InputError
from yoto.geometry import (
    invert_transform,
    quaternion_xyzw_to_rotation,
    rotation_to_quaternion_xyzw,
    transform_points,
    validate_transform,
)
from yoto.io import read_json, write_json_atomic
from yoto.objects.model import ObjectModel
from yoto.sensor.pair_images import ImageSides
from yoto.tracking.config import TrackConfig
from yoto.tracking.evaluate import (
    ErrorCurve,
    motion_interval,
    plot_tracking,
    summarize_errors,
    tracking_errors,
    truth_at,
)
from yoto.tracking.frame_registration import contact_samples
from yoto.tracking.pinning import Retouch, retouch
from yoto.tracking.release import NewTouchEstimator
from yoto.tracking.streams import TactileStream, holds_images, read_sensor_stream, read_tactile_stream
from yoto.tracking.touch import touch_from_pair, touch_time_of
from yoto.tracking.track import TrackResult, tactile_timing_warnings, track
from yoto.trajectory import PoseStream, write_tum


@dataclass(frozen=True)
class Source:
    """A stream in a file: a TUM file or frame folder, or a recording (bag, Motive CSV) and the topic or body in it."""

    path: Path
    topic: str | None = None  # bag topic, or Motive rigid-body name; None for TUM files and frame folders
    # A recording gives rigid bodies: the calibration that maps the body to the frame the job needs, a rig calibration
    # (`yoto rig calibrate-rig`: T_rig_sensor) for a sensor stream, an object calibration (`yoto rig calibrate-object`:
    # T_objectbody_mesh) for the ground truth. None: the stream is that frame's already.
    calibration: Path | None = None


@dataclass(frozen=True)
class TrackJob:
    """What `yoto track` reads and writes."""

    pair: Path  # the touch: a contact pair file (SPEC)
    sensors: dict[str, Source]  # side -> the sensor's pose stream T_world_sensor
    out: Path  # tracked T_world_object (mesh file's frame), TUM
    tactile: dict[str, Source] = field(default_factory=dict)  # side -> tactile frames during motion (closed loop)
    calibration: Path | None = None  # sensor calibration for GelSight images (touch, tactile frames) naming none
    pose_result: Path | None = None  # the touch's pose from a `yoto pose` result instead of estimating it
    method: str = "match"  # contact localizer for the touch's pose
    checkpoint: str | None = None  # network weights for method "yoto"
    model: str | None = None  # object model name or file (default: the pair's object)
    workspace: str | None = None
    touch_time_s: float | None = None  # default: the pair file's "timestamp", else matched to the streams
    truth: Source | None = None  # ground truth T_world_object (mesh file's frame): TUM, or mocap of the object
    report: Path | None = None  # JSON report (per-instant corrections, errors)
    figure: Path | None = None  # error plot (needs `truth`)


@dataclass
class TrackOutcome:
    """What a `TrackJob` produced."""

    result: TrackResult
    touch_source: str
    errors: dict[str, dict[str, Any]] = field(default_factory=dict)  # "closed_loop"/"open_loop" -> Table-3 figures
    written: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    retouch: Retouch | None = None  # where a contact would pin the weakest direction (mesh file's frame), when the
    # contacts pin it worse than the drift target (`TrackConfig.retouch_above`)
    regrasp_errors: list[dict[str, dict[str, Any]]] = field(default_factory=list)  # per regrasp, as `errors`
    # (its touch to its release; `errors` then covers the first grasp only)


def read_stream(source: Source, name: str, frame: str) -> PoseStream:
    """A pose stream of `frame` ("sensor": T_world_sensor, "mesh": T_world_mesh): the file's own, or its rigid body's
    composed with the source's calibration (T_rig_sensor, T_objectbody_mesh)."""
    from yoto.rig.beads import load_object_calibration
    from yoto.rig.calibration import load_rig_calibration

    stream = read_sensor_stream(source.path, source.topic, name)
    if source.calibration is None:
        return stream
    if frame == "sensor":
        T_body_frame = load_rig_calibration(source.calibration).T_rig_sensor
    else:
        T_body_frame = load_object_calibration(source.calibration).T_objectbody_mesh
    return PoseStream(stream.timestamps_s, stream.T_world_frame @ T_body_frame, stream.name, stream.source)


def read_streams(job: TrackJob) -> dict[str, PoseStream]:
    return {side: read_stream(job.sensors[side], f"{side} sensor", "sensor") for side in SIDES}


def read_tactile(job: TrackJob, pair: ContactPair, images: ImageSides) -> dict[str, TactileStream]:
    """Each side's tactile frames; GelSight images among them are reconstructed with the side's calibration: the
    touch side's own `calibration` / `background` entries where it gives an image, else `--calibration`."""
    streams = {}
    for side, source in job.tactile.items():
        calibration = None
        if holds_images(source.path):
            image = pair.contact(side).image
            calibration = images.calibration(image.calibration if image else None, image.background if image else None)
        recording = job.sensors[side].path  # a Motive take puts a folder of images on its clock
        streams[side] = read_tactile_stream(source.path, source.topic, calibration, f"{side} tactile", recording)
    return streams


def read_as_wxyz(stream: PoseStream) -> PoseStream:
    """The stream as it is if its file's quaternion columns were written w x y z (TUM's order is x y z w)."""
    as_read = rotation_to_quaternion_xyzw(stream.T_world_frame[:, :3, :3])  # the file's columns (up to sign)
    T_world_frame = stream.T_world_frame.copy()
    T_world_frame[:, :3, :3] = quaternion_xyzw_to_rotation(as_read[:, [1, 2, 3, 0]])
    return PoseStream(stream.timestamps_s, T_world_frame, stream.name, stream.source)


def quaternion_order_hint(job: TrackJob, pair: ContactPair, streams: dict[str, PoseStream], config: TrackConfig) -> str:
    """When TUM streams far from the pair's sensor poses at the touch fit them with their quaternions read w x y z (a
    writer's wrong column order; a unit quaternion either way), the hint naming the files; else ""."""
    tum = [side for side in SIDES if job.sensors[side].topic is None]
    for sides in [[side] for side in tum] + ([tum] if len(tum) == 2 else []):
        permuted = {side: read_as_wxyz(stream) if side in sides else stream for side, stream in streams.items()}
        if touch_time_of(pair, permuted, job.touch_time_s, config)[2] <= config.touch_mismatch_warning_m:
            files = " and ".join(str(job.sensors[side].path) for side in sides)
            return f" (they fit if the quaternions of {files} are read as w x y z: TUM's order is x y z w)"
    return ""


def touch_pose(job: TrackJob, pair: ContactPair, model: ObjectModel) -> tuple[np.ndarray, str, float | None]:
    """The touch's T_world_object (canonical frame), where it came from, and its confidence (None if unknown)."""
    if job.pose_result is not None:
        payload = read_json(job.pose_result)
        if not isinstance(payload, dict) or "T_world_object" not in payload:
            raise InputError("not a pose result (no 'T_world_object')", job.pose_result)
        T_world_mesh = validate_transform(payload["T_world_object"], "T_world_object", job.pose_result)
        confidence = payload.get("confidence")
        return (
            T_world_mesh @ model.T_mesh_object,
            f"pose result {job.pose_result.name}",
            float(confidence) if isinstance(confidence, (int, float)) else None,
        )
    from yoto.localize import make_localizer
    from yoto.pose import estimate_pose

    estimate = estimate_pose(pair, model, make_localizer(job.method, job.checkpoint))
    source = f"yoto pose ({job.method}), confidence {estimate.confidence:.2f}"
    return estimate.T_world_object, source, estimate.confidence


def new_touch_estimator(job: TrackJob, pair: ContactPair, model: ObjectModel) -> NewTouchEstimator:
    """The pose stage for a new touch after a release (`track`'s `new_touch`): the new pair's clouds and sensor poses
    with the touch pair's sides otherwise (their depth-scale prior), localized with the track's localizer (the
    oracle, which needs the true contacts, with the matched filter)."""
    from yoto.localize import make_localizer
    from yoto.pose.pipeline import PoseConfig, estimate_pose

    localizers: list[Any] = []

    def estimate(new: ContactPair) -> Any:
        if not localizers:  # built on the first new touch only
            method = "match" if job.method == "oracle" else job.method
            localizers.append(make_localizer(method, job.checkpoint if method == job.method else None))
        left, right = (
            replace(
                pair.contact(side),
                points_sensor=new.contact(side).points_sensor,
                T_world_sensor=new.contact(side).T_world_sensor,
                source=None,
                image=None,
            )
            for side in SIDES
        )
        config = PoseConfig(suggest_next_touch=False)
        return estimate_pose(ContactPair(pair.object_name, left, right), model, localizers[0], config)

    return estimate


def check_sources_distinct(job: TrackJob) -> None:
    """Refuse one source for both sensors (the same pose file, tactile folder, or recording and topic), before anything
    is read: the left sensor's stream would be taken for the right one's too, silently."""
    for what, sources in (("pose streams", job.sensors), ("tactile frames", job.tactile)):
        left, right = sources.get("left"), sources.get("right")
        if left is None or right is None or left.path.resolve() != right.path.resolve() or left.topic != right.topic:
            continue
        where = f" (topic {left.topic})" if left.topic else ""
        own = "topic" if left.topic else "file" if what == "pose streams" else "folder or topic"
        raise InputError(
            f"the left and right {what} are the same source, {left.path}{where}: give each sensor its own {own}"
        )


def run_track_job(job: TrackJob, config: TrackConfig = TrackConfig()) -> TrackOutcome:
    """Read the job's files, track, write the tracked poses (and report, figure); return what happened."""
    from yoto.objects.build import load_object_model

    check_sources_distinct(job)
    images = ImageSides(job.calibration)  # the touch's image sides and image tactile frames
    pair = read_contact_pair(job.pair, images)
    model = load_object_model(job.model or pair.object_name, job.workspace)
    streams = read_streams(job)
    tactile = read_tactile(job, pair, images)
    # Every input is read (and the truth checked against the track) before anything is written: a failing
    # command writes nothing.
    truth_stream = None
    if job.truth is not None:
        truth_stream = read_stream(job.truth, "object ground truth", "mesh")
    warnings = []
    time_s, time_source, mismatch = touch_time_of(pair, streams, job.touch_time_s, config)
    hint = (
        " (a recording's rigid body is not its GelSight: give the rig calibrations, --left-rig / --right-rig)"
        if any(job.sensors[side].topic and job.sensors[side].calibration is None for side in SIDES)
        else ""
    )
    if mismatch > config.touch_mismatch_warning_m:
        hint = hint or quaternion_order_hint(job, pair, streams, config)
        where = (
            f"the sensor streams never come closer than {mismatch * 1e3:.1f} mm (position plus 50 mm per radian) to"
            if time_source.startswith("matched")
            else f"at the touch the sensor streams are {mismatch * 1e3:.1f} mm (position plus 50 mm per radian) from"
        )
        warnings.append(
            f"{where} the pair file's sensor poses: are they the same recording, in the same world frame?{hint}"
        )
    T_world_object, pose_source, confidence = touch_pose(job, pair, model)
    if confidence is not None and confidence < config.min_touch_confidence:
        warnings.append(
            f"the touch's pose has confidence {confidence:.2f}: it is likely wrong, and so is everything tracked from "
            "it; touch again (the pose result's next_touch says where) before relying on the track"
        )
    touch = touch_from_pair(pair, T_world_object, time_s, time_source)
    touch.mismatch_m = mismatch
    warnings += tactile_timing_warnings(tactile, streams, time_s) if tactile else []
    estimator = new_touch_estimator(job, pair, model) if set(tactile) >= set(SIDES) else None
    result = track(touch, streams, model, tactile or None, config, estimator)
    outcome = TrackOutcome(result, pose_source, warnings=warnings)
    if result.pinning is not None and result.pinning.spread[0] > config.retouch_above:
        contacts = np.vstack(
            [
                transform_points(
                    invert_transform(T_world_object) @ contact.T_world_sensor,
                    contact_samples(contact.points_sensor, config.correction),  # as the closed loop samples frames
                )
                for contact in map(pair.contact, SIDES)
            ]
        )
        outcome.retouch = retouch(model, result.pinning.twist(0), contacts).in_frame(model.T_mesh_object)
    curves = None
    panels = []
    if truth_stream is not None:
        outcome.errors, curves = evaluate_against_truth(result, truth_stream, streams, model)
        panels.append((f"{model.name}: tracking error", curves, outcome.errors["open_loop"]["motion_s"]))
        for index, regrasp in enumerate(result.regrasps, start=1):
            errors, regrasp_curves = evaluate_against_truth(result, truth_stream, streams, model, index)
            outcome.regrasp_errors.append(errors)
            when = f"{regrasp.touch.time_s - time_s:.2f} s"
            panels.append(
                (f"new touch {index} ({when} after the touch)", regrasp_curves, errors["open_loop"]["motion_s"])
            )
    mode = "closed loop (corrected by tactile frames)" if result.closed_loop else "open loop"
    warnings += grasp_warnings(result, curves is not None, config.min_touch_confidence)
    if result.released_s is not None:
        held = int(np.count_nonzero(~result.grasped))
        mode += (
            f"; released at {result.released_s:.6f} s (both gels without contact), {len(result.regrasps)} new "
            f"touch(es) after releases: the {held} poses while nothing held the object repeat the last pose before"
        )
    outcome.written.append(
        write_tum(
            job.out,
            PoseStream(result.timestamps_s, result.T_world_mesh(model), "object"),
            f"T_world_object of {model.name}, the mesh file's frame; yoto track, {mode}; touch at {time_s:.6f} s",
        )
    )
    pinning = result.pinning
    if pinning is not None and pinning.spread[0] > config.weak_pinning_warning:
        warnings.append(
            "the two contacts barely pin one direction of the object's pose: "
            f"{pinning.describe(0)} (a reconstruction's smooth error moves the registration that far along it); slip "
            "along it is not observable from the contacts, the closed loop corrects it only as far as the slip's "
            "history along the path shows it"
        )
    if result.skipped_times:
        warnings.append(f"{result.skipped_times} stream timestamps had no pose of either sensor (dropouts): skipped")
    if curves is not None:
        if job.figure is not None:
            panels = [(name, lines, None if motion is None else tuple(motion)) for name, lines, motion in panels]
            outcome.written.append(plot_tracking(panels, job.figure))
    elif job.figure is not None:
        warnings.append("--figure needs ground truth (--truth); no figure written")
    if job.report is not None:
        outcome.written.append(write_json_atomic(job.report, report_payload(job, model, outcome)))
    return outcome


def grasp_warnings(result: TrackResult, with_truth: bool, min_confidence: float) -> list[str]:
    """What `yoto track` says about gels that let go, releases and new touches."""
    warnings = []
    for event in result.let_go:
        other = SIDES[1 - SIDES.index(event.side)]
        again = (
            f"; it touched again at {event.touched_again_s:.3f} s: its grasp taken from the tracked pose then"
            if event.touched_again_s is not None
            else ""
        )
        warnings.append(
            f"the {event.side} gel lost contact at {event.time_s:.3f} s while the {other} one held on: from then on "
            f"the {other} sensor alone carries the object{again}"
        )
    grasps = result.grasps()
    for index, (touch, released_s) in enumerate(grasps):
        if released_s is None:
            continue
        what = "the touch" if index == 0 else f"new touch {index}"
        errors = " (the errors cover each grasp, touch to release)" if with_truth else ""
        later = (
            f"both touched again at {grasps[index + 1][0].time_s:.3f} s: a new touch, its pose estimated from that pair"
            if index + 1 < len(grasps)
            else f"{result.frames_after_release} later tactile frames not tracked"
        )
        warnings.append(
            f"both gels lost contact at {released_s:.3f} s, {released_s - touch.time_s:.2f} s after {what}, and stayed "
            f"without it: the object was released, the grasp ends there{errors}; the poses after it repeat the last "
            f"pose before it; {later}"
        )
    for index, regrasp in enumerate(result.regrasps, start=1):
        chosen = (
            f", ambiguous: hypothesis {regrasp.hypothesis} taken, the nearest the last tracked pose"
            if regrasp.ambiguous
            else ""
        )
        warnings.append(f"new touch {index} at {regrasp.touch.time_s:.3f} s: pose from {regrasp.pose_from}{chosen}")
        if regrasp.confidence < min_confidence:
            warnings.append(
                f"new touch {index}'s pose has confidence {regrasp.confidence:.2f}: it is likely wrong, and so is "
                "everything tracked from it"
            )
    for refused in result.regrasps_refused:
        warnings.append(f"a new touch's pose was refused, the last pose held ({refused})")
    return warnings


def evaluate_against_truth(
    result: TrackResult, truth_mesh: PoseStream, streams: dict[str, PoseStream], model: ObjectModel, grasp: int = 0
) -> tuple[dict[str, dict[str, Any]], list[ErrorCurve]]:
    """Table-3 figures of the tracked (and open-loop) poses of one grasp (`TrackResult.grasps`: 0 the touch's, then
    each regrasp's) against a ground-truth `T_world_mesh` stream, and the per-frame error curves (times relative to
    the grasp's touch)."""
    touch = result.grasps()[grasp][0]
    truth, covered = truth_at(truth_mesh, result.timestamps_s, model.T_mesh_object)
    covered &= result.grasp_rows(grasp)  # after a release the tracked pose means nothing
    times = result.timestamps_s[covered]
    truth_touch, _ = truth_at(truth_mesh, np.array([touch.time_s]), model.T_mesh_object)
    motion = motion_interval(streams, times)
    variants = {"open_loop": result.T_world_object_open_loop}
    if result.closed_loop:
        variants = {"closed_loop": result.T_world_object, **variants}
    summaries, curves = {}, []
    for name, poses in variants.items():
        errors = tracking_errors(times, poses[covered], truth[covered], touch.T_world_object, truth_touch[0])
        summaries[name] = summarize_errors(errors, motion)
        mean = summaries[name]["motion_mean"]
        curves.append(
            ErrorCurve(
                name.replace("_", " "),
                times - touch.time_s,
                1e3 * errors.translation_m,
                np.degrees(errors.rotation_rad),
                (mean["mm"], mean["deg"]),
            )
        )
    for summary in summaries.values():  # motion times relative to the touch, as the curves
        if summary["motion_s"] is not None:
            summary["motion_s"] = [value - touch.time_s for value in summary["motion_s"]]
    return summaries, curves


def report_payload(job: TrackJob, model: ObjectModel, outcome: TrackOutcome) -> dict[str, Any]:
    """The JSON report: the touch, the streams' jitter, every tactile instant, errors when there was a truth."""
    result = outcome.result
    return {
        "object": model.name,
        "frame": "mesh file frame (the frame of the mesh the object model was built from)",
        "mode": "closed loop" if result.closed_loop else "open loop",
        "out": str(job.out),
        "touch": {
            "time_s": result.touch.time_s,
            "time_from": result.touch.time_source,
            "pose_from": outcome.touch_source,
            "T_world_object": result.touch.T_world_object @ model.T_object_mesh,
        },
        "frames": len(result.timestamps_s),
        "released_s": result.released_s,  # both gels lost contact for good: poses from then on hold, errors end
        "let_go": [  # one gel let go while the other held: that one alone carried the object until it touched again
            {"side": e.side, "time_s": e.time_s, "seen_s": e.seen_s, "touched_again_s": e.touched_again_s}
            for e in result.let_go
        ],
        "regrasps": [  # both gels touched again after a release: a new touch, tracked to its own release
            {
                "time_s": regrasp.touch.time_s,
                "pose_from": regrasp.pose_from,
                "confidence": regrasp.confidence,
                "ambiguous": regrasp.ambiguous,
                "hypothesis": regrasp.hypothesis,
                "T_world_object": regrasp.touch.T_world_object @ model.T_object_mesh,
                "released_s": regrasp.released_s,
                "errors": outcome.regrasp_errors[index] if index < len(outcome.regrasp_errors) else None,
            }
            for index, regrasp in enumerate(result.regrasps)
        ],
        "regrasps_refused": result.regrasps_refused,
        "skipped_times": result.skipped_times,
        "jitter": {
            side: {
                "translation_mm": 1e3 * jitter.translation_m,
                "rotation_deg": float(np.degrees(jitter.rotation_rad)),
                "glitches": int(jitter.glitch.sum()),
                "left_out": jitter.left_out,  # samples off the stream's motion (a mis-fitted or flipped body)
                "dropouts_s": list(jitter.dropouts_s),  # gaps longer than max_gap_s: the other sensor alone there
            }
            for side, jitter in result.jitter.items()
        },
        "closed_loop": result.correction_summary() if result.closed_loop else None,
        "corrections": [
            {
                "time_s": c.timestamp_s,
                "used": list(c.used),
                "unusable": c.unusable,
                "correction_mm": 1e3 * c.correction_m,
                "correction_deg": float(np.degrees(c.correction_rad)),
                "slip_mm": 1e3 * c.slip_m,
                "slip_deg": float(np.degrees(c.slip_rad)),
                "guard": c.guard,
                "held": c.held,
                "sigma_deg": float(np.degrees(c.sigma_rad)),
                "sigma_mm": 1e3 * c.sigma_m,
                "latency_ms": c.latency_ms,
                "read_mm": {side: 1e3 * depth for side, depth in c.indentation_m.items()},  # each frame's press
            }
            for c in result.corrections
        ],
        "pinning": None
        if result.pinning is None
        else {
            "about": "the directions of the pose (turn in deg, shift in mm; object frame about its centroid), weakest "
            "first, and how far a reconstruction's smooth error moves the two contacts' registration along each "
            "(spread, in units of the direction)",
            "directions": [
                np.concatenate([np.degrees(twist[:3]), 1e3 * twist[3:]]).tolist()
                for twist in map(result.pinning.twist, range(6))
            ],
            "spread": result.pinning.spread.tolist(),
        },
        "retouch": None
        if outcome.retouch is None
        else {
            "about": "where a contact would see the weakest direction of `pinning` (mesh file's frame): the surface "
            "point and its outward normal, and how far one unit of that direction moves the surface there along its "
            "normal (seen_mm; root mean square over a contact-sized patch) against at the touch's contacts",
            "point_mm": (1e3 * outcome.retouch.point).tolist(),
            "normal": outcome.retouch.normal.tolist(),
            "seen_mm": 1e3 * outcome.retouch.seen_m,
            "seen_at_contacts_mm": 1e3 * outcome.retouch.seen_at_contacts_m,
        },
        "errors": outcome.errors or None,
        "warnings": outcome.warnings,
    }
