"""Two-stage training of the localization network (paper Sec. 3.3, App. C.2): `train(config, objects, ...)`.

Stage 1 learns from the virtual patches of every object; stage 2 (when contact pairs with ground truth are
given) fine-tunes on virtual patches plus those "real" contacts, over-sampled and weighted up, at lower
learning rates. One network serves all the objects: each step draws one object's patches and scores them
against that object's blocks (the object is named at query time).

The run folder (hloc-style: importable, idempotent, resumable):
    state.pt     training state after the last finished epoch (weights, optimizer, schedule, history)
    model.pt     the trained localizer (yoto.training.checkpoint), written when training ends
    model_stage1.pt  the virtual-only localizer at the end of stage 1, when a stage 2 follows
    log.jsonl    one JSON record per epoch (losses, learning rates, validation metrics per object)
    log.csv      the same, flat, for spreadsheets and plotting
    curves.png   loss and validation curves
A finished run whose recorded settings match is kept as it is; an interrupted one resumes from its last
finished epoch and, for a seed on the CPU, ends bitwise identical to an uninterrupted run.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError, require_torch
from yoto.io import read_json, write_bytes_atomic, write_json_atomic, write_text_atomic
from yoto.metrics import summarize
from yoto.network.candidates import candidates_of, fit_temperature, rank_hypotheses, rotated_copies
from yoto.network.checkpoint import (
    Calibration,
    LocalizerCheckpoint,
    RealPairs,
    TrainedObject,
    load_torch,
    save_torch_atomic,
)
from yoto.network.inputs import inference_points, make_block_set
from yoto.network.presets import PRESETS as NETWORK_PRESETS
from yoto.network.presets import NetworkConfig
from yoto.objects.build import load_object_model
from yoto.objects.model import ObjectModel
from yoto.patches.generate import generate_patches
from yoto.patches.virtual import VirtualPatchConfig, VirtualPatchDataset
from yoto.provenance import versions
from yoto.training.augment import AugmentConfig
from yoto.training.data import ContactSample, ObjectData, Patch, draw_patch, load_contact_samples, pair_files_digest
from yoto.training.losses import LossConfig, localization_loss
from yoto.training.press import PressPatchConfig, press_patches
from yoto.workspace import runs_dir

log = logging.getLogger("yoto")

DEFAULT_RUN = "default"
STATE_FORMAT_NAME = "yoto-training-state"
CALIBRATION_TOLERANCE_M = 0.010  # a candidate counts as right within this distance (temperature fit)


# ------------------------------------------------------------------------------------------------ configs
@dataclass(frozen=True)
class StageConfig:
    """One training stage."""

    epochs: int  # passes over the stage's sample pool
    lr: float  # peak learning rate (OneCycle max_lr) of the heads and the temperature
    encoder_lr: float  # peak learning rate of the shared encoder
    real_oversample: int = 0  # each real contact appears this many times per epoch (paper stage 2: 10)
    real_weight: float = 1.0  # per-sample loss weight of real contacts (paper stage 2: 2.0)
    virtual_fraction: float = 1.0  # fraction of the virtual training patches drawn per epoch (fresh each epoch)


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides what `train` produces (recorded in the checkpoint)."""

    network: NetworkConfig = field(default_factory=NetworkConfig)  # architecture
    stage1: StageConfig = StageConfig(epochs=500, lr=2e-3, encoder_lr=1e-4)  # virtual pre-training
    stage2: StageConfig = StageConfig(  # fine-tuning on virtual + real contacts (runs only with real contacts)
        epochs=400, lr=4e-4, encoder_lr=1e-5, real_oversample=10, real_weight=2.0
    )
    batch_size: int = 32  # patches per step (all of one object)
    weight_decay: float = 0.01  # AdamW, on weight matrices (not on biases, norms or the temperature)
    pct_start: float = 0.1  # OneCycle warm-up fraction
    div_factor: float = 10.0  # OneCycle initial lr = max_lr / div_factor
    final_div_factor: float = 1000.0  # OneCycle final lr = initial lr / final_div_factor
    grad_clip_norm: float | None = None  # clip the gradient norm at this (None: no clipping)
    block_refresh_every: int = 1  # re-encode (with gradients) an object's blocks every n-th of its steps
    augment: AugmentConfig = AugmentConfig()  # per-step patch augmentations
    loss: LossConfig = LossConfig()  # loss weights
    precision: str = "auto"  # "auto": bf16 autocast on a GPU that supports it, else fp32; or "fp32", "bf16"
    seed: int = 0  # initialisation, data order and augmentation
    val_fraction: float = 0.05  # of each object's virtual patches, held out for validation
    val_max_per_object: int = 300  # at most this many virtual validation patches per object
    max_virtual_per_object: int | None = None  # use only this many virtual patches per object (None: all)
    press: PressPatchConfig = PressPatchConfig(count=0)  # press-shaped virtual patches per object (0: none)
    ball_patches: bool = True  # train on the paper's ball patches (False: press-shaped ones only)
    hypotheses: int = 4  # coarse hypotheses whose best candidates the localizer returns
    test_rotations: int = 1  # in-plane rotations averaged at validation and inference (1: none)
    merge_radius_m: float = 0.005  # candidates closer than this are merged into one

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        values = dict(values)
        augment = values.pop("augment", {})
        loss = values.pop("loss", {})
        press = values.pop("press", {"count": 0})
        return cls(
            network=NetworkConfig.from_dict(values.pop("network")),
            stage1=StageConfig(**values.pop("stage1")),
            stage2=StageConfig(**values.pop("stage2")),
            augment=AugmentConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in augment.items()}),
            loss=LossConfig(**loss),
            press=PressPatchConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in press.items()}),
            **values,
        )


