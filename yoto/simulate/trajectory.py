"""Trajectories after a simulated touch: both sensors carry the object along a smooth SE(3) path while it slips.

The paper's tracking experiment (Sec. 4.3): both gels touch the object once, then two arms move it along a random
~100 mm, 10-15 deg trajectory. This module simulates such a run on an object model, with what makes tracking hard:
- **slip**: the object moves relative to the grasp, plastically (growing with the path length travelled, it stays)
  and elastically (an inertial peak proportional to the path's acceleration, gone at rest). Slip is tangential:
  it keeps both contacts pressed (the translation is chosen so neither contact moves along its sensor's axis);
  its rotation turns mostly about the grasp axis, the line through both contacts;
- **dual-arm asynchrony**: one arm follows the path a few milliseconds behind the other;
- **jitter**: independent noise on every sample of each arm's pose stream, at each stream's own rate and phase;
- **the tactile frames** each gel sees along the way: the contact simulator (`press.PressSimulator`) presses each
  sensor into the object at its slipped pose, at the touch's depth (the sensor settles along its axis, as a
  force-controlled grasp would: its true pose includes that settling). Reconstruction errors follow
  `gel.ReconstructionNoise`, split by where they come from: the depth scale error and the smooth bias field belong
  to a sensor's calibration and lighting, so each sensor draws them once and keeps them on its pad for the whole
  trajectory (a sliding contact meets other parts of the field); pixel noise is new every frame. Or, with a GelSight
  image route (`TrajectorySimulator(..., images=yoto.sensor.optical.image_route(SOURCE))`), each frame's gel height
  map is rendered to a GelSight image and reconstructed by the sensor stage instead (the touch's own clouds too):
  the frames then carry the real reconstruction's errors, and keep their images.

Timeline (seconds): streams start at `start_time_s`; the touch is `before_touch_s` later; the motion starts
`hold_s` after the touch, lasts `motion_s` (minimum-jerk time law) and is followed by `settle_s` of rest.

Frames: the object's canonical frame `object` inside (`T_world_object`); files use the mesh file's frame for the
object (`object_true.tum` holds `T_world_mesh`), the SPEC sensor frame for sensors and tactile clouds.
A simulated trajectory folder (`write_trajectory`):
    touch.json, touch_left.ply, touch_right.ply   the touch (a SPEC contact pair, with ground truth and "timestamp")
    left.tum, right.tum                           the reported sensor pose streams T_world_sensor (TUM)
    object_true.tum                               the true T_world_mesh at every stream timestamp
    left_tactile/, right_tactile/                 tactile frames during motion, <timestamp>.ply (sensor frame), or
                                                  with an image route <timestamp>.png GelSight images ...
    calibration.npz                               ... and the sensor calibration that reconstructs them
    trajectory.json                               settings and what was simulated (slip, lag, path); written last
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.interpolate import CubicSpline

from yoto.contacts import MIN_TACTILE_POINTS, SIDES, write_contact_pair
from yoto.errors import InputError
from yoto.geometry import (
    invert_transform,
    normalize,
    pose_from_twist,
    rotation_angle_rad,
    so3_exp,
    so3_log,
)
from yoto.io import png_bytes, read_json, settings_changed, write_bytes_atomic, write_json_atomic, write_ply_points
from yoto.objects.model import ObjectModel
from yoto.simulate.gel import calibration_errors, gel_surface, reconstruct_points
from yoto.simulate.press import SIMULATOR_VERSION
from yoto.simulate.scenarios import PairSimulator, ScenarioConfig, SimulatedPair
from yoto.trajectory import PoseStream, tactile_frame_name, write_tum

if TYPE_CHECKING:
    from yoto.sensor.calibration import SensorCalibration
    from yoto.sensor.optical import ImagePath

TRAJECTORY_STREAM = 1  # third entry of the seed sequence: the trajectory's random streams, apart from the touch's
SUMMARY_FILE = "trajectory.json"
FOLDER_SETTINGS_FILE = "trajectories.json"
CALIBRATION_FILE = "calibration.npz"  # frames through images: the sensor calibration that reconstructs them


@dataclass(frozen=True)
class TrajectoryConfig:
    """How a trajectory after a simulated touch is drawn (the issue's scenario by default)."""

    scenario: ScenarioConfig = ScenarioConfig()  # the touch: object pose, the two contacts, calibration error
    path_length_m: float = 0.1  # length of the path of the object's centroid
    rotation_range_rad: tuple[float, float] = (float(np.radians(10.0)), float(np.radians(15.0)))  # largest
    # rotation from the start along the path, uniform in this range
    waypoints: int = 3  # random via-points of the path (a clamped cubic spline through them)
    start_time_s: float = 1_700_000_000.0  # the streams' clock at their first sample (Unix time, as mocap writes)
    before_touch_s: float = 0.2  # the streams begin this long before the touch
    hold_s: float = 0.5  # the sensors rest on the object after the touch before the motion
    motion_s: float = 3.0  # duration of the motion
    settle_s: float = 1.0  # rest after the motion (the settled tail)
    left_rate_hz: float = 120.0  # rate of the left sensor's pose stream (mocap or arm state)
    right_rate_hz: float = 100.0  # rate of the right one (its phase is random)
    tactile_rate_hz: float = 25.0  # tactile frame rate of each gel (GelSight Mini: 25 fps); right's phase random
    slip_translation_per_m: float = 0.02  # plastic slip per metre of path: translation of the centroid ...
    slip_rotation_per_m: float = float(np.radians(15.0))  # ... and rotation, rad/m (2 mm / 1.5 deg over 100 mm)
    peak_translation_m: float = 0.001  # elastic slip at the path's peak acceleration (gone at rest) ...
    peak_rotation_rad: float = float(np.radians(1.0))  # ... and its rotation
    grasp_axis_bias: float = 2.0  # slip rotation axes: grasp axis x this + a random unit vector
    arm_lag_s: float = 0.01  # one arm (random which) follows the path this much behind the other
    jitter_translation_m: float = 0.0002  # 1-sigma per axis of each pose sample, independent per arm
    jitter_rotation_rad: float = float(np.radians(0.1))  # 1-sigma per rotation-vector component of each sample
    tactile_pixel_stride: int = 2  # tactile clouds keep every n-th pixel row and column (file size)
    tactile_phase_s: float | None = None  # the right gel's frames start this long after the left's (None: random
    # within a frame period; 0: the two cameras in phase)
    tactile_whole_pad: bool = False  # clouds hold every kept pixel of the pad, the untouched gel at z = 0 (plus the
    # reconstruction's errors), as a reconstruction of the whole image writes them; False: the contact's pixels only
    tactile_stamp_jitter_s: float = 0.0  # 1-sigma error of each frame's recorded time (a recorder stamping frames on
    # arrival); the frame shows the gel at its true time
    # Pose streams as mocap and robot arms deliver them (stop 20; all off by default). Drawn from their own random
    # stream: switching them on leaves every other draw as it was.
    pose_outlier_share: float = 0.0  # share of each pose stream's samples that are mis-fitted rigid bodies (a marker
    # swapped or occluded): bursts of `pose_outlier_frames` samples, each burst one offset of `pose_outlier_m` (a
    # random direction) and `pose_outlier_rad` (a random axis), then back
    pose_outlier_frames: tuple[int, int] = (1, 5)  # burst length in samples, uniform in this range
    pose_outlier_m: tuple[float, float] = (0.005, 0.03)  # burst offset, uniform in this range ...
    pose_outlier_rad: tuple[float, float] = (float(np.radians(5.0)), float(np.radians(30.0)))  # ... and its rotation
    pose_flips: int = 0  # per stream: stretches of `pose_flip_s` where the body is fitted turned half a turn about an
    # axis of its marker set's symmetry (through the markers' centre, `FLIP_CENTRE_M` from the sensor's origin)
    pose_flip_s: float = 1.0
    pose_dropouts: int = 0  # per stream: stretches without samples (the body occluded by the arm), each
    # `pose_dropout_s` long (uniform), after the touch, never within 0.1 s of another (either stream's; as many as
    # fit in 100 draws each)
    pose_dropout_s: tuple[float, float] = (0.2, 1.0)
    arm_error_m: float = 0.0  # a robot arm's forward kinematics: each arm's reported pose errs by a smooth function
    arm_error_rad: float = 0.0  # of where it is (per component, this amplitude times a sine of the sensor's position
    # along a random direction, wavelength `ARM_ERROR_WAVELENGTH_M`), its own for each arm


@dataclass
class TactileFrame:
    """One gel frame during the motion."""

    timestamp_s: float
    points_sensor: np.ndarray  # (N, 3) reconstructed tactile cloud, sensor frame; empty where the gel lost contact
    T_object_sensor_true: np.ndarray  # (4, 4) where the sensor really was on the object (canonical frame)
    image: np.ndarray | None = None  # (rows, cols, 3) uint8 RGB GelSight image the cloud was reconstructed from
    # (frames through images); None for frames with simulated reconstruction errors


@dataclass
class SimulatedTrajectory:
    """A touch and the motion after it: what `yoto track` reads, and the truth behind it."""

    touch: SimulatedPair  # the touch, with its pair (`touch.pair`, reported sensor poses) and ground truth
    touch_time_s: float
    streams: dict[str, PoseStream]  # side -> reported T_world_sensor stream (calibration error and jitter)
    sensors_true: dict[str, PoseStream]  # side -> true T_world_sensor at the same timestamps
    truth: PoseStream  # true T_world_object (canonical frame) at the union of the stream timestamps
    tactile: dict[str, list[TactileFrame]]  # side -> frames from the touch on
    summary: dict[str, Any] = field(default_factory=dict)  # path, slip, lag, motion times (for reports)
    calibration: SensorCalibration | None = None  # reconstructs the frames' images (frames through images)

    def truth_mesh(self, model: ObjectModel) -> PoseStream:
        """The true object poses in the mesh file's frame, `T_world_mesh`."""
        return PoseStream(self.truth.timestamps_s, self.truth.T_world_frame @ model.T_object_mesh, "object truth")


# ------------------------------------------------------------------------------------------------ the path
def minimum_jerk(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 on [0, 1] (held outside) and its first two derivatives."""
    t = np.clip(tau, 0.0, 1.0)
    inside = (tau > 0.0) & (tau < 1.0)
    s = 10 * t**3 - 15 * t**4 + 6 * t**5
    ds = np.where(inside, 30 * t**2 - 60 * t**3 + 30 * t**4, 0.0)
    dds = np.where(inside, 60 * t - 180 * t**2 + 120 * t**3, 0.0)
    return s, ds, dds


@dataclass
class SmoothPath:
    """A smooth motion of a rigid pose: translation and rotation (world frame, about the pose's origin) over time."""

    T_world_start: np.ndarray  # (4, 4) the pose before and at the start of the motion
    translation: CubicSpline  # u in [0, 1] -> displacement (3,), metres, world frame
    rotation: CubicSpline  # u -> rotation vector (3,) applied in the world frame about the moving origin
    start_s: float  # the motion's start time
    duration_s: float
    length_u: np.ndarray  # (G,) grid of u ...
    length_m: np.ndarray  # (G,) ... and the path length travelled up to it

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        T_world_start: np.ndarray,
        start_s: float,
        duration_s: float,
        length_m: float,
        rotation_rad: float,
        waypoints: int,
    ) -> SmoothPath:
        """A random path through `waypoints` via-points (mostly outbound), scaled to `length_m` of centroid travel
        and to a largest rotation of `rotation_rad` from the start."""
        heading = normalize(rng.normal(size=3))
        steps = rng.normal(size=(waypoints, 3)) + 1.5 * heading
        knots = np.linspace(0.0, 1.0, waypoints + 1)
        displacement = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
        turns = np.vstack([np.zeros(3), np.cumsum(rng.normal(size=(waypoints, 3)) + normalize(rng.normal(size=3)), 0)])
        grid = np.linspace(0.0, 1.0, 2001)
        translation = CubicSpline(knots, displacement, bc_type="clamped")
        rotation = CubicSpline(knots, turns, bc_type="clamped")
        travelled = _cumulative_length(translation(grid))
        translation = CubicSpline(knots, displacement * (length_m / travelled[-1]), bc_type="clamped")
        largest = np.linalg.norm(rotation(grid), axis=1).max()
        rotation = CubicSpline(knots, turns * (rotation_rad / largest), bc_type="clamped")
        return cls(
            T_world_start=np.asarray(T_world_start, dtype=np.float64),
            translation=translation,
            rotation=rotation,
            start_s=start_s,
            duration_s=duration_s,
            length_u=grid,
            length_m=_cumulative_length(translation(grid)),
        )

    def progress(self, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Path parameter u(t) in [0, 1] and its first two time derivatives."""
        s, ds, dds = minimum_jerk((np.asarray(times_s, dtype=np.float64) - self.start_s) / self.duration_s)
        return s, ds / self.duration_s, dds / self.duration_s**2

    def poses(self, times_s: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses at the given times."""
        u, _, _ = self.progress(times_s)
        out = np.repeat(self.T_world_start[None], len(u), axis=0)
        out[:, :3, :3] = so3_exp(self.rotation(u)) @ self.T_world_start[:3, :3]
        out[:, :3, 3] += self.translation(u)
        return out

    def travelled_m(self, times_s: np.ndarray) -> np.ndarray:
        """Path length travelled by the origin up to each time."""
        u, _, _ = self.progress(times_s)
        return np.interp(u, self.length_u, self.length_m)

    def acceleration(self, times_s: np.ndarray) -> np.ndarray:
        """(N, 3) linear acceleration of the origin, m/s^2."""
        u, du, ddu = self.progress(times_s)
        return self.translation(u, 2) * du[:, None] ** 2 + self.translation(u, 1) * ddu[:, None]

    @property
    def total_length_m(self) -> float:
        return float(self.length_m[-1])


def _cumulative_length(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


# ------------------------------------------------------------------------------------------------ slip
def tangential_twist(
    rng: np.random.Generator,
    p_object: dict[str, np.ndarray],
    z_object: dict[str, np.ndarray],
    rotation_rad: float,
    translation_m: float,
    axis_bias: float,
) -> np.ndarray:
    """A slip twist (omega, v) about the object's origin that keeps both contacts pressed.

    The rotation (angle `rotation_rad`) turns about the grasp axis (the line through the two contacts) x
    `axis_bias` plus a random unit vector. The translation cancels the motion the rotation causes along each
    sensor's axis `z` at its contact `p`, (z . (omega x p + v) = 0 for both), and slides the rest of the way to
    `translation_m` along the directions both contacts leave free.
    """
    grasp_axis = normalize(p_object["right"] - p_object["left"])
    axis = normalize(axis_bias * grasp_axis + normalize(rng.normal(size=3)))
    omega = axis * rotation_rad * rng.choice([-1.0, 1.0])
    constraints = np.stack([z_object[side] for side in SIDES])  # (2, 3): rows z_s
    pushed = -np.array([z_object[side] @ np.cross(omega, p_object[side]) for side in SIDES])
    particular = np.linalg.pinv(constraints) @ pushed
    _, singular, vt = np.linalg.svd(constraints)
    free = vt[int(np.sum(singular > 1e-6)) :]  # rows spanning the directions neither contact constrains
    slide = normalize(rng.normal(size=len(free)) @ free)
    room = translation_m**2 - particular @ particular
    return np.concatenate([omega, particular + np.sqrt(max(room, 0.0)) * slide])


# ------------------------------------------------------------------------------------------------ simulation
def _stream_times(start: float, end: float, rate_hz: float, phase_s: float) -> np.ndarray:
    count = int(np.floor((end - start - phase_s) * rate_hz)) + 1
    return np.round(start + phase_s + np.arange(count) / rate_hz, 9)


def _jitter(rng: np.random.Generator, count: int, translation_m: float, rotation_rad: float) -> np.ndarray:
    """(count, 4, 4) independent small pose errors: Gaussian rotation vectors and translations."""
    return pose_from_twist(
        np.hstack([rng.normal(size=(count, 3)) * rotation_rad, rng.normal(size=(count, 3)) * translation_m])
    )


FLIP_CENTRE_M = 0.04  # a flipped rigid body turns about its markers' centre, this far from the sensor's origin
ARM_ERROR_WAVELENGTH_M = 0.5  # an arm's kinematic error changes over this much travel (a smooth function of pose)


def _as_recorded(
    streams: dict[str, PoseStream], config: TrajectoryConfig, rng: np.random.Generator, after_s: float, end_s: float
) -> dict[str, PoseStream]:
    """The reported pose streams as a mocap system or a robot arm delivers them (`TrajectoryConfig.pose_*`,
    `arm_error_*`): mis-fitted bursts, flipped stretches, dropouts after `after_s` (ending before `end_s`), a smooth
    pose-dependent kinematic error. Unchanged where those are off. Each fault of each stream draws from its own
    generator: switching one on leaves the others' draws alone."""
    out = {}
    taken: list[tuple[float, float]] = []  # dropouts of both streams: one stream occluded at a time
    seeds = rng.integers(2**62, size=(len(SIDES), 4))
    for side, (arm, bursts, flips, dropouts) in zip(SIDES, seeds, strict=True):
        rng = np.random.default_rng(arm)
        stream = streams[side]
        times, poses = stream.timestamps_s, stream.T_world_frame.copy()
        count = len(times)
        # a smooth kinematic error: per component, amplitude x sin(2 pi (direction . position) / wavelength + phase)
        directions = normalize(rng.normal(size=(6, 3)))
        phases = rng.uniform(0.0, 2.0 * np.pi, size=6)
        origin = poses[0, :3, 3]
        if config.arm_error_m > 0 or config.arm_error_rad > 0:
            angle = 2.0 * np.pi * (poses[:, :3, 3] - origin) @ directions.T / ARM_ERROR_WAVELENGTH_M + phases
            error = np.sin(angle) * np.repeat([config.arm_error_rad, config.arm_error_m], 3)
            poses[:, :3, :3] = so3_exp(error[:, :3]) @ poses[:, :3, :3]
            poses[:, :3, 3] += error[:, 3:]
        # mis-fitted bursts
        rng = np.random.default_rng(bursts)
        mean_length = 0.5 * sum(config.pose_outlier_frames)
        starts = rng.random(count) < config.pose_outlier_share / mean_length
        for first in np.flatnonzero(starts):
            length = int(rng.integers(config.pose_outlier_frames[0], config.pose_outlier_frames[1] + 1))
            twist = np.concatenate(
                [
                    normalize(rng.normal(size=3)) * rng.uniform(*config.pose_outlier_rad),
                    normalize(rng.normal(size=3)) * rng.uniform(*config.pose_outlier_m),
                ]
            )
            poses[first : first + length] = pose_from_twist(twist[None])[0] @ poses[first : first + length]
        # flipped stretches: half a turn about a symmetry axis through the markers' centre (sensor frame)
        rng = np.random.default_rng(flips)
        for _ in range(config.pose_flips):
            begin = rng.uniform(times[0], max(times[-1] - config.pose_flip_s, times[0]))
            flip = np.eye(4)
            flip[:3, :3] = so3_exp(np.pi * normalize(rng.normal(size=3)))
            centre = normalize(rng.normal(size=3)) * FLIP_CENTRE_M
            flip[:3, 3] = centre - flip[:3, :3] @ centre
            inside = (times >= begin) & (times < begin + config.pose_flip_s)
            poses[inside] = poses[inside] @ flip
        # dropouts, one stream at a time
        rng = np.random.default_rng(dropouts)
        keep = np.ones(count, bool)
        for _ in range(config.pose_dropouts):
            for _attempt in range(100):
                gap = rng.uniform(*config.pose_dropout_s)
                begin = rng.uniform(after_s, max(end_s - 0.25 - gap, after_s))
                if all(begin > b + 0.1 or begin + gap < a - 0.1 for a, b in taken):
                    taken.append((begin, begin + gap))
                    keep &= (times < begin) | (times > begin + gap)
                    break
        out[side] = PoseStream(times[keep], poses[keep], stream.name, stream.source)
    return out


def _keep_pixel_stride(points_sensor: np.ndarray, stride: int, pixel_size_m: float, width: int, height: int):
    """The points on every `stride`-th pixel row and column (points from a height map, sensor frame)."""
    if stride <= 1 or len(points_sensor) == 0:
        return points_sensor
    columns = np.rint(points_sensor[:, 0] / pixel_size_m + (width - 1) / 2).astype(int)
    rows = np.rint(points_sensor[:, 1] / pixel_size_m + (height - 1) / 2).astype(int)
    return points_sensor[(columns % stride == 0) & (rows % stride == 0)]


class TrajectorySimulator:
    """Draws trajectories after simulated touches on one object. Build once per object."""

    def __init__(
        self, model: ObjectModel, config: TrajectoryConfig = TrajectoryConfig(), images: ImagePath | None = None
    ):
        """`images`: the frames' (and the touch's) clouds are reconstructed from the GelSight images their gel height
        maps render to (`yoto.sensor.optical.image_route`) instead of drawn from the simulated reconstruction errors;
        the touch, path, slip and streams stay the same (they draw from their own random streams)."""
        if config.motion_s <= 0 or config.path_length_m <= 0:
            raise InputError(
                f"a trajectory needs a positive motion time and path length (got {config.motion_s} s, "
                f"{config.path_length_m} m)"
            )
        self.model = model
        self.config = config
        self.pairs = PairSimulator(model, config.scenario)
        self.presses = self.pairs.presses
        self.images = images

    def streams(self, seed: int, index: int) -> dict[str, np.random.Generator]:
        """The trajectory's own random streams (the touch draws from the pair simulator's): by purpose, so that
        changing one setting (jitter, say) leaves the others' draws alone."""
        children = np.random.SeedSequence([seed, index, TRAJECTORY_STREAM]).spawn(6)  # the first 5 as spawn(5)'s
        names = ("path", "slip", "timing", "jitter", "tactile", "recorder")
        return {name: np.random.default_rng(child) for name, child in zip(names, children, strict=True)}

    def trajectory(self, seed: int, index: int) -> SimulatedTrajectory:
        """Trajectory `index` of the set `seed`: the touch is pair `index` of `yoto simulate pairs --seed seed`."""
        config = self.config
        touch = self.pairs.pair(seed, index)
        rng = self.streams(seed, index)
        start = config.start_time_s
        touch_time = round(start + config.before_touch_s, 6)
        motion_start = touch_time + config.hold_s
        end = motion_start + config.motion_s + config.settle_s
        path = SmoothPath.random(
            rng["path"],
            touch.T_world_object,
            motion_start,
            config.motion_s,
            config.path_length_m,
            rng["path"].uniform(*config.rotation_range_rad),
            config.waypoints,
        )

        # Slip: a plastic part growing with the path travelled and an elastic part following the acceleration.
        T_object_sensor_touch = {side: touch.contacts[side].press.T_object_sensor for side in SIDES}
        z_object = {side: T_object_sensor_touch[side][:3, 2] for side in SIDES}
        plastic = tangential_twist(
            rng["slip"],
            touch.p_object_true,
            z_object,
            config.slip_rotation_per_m * config.path_length_m,
            config.slip_translation_per_m * config.path_length_m,
            config.grasp_axis_bias,
        )
        elastic = tangential_twist(
            rng["slip"],
            touch.p_object_true,
            z_object,
            config.peak_rotation_rad,
            config.peak_translation_m,
            config.grasp_axis_bias,
        )
        during = np.linspace(motion_start, motion_start + config.motion_s, 1001)
        peak_acceleration = float(np.linalg.norm(path.acceleration(during), axis=1).max())

        def slip_twists(times: np.ndarray) -> np.ndarray:
            travelled = path.travelled_m(times) / path.total_length_m
            shaking = np.linalg.norm(path.acceleration(times), axis=1) / peak_acceleration
            return np.outer(travelled, plastic) + np.outer(shaking, elastic)

        lagging = str(rng["timing"].choice(SIDES))
        lag = {side: config.arm_lag_s if side == lagging else 0.0 for side in SIDES}

        def object_true(times: np.ndarray) -> np.ndarray:
            """T_world_object: the grasp between both arms, and the slip in it."""
            return path.poses(times - 0.5 * config.arm_lag_s) @ pose_from_twist(slip_twists(times))

        def commanded(side: str, times: np.ndarray) -> np.ndarray:
            """T_world_sensor where the arm puts the sensor (before it settles along its axis)."""
            return path.poses(times - lag[side]) @ T_object_sensor_touch[side]

        times = {
            "left": _stream_times(start, end, config.left_rate_hz, 0.0),
            "right": _stream_times(
                start, end, config.right_rate_hz, rng["timing"].uniform(0.0, 1.0 / config.right_rate_hz)
            ),
        }
        tactile_phase = {"left": 0.0, "right": rng["timing"].uniform(0.0, 1.0 / config.tactile_rate_hz)}
        if config.tactile_phase_s is not None:  # drawn all the same: the later draws stay the default's
            tactile_phase["right"] = config.tactile_phase_s
        noise = config.scenario.press.noise
        frames: dict[str, list[TactileFrame]] = {}
        streams, sensors_true = {}, {}
        for side in SIDES:
            tactile_times = np.round(_stream_times(touch_time, end, config.tactile_rate_hz, tactile_phase[side]), 6)
            # The reconstruction's depth scale error and smooth bias come from the sensor's calibration and lighting:
            # drawn once per sensor, fixed on its pad (a sliding contact sees other parts of the bias field).
            # Pixel noise is new every frame.
            calibration_error = calibration_errors(noise, rng["tactile"], config.scenario.press.spec)
            # The touch's own cloud is this sensor's first frame: the same calibration errors as the ones after it.
            touch_press = touch.contacts[side].press
            touch_cloud, _ = self._reconstruct(
                touch_press.height_map_m, touch_press.contact_mask, calibration_error, rng["tactile"]
            )
            if len(touch_cloud) >= MIN_TACTILE_POINTS:
                touch.contacts[side].points_sensor = touch_cloud
                touch.pair.contact(side).points_sensor = touch_cloud
                if self.images is None:
                    touch.pair.extra["simulation"][side]["scale_error"] = calibration_error[0]
            T_object_sensor_start = invert_transform(object_true(tactile_times)) @ commanded(side, tactile_times)
            depth = touch.contacts[side].press.depth_m
            frames[side], shifts = [], []
            for timestamp, T_start in zip(tactile_times, T_object_sensor_start, strict=True):
                frame, shift = self._frame(float(timestamp), T_start, depth, calibration_error, rng["tactile"])
                frames[side].append(frame)
                shifts.append(shift)
            # The true sensor pose: where the arm put it, settled along its axis as the tactile frames say.
            settle = np.interp(times[side], tactile_times, shifts, left=0.0)
            along_axis = np.repeat(np.eye(4)[None], len(settle), axis=0)
            along_axis[:, 2, 3] = settle
            true = commanded(side, times[side]) @ along_axis
            calibration = invert_transform(touch.T_world_sensor_true[side]) @ touch.pair.contact(side).T_world_sensor
            jitter = _jitter(rng["jitter"], len(true), config.jitter_translation_m, config.jitter_rotation_rad)
            sensors_true[side] = PoseStream(times[side], true, f"{side} sensor (true)")
            streams[side] = PoseStream(times[side], true @ calibration @ jitter, f"{side} sensor")

        streams = _as_recorded(streams, config, rng["recorder"], touch_time + 0.5 * config.hold_s, end)
        if config.tactile_stamp_jitter_s > 0:  # the recorded times err; the frames stay in their order
            for side in SIDES:
                errors = rng["timing"].normal(0.0, config.tactile_stamp_jitter_s, len(frames[side]))
                stamps = np.round(np.array([f.timestamp_s for f in frames[side]]) + errors, 6)
                stamps = np.maximum.accumulate(stamps)
                recorded = zip(frames[side], stamps, strict=True)
                frames[side] = [dataclasses.replace(frame, timestamp_s=float(t)) for frame, t in recorded]
        union = np.union1d(streams["left"].timestamps_s, streams["right"].timestamps_s)
        truth = PoseStream(union, object_true(union), "object (true)")
        touch.pair.extra["timestamp"] = touch_time
        final_slip = pose_from_twist(slip_twists(np.array([end])))[0]
        slips = pose_from_twist(slip_twists(union))
        sensor_slip = {}
        for side in SIDES:
            T_end = frames[side][-1].T_object_sensor_true
            sensor_slip[side] = {
                "translation_mm": 1e3 * float(np.linalg.norm(T_end[:3, 3] - T_object_sensor_touch[side][:3, 3])),
                "rotation_deg": float(np.degrees(rotation_angle_rad(T_end, T_object_sensor_touch[side]))),
            }
        net = path.poses(np.array([end]))[0]
        summary = {
            "touch_time_s": touch_time,
            "motion_start_s": motion_start,
            "motion_end_s": motion_start + config.motion_s,
            "end_s": end,
            "path_length_mm": 1e3 * path.total_length_m,
            "net_displacement_mm": 1e3 * float(np.linalg.norm(net[:3, 3] - touch.T_world_object[:3, 3])),
            "rotation_deg": float(np.degrees(np.linalg.norm(path.rotation(path.length_u), axis=1).max())),
            "slip_final_mm": 1e3 * float(np.linalg.norm(final_slip[:3, 3])),
            "slip_final_deg": float(np.degrees(rotation_angle_rad(final_slip, np.eye(4)))),
            "slip_peak_mm": 1e3 * float(np.linalg.norm(slips[:, :3, 3], axis=1).max()),
            "slip_peak_deg": float(np.degrees(np.linalg.norm(so3_log(slips[:, :3, :3]), axis=1).max())),
            "sensor_slip_final": sensor_slip,
            "lagging_arm": lagging,
            "arm_lag_ms": 1e3 * config.arm_lag_s,
            "tactile_frames": {side: len(frames[side]) for side in SIDES},
            "frames_without_contact": {side: sum(len(f.points_sensor) == 0 for f in frames[side]) for side in SIDES},
            "frames_via": "images" if self.images is not None else "simulated reconstruction errors",
        }
        calibration = self.images.calibration if self.images is not None else None
        return SimulatedTrajectory(touch, touch_time, streams, sensors_true, truth, frames, summary, calibration)

    def _frame(
        self,
        timestamp: float,
        T_object_sensor_start: np.ndarray,
        depth_m: float,
        calibration_error: tuple[float, np.ndarray | float],
        rng: np.random.Generator,
    ) -> tuple[TactileFrame, float]:
        """The gel frame of a sensor pressed from `T_object_sensor_start` to `depth_m`, and how far it settled
        along its axis. Any contact counts: the press simulator's reachability checks are for new touches.
        `calibration_error`: the sensor's depth scale error and bias field (metres, (H, W)), the same every frame."""
        press = self.presses.press(T_object_sensor_start, depth_m)
        spec = self.config.scenario.press.spec
        if press.rejection == "no_contact":  # the camera still sees the gel: flat, untouched
            flat = None if self.images is None else self.images.image(np.zeros((spec.height_px, spec.width_px)), rng)
            untouched = np.empty((0, 3))
            if self.config.tactile_whole_pad and self.images is None:  # the whole flat pad, its errors on it
                flat_map = np.zeros((spec.height_px, spec.width_px))
                untouched, _ = self._reconstruct(flat_map, flat_map > 0, calibration_error, rng)
                untouched = _keep_pixel_stride(
                    untouched, self.config.tactile_pixel_stride, spec.pixel_size_m, spec.width_px, spec.height_px
                )
            return TactileFrame(timestamp, untouched, T_object_sensor_start, flat), 0.0
        if press.accepted:
            height_map, mask = press.height_map_m, press.contact_mask
        else:  # a contact the simulator would not accept as a new touch (border, thin edge...): the gel still sees it
            height_map, mask, _ = gel_surface(press.object_z_m, self.config.scenario.press.gel, spec)
        points, image = self._reconstruct(height_map, mask, calibration_error, rng)
        points = _keep_pixel_stride(  # a frame's image keeps every pixel: its reader reconstructs them all
            points, self.config.tactile_pixel_stride, spec.pixel_size_m, spec.width_px, spec.height_px
        )
        shift = float((invert_transform(T_object_sensor_start) @ press.T_object_sensor)[2, 3])
        return TactileFrame(timestamp, points, press.T_object_sensor, image), shift

    def _reconstruct(
        self,
        height_map: np.ndarray,
        mask: np.ndarray,
        calibration_error: tuple[float, np.ndarray | float],
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The tactile cloud of a noise-free height map, and the GelSight image it came from (None without images):
        reconstructed from the image the height map renders to (with `images`; a frame the reconstruction refuses
        gives no cloud, as a lab's pipeline would), else the sensor's fixed scale error and bias, new pixel noise."""
        spec, noise = self.config.scenario.press.spec, self.config.scenario.press.noise
        if self.images is not None:
            from yoto.sensor.reconstruction import reconstruct

            image = self.images.image(height_map, rng)  # the camera's noise new every frame
            try:
                return reconstruct(image, self.images.calibration).points_sensor, image
            except InputError:
                return np.empty((0, 3)), image
        if self.config.tactile_whole_pad:  # every pixel, however little pressed (the same noise draws)
            mask = np.ones_like(mask, dtype=bool)
            noise = dataclasses.replace(noise, mask_threshold_m=-np.inf)
        if noise.is_noise_free:
            return spec.height_map_to_points(height_map, mask), None
        scale_error, bias = calibration_error
        per_frame = dataclasses.replace(noise, scale_std=0.0, bias_std_m=0.0)
        return reconstruct_points(height_map * (1.0 + scale_error) + bias, mask, per_frame, rng, spec)[0], None


# ------------------------------------------------------------------------------------------------ files
# TrajectoryConfig fields added in stops 19 and 20 (stored only where they differ from the dataclass's defaults)
LATER_OPTIONS = (
    "tactile_phase_s",
    "tactile_whole_pad",
    "tactile_stamp_jitter_s",
    "pose_outlier_share",  # stop 20
    "pose_outlier_frames",
    "pose_outlier_m",
    "pose_outlier_rad",
    "pose_flips",
    "pose_flip_s",
    "pose_dropouts",
    "pose_dropout_s",
    "arm_error_m",
    "arm_error_rad",
)


def trajectory_settings(model: ObjectModel, seed: int, config: TrajectoryConfig) -> dict[str, Any]:
    """What determines a folder's trajectories; stored beside them so a resumed run can check it is the same.
    Options added later are stored only where they differ from their default (earlier folders stay resumable)."""
    stored = asdict(config)
    defaults = TrajectoryConfig()
    for name in LATER_OPTIONS:
        if stored[name] == getattr(defaults, name):
            del stored[name]
    return json.loads(
        json.dumps(
            {
                "simulator": f"yoto.simulate.trajectory v{SIMULATOR_VERSION}",
                "object": model.name,
                "object_source": model.meta.get("source", {}),
                "seed": seed,
                "config": stored,
            },
            default=str,
        )
    )


def write_trajectory(trajectory: SimulatedTrajectory, model: ObjectModel, folder: str | Path) -> Path:
    """Write one simulated trajectory as the files `yoto track` reads (see the module docstring). Returns the
    folder. `trajectory.json` is written last: a folder without it is unfinished."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_contact_pair(folder / "touch.json", trajectory.touch.pair)
    for side in SIDES:
        write_tum(
            folder / f"{side}.tum", trajectory.streams[side], f"T_world_sensor of the {side} GelSight (simulated)"
        )
        tactile = folder / f"{side}_tactile"
        tactile.mkdir(exist_ok=True)
        for frame in trajectory.tactile[side]:
            name = tactile_frame_name(frame.timestamp_s)
            if frame.image is not None:  # a GelSight image, as the camera gives it: `yoto track --calibration` reads it
                write_bytes_atomic(tactile / Path(name).with_suffix(".png").name, png_bytes(frame.image))
            else:
                write_ply_points(tactile / name, frame.points_sensor)
    if trajectory.calibration is not None:
        trajectory.calibration.save(folder / CALIBRATION_FILE)
    write_tum(
        folder / "object_true.tum",
        trajectory.truth_mesh(model),
        f"true T_world_object of {model.name}, mesh file's frame (simulated)",
    )
    return write_json_atomic(folder / SUMMARY_FILE, trajectory.summary).parent


@dataclass
class TrajectoryReport:
    """What `write_trajectories` did."""

    out_dir: Path
    written: list[Path] = field(default_factory=list)
    kept: list[Path] = field(default_factory=list)
    seconds: float = 0.0
    summaries: list[dict[str, Any]] = field(default_factory=list)

    def summary(self) -> str:
        lines = [
            f"{len(self.written)} trajectories written, {len(self.kept)} kept from an earlier run, in {self.out_dir} "
            f"({self.seconds:.1f} s)"
        ]
        if self.summaries:
            for key, unit in (("path_length_mm", "mm path"), ("rotation_deg", "deg rotation")):
                values = [s[key] for s in self.summaries]
                lines.append(f"{unit}: {min(values):.1f} - {max(values):.1f}")
            slip = np.array([[s["slip_final_mm"], s["slip_final_deg"], s["slip_peak_mm"]] for s in self.summaries])
            lines.append(
                f"slip at the end: mean {slip[:, 0].mean():.2f} mm / {slip[:, 1].mean():.2f} deg; "
                f"peak mean {slip[:, 2].mean():.2f} mm"
            )
        return "\n".join(lines)


def trajectory_folder_name(index: int) -> str:
    return f"traj_{index:04d}"


def write_trajectories(
    model: ObjectModel,
    out_dir: str | Path,
    count: int,
    seed: int = 0,
    config: TrajectoryConfig = TrajectoryConfig(),
    overwrite: bool = False,
    progress: bool = False,
    frames_via: str | None = None,
) -> TrajectoryReport:
    """Write trajectories 0..count-1 into `out_dir/traj_NNNN/`; resumable and idempotent.

    Finished trajectories (with their `trajectory.json`) are kept unless `overwrite`; an unfinished folder is
    redone from scratch. A folder made with other settings is refused unless `overwrite`. `frames_via`: the tactile
    frames are GelSight images (`<timestamp>.png`, with the `calibration.npz` that reconstructs them) rendered by
    `yoto.sensor.optical.image_route(frames_via)` (a calibration file, or `shading[:SEED]`).
    """
    out_dir = Path(out_dir)
    settings = trajectory_settings(model, seed, config)
    if frames_via is not None:
        settings["frames_via"] = frames_via
    settings_path = out_dir / FOLDER_SETTINGS_FILE
    stored = read_json(settings_path) if settings_path.exists() else None
    settings_changed(out_dir, stored, settings, "trajectories", overwrite)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(settings_path, settings)
    report = TrajectoryReport(out_dir=out_dir)
    todo = []
    for index in range(count):
        folder = out_dir / trajectory_folder_name(index)
        if (folder / SUMMARY_FILE).exists() and not overwrite:
            report.kept.append(folder)
        else:
            todo.append(index)
    if not todo:
        return report
    images = None
    if frames_via is not None:
        from yoto.sensor.optical import image_route

        images = image_route(frames_via)
    simulator = TrajectorySimulator(model, config, images)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="trajectory", desc=f"simulating {model.name}")
    started = time.perf_counter()
    try:
        for index in todo:
            folder = out_dir / trajectory_folder_name(index)
            if folder.exists():
                shutil.rmtree(folder)  # unfinished or overwritten: no stale frames may remain
            trajectory = simulator.trajectory(seed, index)
            report.written.append(write_trajectory(trajectory, model, folder))
            report.summaries.append(trajectory.summary)
            if bar is not None:
                bar.update(1)
    finally:
        report.seconds = time.perf_counter() - started
        if bar is not None:
            bar.close()
    return report
