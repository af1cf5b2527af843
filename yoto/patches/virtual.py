"""Virtual tactile patches sampled from the parent cloud, with labels (paper App. A.3).

For each of 29 parent variants (rotations about the canonical z axis: none, 14 fixed at 12..168 deg, 14
random) we make 300 attempts. An attempt picks a centre on the surface, binary-searches a ball radius in
[0, r] (r = 20 mm) until the ball holds 700-1200 parent points, rejects degenerate patches, and labels the
patch: contact location p (the parent point nearest the patch centroid), dominant block, offset p - c_block.
Labels are in the unrotated object frame, so they transfer across variants.

Where the paper's text and a working generator part ways we say so:
- Centres are parent points (uniform on the surface). The paper samples them inside the bounding box
  "no closer than 1.2 r to any face", which leaves most of a convex object's surface out of reach;
  its purpose, keeping balls clear of the cloud's edge, is kept: on open meshes (scans with holes) a
  centre must be at least 1.2 x the ball radius from any open boundary.
- Patches whose points face both ways (a ball through a part thinner than itself) are rejected, as no
  sensor could touch both sides at once.

The dataset file stores each patch as its parent-point indices and the transform to canonical form, so
it is exact and small; `VirtualPatchDataset.patch(i)` materializes canonical points and normals.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from yoto.errors import DegenerateGeometryError, InputError
from yoto.geometry import rotation_about_axis
from yoto.io import load_npz, save_npz_atomic
from yoto.objects.model import ObjectModel
from yoto.patches.canonical import canonicalize_patch

log = logging.getLogger("yoto")

FORMAT_NAME = "yoto-virtual-patches"
FORMAT_VERSION = 1
REJECTION_REASONS = ("too_few_points", "too_many_points", "near_open_boundary", "two_sided", "degenerate_concavity")


@dataclass(frozen=True)
class VirtualPatchConfig:
    """The paper's generator settings (App. A.3)."""

    fixed_variants: int = 14  # rotations at step_deg, 2 x step_deg, ... (plus the unrotated original)
    random_variants: int = 14  # further rotations drawn uniformly in [0, 360) deg
    step_deg: float = 12.0  # spacing of the fixed rotations
    min_random_gap_deg: float = 0.5  # random rotations keep this far from any fixed one
    attempts_per_variant: int = 300  # patches attempted per variant
    retries_per_attempt: int = 10  # a rejected candidate is redrawn up to this many times
    max_radius_m: float = 0.020  # r: the largest ball, comparable to the GelSight Mini footprint
    min_points: int = 700  # accepted point-count band of a patch
    max_points: int = 1200
    boundary_margin: float = 1.2  # on open meshes, centres stay this many ball radii from the boundary
    max_backfacing_fraction: float = 0.05  # more points than this facing against the mean normal: two-sided
    seed: int = 0

    @property
    def num_variants(self) -> int:
        return 1 + self.fixed_variants + self.random_variants


def variant_angles_rad(config: VirtualPatchConfig) -> np.ndarray:
    """Rotation angle of every parent variant about the canonical z axis: 0, fixed steps, then random ones."""
    fixed = config.step_deg * np.arange(1, config.fixed_variants + 1)
    rng = np.random.default_rng([config.seed, 29])
    random_angles: list[float] = []
    grid = np.concatenate([[0.0], fixed])
    while len(random_angles) < config.random_variants:
        angle = rng.uniform(0.0, 360.0)
        gap = np.abs((grid - angle + 180.0) % 360.0 - 180.0).min()
        if gap >= config.min_random_gap_deg:
            random_angles.append(angle)
    return np.radians(np.concatenate([[0.0], fixed, random_angles]))


def open_boundary_points(model: ObjectModel, spacing_m: float) -> np.ndarray:
    """Points along the mesh's open boundary edges (object frame); empty for a watertight mesh."""
    faces = model.mesh_faces
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1).astype(np.int64)
    keys = edges[:, 0] * (faces.max() + 1) + edges[:, 1]
    unique_keys, counts = np.unique(keys, return_counts=True)
    boundary = edges[np.isin(keys, unique_keys[counts == 1])]
    if len(boundary) == 0:
        return np.zeros((0, 3))
    vertices = model.mesh_object.vertices
    start, end = vertices[boundary[:, 0]], vertices[boundary[:, 1]]
    steps = np.maximum(1, np.ceil(np.linalg.norm(end - start, axis=1) / spacing_m).astype(int))
    return np.concatenate(
        [start[i] + np.linspace(0, 1, s + 1)[:, None] * (end[i] - start[i]) for i, s in enumerate(steps)]
    )


@dataclass
class _GeneratorState:
    """What each worker process needs; set once per process."""

    model: ObjectModel
    config: VirtualPatchConfig
    boundary_tree: cKDTree | None