PRESETS: dict[str, TrainConfig] = {
    # Every number from the paper (App. C.2): 500 + 400 epochs, batch 32, lr 2e-3 / 1e-4 (encoder), then
    # 4e-4 / 1e-5, real contacts over-sampled 10x and weighted 2.0, bf16 on a GPU.
    "paper": TrainConfig(network=NETWORK_PRESETS["paper"]),
    # A 2-core CPU: the `cpu` network; sizes and rates chosen by measurement (docs/network.md).
    "cpu": TrainConfig(
        network=NETWORK_PRESETS["cpu"],
        stage1=StageConfig(epochs=14, lr=2e-3, encoder_lr=1e-3),
        stage2=StageConfig(
            epochs=4, lr=4e-4, encoder_lr=2e-4, real_oversample=10, real_weight=2.0, virtual_fraction=0.25
        ),
        batch_size=128,
        # The 0.2 mm voxel grid removes ~8% of a virtual patch's points (near-duplicates of a 0.45 mm-spaced
        # cloud); with 128 of ~900 points sampled that changes nothing measurable but costs 0.3 ms a patch.
        augment=AugmentConfig(voxel_size_m=0.0, rotation_prob=1.0, rotation_max_rad=3.141592653589793),
        # Press-shaped virtual patches instead of balls: on held-out simulated contacts of the fruit they gave
        # the best block recall and error of the patch kinds measured (docs/network.md).
        press=PressPatchConfig(count=8700),
        ball_patches=False,
    ),
}


def preset(name: str) -> TrainConfig:
    if name not in PRESETS:
        raise InputError(f"unknown training preset {name!r} (presets: {', '.join(PRESETS)})")
    return PRESETS[name]


# ------------------------------------------------------------------------------------------------ batches
def plan_epoch(
    objects: list[ObjectData], stage: StageConfig, batch_size: int, rng: np.random.Generator, use_real: bool
) -> list[tuple[int, list[tuple[str, int]]]]:
    """The epoch's batches: (object index, [(kind, sample index), ...]), objects interleaved at random.

    The number of batches depends only on the pool sizes, not on the draw (the schedule needs it up front).
    """
    batches: list[tuple[int, list[tuple[str, int]]]] = []
    for obj_index, data in enumerate(objects):
        pool = []
        for kind, indices in (("virtual", data.virtual_train), ("press", data.press_train)):
            if stage.virtual_fraction < 1.0 and len(indices):
                count = max(1, int(round(stage.virtual_fraction * len(indices))))
                indices = rng.choice(indices, size=count, replace=False)
            pool += [(kind, int(i)) for i in indices]
        if use_real:
            pool += [("real", j) for j in range(len(data.real_train))] * stage.real_oversample
        if not pool:
            continue
        order = rng.permutation(len(pool))
        chunks = max(1, math.ceil(len(pool) / batch_size))
        for chunk in np.array_split(order, chunks):
            batches.append((obj_index, [pool[i] for i in chunk]))
    order = rng.permutation(len(batches))
    return [batches[i] for i in order]


