"""Dual-contact scenarios: a random object pose and two reachable, non-coaxial GelSight contacts.

Pair i is drawn from its own random streams, seeded by (seed, i) alone: the same pair comes out whatever
N is, whichever other pairs were made, and in whatever order, so a benchmark can grow N without changing
its first pairs. Each pair's streams are split by purpose (object pose, contacts, reconstruction noise,
calibration noise), so switching noise on or off leaves the geometry of every pair unchanged.

Frames: the simulator works in YOTO's canonical `object` frame (`model.mesh_object`). Files and
`ContactPair` ground truth are in the mesh file's frame (`T_world_mesh_true`, `p_mesh_true`), as SPEC
requires: `T_world_mesh = T_world_object @ T_object_mesh`, `p_mesh = T_mesh_object @ p_object`.
"""

from __future__ import annotations

import json
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.contacts import (
    FOLDER_SETTINGS_FILE,
    SIDES,
    WELL_CONDITIONED,
    ContactPair,
    TactileContact,
    dual_contact_conditioning,
    write_contact_pair,
)
from yoto.errors import InputError, YotoError
from yoto.geometry import (
    make_transform,
    random_perturbation,
    random_rotations,
    rotation_angle_rad,
    transform_points,
)
from yoto.io import read_json, settings_changed, write_json_atomic
from yoto.objects.model import ObjectModel
from yoto.simulate.press import (
    REJECTION_REASONS,
    SIMULATOR_VERSION,
    PressConfig,
    PressSimulator,
    SimulatedContact,
    finish_contact,
    press_contact,
)

log = logging.getLogger("yoto")

PAIR_REJECTION_REASONS = {
    "contacts_too_close": "the two contacts are closer than the minimum separation",
    "ill_conditioned": "the contacts are near-coaxial: sigma_2/sigma_1 of [d, n_L, n_R] is below the floor",
    "sensors_collide": "the two sensor bodies would collide with each other",
}
SETTINGS_FILE = FOLDER_SETTINGS_FILE

# Mean norm of a 3-D standard normal vector, and mean |x| of a 1-D one: turn "mean error" into a std.
_MEAN_NORM_3D = float(np.sqrt(8.0 / np.pi))
_MEAN_ABS_1D = float(np.sqrt(2.0 / np.pi))


class SimulationError(YotoError):
    """No acceptable pair was found within the attempt budget (the message lists the rejections)."""


@dataclass(frozen=True)
class ScenarioConfig:
    """How dual-contact scenarios are drawn."""

    press: PressConfig = PressConfig()
    workspace_min_m: tuple[float, float, float] = (0.3, -0.2, 0.0)  # object position range, robot base frame
    workspace_max_m: tuple[float, float, float] = (0.7, 0.2, 0.3)
    min_conditioning: float = WELL_CONDITIONED  # sigma_2 / sigma_1 of [d, n_L, n_R] (object frame) at least this
    min_separation_m: float = 0.02  # the two ground-truth contacts at least this far apart
    calibration_translation_m: float = 0.0  # mean |translation error| of each reported T_world_sensor
    calibration_rotation_rad: float = 0.0  # mean rotation error angle of each reported T_world_sensor
    max_attempts: int = 3000  # presses tried for one pair before giving up
    second_contact_tries: int = 40  # presses tried for the second contact before redrawing the first