_STATE: _GeneratorState | None = None


def _init_worker(model: ObjectModel, config: VirtualPatchConfig, boundary: np.ndarray) -> None:
    global _STATE
    _STATE = _GeneratorState(model, config, cKDTree(boundary) if len(boundary) else None)


def _sample_ball(distances: np.ndarray, config: VirtualPatchConfig) -> tuple[float, int] | str:
    """Binary-search the ball radius over [0, r] until it holds min..max points; distances are sorted."""
    if np.searchsorted(distances, config.max_radius_m, side="right") < config.min_points:
        return "too_few_points"
    low, high = 0.0, config.max_radius_m
    for _ in range(40):
        radius = 0.5 * (low + high)
        count = int(np.searchsorted(distances, radius, side="right"))
        if count < config.min_points:
            low = radius
        elif count > config.max_points:
            high = radius
        else:
            return radius, count
    return "too_many_points"


@dataclass
class _VariantPatches:
    """The accepted patches of one parent variant (per-patch lists, keyed like the dataset's columns)."""

    variant: int
    records: dict[str, list]
    rejections: dict[str, int]


def _generate_variant(variant: int, angle_rad: float) -> _VariantPatches:
    """All attempts of one parent variant. Deterministic from (seed, variant)."""
    assert _STATE is not None
    model, config = _STATE.model, _STATE.config
    rng = np.random.default_rng([config.seed, variant])
    rotation_variant = rotation_about_axis(np.array([0.0, 0.0, 1.0]), angle_rad)
    points_object = model.points_object.astype(np.float64)
    normals_object = model.normals_object.astype(np.float64)
    tree = model.kdtree
    rejections = dict.fromkeys(REJECTION_REASONS, 0)
    records: dict[str, list] = {k: [] for k in ("indices", "rotation", "translation", "p", "block", "radius")}

    for _ in range(config.attempts_per_variant):
        for _retry in range(config.retries_per_attempt):
            centre = points_object[rng.integers(len(points_object))]
            distances, neighbours = tree.query(centre, k=config.max_points + 1)
            ball = _sample_ball(distances, config)
            if isinstance(ball, str):
                rejections[ball] += 1
                continue
            radius, count = ball
            if (
                _STATE.boundary_tree is not None
                and _STATE.boundary_tree.query(centre)[0] < config.boundary_margin * radius
            ):
                rejections["near_open_boundary"] += 1
                continue
            members = np.sort(neighbours[:count])
            normals = normals_object[members]
            mean_normal = normals.sum(axis=0)
            if (normals @ mean_normal < 0).mean() > config.max_backfacing_fraction:
                rejections["two_sided"] += 1
                continue
            # The patch as it lies on the rotated parent; labels stay in the unrotated object frame.
            try:
                canonical = canonicalize_patch(
                    points_object[members] @ rotation_variant.T, normals @ rotation_variant.T
                )
            except DegenerateGeometryError:
                rejections["degenerate_concavity"] += 1
                continue
            centroid_object = rotation_variant.T @ canonical.centroid_source
            p_object = points_object[
                members[np.argmin(np.linalg.norm(points_object[members] - centroid_object, axis=1))]
            ]
            block_votes = np.bincount(model.point_block[members][model.point_block[members] >= 0], minlength=1)
            # p_canonical = R_c (R_v p_object - c) = (R_c R_v) p_object - R_c c
            rotation = canonical.rotation_canonical_source @ rotation_variant
            records["indices"].append(members.astype(np.uint32))
            records["rotation"].append(rotation)
            records["translation"].append(-canonical.rotation_canonical_source @ canonical.centroid_source)
            records["p"].append(p_object)
            records["block"].append(int(np.argmax(block_votes)) if block_votes.sum() else -1)
            records["radius"].append(radius)
            break
    return _VariantPatches(variant, records, rejections)