def epoch_batch_count(objects: list[ObjectData], stage: StageConfig, batch_size: int, use_real: bool) -> int:
    total = 0
    for data in objects:
        count = 0
        for indices in (data.virtual_train, data.press_train):
            if stage.virtual_fraction < 1.0 and len(indices):
                count += max(1, int(round(stage.virtual_fraction * len(indices))))
            else:
                count += len(indices)
        if use_real:
            count += len(data.real_train) * stage.real_oversample
        total += max(1, math.ceil(count / batch_size)) if count else 0
    return total


def collate(patches: list[Patch], real_weight: float) -> dict[str, Any]:
    torch = require_torch("training")
    return {
        "patch_points": torch.from_numpy(np.stack([p.points for p in patches])),
        "patch_normals": torch.from_numpy(np.stack([p.normals for p in patches])),
        "p_object": torch.from_numpy(np.stack([p.p_object for p in patches]).astype(np.float32)),
        "block": torch.tensor([p.block for p in patches], dtype=torch.int64),
        "weight": torch.tensor([real_weight if p.real else 1.0 for p in patches], dtype=torch.float32),
    }


# ---------------------------------------------------------------------------------------------- evaluation
@dataclass
class EvalSet:
    """Fixed validation inputs of one object and one kind (virtual or real)."""

    points: np.ndarray  # (n, N, 3)
    normals: np.ndarray  # (n, N, 3)
    p_object: np.ndarray  # (n, 3)
    block: np.ndarray  # (n,)


def make_eval_set(
    data: ObjectData, kind: str, num_points: int, real: list[ContactSample] | None = None
) -> EvalSet | None:
    items: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
    if kind in ("virtual", "press"):
        dataset = data.virtual if kind == "virtual" else data.press
        for index in data.virtual_val if kind == "virtual" else data.press_val:
            points, normals = dataset.patch(int(index))
            items.append((points, normals, dataset.p_object[index], int(dataset.block[index])))
    else:
        items = [(s.points, s.normals, s.p_object, s.block) for s in (real or [])]
    if not items:
        return None
    sampled = [inference_points(points, normals, num_points) for points, normals, _, _ in items]
    return EvalSet(
        points=np.stack([s[0] for s in sampled]),
        normals=np.stack([s[1] for s in sampled]),
        p_object=np.stack([item[2] for item in items]).astype(np.float64),
        block=np.array([item[3] for item in items], dtype=np.int64),
    )