@dataclass
class SimulatedPair:
    """One dual-contact scenario: the pair (as `yoto pose` reads it) and everything behind it."""

    index: int
    seed: int
    pair: ContactPair  # tactile clouds, reported sensor poses, ground truth in the mesh frame
    T_world_object: np.ndarray  # (4, 4) true pose of YOTO's canonical object frame
    contacts: dict[str, SimulatedContact]  # side -> the press and its tactile cloud
    T_world_sensor_true: dict[str, np.ndarray]  # side -> true sensor pose (the tactile cloud comes from it)
    conditioning: float  # sigma_2 / sigma_1 of [d, n_L, n_R] in the object frame
    attempts: int  # presses tried for this pair
    rejections: Counter = field(default_factory=Counter)  # reason -> count, presses and pair checks

    @property
    def height_maps(self) -> dict[str, np.ndarray]:
        """Noise-free gel height maps, side -> (240, 320) metres (z <= 0)."""
        return {side: contact.press.height_map_m for side, contact in self.contacts.items()}

    @property
    def p_object_true(self) -> dict[str, np.ndarray]:
        """Ground-truth contact locations in YOTO's canonical object frame."""
        return {side: contact.p_object for side, contact in self.contacts.items()}


# ------------------------------------------------------------------------------------------------ simulator
class PairSimulator:
    """Draws dual-contact scenarios on one object. Build once per object (it uses the model's ray-casting scene)."""

    def __init__(
        self,
        model: ObjectModel,
        config: ScenarioConfig = ScenarioConfig(),
        reconstruct: Callable[[np.ndarray], np.ndarray] | None = None,
    ):
        self.model = model
        self.config = config
        self.reconstruct = reconstruct
        self.presses = PressSimulator(model.mesh_object, config.press, model.raycaster)
        self._body_boxes = config.press.body.boxes(config.press.spec, with_gel=True)

    def streams(self, seed: int, index: int) -> dict[str, np.random.Generator]:
        """The independent random streams of pair `index` (a function of seed and index only)."""
        if seed < 0 or index < 0:
            raise InputError(f"seed and pair index must be non-negative (got seed {seed}, index {index})")
        children = np.random.SeedSequence([seed, index]).spawn(4)
        names = ("pose", "contacts", "noise", "calibration")
        return {name: np.random.default_rng(child) for name, child in zip(names, children, strict=True)}

    def _contact(self, rng: np.random.Generator) -> SimulatedContact:
        p_object = self.presses.sample_surface(rng)[0]
        return press_contact(self.presses, p_object, self.model.aggregated_normal(p_object), rng)

    def _pair_rejection(self, first: SimulatedContact, second: SimulatedContact) -> tuple[str | None, float]:
        p_first, p_second = first.p_object, second.p_object
        offset = p_second - p_first
        if np.linalg.norm(offset) < self.config.min_separation_m:
            return "contacts_too_close", 0.0
        conditioning = direction_conditioning(
            offset, self.model.aggregated_normal(p_first), self.model.aggregated_normal(p_second)
        )
        if conditioning < self.config.min_conditioning:
            return "ill_conditioned", conditioning
        if self.sensors_collide(first.press.T_object_sensor, second.press.T_object_sensor):
            return "sensors_collide", conditioning
        return None, conditioning

    def sensors_collide(self, T_object_sensor_a: np.ndarray, T_object_sensor_b: np.ndarray) -> bool:
        """Whether two sensors' bodies (gel block, housing, probe) overlap."""
        for centre_a, half_a in self._body_boxes:
            for centre_b, half_b in self._body_boxes:
                if boxes_overlap(T_object_sensor_a, centre_a, half_a, T_object_sensor_b, centre_b, half_b):
                    return True
        return False

    def pair(self, seed: int, index: int) -> SimulatedPair:
        """Pair `index` of the scenario set `seed`. Raises SimulationError if the attempt budget runs out."""
        config = self.config
        rng = self.streams(seed, index)
        rotation = random_rotations(rng["pose"], 1)[0]
        position = rng["pose"].uniform(config.workspace_min_m, config.workspace_max_m)
        T_world_object = make_transform(rotation, position)

        rejections: Counter = Counter()
        attempts = 0
        while attempts < config.max_attempts:
            first = self._contact(rng["contacts"])
            attempts += 1
            if not first.press.accepted:
                rejections[first.rejection] += 1
                continue
            for _ in range(config.second_contact_tries):
                if attempts >= config.max_attempts:
                    break
                second = self._contact(rng["contacts"])
                attempts += 1
                if not second.press.accepted:
                    rejections[second.rejection] += 1
                    continue
                reason, conditioning = self._pair_rejection(first, second)
                if reason is not None:
                    rejections[reason] += 1
                    continue
                for contact in (first, second):
                    finish_contact(self.presses, contact, rng["noise"], self.reconstruct)
                if not (first.accepted and second.accepted):  # the reconstruction hook returned too little
                    rejections["reconstruction_failed"] += 1
                    break
                return self._assemble(
                    seed, index, T_world_object, (first, second), conditioning, attempts, rejections, rng
                )
        raise SimulationError(
            f"{self.model.name}: no acceptable contact pair in {attempts} presses (pair {index}, seed {seed}); "
            f"rejections: {format_rejections(rejections)}. Is the mesh open, very concave or too small for a "
            "GelSight Mini?"
        )

    def _assemble(
        self,
        seed: int,
        index: int,
        T_world_object: np.ndarray,
        first_second: tuple[SimulatedContact, SimulatedContact],
        conditioning: float,
        attempts: int,
        rejections: Counter,
        rng: dict[str, np.random.Generator],
    ) -> SimulatedPair:
        config, model = self.config, self.model
        contacts = dict(zip(SIDES, first_second, strict=True))
        noisy_calibration = config.calibration_translation_m > 0 or config.calibration_rotation_rad > 0
        tactile, true_poses, record = {}, {}, {}
        for side, contact in contacts.items():
            T_world_sensor = T_world_object @ contact.press.T_object_sensor
            true_poses[side] = T_world_sensor
            T_reported = T_world_sensor
            if noisy_calibration:
                T_reported = T_world_sensor @ calibration_error(
                    rng["calibration"], config.calibration_translation_m, config.calibration_rotation_rad
                )
            tactile[side] = TactileContact(points_sensor=contact.points_sensor, T_world_sensor=T_reported)
            record[side] = {
                **{key: round(value, 6) for key, value in contact.approach.items()},
                "contact_pixels": contact.press.contact_pixels,
                "border_fraction": round(contact.press.details["border_fraction"], 4),
                "contact_width_mm": round(contact.press.details["contact_width_mm"], 3),
                "tactile_points": len(contact.points_sensor),
                "target_mesh": transform_points(model.T_mesh_object, contact.target_object),
                "T_world_sensor_true": T_world_sensor,
                "calibration_error_mm": float(np.linalg.norm(T_reported[:3, 3] - T_world_sensor[:3, 3]) * 1e3),
                "calibration_error_deg": float(np.degrees(rotation_angle_rad(T_reported, T_world_sensor))),
                **{key: float(value) for key, value in contact.noise.items()},
            }
        p_object = {side: contact.p_object for side, contact in contacts.items()}
        extra = {
            "simulation": {
                "simulator": f"yoto.simulate v{SIMULATOR_VERSION}",
                "seed": seed,
                "index": index,
                "attempts": attempts,
                "conditioning": conditioning,
                "separation_mm": float(np.linalg.norm(p_object["right"] - p_object["left"]) * 1e3),
                **record,
            }
        }
        pair = ContactPair(
            object_name=model.name,
            left=tactile["left"],
            right=tactile["right"],
            T_world_mesh_true=T_world_object @ model.T_object_mesh,
            p_mesh_true={side: transform_points(model.T_mesh_object, p) for side, p in p_object.items()},
            extra=extra,
        )
        return SimulatedPair(
            index=index,
            seed=seed,
            pair=pair,
            T_world_object=T_world_object,
            contacts=contacts,
            T_world_sensor_true=true_poses,
            conditioning=conditioning,
            attempts=attempts,
            rejections=rejections,
        )


