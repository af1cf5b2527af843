"""Training data: each object's blocks and patches, labelled tactile patches (virtual and "real"), draws.

A training sample is a patch in canonical form (yoto.patches.canonical) with its object-frame contact
location `p_object` and ground-truth block. Virtual samples come from the virtual patch dataset of each
object; "real" samples from contact-pair files with ground truth (until real GelSight data exists: the
contact simulator's pairs), brought to canonical form exactly as at inference: prepare -> canonicalize.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from yoto.contacts import SIDES, find_pair_files, is_pair_file_name, read_contact_pair
from yoto.errors import DegenerateGeometryError, InputError
from yoto.geometry import invert_transform, transform_points
from yoto.io import read_json
from yoto.network.inputs import BlockSet, make_block_set, subsample_indices
from yoto.objects.model import ObjectModel
from yoto.patches.canonical import canonicalize_patch, prepare_tactile_cloud
from yoto.patches.generate import generate_patches
from yoto.patches.virtual import VirtualPatchConfig, VirtualPatchDataset
from yoto.rig.samples import FORMAT_NAME as LABELLED_CONTACT_FORMAT
from yoto.rig.samples import is_labelled_contact_file, read_labelled_contact
from yoto.training.augment import (
    AugmentConfig,
    depth_crop_mask,
    jitter,
    perturb_normals,
    point_dropout,
    random_in_plane_rotation,
    voxel_keep_first,
)
from yoto.training.config import TrainConfig
from yoto.training.press import press_patches

log = logging.getLogger("yoto")


# ------------------------------------------------------------------------------------------ contact samples
@dataclass
class ContactSample:
    """A labelled tactile patch in canonical form (a real or simulated contact)."""

    points: np.ndarray  # (n, 3) float32 canonical coordinates
    normals: np.ndarray  # (n, 3) float32 outward normals, canonical frame
    p_object: np.ndarray  # (3,) contact location, object frame
    block: int  # ground-truth (dominant) block
    source: str = ""  # where it came from, for messages


def dominant_block(model: ObjectModel, points_object: np.ndarray) -> int:
    """The valid block holding most of the points (nearest parent point's block), as for virtual patches."""
    blocks = model.block_of_points(points_object)
    blocks = blocks[blocks >= 0]
    if len(blocks) == 0:
        raise DegenerateGeometryError("the contact lies on no valid block")
    return int(np.bincount(blocks).argmax())


def contact_sample(
    points_sensor: np.ndarray,
    model: ObjectModel,
    p_object: np.ndarray,
    T_object_sensor: np.ndarray | None = None,
    source: str = "",
) -> ContactSample:
    """A tactile cloud (sensor frame) with its true contact location -> canonical training sample.

    The block label is the dominant block of the cloud mapped into the object frame when the sensor pose on
    the object is known, else the block of the contact location.
    """
    points, normals = prepare_tactile_cloud(points_sensor, model.point_spacing_m)
    canonical = canonicalize_patch(points, normals)
    if T_object_sensor is not None:
        block = dominant_block(model, transform_points(T_object_sensor, points))
    else:
        block = int(model.block_of_points(p_object)[0])
    return ContactSample(
        points=canonical.points.astype(np.float32),
        normals=canonical.normals.astype(np.float32),
        p_object=np.asarray(p_object, dtype=np.float64),
        block=block,
        source=source,
    )


def pair_files_digest(paths: list[Path]) -> str:
    """Hash of pair files and the clouds they name: a run records which contacts it was fine-tuned on."""
    digest = hashlib.sha256()
    for path in sorted(paths):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
        for ply in sorted(path.parent.glob(path.stem + "_*.ply")):
            digest.update(ply.read_bytes())
    return digest.hexdigest()[:16]


def _looks_like_pair_file(path: Path) -> bool:
    """A JSON object with 'object', 'left' and 'right' (folders may hold other JSON, e.g. simulation settings)."""
    try:
        payload = read_json(path)
    except InputError:
        return False
    if isinstance(payload, dict) and payload.get("format") == LABELLED_CONTACT_FORMAT:  # `yoto rig label`'s contacts
        return True
    return isinstance(payload, dict) and all(key in payload for key in ("object", *SIDES))


def find_pair_files_recursive(inputs: list[str | Path]) -> list[Path]:
    """Pair files from files and folders, folders searched recursively (one subfolder per object, say).

    JSON files in the folders that are not contact pairs (simulation settings, pose results) are left out.
    """
    found: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found.extend(sorted(p for p in item.rglob("*.json") if is_pair_file_name(p) and _looks_like_pair_file(p)))
        else:
            found.extend(find_pair_files([item]))
    if not found:
        raise InputError(f"no contact pair files (*.json) in {', '.join(map(str, inputs))}")
    return found


@dataclass
class LabelledContact:
    """A tactile contact of a pair file with its ground truth, in the frames of the object model it trains."""

    points_sensor: np.ndarray  # (N, 3) tactile cloud, sensor frame
    p_object: np.ndarray  # (3,) true contact location, object frame
    T_object_sensor: np.ndarray  # (4, 4) true sensor pose on the object
    source: str  # "pair file:side", for messages


def load_labelled_contacts(
    pair_inputs: list[str | Path], models: dict[str, ObjectModel], pair_objects: dict[str, str] | None = None
) -> tuple[dict[str, list[LabelledContact]], list[Path]]:
    """The contacts of contact-pair files with ground truth, grouped by the name of the model they train.

    `pair_objects` maps a pair file's object name to the model it trains (e.g. "drill" -> "drill_scan": contacts
    recorded on the real drill train the model built from its scan, whose mesh frame is the drill's). Pairs of
    objects not in `models` are skipped with a note; contacts without ground truth are skipped with a warning.
    Returns the contacts and the pair files read.
    """
    pair_objects = pair_objects or {}
    contacts: dict[str, list[LabelledContact]] = {name: [] for name in models}
    files = find_pair_files_recursive(pair_inputs)
    skipped_objects: set[str] = set()
    for path in files:
        if is_labelled_contact_file(path):  # a single contact labelled by `yoto rig label` (docs/formats.md)
            labelled = read_labelled_contact(path)
            model = models.get(pair_objects.get(labelled.object_name, labelled.object_name))
            if model is None:
                skipped_objects.add(labelled.object_name)
                continue
            contacts[model.name].append(
                LabelledContact(
                    points_sensor=labelled.contact.points_sensor,
                    p_object=transform_points(model.T_object_mesh, labelled.p_mesh),
                    T_object_sensor=model.T_object_mesh
                    @ invert_transform(labelled.T_world_mesh)
                    @ labelled.contact.T_world_sensor,
                    source=path.name,
                )
            )
            continue
        pair = read_contact_pair(path)
        model = models.get(pair_objects.get(pair.object_name, pair.object_name))
        if model is None:
            skipped_objects.add(pair.object_name)
            continue
        if pair.T_world_mesh_true is None:
            raise InputError("a training contact needs ground_truth.T_world_object", path)
        T_object_world = model.T_object_mesh @ invert_transform(pair.T_world_mesh_true)
        for side in SIDES:
            if side not in pair.p_mesh_true:
                log.warning("%s: no ground_truth.%s_p_object; that contact is skipped", path, side)
                continue
            contact = pair.contact(side)
            contacts[model.name].append(
                LabelledContact(
                    points_sensor=contact.points_sensor,
                    p_object=transform_points(model.T_object_mesh, pair.p_mesh_true[side]),
                    T_object_sensor=T_object_world @ contact.T_world_sensor,
                    source=f"{path.name}:{side}",
                )
            )
    if skipped_objects:
        log.info("pair files of objects not being trained were skipped: %s", ", ".join(sorted(skipped_objects)))
    return contacts, files


def contact_samples(contacts: list[LabelledContact], model: ObjectModel) -> list[ContactSample]:
    """The point network's canonical samples of labelled contacts; those that cannot be canonicalized are skipped
    with a warning."""
    samples = []
    for contact in contacts:
        try:
            samples.append(
                contact_sample(contact.points_sensor, model, contact.p_object, contact.T_object_sensor, contact.source)
            )
        except DegenerateGeometryError as exc:
            log.warning("%s: skipped, %s", contact.source, exc)
    return samples


# ------------------------------------------------------------------------------------------------ objects
@dataclass
class ObjectData:
    """Everything training needs about one object."""

    model: ObjectModel
    blocks: BlockSet
    virtual: VirtualPatchDataset | None
    virtual_train: np.ndarray  # indices into `virtual`
    virtual_val: np.ndarray
    press: VirtualPatchDataset | None = None  # press-shaped virtual patches (yoto.training.press), if used
    press_train: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    press_val: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    real_train: list[ContactSample] = field(default_factory=list)
    real_val: list[ContactSample] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.model.name

    def dataset(self, kind: str) -> VirtualPatchDataset:
        dataset = self.virtual if kind == "virtual" else self.press
        assert dataset is not None, kind
        return dataset


def split_virtual(
    count: int, val_fraction: float, val_max: int, limit: int | None, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Shuffle the virtual patches once (by seed), keep `limit` of them, and split off a validation set."""
    order = np.random.default_rng([seed, 7919]).permutation(count)
    if limit is not None:
        order = order[:limit]
    val_count = min(val_max, int(round(val_fraction * len(order))))
    return np.sort(order[val_count:]), np.sort(order[:val_count])


def load_objects(
    names: list[str],
    models: list[ObjectModel],
    workspace: str | Path | None,
    config: TrainConfig,
    patch_config: VirtualPatchConfig,
    progress: bool,
) -> list[ObjectData]:
    """The training data of each object: its blocks, and its virtual patches (generated with `patch_config`
    and the press-shaped ones with `config.press` where missing) split into training and validation."""
    objects = []
    for name, model in zip(names, models, strict=True):
        dataset_path = generate_patches(name, patch_config, workspace, progress=progress)
        dataset = VirtualPatchDataset.load(dataset_path, model)
        train_idx, val_idx = split_virtual(
            len(dataset), config.val_fraction, config.val_max_per_object, config.max_virtual_per_object, config.seed
        )
        if not config.ball_patches:
            train_idx = train_idx[:0]
        obj = ObjectData(
            model=model,
            blocks=make_block_set(model, config.network),
            virtual=dataset,
            virtual_train=train_idx,
            virtual_val=val_idx,
        )
        if config.press.count > 0:
            obj.press = press_patches(model, config.press, workspace)
            obj.press_train, obj.press_val = split_virtual(
                len(obj.press), config.val_fraction, config.val_max_per_object, None, config.seed
            )
        objects.append(obj)
    seen = [o.name for o in objects]
    if len(set(seen)) != len(seen):
        raise InputError(f"an object is named twice among {seen}")
    return objects


# ------------------------------------------------------------------------------------------------ samples
@dataclass
class Patch:
    """One patch drawn for a batch: points, normals and labels."""

    points: np.ndarray  # (N, 3) float32
    normals: np.ndarray  # (N, 3) float32
    p_object: np.ndarray  # (3,)
    block: int
    real: bool


def _cropped_virtual_patch(
    data: ObjectData, index: int, rng: np.random.Generator, augment: AugmentConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """A sensor-like crop of virtual patch `index`, re-canonicalized and relabelled; None if none is drawn."""
    if augment.crop_prob <= 0 or rng.random() >= augment.crop_prob:
        return None
    dataset = data.virtual
    assert dataset is not None
    points, normals = dataset.patch(index)
    keep = depth_crop_mask(points, normals, rng, augment)
    if keep is None:
        return None
    try:
        canonical = canonicalize_patch(points[keep].astype(np.float64), normals[keep].astype(np.float64))
    except DegenerateGeometryError:
        return None
    # Relabel like the generator: the parent point nearest the crop's centroid, the crop's dominant block.
    model = data.model
    members = dataset.indices[dataset.offsets[index] : dataset.offsets[index + 1]][keep]
    rotation, translation = dataset.rotation_canonical_object[index], dataset.translation_canonical[index]
    centroid_object = rotation.T @ (points[keep].mean(axis=0) - translation)
    member_points = model.points_object[members]
    p_object = member_points[np.argmin(np.linalg.norm(member_points - centroid_object, axis=1))].astype(np.float64)
    member_blocks = model.point_block[members]
    member_blocks = member_blocks[member_blocks >= 0]
    block = int(np.bincount(member_blocks).argmax()) if len(member_blocks) else int(dataset.block[index])
    return canonical.points.astype(np.float32), canonical.normals.astype(np.float32), p_object, block


def _virtual_points(dataset: VirtualPatchDataset, index: int, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical points and normals of the `chosen` members of virtual patch `index` (only those are moved)."""
    members = dataset.indices[dataset.offsets[index] : dataset.offsets[index + 1]][chosen]
    rotation = dataset.rotation_canonical_object[index]
    points = dataset.model.points_object[members] @ rotation.T + dataset.translation_canonical[index]
    return points.astype(np.float32), (dataset.model.normals_object[members] @ rotation.T).astype(np.float32)


def draw_patch(
    data: ObjectData,
    kind: str,
    index: int,
    num_points: int,
    rng: np.random.Generator,
    augment: AugmentConfig | None,
) -> Patch:
    """Sample `num_points` points of a patch (repeat-padded), augmented when `augment` is given."""
    points: np.ndarray | None = None
    normals: np.ndarray | None = None
    if kind in ("virtual", "press"):
        dataset = data.dataset(kind)
        cropped = None if augment is None or kind == "press" else _cropped_virtual_patch(data, index, rng, augment)
        if cropped is None:
            p_object, block = dataset.p_object[index], int(dataset.block[index])
            count = int(dataset.offsets[index + 1] - dataset.offsets[index])
            if augment is not None and augment.voxel_size_m > 0:
                points, normals = dataset.patch(index)
        else:
            points, normals, p_object, block = cropped
    else:
        sample = (data.real_train if kind == "real" else data.real_val)[index]
        points, normals, p_object, block = sample.points, sample.normals, sample.p_object, sample.block
    if points is not None:
        count = len(points)
    pool = np.arange(count)
    if augment is not None and augment.voxel_size_m > 0 and points is not None:
        pool = voxel_keep_first(points, augment.voxel_size_m)
    chosen = pool[subsample_indices(len(pool), num_points, rng)]
    if augment is not None:
        chosen = point_dropout(chosen, rng, augment.dropout_prob, augment.dropout_ratio)
    if points is None or normals is None:  # both or neither
        points, normals = _virtual_points(dataset, index, chosen)
    else:
        points, normals = points[chosen], normals[chosen]
    if augment is not None:
        points, normals = random_in_plane_rotation(
            points, normals, rng, augment.rotation_prob, augment.rotation_max_rad
        )
        points = jitter(points, rng, augment.jitter_sigma_m, augment.jitter_clip_m)
        normals = perturb_normals(normals, rng, augment.normal_noise_rad)
    return Patch(
        points=np.ascontiguousarray(points, dtype=np.float32),
        normals=np.ascontiguousarray(normals, dtype=np.float32),
        p_object=np.asarray(p_object, dtype=np.float64),
        block=int(block),
        real=kind not in ("virtual", "press"),
    )