def evaluate_set(
    net: Any,
    eval_set: EvalSet,
    block_tensors: dict[str, Any],
    block_features: Any,
    config: TrainConfig,
    rotations: int | None = None,
) -> dict[str, Any]:
    """Metrics of one validation set, and the candidate scores for the temperature fit."""
    torch = require_torch("validation")
    rankings = []
    rotations = max(1, rotations if rotations is not None else config.test_rotations)
    chunk = max(1, 256 // rotations)
    with torch.no_grad():
        for start in range(0, len(eval_set.points), chunk):
            points, normals = eval_set.points[start : start + chunk], eval_set.normals[start : start + chunk]
            if rotations > 1:
                copies = [rotated_copies(p, n, rotations) for p, n in zip(points, normals, strict=True)]
                points = np.concatenate([c[0] for c in copies])
                normals = np.concatenate([c[1] for c in copies])
            features = net.encode(torch.from_numpy(points), torch.from_numpy(normals))
            features = features.reshape(-1, rotations, features.shape[-1])
            rankings.append(rank_hypotheses(net, features, block_features, block_tensors, config.hypotheses))
    ranking = {key: np.concatenate([r[key] for r in rankings]) for key in rankings[0]}
    k = min(config.network.candidates, ranking["logits"].shape[1])
    order = np.argsort(-ranking["logits"], axis=1)
    top1 = order[:, 0] == eval_set.block
    topk = (order[:, :k] == eval_set.block[:, None]).any(axis=1)
    answer_errors, best_errors, score_lists, correct_lists = [], [], [], []
    for i in range(len(eval_set.block)):
        candidates = candidates_of(ranking, i, 1.0, config.merge_radius_m)
        errors = np.array([np.linalg.norm(c.p_object - eval_set.p_object[i]) for c in candidates])
        answer_errors.append(errors[0])
        best_errors.append(errors.min())
        score_lists.append(np.array([c.score for c in candidates]))
        correct_lists.append(errors <= CALIBRATION_TOLERANCE_M)
    answer_mm = 1000.0 * np.array(answer_errors)
    return {
        "count": len(eval_set.block),
        "top1": float(top1.mean()),
        "topk": float(topk.mean()),
        "error_mm": summarize(answer_mm),
        "within_5mm": float((answer_mm <= 5.0).mean()),
        "best_of_candidates_error_mm": summarize(1000.0 * np.array(best_errors)),
        "_scores": score_lists,
        "_correct": correct_lists,
    }


def pooled(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Sample-weighted mean of per-object metrics (errors pooled by their means and medians' average)."""
    total = sum(r["count"] for r in results)
    out: dict[str, Any] = {"count": total}
    for key in ("top1", "topk", "within_5mm"):
        out[key] = sum(r[key] * r["count"] for r in results) / total
    out["error_mean_mm"] = sum(r["error_mm"]["mean"] * r["count"] for r in results) / total
    return out


# -------------------------------------------------------------------------------------------------- train
def _identity(
    config: TrainConfig,
    models: list[ObjectModel],
    patch_config: VirtualPatchConfig,
    real_digest: str | None,
    val_digest: str | None,
) -> dict[str, Any]:
    return json.loads(
        json.dumps(
            {
                "train_config": config.to_dict(),
                "objects": [{"name": m.name, "fingerprint": m.fingerprint} for m in models],
                "patch_config": asdict(patch_config),
                "real_pairs": real_digest,
                "val_pairs": val_digest,
            }
        )
    )


def _device_and_autocast(precision: str, device: str | None) -> tuple[Any, Any]:
    torch = require_torch("training")
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if precision not in ("auto", "fp32", "bf16"):
        raise InputError(f"precision must be auto, fp32 or bf16, not {precision!r}")
    use_bf16 = precision == "bf16" or (precision == "auto" and dev.type == "cuda" and torch.cuda.is_bf16_supported())
    return dev, (torch.bfloat16 if use_bf16 else None)


def _optimizer(net: Any, stage: StageConfig, config: TrainConfig, total_steps: int) -> tuple[Any, Any]:
    torch = require_torch("training")
    groups: dict[str, list] = {"encoder_decay": [], "encoder_plain": [], "head_decay": [], "head_plain": []}
    for name, parameter in net.named_parameters():
        part = "encoder" if name.startswith("encoder.") else "head"
        kind = "decay" if parameter.ndim >= 2 else "plain"
        groups[f"{part}_{kind}"].append(parameter)
    param_groups, max_lrs = [], []
    for key, params in groups.items():
        if not params:
            continue
        param_groups.append({"params": params, "weight_decay": config.weight_decay if "decay" in key else 0.0})
        max_lrs.append(stage.encoder_lr if key.startswith("encoder") else stage.lr)
    optimizer = torch.optim.AdamW(param_groups, lr=max_lrs[0], weight_decay=config.weight_decay)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimizer,
        max_lr=max_lrs,
        total_steps=max(1, total_steps),
        pct_start=config.pct_start,
        anneal_strategy="cos",
        div_factor=config.div_factor,
        final_div_factor=config.final_div_factor,
    )
    return optimizer, scheduler


def _write_logs(run_dir: Path, history: list[dict[str, Any]]) -> None:
    write_text_atomic(run_dir / "log.jsonl", "".join(json.dumps(record) + "\n" for record in history))
    flat_rows = []
    for record in history:
        flat_rows.append({k: v for k, v in record.items() if not isinstance(v, dict | list)})
    columns: list[str] = []
    for row in flat_rows:
        columns.extend(c for c in row if c not in columns)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns)
    writer.writeheader()
    writer.writerows(flat_rows)
    write_text_atomic(run_dir / "log.csv", buffer.getvalue())


def plot_curves(run_dir: Path, history: list[dict[str, Any]]) -> Path | None:
    """curves.png: training loss, block recall and localization error per epoch."""
    if not history:
        return None
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    x = np.arange(1, len(history) + 1)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    axes[0].plot(x, [r["train_loss"] for r in history], label="total")
    for part in ("train_cls", "train_pos", "train_select"):
        axes[0].plot(x, [r[part] for r in history], label=part.removeprefix("train_"), alpha=0.7)
    axes[0].set(title="training loss", xlabel="epoch", yscale="log")
    for kind in ("virtual", "press", "real"):
        if f"val_{kind}_top1" in history[-1]:
            axes[1].plot(x, [r.get(f"val_{kind}_top1", np.nan) for r in history], label=f"{kind} top-1")
            axes[1].plot(x, [r.get(f"val_{kind}_topk", np.nan) for r in history], "--", label=f"{kind} top-K")
            axes[2].plot(x, [r.get(f"val_{kind}_error_mean_mm", np.nan) for r in history], label=f"{kind}")
    axes[1].set(title="block recall (validation)", xlabel="epoch", ylim=(0, 1))
    axes[2].set(title="localization error, mean (mm)", xlabel="epoch", yscale="log")
    stage_changes = [i + 1 for i in range(1, len(history)) if history[i]["stage"] != history[i - 1]["stage"]]
    for ax in axes:
        for change in stage_changes:
            ax.axvline(change - 0.5, color="grey", lw=0.8, ls=":")
        ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return write_bytes_atomic(run_dir / "curves.png", buffer.getvalue())


def _load_objects(
    names: list[str],
    models: list[ObjectModel],
    workspace: str | Path | None,
    config: TrainConfig,
    patch_config: VirtualPatchConfig,
    progress: bool,
) -> list[ObjectData]:
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


def split_virtual(
    count: int, val_fraction: float, val_max: int, limit: int | None, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Shuffle the virtual patches once (by seed), keep `limit` of them, and split off a validation set."""
    order = np.random.default_rng([seed, 7919]).permutation(count)
    if limit is not None:
        order = order[:limit]
    val_count = min(val_max, int(round(val_fraction * len(order))))
    return np.sort(order[val_count:]), np.sort(order[:val_count])


class StepRunner:
    """One optimisation step on one object's batch: draw and augment patches, encode them and the object's
    blocks, take the loss and step. Holds each object's blocks as tensors (with their fixed kNN)."""

    def __init__(self, net: Any, data: list[ObjectData], config: TrainConfig, device: Any, autocast_dtype: Any):
        self.net, self.data, self.config = net, data, config
        self.device, self.autocast_dtype = device, autocast_dtype
        self.block_tensors = []
        for obj in data:
            tensors = {k: v.to(device) for k, v in obj.blocks.tensors().items()}
            tensors["block_knn"] = net.encoder.neighbours(tensors["block_points"])
            self.block_tensors.append(tensors)
        self.new_epoch()

    def new_epoch(self) -> None:
        self.block_cache: dict[int, Any] = {}
        self.object_steps = [0] * len(self.data)
        self.net.train()

    def step(
        self,
        obj_index: int,
        entries: list[tuple[str, int]],
        rng: np.random.Generator,
        real_weight: float,
        optimizer: Any,
        scheduler: Any,
    ) -> dict[str, float]:
        torch = require_torch("training")
        config = self.config
        obj = self.data[obj_index]
        patches = [
            draw_patch(obj, kind, index, config.network.points_per_patch, rng, config.augment)
            for kind, index in entries
        ]
        batch = {k: v.to(self.device) for k, v in collate(patches, real_weight).items()}
        blocks = self.block_tensors[obj_index]
        inputs = {
            "patch_points": batch["patch_points"],
            "patch_normals": batch["patch_normals"],
            **blocks,
            "force_block": batch["block"],
        }
        refresh = self.object_steps[obj_index] % config.block_refresh_every == 0
        self.object_steps[obj_index] += 1
        if not refresh:
            inputs["block_features"] = self.block_cache[obj_index]
        with torch.autocast(
            self.device.type, dtype=self.autocast_dtype or torch.float32, enabled=self.autocast_dtype is not None
        ):
            outputs = self.net(inputs)
            loss, parts = localization_loss(
                outputs, batch["block"], batch["p_object"], blocks["block_centres"], batch["weight"], config.loss
            )
        if refresh and config.block_refresh_every > 1:
            self.block_cache[obj_index] = outputs["block_features"].detach()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if config.grad_clip_norm is not None:
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), config.grad_clip_norm)
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        return parts