def simulate_pairs(
    model: ObjectModel,
    indices: int | Iterable[int],
    seed: int = 0,
    config: ScenarioConfig = ScenarioConfig(),
    reconstruct: Callable[[np.ndarray], np.ndarray] | None = None,
) -> list[SimulatedPair]:
    """Simulated pairs in memory: `indices` is a count N (pairs 0..N-1) or explicit pair indices."""
    simulator = PairSimulator(model, config, reconstruct)
    return list(iter_pairs(simulator, indices, seed))


def iter_pairs(simulator: PairSimulator, indices: int | Iterable[int], seed: int = 0) -> Iterator[SimulatedPair]:
    for index in range(indices) if isinstance(indices, int) else indices:
        yield simulator.pair(seed, int(index))


# ------------------------------------------------------------------------------------------------ files
@dataclass
class SimulationReport:
    """What `write_pairs` did."""

    out_dir: Path
    written: list[Path] = field(default_factory=list)
    kept: list[Path] = field(default_factory=list)
    attempts: int = 0  # presses tried for the pairs written in this run
    rejections: Counter = field(default_factory=Counter)
    seconds: float = 0.0
    oracle_errors: list[tuple[float, float]] = field(default_factory=list)  # (m, rad) per written pair

    def summary(self) -> str:
        accepted = 2 * len(self.written)
        lines = [
            f"{len(self.written)} pairs written, {len(self.kept)} kept from an earlier run, in {self.out_dir} "
            f"({self.seconds:.1f} s)"
        ]
        if self.written:
            press_rejections = sum(n for reason, n in self.rejections.items() if reason in REJECTION_REASONS)
            lines.append(
                f"presses: {self.attempts} tried, {self.attempts - press_rejections} reachable; "
                f"{accepted} used in pairs ({100.0 * accepted / max(self.attempts, 1):.0f}% of presses)"
            )
            lines.append(f"rejections: {format_rejections(self.rejections)}")
        if self.oracle_errors:
            errors = np.array(self.oracle_errors)
            lines.append(
                "sanity check, solver fed the true contact locations (oracle): median pose error "
                f"{np.median(errors[:, 0]) * 1e3:.2f} mm, {np.degrees(np.median(errors[:, 1])):.2f} deg"
            )
        return "\n".join(lines)


