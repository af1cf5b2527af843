"""Press-shaped virtual patches: what a flat GelSight pad pressed into the parent cloud would touch.

The paper's virtual patches are Euclidean balls of 700-1200 parent points (about 7.5 mm radius here). A real
GelSight Mini contact is shaped by the press instead: the part of the surface within the indentation depth
of the point nearest the pad, inside the 20.3 x 15.2 mm pad, so it is small on sharp curvature, fills the
pad on flat areas, and is elongated on cylinders. This sampler cuts such regions from the parent cloud, with
the SPEC's description of a press (depth 0.5-1.5 mm, approach within a few degrees of the surface normal,
random roll, the pad centred near the target). It is purely geometric (no gel, no reconstruction noise) and
shares no code with the contact simulator that tests and benchmarks grade on.

Per attempt: a target parent point t with outward normal n (kNN-aggregated); a pressing direction -n tilted by
up to `max_tilt_deg`, a random roll, a pad-centre offset; the parent points around t that face the pad and
lie inside it; the contact is those within `depth` of the one nearest the pad. Rejected when the target is
not in the contact (a concavity the pad cannot reach), when the contact holds too few points, or when its
concave direction is degenerate. Labels as for ball patches: the parent point nearest the contact's centroid
and the contact's dominant block. Stored like ball patches (VirtualPatchDataset, parent-point indices and the
transform to canonical form) in WORKSPACE/patches/NAME.press.npz.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from yoto.errors import DegenerateGeometryError, InputError
from yoto.geometry import normalize, rotation_about_axis
from yoto.objects.model import ObjectModel
from yoto.patches.canonical import canonicalize_patch
from yoto.patches.virtual import VirtualPatchDataset, dataset_from_columns
from yoto.workspace import patch_dataset_path

log = logging.getLogger("yoto")


@dataclass(frozen=True)
class PressPatchConfig:
    """How press-shaped patches are cut from the parent cloud."""

    count: int = 8700  # patches per object (as many as the paper's 29 x 300 ball patches)
    depth_m: tuple[float, float] = (0.0005, 0.0015)  # indentation depth, uniform (SPEC: typically 0.5-1.5 mm)
    max_tilt_deg: float = 10.0  # pressing direction within this angle of the reversed surface normal
    max_offset_m: float = 0.0015  # the pad centre lies up to this far from the target, uniform on a disc
    pad_size_m: tuple[float, float] = (0.0203, 0.0152)  # GelSight Mini sensed area (x, y)
    min_points: int = 60  # fewer contact points (at the parent's density) are rejected
    max_attempts_factor: int = 5  # give up after count x this many attempts
    seed: int = 0


def press_dataset_path(name: str, workspace: str | Path | None = None) -> Path:
    path = patch_dataset_path(name, workspace)
    return path.with_name(f"{name}.press.npz")


def _random_tilt(normal: np.ndarray, max_tilt_rad: float, rng: np.random.Generator) -> np.ndarray:
    """The reversed normal tilted by an angle uniform on the spherical cap of half-angle max_tilt."""
    cos_tilt = rng.uniform(np.cos(max_tilt_rad), 1.0)
    axis = np.cross(normal, rng.normal(size=3))
    if np.linalg.norm(axis) < 1e-9:
        return -normal
    return rotation_about_axis(axis, float(np.arccos(cos_tilt))) @ (-normal)


def sample_press(
    model: ObjectModel, target_index: int, rng: np.random.Generator, config: PressPatchConfig
) -> np.ndarray | str:
    """Parent-point indices of one press-shaped contact aimed at parent point `target_index`, or the reason
    it was rejected."""
    points = model.points_object
    target = points[target_index].astype(np.float64)
    normal = model.aggregated_normal(target, 20)
    z_axis = _random_tilt(normal, np.radians(config.max_tilt_deg), rng)  # pressing direction, into the object
    x_axis = normalize(np.cross(z_axis, rng.normal(size=3)))
    y_axis = np.cross(z_axis, x_axis)
    radius = rng.uniform(0.0, 1.0) ** 0.5 * config.max_offset_m
    angle = rng.uniform(0.0, 2.0 * np.pi)
    pad_centre = target + radius * (np.cos(angle) * x_axis + np.sin(angle) * y_axis)
    half_w, half_h = config.pad_size_m[0] / 2, config.pad_size_m[1] / 2
    around = np.asarray(model.kdtree.query_ball_point(pad_centre, float(np.hypot(half_w, half_h)) + 1e-4))
    offsets = points[around].astype(np.float64) - pad_centre
    u, v, h = offsets @ x_axis, offsets @ y_axis, offsets @ z_axis
    facing = model.normals_object[around].astype(np.float64) @ z_axis < 0.0  # outward normal toward the pad
    inside = facing & (np.abs(u) <= half_w) & (np.abs(v) <= half_h)
    if not inside.any():
        return "no_contact"
    depth = rng.uniform(*config.depth_m)
    contact = inside & (h <= h[inside].min() + depth)
    target_height = (target - pad_centre) @ z_axis
    if target_height > h[inside].min() + depth:
        return "target_not_in_contact"
    if contact.sum() < config.min_points:
        return "small_contact"
    return np.sort(around[contact])


def generate_press_patches(model: ObjectModel, config: PressPatchConfig = PressPatchConfig()) -> VirtualPatchDataset:
    """`config.count` labelled press-shaped patches of `model` (deterministic for the config's seed)."""
    rng = np.random.default_rng([config.seed, 31337])
    points_object = model.points_object.astype(np.float64)
    normals_object = model.normals_object.astype(np.float64)
    columns: dict[str, list] = {k: [] for k in ("indices", "rotation", "translation", "p", "block", "radius")}
    rejections: dict[str, int] = {}
    attempts = 0
    while len(columns["p"]) < config.count and attempts < config.count * config.max_attempts_factor:
        attempts += 1
        members = sample_press(model, int(rng.integers(len(points_object))), rng, config)
        if isinstance(members, str):
            rejections[members] = rejections.get(members, 0) + 1
            continue
        try:
            canonical = canonicalize_patch(points_object[members], normals_object[members])
        except DegenerateGeometryError:
            rejections["degenerate_concavity"] = rejections.get("degenerate_concavity", 0) + 1
            continue
        member_points = points_object[members]
        p_object = member_points[np.argmin(np.linalg.norm(member_points - canonical.centroid_source, axis=1))]
        blocks = model.point_block[members]
        blocks = blocks[blocks >= 0]
        if len(blocks) == 0:
            rejections["no_block"] = rejections.get("no_block", 0) + 1
            continue
        columns["indices"].append(members.astype(np.uint32))
        columns["rotation"].append(canonical.rotation_canonical_source)
        columns["translation"].append(-canonical.rotation_canonical_source @ canonical.centroid_source)
        columns["p"].append(p_object)
        columns["block"].append(int(np.bincount(blocks).argmax()))
        columns["radius"].append(float(np.linalg.norm(member_points - canonical.centroid_source, axis=1).max()))
    if not columns["p"]:
        raise InputError(f"no press-shaped patch could be cut from {model.name!r} (rejections: {rejections})")
    meta = {"kind": "press", "config": asdict(config), "rejections": rejections, "attempted": attempts}
    return dataset_from_columns(model, columns, np.zeros(len(columns["p"]), dtype=np.int32), meta)


def press_patches(
    model: ObjectModel, config: PressPatchConfig, workspace: str | Path | None = None, overwrite: bool = False
) -> VirtualPatchDataset:
    """The press-shaped patches of `model`: loaded if an up-to-date file exists, else generated and saved."""
    path = press_dataset_path(model.name, workspace)
    wanted = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()}
    if path.exists() and not overwrite:
        try:
            existing = VirtualPatchDataset.load(path, model)
            if existing.meta.get("kind") == "press" and existing.meta.get("config") == wanted:
                return existing
        except InputError as exc:
            log.info("%s: regenerating (%s)", path, exc.problem)
    dataset = generate_press_patches(model, config)
    dataset.save(path)
    log.info(
        "%s: %d press-shaped patches in %d attempts (rejections %s)",
        model.name,
        len(dataset),
        dataset.meta["attempted"],
        dataset.meta["rejections"],
    )
    return dataset