def train(
    config: TrainConfig,
    objects: list[str],
    workspace: str | Path | None = None,
    run_dir: str | Path | None = None,
    real_pairs_dir: str | Path | None = None,
    resume: bool = True,
    val_pairs_dir: str | Path | None = None,
    overwrite: bool = False,
    patch_config: VirtualPatchConfig = VirtualPatchConfig(),
    device: str | None = None,
    progress: bool = True,
    max_steps: int | None = None,
    pair_objects: dict[str, str] | None = None,
) -> Path:
    """Train (or keep, or resume) the localization network on `objects`; returns the checkpoint path.

    objects: object names in the workspace (built-in objects are built on first use) or model files; their
    virtual patches are generated with `patch_config` if missing. real_pairs_dir: contact pairs with ground
    truth for stage 2 (stage 2 runs only with them). val_pairs_dir: held-out pairs validated every epoch
    (never the fine-tuning ones). max_steps: stop after this many steps in all (tests, speed checks); the
    result is then not a finished run and no model.pt is written. pair_objects: pair-file object name ->
    trained object name, for training a model of a scan with contacts recorded on the real object.
    """
    torch = require_torch("training the localization network")
    if not objects:
        raise InputError("name at least one object to train on")
    run_dir = Path(run_dir) if run_dir is not None else runs_dir(workspace) / DEFAULT_RUN
    final_path, state_path = run_dir / "model.pt", run_dir / "state.pt"

    models = [load_object_model(name, workspace) for name in objects]
    by_name = {m.name: m for m in models}
    real_files = val_files = None
    real_samples: dict[str, list[ContactSample]] = {}
    val_samples: dict[str, list[ContactSample]] = {}
    if real_pairs_dir is not None:
        real_samples, real_files = load_contact_samples([real_pairs_dir], by_name, pair_objects)
    if val_pairs_dir is not None:
        val_samples, val_files = load_contact_samples([val_pairs_dir], by_name, pair_objects)
    if real_files and val_files:
        overlap = {pair_files_digest([p]) for p in real_files} & {pair_files_digest([p]) for p in val_files}
        if overlap:
            raise InputError(f"{len(overlap)} validation pair(s) are also fine-tuning pairs; keep them apart")
    real_digest = pair_files_digest(real_files) if real_files else None
    val_digest = pair_files_digest(val_files) if val_files else None
    identity = _identity(config, models, patch_config, real_digest, val_digest)

    if overwrite and run_dir.exists():
        for name in ("model.pt", "model_stage1.pt", "state.pt", "log.jsonl", "log.csv", "curves.png", "run.json"):
            (run_dir / name).unlink(missing_ok=True)
    if final_path.exists():
        recorded = read_json(run_dir / "run.json") if (run_dir / "run.json").exists() else None
        if recorded == identity:
            log.info("%s: up to date, kept (pass --overwrite to retrain)", final_path)
            return final_path
        raise InputError(
            "this run folder holds a model trained with other settings, objects or contacts; choose another run "
            "name or pass --overwrite",
            run_dir,
        )
    run_dir.mkdir(parents=True, exist_ok=True)

    device_, autocast_dtype = _device_and_autocast(config.precision, device)
    torch.manual_seed(config.seed)
    from yoto.network.model import ContactLocalizationNet, count_parameters

    net = ContactLocalizationNet(config.network).to(device_)
    data = _load_objects(objects, models, workspace, config, patch_config, progress)
    for obj in data:
        obj.real_train = real_samples.get(obj.name, [])
        obj.real_val = val_samples.get(obj.name, [])
    use_real = any(obj.real_train for obj in data)
    stages = [("stage1", config.stage1)] + ([("stage2", config.stage2)] if use_real else [])

    runner = StepRunner(net, data, config, device_, autocast_dtype)
    block_tensors = runner.block_tensors
    eval_sets = {
        (i, kind): s
        for i, obj in enumerate(data)
        for kind in ("virtual", "press", "real")
        if (s := make_eval_set(obj, kind, config.network.points_per_patch, obj.real_val)) is not None
    }

    history: list[dict[str, Any]] = []
    start_stage, start_epoch = 0, 0
    resume_state = None
    if resume and state_path.exists():
        state = load_torch(state_path, "training state")
        if state.get("format") == STATE_FORMAT_NAME and state.get("identity") == identity:
            resume_state = state
            net.load_state_dict(state["net"])
            history = list(state["history"])
            start_stage, start_epoch = state["stage_index"], state["epoch"]
            log.info(
                "%s: resuming at %s epoch %d", run_dir, stages[min(start_stage, len(stages) - 1)][0], start_epoch + 1
            )
        else:
            log.info("%s: its training state belongs to other settings; starting afresh", state_path)
    write_json_atomic(run_dir / "run.json", identity)
    log.info(
        "training %s on %s (%d parameters, %s, %s)",
        "stage 1" + (" + stage 2" if use_real else ""),
        ", ".join(
            f"{o.name} ({len(o.virtual_train)} ball, {len(o.press_train)} press, {len(o.real_train)} real)"
            for o in data
        ),
        count_parameters(net),
        device_,
        "bf16" if autocast_dtype else "fp32",
    )

    steps_done = 0
    stopped_early = False
    for stage_index, (stage_name, stage) in enumerate(stages):
        if stage_index < start_stage:
            continue
        steps_per_epoch = epoch_batch_count(data, stage, config.batch_size, stage_name == "stage2")
        optimizer, scheduler = _optimizer(net, stage, config, steps_per_epoch * stage.epochs)
        first_epoch = 0
        if resume_state is not None and stage_index == start_stage:
            first_epoch = start_epoch
            if 0 < start_epoch:
                optimizer.load_state_dict(resume_state["optimizer"])
                scheduler.load_state_dict(resume_state["scheduler"])
        for epoch in range(first_epoch, stage.epochs):
            rng = np.random.default_rng([config.seed, stage_index, epoch])
            torch.manual_seed(config.seed * 1_000_003 + stage_index * 10_007 + epoch)
            plan = plan_epoch(data, stage, config.batch_size, rng, stage_name == "stage2")
            runner.new_epoch()
            sums: dict[str, float] = {}
            tick = time.perf_counter()
            samples = 0
            bar = _progress(len(plan), f"{stage_name} epoch {epoch + 1}/{stage.epochs}", progress)
            for obj_index, entries in plan:
                parts = runner.step(obj_index, entries, rng, stage.real_weight, optimizer, scheduler)
                samples += len(entries)
                for key, value in parts.items():
                    sums[key] = sums.get(key, 0.0) + value * len(entries)
                bar.update(1)
                bar.set_postfix(loss=f"{parts['loss']:.3f}", refresh=False)
                steps_done += 1
                if max_steps is not None and steps_done >= max_steps:
                    stopped_early = True
                    break
            bar.close()
            elapsed = time.perf_counter() - tick
            if stopped_early:
                break
            record: dict[str, Any] = {
                "stage": stage_name,
                "epoch": epoch + 1,
                "step": scheduler.last_epoch,
                "lr": optimizer.param_groups[-1]["lr"],
                "encoder_lr": optimizer.param_groups[0]["lr"],
                "temperature": float(net.temperature.detach()),
                "samples_per_s": samples / elapsed,
                "epoch_time_s": elapsed,
                **{f"train_{k}": v / max(samples, 1) for k, v in sums.items()},
            }
            record.update(_validate(net, data, block_tensors, eval_sets, config))
            history.append(record)
            _log_epoch(record)
            save_torch_atomic(
                state_path,
                {
                    "format": STATE_FORMAT_NAME,
                    "identity": identity,
                    "stage_index": stage_index if epoch + 1 < stage.epochs else stage_index + 1,
                    "epoch": epoch + 1 if epoch + 1 < stage.epochs else 0,
                    "net": net.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict(),
                    "history": history,
                },
            )
            _write_logs(run_dir, history)
        if stopped_early:
            break
        resume_state = None
        if stage_name == "stage1" and len(stages) > 1 and not (run_dir / "model_stage1.pt").exists():
            # The virtual-only network, for comparisons with the fine-tuned one (the paper's "virtual only").
            _localizer_checkpoint(net, data, block_tensors, eval_sets, config, history, None).save(
                run_dir / "model_stage1.pt"
            )

    if stopped_early:
        log.info("stopped after %d steps (max_steps); no model written", steps_done)
        return state_path
    checkpoint = _localizer_checkpoint(net, data, block_tensors, eval_sets, config, history, real_digest)
    checkpoint.save(final_path)
    _write_logs(run_dir, history)
    plot_curves(run_dir, history)
    log.info("%s: written (score temperature %.2f)", final_path, checkpoint.calibration.temperature)
    return final_path