def pair_file_name(index: int) -> str:
    return f"pair_{index:04d}.json"


def _remove_pairs(out_dir: Path, first_index: int) -> None:
    """Delete the simulated pair files (JSON and both clouds) with index >= first_index."""
    for path in out_dir.glob("pair_*.json"):
        stem = path.stem
        if stem[5:].isdigit() and int(stem[5:]) >= first_index:
            for side in SIDES:
                (out_dir / f"{stem}_{side}.ply").unlink(missing_ok=True)
            path.unlink()


def simulation_settings(model: ObjectModel, seed: int, config: ScenarioConfig, reconstruct: bool) -> dict[str, Any]:
    """What determines a folder's pairs; stored next to them so a resumed run can check it is the same."""
    return json.loads(
        json.dumps(
            {
                "simulator": f"yoto.simulate v{SIMULATOR_VERSION}",
                "object": model.name,
                "object_source": model.meta.get("source", {}),
                "object_build": model.meta.get("build_config", {}),
                "seed": seed,
                "reconstruct_hook": reconstruct,
                "config": asdict(config),
            },
            default=str,
        )
    )


def write_pairs(
    model: ObjectModel,
    out_dir: str | Path,
    count: int,
    seed: int = 0,
    config: ScenarioConfig = ScenarioConfig(),
    overwrite: bool = False,
    reconstruct: Callable[[np.ndarray], np.ndarray] | None = None,
    progress: bool = False,
    check: Callable[[ContactPair], tuple[float, float]] | None = None,
) -> SimulationReport:
    """Write pairs 0..count-1 as pair files (SPEC format) into `out_dir`; resumable and idempotent.

    `check`, if given, measures each written pair (e.g. the pose stage's `oracle_pose_errors`: translation in
    metres, rotation in radians); the report summarises it as a sanity check.

    Pair files already present are kept unless `overwrite`. A folder made with other settings (object,
    seed, config) is refused unless `overwrite`, which then also removes that run's pairs beyond `count`:
    a folder never mixes two scenario sets.
    """
    out_dir = Path(out_dir)
    settings = simulation_settings(model, seed, config, reconstruct is not None)
    settings_path = out_dir / SETTINGS_FILE
    stored = read_json(settings_path) if settings_path.exists() else None
    if stored is None and not overwrite and any(out_dir.glob("pair_*.json")):
        raise InputError(
            f"this folder holds pair files but no {SETTINGS_FILE}: they were not made by `yoto simulate pairs`; pass "
            "--overwrite to replace them, or choose another --out",
            out_dir,
        )
    if settings_changed(out_dir, stored, settings, "pairs", overwrite):
        _remove_pairs(out_dir, first_index=count)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(settings_path, settings)

    report = SimulationReport(out_dir=out_dir)
    todo = []
    for index in range(count):
        path = out_dir / pair_file_name(index)
        if path.exists() and not overwrite:
            report.kept.append(path)
        else:
            todo.append(index)
    if not todo:
        return report

    simulator = PairSimulator(model, config, reconstruct)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="pair", desc=f"simulating {model.name}")
    start = time.perf_counter()
    try:
        for index in todo:
            simulated = simulator.pair(seed, index)
            report.written.append(write_contact_pair(out_dir / pair_file_name(index), simulated.pair))
            report.attempts += simulated.attempts
            report.rejections.update(simulated.rejections)
            if check is not None:
                report.oracle_errors.append(check(simulated.pair))
            if bar is not None:
                bar.update(1)
    finally:
        report.seconds = time.perf_counter() - start
        if bar is not None:
            bar.close()
    return report