def generate_virtual_patches(
    model: ObjectModel,
    config: VirtualPatchConfig = VirtualPatchConfig(),
    workers: int | None = None,
    progress: bool = True,
) -> VirtualPatchDataset:
    """Run the generator over all variants (in parallel processes) and return the labelled dataset."""
    angles = variant_angles_rad(config)
    boundary = open_boundary_points(model, model.point_spacing_m)
    workers = workers or min(len(angles), os.cpu_count() or 1)
    results = []
    bar = tqdm(total=len(angles), desc=f"virtual patches {model.name}", unit="variant", disable=not progress)
    if workers <= 1:
        _init_worker(model, config, boundary)
        for variant, angle in enumerate(angles):
            results.append(_generate_variant(variant, angle))
            bar.update()
    else:
        context = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        with ProcessPoolExecutor(
            workers, mp_context=context, initializer=_init_worker, initargs=(model, config, boundary)
        ) as pool:
            futures = [pool.submit(_generate_variant, v, a) for v, a in enumerate(angles)]
            for future in futures:
                results.append(future.result())
                bar.update()
    bar.close()

    rejections = dict.fromkeys(REJECTION_REASONS, 0)
    columns: dict[str, list] = {
        k: [] for k in ("indices", "rotation", "translation", "p", "block", "radius", "variant")
    }
    for result in sorted(results, key=lambda r: r.variant):
        for reason, count in result.rejections.items():
            rejections[reason] += count
        for key, values in result.records.items():
            columns[key].extend(values)
        columns["variant"].extend([result.variant] * len(result.records["p"]))
    if not columns["p"]:
        raise InputError(
            f"no virtual patch could be generated for {model.name!r} (rejections: {rejections}); is the parent cloud "
            f"too sparse for {config.min_points}-{config.max_points} points within {config.max_radius_m * 1000:.0f} mm?"
        )
    meta = {
        "config": asdict(config),
        "rejections": rejections,
        "attempted": config.num_variants * config.attempts_per_variant,
        "variant_angles_deg": np.degrees(angles).tolist(),
    }
    return dataset_from_columns(model, columns, np.array(columns["variant"], dtype=np.int32), meta)


def dataset_from_columns(
    model: ObjectModel, columns: dict[str, list], variant: np.ndarray, meta: dict
) -> VirtualPatchDataset:
    """Assemble a dataset from per-patch lists (indices, rotation, translation, p, block, radius)."""
    sizes = np.array([len(i) for i in columns["indices"]])
    p_object = np.array(columns["p"])
    blocks = np.array(columns["block"], dtype=np.int32)
    return VirtualPatchDataset(
        model=model,
        indices=np.concatenate(columns["indices"]),
        offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        rotation_canonical_object=np.array(columns["rotation"]),
        translation_canonical=np.array(columns["translation"]),
        p_object=p_object,
        block=blocks,
        offset_object=p_object - model.block_centres_object[blocks],
        radius_m=np.array(columns["radius"]),
        variant=variant,
        meta=meta,
    )


@dataclass
class VirtualPatchDataset:
    """Labelled virtual patches of one object. Patch i is parent points indices[offsets[i]:offsets[i+1]]."""

    model: ObjectModel
    indices: np.ndarray  # (total,) uint32 parent-point indices of all patches, concatenated
    offsets: np.ndarray  # (M + 1,) int64 start of each patch in `indices`
    rotation_canonical_object: np.ndarray  # (M, 3, 3): p_canonical = R p_object + t
    translation_canonical: np.ndarray  # (M, 3) t
    p_object: np.ndarray  # (M, 3) contact location label (object frame)
    block: np.ndarray  # (M,) dominant block label
    offset_object: np.ndarray  # (M, 3) p_object - block centre
    radius_m: np.ndarray  # (M,) ball radius of each patch
    variant: np.ndarray  # (M,) parent variant index
    meta: dict

    def __len__(self) -> int:
        return len(self.p_object)

    def patch(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Canonical points and outward normals of patch i, (n_i, 3) float32 each."""
        members = self.indices[self.offsets[i] : self.offsets[i + 1]]
        rotation = self.rotation_canonical_object[i]
        points = self.model.points_object[members] @ rotation.T + self.translation_canonical[i]
        return points.astype(np.float32), (self.model.normals_object[members] @ rotation.T).astype(np.float32)

    def counts(self) -> dict[str, int]:
        return {"accepted": len(self), "attempted": int(self.meta["attempted"])}

    def save(self, path: str | Path) -> Path:
        arrays = {
            "indices": self.indices,
            "offsets": self.offsets,
            "rotation_canonical_object": self.rotation_canonical_object,
            "translation_canonical": self.translation_canonical,
            "p_object": self.p_object,
            "block": self.block,
            "offset_object": self.offset_object,
            "radius_m": self.radius_m,
            "variant": self.variant,
        }
        meta = {
            **self.meta,
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "object": self.model.name,
            "model_fingerprint": self.model.fingerprint,
        }
        return save_npz_atomic(path, arrays, meta)

    @classmethod
    def load(cls, path: str | Path, model: ObjectModel) -> VirtualPatchDataset:
        arrays, meta = load_npz(path, "virtual patch dataset")
        if meta.get("format") != FORMAT_NAME or meta.get("format_version") != FORMAT_VERSION:
            raise InputError(f"not a YOTO virtual patch dataset of version {FORMAT_VERSION}", path)
        if meta.get("model_fingerprint") != model.fingerprint:
            raise InputError(
                f"patches were generated from another build of object {meta.get('object')!r}; regenerate them with "
                "`yoto patches generate`",
                path,
            )
        return cls(model=model, meta=meta, **arrays)
