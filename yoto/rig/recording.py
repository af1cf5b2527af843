"""`yoto simulate recording`: a scripted lab session on a known mesh, written as a real rig would record it.

The session (paper App. B), with two hand-held GelSight rigs, a bead-instrumented object and OptiTrack:
- `gel_left`, `gel_right`: the dual-ball procedure, each rig held still in `calibration_poses` poses with a ball on
  its gel centre (`GelBall`) and a reference ball (`RefBall`) visible as single markers;
- `plate_left`, `plate_right`: flat presses on a plate rigid body (`Plate`, surface normal = its body's +z);
- `beads`: a still capture of the object's rigid body (`Object`) and its bead markers (`Bead1`...);
- `trials`: single contacts of each rig (approach, hold about `hold_s`, withdrawal), dual contacts, and on request
  near misses, slipping holds and long dropouts; the object body, both rig bodies and both GelSight image streams.
Contacts are pressed into the mesh by the contact simulator (`yoto.simulate`), their GelSight frames rendered by the
optical simulator (`yoto.sensor.render_image`) from a sensor calibration. Mocap reports rigid-body poses and
markers with noise and dropouts (`MocapNoise`); the user's bead picks on the mesh carry a picking error; the rig's
CAD rotation differs from the assembled rig by `cad_rotation_error_deg`.

Written as ROS1 bags (`ros1/*.bag`: PoseStamped, PointStamped, Image rgb8 / bgr8), ROS2 bags (`ros2_db3/`,
PoseStamped and Image; `ros2_mcap/`, rigid bodies on TF and CompressedImage PNG) and Motive CSV takes
(`motive/*.csv` in millimetres, GelSight PNGs named by take time in `motive/trials_left/`, `trials_right/`). Beside
them: `beads.json` (the picks), `cad_left.json`, `cad_right.json` (the CAD rotations), `session.json` (names and
topics), `truth.json` (everything the simulator knows, for benchmarks) and `true.object.json` (the simulator's own
object calibration in `yoto rig calibrate-object`'s format, for `yoto track --truth-calibration`: the truth without
the bead fit's error).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError
from yoto.geometry import (
    invert_transform,
    make_transform,
    normalize,
    quaternion_xyzw_to_rotation,
    random_rotations,
    rotation_about_axis,
    rotation_between,
    rotation_to_quaternion_xyzw,
    so3_exp,
    transform_points,
)
from yoto.io import png_bytes, write_bytes_atomic, write_json_atomic
from yoto.objects.model import ObjectModel
from yoto.rig.bags import BagWriter
from yoto.rig.beads import ObjectCalibration, pick_vertices_mesh
from yoto.rig.motive import write_motive_csv
from yoto.rig.timeline import slerp
from yoto.sensor.calibration import SensorCalibration
from yoto.sensor.optical import render_image
from yoto.simulate.gel import ReconstructionNoise, gel_surface
from yoto.simulate.press import Press, PressConfig, press_contact
from yoto.simulate.scenarios import PairSimulator, ScenarioConfig, SimulationError

log = logging.getLogger("yoto")

FORMATS = ("ros1", "ros2-db3", "ros2-mcap", "motive")
FORMAT_FOLDERS = {"ros1": "ros1", "ros2-db3": "ros2_db3", "ros2-mcap": "ros2_mcap", "motive": "motive"}
SIDES = ("left", "right")
BODY_TOPIC = "/vrpn_client_node/{}/pose"
MARKER_TOPIC = "/mocap/marker/{}"
IMAGE_TOPIC = "/gelsight_{}/image_raw"
RIG_BODIES = {"left": "RigLeft", "right": "RigRight"}
OBJECT_BODY = "Object"  # the object's rigid body (its mocap name and topic)


@dataclass(frozen=True)
class MocapNoise:
    """What the mocap and the user get wrong. The defaults ("paper") give the paper's sub-millimetre gel-centre
    dispersion and its bead residuals (1.5-2.2 mm, mostly the picking of beads on the mesh); `mocap()` keeps the
    mocap's jitter and dropouts but picks the beads carefully (0.3 mm)."""

    body_position_std_m: float = 0.0002  # per-frame jitter of a rigid body's position, per axis
    body_rotation_std_deg: float = 0.1  # per-frame jitter of its orientation (rotation vector, per axis)
    marker_std_m: float = 0.0002  # per-frame jitter of a single marker, per axis
    dropout_fraction: float = 0.01  # share of frames lost to occlusion (each body and marker on its own)
    dropout_mean_frames: float = 4.0  # mean length of an occlusion
    bead_pick_std_m: float = 0.002  # the user's pick of a bead on the mesh, per axis (snapped to a vertex)
    cad_rotation_error_deg: float = 1.0  # the rig as built vs its CAD rotation
    cad_translation_error_m: float = 0.001  # ... and gel centre

    @classmethod
    def none(cls) -> MocapNoise:
        return cls(0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    @classmethod
    def mocap(cls) -> MocapNoise:
        return dataclasses.replace(cls(), bead_pick_std_m=0.0003)

    @classmethod
    def preset(cls, name: str) -> MocapNoise:
        presets: dict[str, Callable[[], MocapNoise]] = {"paper": cls, "mocap": cls.mocap, "none": cls.none}
        if name not in presets:
            raise InputError(f"unknown noise preset '{name}' (use {', '.join(presets)})")
        return presets[name]()


@dataclass(frozen=True)
class RecordingConfig:
    """The scripted session."""

    mocap_rate_hz: float = 120.0  # rigid bodies and markers
    camera_rate_hz: float = 25.0  # GelSight frames
    single_trials: int = 4  # single contacts per rig
    dual_trials: int = 3  # both rigs at once
    miss_trials: int = 0  # approaches that stop 3 mm short of the surface (no contact)
    slip_trials: int = 0  # holds during which the gel slides 4 mm over the surface
    dropout_trials: int = 0  # holds with a 0.4 s occlusion of the rig
    calibration_poses: int = 6  # still poses of the dual-ball procedure
    plate_presses: int = 4
    hold_s: float = 1.0  # the hold of a contact
    approach_s: float = 0.6  # from `approach_distance_m` off the surface to the full press (and back)
    approach_distance_m: float = 0.03
    move_s: float = 0.5  # from the parking sphere to the approach start (and back)
    transfer_s: float = 0.8  # between trials, along the parking sphere
    park_margin_m: float = 0.12  # the parking sphere's radius beyond the object's bounding sphere
    tremor_m: float = 5e-5  # hand tremor during a hold (per axis, slow)
    beads: int = 5
    bead_radius_m: float = 0.005
    ball_height_m: float = 0.0025  # the gel ball's centre above the gel
    noise: MocapNoise = MocapNoise()
    start_epoch_s: float = 1_700_000_000.0  # header stamps: POSIX seconds of the session's start
    seed: int = 0


@dataclass
class Trial:
    """One scripted contact of one rig."""

    side: str
    kind: str  # single, dual, miss, slip, dropout
    press: Press
    T_mesh_sensor: np.ndarray  # final (full-press) sensor pose, mesh frame
    start_s: float = 0.0  # block start (after the transfer)
    slip_direction: np.ndarray | None = None  # sensor-frame unit vector of the slide (slip trials)
    extra_backoff_m: float = 0.0  # a miss stops this far short of the full press

    def timings(self, config: RecordingConfig) -> tuple[float, float, float, float]:
        """Block-relative times: approach start, hold start, hold end, withdrawal end."""
        a = config.move_s
        b = a + config.approach_s
        c = b + config.hold_s
        return a, b, c, c + config.approach_s


def minimum_jerk(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u**2)


# ---------------------------------------------------------------------------------------------------------
# The scene


class Scene:
    """The truth: object, beads, rigs, plate."""

    def __init__(self, model: ObjectModel, config: RecordingConfig, rng: np.random.Generator):
        self.model = model
        self.config = config
        noise = config.noise
        self.T_world_mesh = make_transform(random_rotations(rng, 1)[0], np.array([0.0, 0.0, 0.25]))
        vertices = model.mesh_vertices_mesh
        self.centre_mesh = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        self.radius = float(np.linalg.norm(vertices - self.centre_mesh, axis=1).max())
        self.park_radius = self.radius + config.park_margin_m
        # Beads: spread over the surface (farthest-point picks of the parent cloud), centres r along the normal.
        points_mesh = transform_points(
            model.T_mesh_object, model.points_object[:: max(1, len(model.points_object) // 4000)]
        )
        chosen = [int(rng.integers(len(points_mesh)))]
        for _ in range(config.beads - 1):
            distance = np.min(np.linalg.norm(points_mesh[:, None] - points_mesh[chosen][None], axis=2), axis=1)
            chosen.append(int(np.argmax(distance)))
        feet = points_mesh[chosen]
        normals = model.T_mesh_object[:3, :3] @ model.aggregated_normal(transform_points(model.T_object_mesh, feet)).T
        self.bead_foot_mesh = model.raycaster.closest_points(transform_points(model.T_object_mesh, feet))
        self.bead_foot_mesh = transform_points(model.T_mesh_object, self.bead_foot_mesh)
        self.bead_centre_mesh = self.bead_foot_mesh + config.bead_radius_m * normalize(normals.T)
        self.bead_names = [f"Bead{i + 1}" for i in range(config.beads)]
        picked = self.bead_foot_mesh + rng.normal(scale=noise.bead_pick_std_m, size=self.bead_foot_mesh.shape)
        # Picked as a user picks them in a mesh viewer: ids of the mesh file's vertices, in the file's order.
        pick_vertices = pick_vertices_mesh(model)
        self.bead_pick_vertices = [int(np.argmin(np.linalg.norm(pick_vertices - p, axis=1))) for p in picked]
        # The object's rigid body: origin at the beads' centroid, axes along the world's (as Motive defines one).
        centroid_world = transform_points(self.T_world_mesh, self.bead_centre_mesh).mean(axis=0)
        self.T_world_objectbody = make_transform(np.eye(3), centroid_world)
        self.T_objectbody_mesh = invert_transform(self.T_world_objectbody) @ self.T_world_mesh
        # Rigs: an L-shaped handle; the GelSight at the tip, its z along the rig's x, small assembly offsets.
        self.T_rig_sensor: dict[str, np.ndarray] = {}
        self.cad: dict[str, np.ndarray] = {}
        self.p_rig_reference = {"left": np.array([0.02, 0.035, 0.01]), "right": np.array([0.025, -0.03, 0.012])}
        for side in SIDES:
            nominal = make_transform(
                rotation_between(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])), np.array([0.09, 0.0, -0.02])
            )
            assembly = make_transform(so3_exp(rng.normal(size=3) * np.radians(1.5)), rng.normal(size=3) * 0.002)
            self.T_rig_sensor[side] = nominal @ assembly
            error_axis = rng.normal(size=3)
            cad_rotation = (
                rotation_about_axis(error_axis, np.radians(noise.cad_rotation_error_deg))
                @ self.T_rig_sensor[side][:3, :3]
            )
            cad_translation = (
                self.T_rig_sensor[side][:3, 3] + normalize(rng.normal(size=3)) * noise.cad_translation_error_m
            )
            self.cad[side] = make_transform(cad_rotation, cad_translation)
        self.T_world_plate = make_transform(
            rotation_about_axis(np.array([1.0, 0.3, 0.0]), np.radians(4.0)), np.array([0.5, 0.0, 0.0])
        )

    def far_pose(self, T_world_sensor: np.ndarray) -> tuple[np.ndarray, float]:
        """The sensor backed off along its axis onto the parking sphere, and the back-off distance."""
        a = T_world_sensor[:3, 3] - transform_points(self.T_world_mesh, self.centre_mesh)
        z = T_world_sensor[:3, 2]
        along = float(a @ z)
        backoff = along + np.sqrt(max(along**2 - a @ a + self.park_radius**2, 0.0))
        return T_world_sensor @ make_transform(np.eye(3), np.array([0.0, 0.0, -backoff])), backoff

    def park_pose(self, side: str) -> np.ndarray:
        """A rig's resting pose at the start: on the parking sphere, on its own side, facing the object."""
        direction = np.array([0.0, 1.0 if side == "left" else -1.0, 0.3])
        centre = transform_points(self.T_world_mesh, self.centre_mesh)
        position = centre + self.park_radius * normalize(direction)
        return make_transform(rotation_between(np.array([0.0, 0.0, 1.0]), -normalize(direction)), position)


def sphere_path(scene: Scene, T_a: np.ndarray, T_b: np.ndarray, u: np.ndarray) -> np.ndarray:
    """From one parked pose to another along the parking sphere (positions) and by slerp (rotations)."""
    centre = transform_points(scene.T_world_mesh, scene.centre_mesh)
    s = minimum_jerk(u)
    da, db = normalize(T_a[:3, 3] - centre), normalize(T_b[:3, 3] - centre)
    qa, qb = rotation_to_quaternion_xyzw(T_a[:3, :3]), rotation_to_quaternion_xyzw(T_b[:3, :3])
    qb = qb if qa @ qb >= 0 else -qb
    if np.linalg.norm(da - db) < 1e-9:
        directions = np.tile(da, (len(u), 1))
    else:
        angle = np.arccos(np.clip(da @ db, -1, 1))
        directions = (np.sin((1 - s) * angle)[:, None] * da + np.sin(s * angle)[:, None] * db) / np.sin(angle)
    T = np.tile(np.eye(4), (len(u), 1, 1))
    T[:, :3, :3] = quaternion_xyzw_to_rotation(slerp(np.tile(qa, (len(u), 1)), np.tile(qb, (len(u), 1)), s))
    T[:, :3, 3] = centre + scene.park_radius * directions
    return T


# ---------------------------------------------------------------------------------------------------------
# Mocap sampling


def dropout_mask(rng: np.random.Generator, count: int, noise: MocapNoise) -> np.ndarray:
    """True where a stream delivers its frame (occlusions of geometric length)."""
    delivered = np.ones(count, bool)
    if noise.dropout_fraction <= 0:
        return delivered
    starts = np.flatnonzero(rng.random(count) < noise.dropout_fraction / noise.dropout_mean_frames)
    for start in starts:
        delivered[start : start + int(rng.geometric(1.0 / noise.dropout_mean_frames))] = False
    return delivered


def noisy_poses(rng: np.random.Generator, T: np.ndarray, noise: MocapNoise) -> np.ndarray:
    out = T.copy()
    out[:, :3, :3] = T[:, :3, :3] @ so3_exp(rng.normal(size=(len(T), 3)) * np.radians(noise.body_rotation_std_deg))
    out[:, :3, 3] += rng.normal(size=(len(T), 3)) * noise.body_position_std_m
    return out


def still_hops(
    rng: np.random.Generator, T_poses: list[np.ndarray], times: np.ndarray, hold_s: float, move_s: float
) -> np.ndarray:
    """Poses over `times`: each of `T_poses` held for `hold_s`, with smooth moves of `move_s` between them."""
    out = np.empty((len(times), 4, 4))
    period = hold_s + move_s
    for k, t in enumerate(times):
        i = min(int(t // period), len(T_poses) - 1)
        phase = t - i * period
        if phase <= hold_s or i + 1 >= len(T_poses):
            out[k] = T_poses[i]
        else:
            u = np.array([(phase - hold_s) / move_s])
            a, b = T_poses[i], T_poses[i + 1]
            qa, qb = rotation_to_quaternion_xyzw(a[:3, :3]), rotation_to_quaternion_xyzw(b[:3, :3])
            qb = qb if qa @ qb >= 0 else -qb
            s = minimum_jerk(u)
            out[k] = make_transform(
                quaternion_xyzw_to_rotation(slerp(qa[None], qb[None], s))[0], (1 - s[0]) * a[:3, 3] + s[0] * b[:3, 3]
            )
    return out


# ---------------------------------------------------------------------------------------------------------
# Output: every format at once


class Outputs:
    """Writers of every requested format. Messages are queued and written in time order by `close()` (bags are read
    in receive order); GelSight frames are rendered only then, one at a time, by the function queued with them."""

    def __init__(self, out_dir: Path, name: str, formats: tuple[str, ...], start_epoch_s: float):
        self.out_dir = out_dir
        self.name = name
        self.formats = formats
        self.start = start_epoch_s
        self.events: list[tuple[float, int, Callable[[], None]]] = []
        self.csv_bodies: dict[str, np.ndarray] = {}
        self.csv_markers: dict[str, np.ndarray] = {}
        self.bags: dict[str, BagWriter] = {}

    def body(self, name: str, times: np.ndarray, T: np.ndarray, delivered: np.ndarray) -> None:
        for t, pose in zip(times[delivered], T[delivered]):
            self.events.append((float(t), 0, functools.partial(self._write_body, name, float(t), pose)))
        self.csv_bodies[name] = np.where(delivered[:, None, None], T, np.nan)

    def marker(self, name: str, times: np.ndarray, p: np.ndarray, delivered: np.ndarray) -> None:
        for t, point in zip(times[delivered], p[delivered]):
            self.events.append((float(t), 1, functools.partial(self._write_marker, name, float(t), point)))
        self.csv_markers[name] = np.where(delivered[:, None], p, np.nan)

    def images(self, side: str, times: np.ndarray, render: Callable[[float], np.ndarray]) -> None:
        for t in times:
            self.events.append((float(t), 2, functools.partial(self._write_rendered, side, float(t), render)))

    def _write_body(self, name: str, t: float, pose: np.ndarray) -> None:
        stamp = self.start + t
        for kind, writer in self.bags.items():
            if kind == "ros2-mcap":
                writer.write("/tf", "tf2_msgs/msg/TFMessage", stamp, writer.tf_message(stamp, "world", name, pose))
            else:
                message = writer.pose_stamped(stamp, "world", pose)
                writer.write(BODY_TOPIC.format(name), "geometry_msgs/msg/PoseStamped", stamp, message)

    def _write_marker(self, name: str, t: float, point: np.ndarray) -> None:
        stamp = self.start + t
        for writer in self.bags.values():
            message = writer.point_stamped(stamp, "world", point)
            writer.write(MARKER_TOPIC.format(name), "geometry_msgs/msg/PointStamped", stamp, message)

    def _write_rendered(self, side: str, t: float, render: Callable[[float], np.ndarray]) -> None:
        self._write_image(side, t, render(t))

    def _write_image(self, side: str, t: float, frame: np.ndarray) -> None:
        stamp = self.start + t
        for kind, writer in self.bags.items():
            if kind == "ros2-mcap":
                message = writer.compressed_image(stamp, f"gelsight_{side}", frame)
                writer.write(
                    IMAGE_TOPIC.format(side) + "/compressed", "sensor_msgs/msg/CompressedImage", stamp, message
                )
            else:
                encoding = "bgr8" if (kind == "ros1" and side == "right") else "rgb8"
                message = writer.image(stamp, f"gelsight_{side}", frame, encoding)
                writer.write(IMAGE_TOPIC.format(side), "sensor_msgs/msg/Image", stamp, message)
        if "motive" in self.formats:
            folder = self.out_dir / "motive" / f"{self.name}_{side}"
            write_bytes_atomic(folder / f"{t:.6f}.png", png_bytes(frame))

    def close(self, times: np.ndarray, rate_hz: float) -> None:
        """Write everything; on any error no bag of this recording is left behind."""
        try:
            for kind in self.formats:
                if kind != "motive":
                    name = f"{self.name}.bag" if kind == "ros1" else self.name
                    self.bags[kind] = BagWriter(self.out_dir / FORMAT_FOLDERS[kind] / name, kind)
            for _, _, write in sorted(self.events, key=lambda event: (event[0], event[1])):
                write()
            for writer in self.bags.values():
                writer.close()
        except BaseException:
            for writer in self.bags.values():
                writer.abort()
            raise
        if "motive" in self.formats:
            write_motive_csv(
                self.out_dir / "motive" / f"{self.name}.csv",
                times,
                self.csv_bodies,
                self.csv_markers,
                capture_start=dt.datetime.fromtimestamp(self.start),
                frame_rate_hz=rate_hz,
                take_name=self.name,
            )


# ---------------------------------------------------------------------------------------------------------
# The session


def simulate_recording(
    model: ObjectModel,
    gelsight: SensorCalibration | dict[str, SensorCalibration],
    out_dir: str | Path,
    config: RecordingConfig = RecordingConfig(),
    formats: tuple[str, ...] = FORMATS,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Simulate the session and write it (module docstring). Returns the truth (also written to truth.json).

    `gelsight`: the sensor calibration that renders both rigs' frames, or one per side.
    """
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise InputError(f"unknown recording formats {unknown} (use {', '.join(FORMATS)})")
    out_dir = Path(out_dir)
    calibrations = gelsight if isinstance(gelsight, dict) else {side: gelsight for side in SIDES}
    rng = np.random.default_rng(config.seed)
    scene = Scene(model, config, rng)
    say = progress or (lambda text: log.info(text))
    truth: dict[str, Any] = {
        "object": model.name,
        "T_world_mesh": scene.T_world_mesh,
        "T_objectbody_mesh": scene.T_objectbody_mesh,
        "bead_centres_mesh": scene.bead_centre_mesh,
        "T_rig_sensor": {side: scene.T_rig_sensor[side] for side in SIDES},
        "config": dataclasses.asdict(config),
    }
    for side in SIDES:
        say(f"dual-ball calibration of the {side} rig")
        _gel_calibration(scene, side, out_dir, formats, rng)
        say(f"plate presses of the {side} rig")
        _plate_presses(scene, side, out_dir, formats, rng)
    say("bead capture")
    _bead_capture(scene, out_dir, formats, rng)
    say("contact trials")
    truth["trials"] = _trials(scene, calibrations, out_dir, formats, rng, say)
    beads = {
        "bead_radius_mm": config.bead_radius_m * 1e3,
        "units": "m",
        "beads": [{"name": name, "vertex": vertex} for name, vertex in zip(scene.bead_names, scene.bead_pick_vertices)],
    }
    write_json_atomic(out_dir / "beads.json", beads)
    for side in SIDES:
        write_json_atomic(out_dir / f"cad_{side}.json", {"T_rig_sensor": scene.cad[side]})
    session = {
        "object": model.name,
        "object_body": OBJECT_BODY,
        "rig_bodies": RIG_BODIES,
        "gel_ball": "GelBall",
        "reference_ball": "RefBall",
        "plate_body": "Plate",
        "plate_normal_body": [0.0, 0.0, 1.0],
        "ball_height_mm": config.ball_height_m * 1e3,
        "images": {
            "ros1": {side: IMAGE_TOPIC.format(side) for side in SIDES},
            "ros2-db3": {side: IMAGE_TOPIC.format(side) for side in SIDES},
            "ros2-mcap": {side: IMAGE_TOPIC.format(side) + "/compressed" for side in SIDES},
            "motive": {side: f"trials_{side}" for side in SIDES},
        },
        "recordings": {
            kind: {
                name: str(
                    Path(FORMAT_FOLDERS[kind])
                    / (f"{name}.bag" if kind == "ros1" else f"{name}.csv" if kind == "motive" else name)
                )
                for name in ("gel_left", "gel_right", "plate_left", "plate_right", "beads", "trials")
            }
            for kind in formats
        },
    }
    write_json_atomic(out_dir / "session.json", session)
    write_json_atomic(out_dir / "truth.json", truth)
    # the bead fit turns the mesh frame by the picks' error (degrees): tracks judged against it carry that error
    ObjectCalibration(model.name, OBJECT_BODY, scene.T_objectbody_mesh, sources={"simulator": "truth.json"}).save(
        out_dir / "true.object.json"
    )
    return truth


def _write_stream_set(
    scene: Scene,
    out_dir: Path,
    name: str,
    formats: tuple[str, ...],
    times: np.ndarray,
    bodies: dict[str, np.ndarray],
    markers: dict[str, np.ndarray],
    rng: np.random.Generator,
) -> None:
    """Write rigid bodies and markers (true values) with mocap noise and dropouts, in every format."""
    noise = scene.config.noise
    outputs = Outputs(out_dir, name, formats, scene.config.start_epoch_s)
    for body, T in bodies.items():
        outputs.body(body, times, noisy_poses(rng, T, noise), dropout_mask(rng, len(times), noise))
    for marker, p in markers.items():
        noisy = p + rng.normal(size=p.shape) * noise.marker_std_m
        outputs.marker(marker, times, noisy, dropout_mask(rng, len(times), noise))
    outputs.close(times, scene.config.mocap_rate_hz)


def _gel_calibration(
    scene: Scene, side: str, out_dir: Path, formats: tuple[str, ...], rng: np.random.Generator
) -> None:
    config = scene.config
    hold, move = 0.8, 0.5
    poses = []
    for _ in range(config.calibration_poses):
        rotation = random_rotations(rng, 1)[0]
        poses.append(make_transform(rotation, rng.uniform([-0.15, -0.15, 0.1], [0.15, 0.15, 0.4])))
    times = np.arange(0.0, config.calibration_poses * (hold + move), 1.0 / config.mocap_rate_hz)
    T_world_rig = still_hops(rng, poses, times, hold, move)
    T_rig_sensor = scene.T_rig_sensor[side]
    gel_ball = T_rig_sensor[:3, 3] + config.ball_height_m * T_rig_sensor[:3, 2]
    markers = {
        "GelBall": np.einsum("nij,j->ni", T_world_rig[:, :3, :3], gel_ball) + T_world_rig[:, :3, 3],
        "RefBall": np.einsum("nij,j->ni", T_world_rig[:, :3, :3], scene.p_rig_reference[side]) + T_world_rig[:, :3, 3],
    }
    _write_stream_set(scene, out_dir, f"gel_{side}", formats, times, {RIG_BODIES[side]: T_world_rig}, markers, rng)


def _plate_presses(scene: Scene, side: str, out_dir: Path, formats: tuple[str, ...], rng: np.random.Generator) -> None:
    config = scene.config
    hold, move = 0.8, 0.6
    plate = scene.T_world_plate
    poses = []
    for k in range(config.plate_presses):
        in_plane = rotation_about_axis(
            np.array([0.0, 0.0, 1.0]), 2 * np.pi * k / config.plate_presses + rng.uniform(0, 0.5)
        )
        # The sensor's z is the plate's inward normal (-z of the plate body); the gel is pressed 0.5 mm in.
        R_plate_sensor = in_plane @ rotation_between(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]))
        position = np.array([*rng.uniform(-0.08, 0.08, size=2), -0.0005])
        T_world_sensor = plate @ make_transform(R_plate_sensor, position)
        poses.append(T_world_sensor @ invert_transform(scene.T_rig_sensor[side]))
        lifted = T_world_sensor @ make_transform(np.eye(3), np.array([0.0, 0.0, -0.05]))
        poses.append(lifted @ invert_transform(scene.T_rig_sensor[side]))
    times = np.arange(0.0, len(poses) * (hold + move), 1.0 / config.mocap_rate_hz)
    T_world_rig = still_hops(rng, poses, times, hold, move)
    bodies = {RIG_BODIES[side]: T_world_rig, "Plate": np.tile(plate, (len(times), 1, 1))}
    _write_stream_set(scene, out_dir, f"plate_{side}", formats, times, bodies, {}, rng)


def _bead_capture(scene: Scene, out_dir: Path, formats: tuple[str, ...], rng: np.random.Generator) -> None:
    times = np.arange(0.0, 2.0, 1.0 / scene.config.mocap_rate_hz)
    T_body = np.tile(scene.T_world_objectbody, (len(times), 1, 1))
    centres_world = transform_points(scene.T_world_mesh, scene.bead_centre_mesh)
    markers = {name: np.tile(p, (len(times), 1)) for name, p in zip(scene.bead_names, centres_world)}
    _write_stream_set(scene, out_dir, "beads", formats, times, {OBJECT_BODY: T_body}, markers, rng)


def _draw_trials(scene: Scene, rng: np.random.Generator) -> list[list[Trial]]:
    """The script: blocks of one or two simultaneous trials."""
    config, model = scene.config, scene.model
    scenario = ScenarioConfig(press=PressConfig(noise=ReconstructionNoise.none(), max_offset_m=0.001))
    pairs = PairSimulator(model, scenario)
    presses = pairs.presses

    def single(side: str, kind: str) -> Trial:
        for _ in range(2000):
            p_object = presses.sample_surface(rng)[0]
            contact = press_contact(presses, p_object, model.aggregated_normal(p_object), rng)
            if contact.press.accepted:
                return Trial(side, kind, contact.press, model.T_mesh_object @ contact.press.T_object_sensor)
        raise SimulationError(f"{model.name}: no reachable GelSight contact in 2000 presses")

    blocks: list[list[Trial]] = []
    kinds = ["single"] * config.single_trials + ["miss"] * config.miss_trials + ["slip"] * config.slip_trials
    kinds += ["dropout"] * config.dropout_trials
    for kind in kinds:
        for side in SIDES:
            trial = single(side, kind)
            if kind == "slip":
                trial.slip_direction = np.array([1.0, 0.0, 0.0])
            if kind == "miss":
                trial.extra_backoff_m = trial.press.depth_m + 0.003
            blocks.append([trial])
    for index in range(config.dual_trials):
        simulated = pairs.pair(int(rng.integers(1 << 30)), index)
        blocks.append(
            [
                Trial(side, "dual", contact.press, model.T_mesh_object @ contact.press.T_object_sensor)
                for side, contact in simulated.contacts.items()
            ]
        )
    return blocks


def _backoff(trial: Trial, config: RecordingConfig, tau: np.ndarray, park: float) -> np.ndarray:
    """How far the sensor is backed off along its axis from the full press at block-relative times `tau`."""
    a, b, c, d = trial.timings(config)
    near = config.approach_distance_m
    out = np.where(tau < a, park + (near - park) * minimum_jerk(tau / a), 0.0)
    out = np.where((tau >= a) & (tau < b), near * (1 - minimum_jerk((tau - a) / (b - a))), out)
    out = np.where((tau >= c) & (tau < d), near * minimum_jerk((tau - c) / (d - c)), out)
    out = np.where(tau >= d, near + (park - near) * minimum_jerk((tau - d) / config.move_s), out)
    # A miss's arm moves from the parking sphere to its shorter approach (and back) in the same moves: the extra
    # back-off ramps in and out with them, as an arm does (a step would be metres per second in one mocap frame).
    extra = np.where(
        tau < a, minimum_jerk(tau / a), np.where(tau < d, 1.0, 1 - minimum_jerk((tau - d) / config.move_s))
    )
    return out + trial.extra_backoff_m * extra


def _slide(trial: Trial, config: RecordingConfig, tau: np.ndarray) -> np.ndarray:
    """Sensor-frame in-plane displacement during the hold of a slipping trial (4 mm), (M, 3)."""
    if trial.slip_direction is None:
        return np.zeros((len(tau), 3))
    _, b, c, _ = trial.timings(config)
    amount = 0.004 * minimum_jerk((tau - b - 0.3 * (c - b)) / (0.4 * (c - b)))
    return amount[:, None] * trial.slip_direction


def _trials(
    scene: Scene,
    calibrations: dict[str, SensorCalibration],
    out_dir: Path,
    formats: tuple[str, ...],
    rng: np.random.Generator,
    say: Callable[[str], None],
) -> list[dict[str, Any]]:
    config = scene.config
    blocks = _draw_trials(scene, rng)
    block_s = config.move_s * 2 + config.approach_s * 2 + config.hold_s
    total = len(blocks) * (config.transfer_s + block_s) + config.transfer_s
    times = np.arange(0.0, total, 1.0 / config.mocap_rate_hz)
    T_world_sensor = {side: np.empty((len(times), 4, 4)) for side in SIDES}
    current = {side: scene.park_pose(side) for side in SIDES}
    active: dict[str, list[tuple[float, Trial, float]]] = {side: [] for side in SIDES}
    cursor = 0.0
    truth = []
    for block in blocks:
        by_side = {trial.side: trial for trial in block}
        start = cursor + config.transfer_s
        for side in SIDES:
            trial = by_side.get(side)
            target = current[side]
            park = 0.0
            if trial is not None:
                T_final = scene.T_world_mesh @ trial.T_mesh_sensor
                target, park = scene.far_pose(T_final)
            moving = (times >= cursor) & (times < start)
            T_world_sensor[side][moving] = sphere_path(
                scene, current[side], target, (times[moving] - cursor) / config.transfer_s
            )
            inside = (times >= start) & (times < start + block_s)
            if trial is None:
                T_world_sensor[side][inside] = target
            else:
                trial.start_s = start
                tau = times[inside] - start
                backoff = _backoff(trial, config, tau, park)
                offset = _slide(trial, config, tau)
                offset[:, 2] -= backoff
                tremor = np.cumsum(rng.normal(size=(len(tau), 3)), axis=0)
                tremor = config.tremor_m * (tremor - tremor.mean(axis=0)) / max(np.sqrt(len(tau)), 1.0)
                offset += tremor * (backoff == 0)[:, None]
                T = np.tile(T_final, (len(tau), 1, 1))
                T[:, :3, 3] += np.einsum("ij,nj->ni", T_final[:3, :3], offset)
                T_world_sensor[side][inside] = T
                active[side].append((start, trial, park))
                a, b, c, _ = trial.timings(config)
                assert trial.press.p_object is not None  # scripted trials are accepted presses
                truth.append(
                    {
                        "side": side,
                        "kind": trial.kind,
                        "hold_s": [config.start_epoch_s + start + b, config.start_epoch_s + start + c],  # ROS stamps
                        "hold_take_s": [start + b, start + c],  # Motive take time
                        "p_object": transform_points(scene.model.T_mesh_object, trial.press.p_object),
                        "depth_mm": trial.press.depth_m * 1e3,
                        "T_mesh_sensor": trial.T_mesh_sensor,
                    }
                )
            current[side] = target
        cursor = start + block_s
    tail = times >= cursor
    for side in SIDES:
        T_world_sensor[side][tail] = current[side]
    # Dropout trials: a 0.4 s occlusion of the rig in the middle of the hold.
    occluded = {side: np.zeros(len(times), bool) for side in SIDES}
    for side in SIDES:
        for start, trial, _ in active[side]:
            if trial.kind == "dropout":
                _, b, c, _ = trial.timings(config)
                middle = start + (b + c) / 2
                occluded[side] |= (times >= middle - 0.2) & (times < middle + 0.2)
    noise = config.noise
    outputs = Outputs(out_dir, "trials", formats, config.start_epoch_s)
    object_poses = noisy_poses(rng, np.tile(scene.T_world_objectbody, (len(times), 1, 1)), noise)
    outputs.body(OBJECT_BODY, times, object_poses, dropout_mask(rng, len(times), noise))
    for side in SIDES:
        T_world_rig = T_world_sensor[side] @ invert_transform(scene.T_rig_sensor[side])
        delivered = dropout_mask(rng, len(times), noise) & ~occluded[side]
        outputs.body(RIG_BODIES[side], times, noisy_poses(rng, T_world_rig, noise), delivered)
    frame_times = np.arange(0.0, total, 1.0 / config.camera_rate_hz)
    for side in SIDES:
        outputs.images(side, frame_times, _renderer(active[side], calibrations[side], config, rng))
    say(f"writing {len(times)} mocap frames and {len(frame_times)} GelSight frames per rig ({', '.join(formats)})")
    outputs.close(times, config.mocap_rate_hz)
    return truth


def _renderer(
    trials: list[tuple[float, Trial, float]],
    calibration: SensorCalibration,
    config: RecordingConfig,
    rng: np.random.Generator,
) -> Callable[[float], np.ndarray]:
    """The GelSight frame at a time: the gel pressed by the active trial, rendered with sensor noise."""
    background = calibration.background.astype(np.float32)
    noise_std = calibration.noise_std.astype(np.float32)

    def render(t: float) -> np.ndarray:
        height = _height_map(trials, config, t)
        if height is None:  # a flat gel renders exactly the background (plus the sensor's noise)
            image = background + rng.normal(size=background.shape).astype(np.float32) * noise_std
            return np.clip(np.rint(image), 0, 255).astype(np.uint8)
        return render_image(height, calibration, rng)

    return render


def _height_map(trials: list[tuple[float, Trial, float]], config: RecordingConfig, t: float) -> np.ndarray | None:
    """The gel's height map at time t, or None when the gel touches nothing."""
    press_config = PressConfig()
    for start, trial, park in trials:
        tau = np.array([t - start])
        _, _, _, d = trial.timings(config)
        if not 0 <= tau[0] < d + config.move_s:
            continue
        backoff = float(_backoff(trial, config, tau, park)[0])
        if backoff >= trial.press.depth_m:
            return None
        object_z = trial.press.object_z_m + backoff
        shift = _slide(trial, config, tau)[0]
        columns = int(round(shift[0] / press_config.spec.pixel_size_m))
        if columns > 0:  # the object moves the other way across the pad
            object_z = np.concatenate([object_z[:, columns:], np.full((object_z.shape[0], columns), np.inf)], axis=1)
        height, _, _ = gel_surface(object_z, press_config.gel, press_config.spec)
        return height
    return None