# ------------------------------------------------------------------------------------------------ checks
def direction_conditioning(offset: np.ndarray, n_first: np.ndarray, n_second: np.ndarray) -> float:
    """sigma_2 / sigma_1 of the unit columns [d, n_first, n_second], as the solver measures it."""
    return dual_contact_conditioning(offset, n_first, n_second)[0]


def boxes_overlap(
    T_frame_a: np.ndarray,
    centre_a: np.ndarray,
    half_a: np.ndarray,
    T_frame_b: np.ndarray,
    centre_b: np.ndarray,
    half_b: np.ndarray,
) -> bool:
    """Separating-axis test of two boxes, each axis-aligned in its own frame (poses given in a common frame)."""
    axes_a, axes_b = T_frame_a[:3, :3], T_frame_b[:3, :3]
    between = transform_points(T_frame_b, centre_b) - transform_points(T_frame_a, centre_a)
    candidates = [axes_a[:, i] for i in range(3)] + [axes_b[:, i] for i in range(3)]
    for i in range(3):
        for j in range(3):
            cross = np.cross(axes_a[:, i], axes_b[:, j])
            if np.linalg.norm(cross) > 1e-9:
                candidates.append(cross / np.linalg.norm(cross))
    for axis in candidates:
        reach_a = np.abs(axes_a.T @ axis) @ half_a
        reach_b = np.abs(axes_b.T @ axis) @ half_b
        if abs(between @ axis) > reach_a + reach_b:
            return False
    return True


def calibration_error(rng: np.random.Generator, translation_mean_m: float, rotation_mean_rad: float) -> np.ndarray:
    """A random sensor-frame pose error whose translation norm and rotation angle have the given means.

    Gaussian translation (isotropic) and a rotation by a Gaussian angle about a uniformly random axis,
    with standard deviations chosen so that E|t| = translation_mean_m and E|angle| = rotation_mean_rad.
    """
    return random_perturbation(rng, translation_mean_m / _MEAN_NORM_3D, rotation_mean_rad / _MEAN_ABS_1D)


def format_rejections(rejections: Counter) -> str:
    if not rejections:
        return "none"
    return ", ".join(f"{reason} {count}" for reason, count in rejections.most_common())