def _localizer_checkpoint(
    net: Any,
    data: list[ObjectData],
    block_tensors: list[dict],
    eval_sets: dict,
    config: TrainConfig,
    history: list[dict[str, Any]],
    real_digest: str | None,
) -> LocalizerCheckpoint:
    """The localizer checkpoint of the network as it is now, beliefs calibrated."""
    temperature = _calibrate(net, data, block_tensors, eval_sets, config)
    return LocalizerCheckpoint(
        network_config=config.network,
        state_dict={k: v.detach().float().cpu() for k, v in net.state_dict().items()},
        objects=[TrainedObject(o.name, o.model.fingerprint, o.model.num_blocks) for o in data],
        train_config=config.to_dict(),
        seed=config.seed,
        versions=versions(),
        real_pairs=RealPairs(real_digest, sum(len(o.real_train) for o in data)) if real_digest else None,
        metrics=dict(history[-1]) if history else {},
        calibration=Calibration(temperature, config.merge_radius_m, config.hypotheses, config.test_rotations),
    )


def _progress(total: int, description: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=description, unit="step", disable=not enabled, leave=False)


def _validate(
    net: Any, data: list[ObjectData], block_tensors: list[dict], eval_sets: dict, config: TrainConfig
) -> dict[str, Any]:
    torch = require_torch("validation")
    net.eval()
    record: dict[str, Any] = {}
    per_kind: dict[str, list[dict]] = {"virtual": [], "press": [], "real": []}
    with torch.no_grad():
        features = [net.encode(b["block_points"], b["block_normals"], b["block_knn"]) for b in block_tensors]
        for (obj_index, kind), eval_set in eval_sets.items():
            result = evaluate_set(net, eval_set, block_tensors[obj_index], features[obj_index], config)
            result = {k: v for k, v in result.items() if not k.startswith("_")}
            record[f"val_{kind}_{data[obj_index].name}"] = result
            per_kind[kind].append(result)
    for kind, results in per_kind.items():
        if results:
            for key, value in pooled(results).items():
                record[f"val_{kind}_{key}"] = value
    net.train()
    return record


def _calibrate(
    net: Any, data: list[ObjectData], block_tensors: list[dict], eval_sets: dict, config: TrainConfig
) -> float:
    """Fit the candidate-belief temperature on the real validation contacts, or the virtual ones if none."""
    torch = require_torch("calibration")
    kind = "real" if any(k == "real" for _, k in eval_sets) else "virtual"
    scores, correct = [], []
    net.eval()
    with torch.no_grad():
        for (obj_index, set_kind), eval_set in eval_sets.items():
            if set_kind != kind:
                continue
            b = block_tensors[obj_index]
            features = net.encode(b["block_points"], b["block_normals"], b["block_knn"])
            result = evaluate_set(net, eval_set, b, features, config)
            scores += result["_scores"]
            correct += result["_correct"]
    return fit_temperature(scores, correct)


def _log_epoch(record: dict[str, Any]) -> None:
    text = (
        f"{record['stage']} epoch {record['epoch']}: loss {record['train_loss']:.3f} "
        f"({record['samples_per_s']:.0f} samples/s, tau {record['temperature']:.1f})"
    )
    for kind in ("virtual", "press", "real"):
        if f"val_{kind}_top1" in record:
            text += (
                f" | val {kind}: top-1 {record[f'val_{kind}_top1']:.2f}, top-K {record[f'val_{kind}_topk']:.2f}, "
                f"error {record[f'val_{kind}_error_mean_mm']:.1f} mm, <=5mm {record[f'val_{kind}_within_5mm']:.2f}"
            )
    log.info(text)


def with_overrides(config: TrainConfig, **stage_epochs: int | None) -> TrainConfig:
    """A copy with stage epochs replaced where given (CLI --stage1-epochs / --stage2-epochs)."""
    for key in ("stage1", "stage2"):
        epochs = stage_epochs.get(f"{key}_epochs")
        if epochs is not None:
            config = replace(config, **{key: replace(getattr(config, key), epochs=int(epochs))})
    return config


def export_weights(run_dir: str | Path, destination: str | Path, command: str = "") -> tuple[Path, Path]:
    """Copy a finished run's model.pt to `destination` (e.g. yoto/weights/default.pt) and write a JSON card
    next to it: how the weights were trained (command, config, objects, contacts, versions) and their
    validation metrics. Returns the two paths."""
    source = Path(run_dir) / "model.pt"
    if not source.exists():
        raise InputError("no finished model in this run folder", run_dir)
    checkpoint = LocalizerCheckpoint.load(source).to_payload()
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source, destination)
    metrics = checkpoint["metrics"]
    card = {
        "weights": destination.name,
        "size_bytes": destination.stat().st_size,
        "command": command,
        **{key: checkpoint[key] for key in ("objects", "real_pairs", "seed", "versions", "network_config")},
        **{key: checkpoint[key] for key in ("train_config", "calibration")},
        "validation": {k: v for k, v in metrics.items() if k.startswith("val_")},
        "final_epoch": {k: v for k, v in metrics.items() if not k.startswith("val_")},
    }
    card_path = write_json_atomic(destination.with_suffix(".json"), card)
    return destination, card_path
