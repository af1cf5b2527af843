"""Training of the anchor-descriptor network (`cpu` preset, yoto.network.descriptor), the paper's protocol.

Stage 1 on virtual contacts of every object (yoto.training.virtual_contacts); stage 2, when contact pairs with
ground truth are given, on virtual contacts plus those "real" ones, over-sampled and weighted up, at lower learning
rates. One network serves every object: each step draws one object's contacts and scores them against all of that
object's anchors.

The loss is a contrastive one over anchors: for a contact, every anchor within `positive_radius_m` of its true
location is a right answer, the other anchors of a candidate set S wrong ones,

    loss = -log( sum_{a right} exp(tau cos(q, b_a)) / sum_{a in S} exp(tau cos(q, b_a)) ).

Describing all of an object's anchors with gradients at every step would cost thousands of encoder passes, so S is
the batch's right anchors, the `hard_negatives` wrong anchors each contact scores highest, and `random_negatives`
anchors drawn at random, all described afresh with gradients. The hardest wrong anchors are found in a bank of all
anchors' descriptors, refreshed every `bank_refresh_every` steps of the object. (Scoring against the whole stale
bank instead, with gradients only through the right anchors, let the tiny test network collapse: every
descriptor alike.)

The run folder is the point network's (yoto.training.train): state.pt after every epoch (an interrupted run
resumes), model.pt when done (and model_stage1.pt, the virtual-only network, when a stage 2 follows), log.jsonl,
log.csv, curves.png, run.json.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from yoto.errors import DegenerateGeometryError, InputError
from yoto.io import write_json_atomic
from yoto.network.anchors import AnchorSet, make_anchor_set
from yoto.network.checkpoint import LocalizerCheckpoint, RealPairs, TrainedObject
from yoto.network.descriptor import DescriptorNet, invariant_feature_count, invariant_features
from yoto.network.polar import PolarGrid, contact_polar_map
from yoto.objects.model import ObjectModel
from yoto.provenance import versions
from yoto.training.config import DescriptorTrainConfig, StageConfig
from yoto.training.data import LabelledContact, split_virtual
from yoto.training.logs import log_descriptor_epoch, plot_descriptor_curves, write_logs
from yoto.training.state import TrainingState, resume_stage
from yoto.training.step import device_and_autocast, make_optimizer
from yoto.training.virtual_contacts import virtual_contacts

log = logging.getLogger("yoto")

RECALL_AT = (1, 8, 32, 128)  # validation: share of contacts with a right anchor among the best k
RECALL_TOLERANCE_M = 0.003  # an anchor this close to the truth counts as found


@dataclass
class ContactSet:
    """Contacts of one object as network inputs: polar maps and true locations."""

    maps: np.ndarray  # (n, 2, R, T) float32
    p_object: np.ndarray  # (n, 3)

    def __len__(self) -> int:
        return len(self.p_object)

    def subset(self, index: np.ndarray) -> ContactSet:
        return ContactSet(self.maps[index], self.p_object[index])

    def features(self, device: torch.device, config: DescriptorTrainConfig) -> torch.Tensor:
        """(n, F) the network's fixed roll-invariant features of the maps, on `device` (computed once)."""
        maps = torch.from_numpy(self.maps).to(device)
        harmonics = config.network.harmonics
        rows = [invariant_features(maps[i : i + 8192], harmonics) for i in range(0, len(maps), 8192)]
        return torch.cat(rows) if rows else torch.zeros((0, invariant_feature_count(config.network)), device=device)


def contact_set(contacts: list[LabelledContact], grid: PolarGrid, config: DescriptorTrainConfig) -> ContactSet:
    """Real contacts as network inputs, as the localizer reads them; clouds that cannot be read are skipped."""
    network = config.network
    maps, locations = [], []
    for contact in contacts:
        try:
            polar = contact_polar_map(contact.points_sensor, grid, network.contact_pixel_m, network.contact_erode_px)
        except DegenerateGeometryError as exc:
            log.warning("%s: skipped, %s", contact.source, exc)
            continue
        maps.append(polar.network_input(network.height_unit_m))
        locations.append(contact.p_object)
    rings, angles = grid.rings, grid.angles
    return ContactSet(
        np.asarray(maps, dtype=np.float32).reshape(-1, 2, rings, angles), np.asarray(locations).reshape(-1, 3)
    )


@dataclass
class ObjectSet:
    """Everything training needs about one object."""

    model: ObjectModel
    anchors: AnchorSet
    anchor_features: torch.Tensor  # (A, F) the anchors' invariant features, on the training device
    tree: cKDTree  # over the anchors
    virtual_train: ContactSet
    virtual_val: ContactSet
    real_train: ContactSet
    real_val: ContactSet
    positive_radius_m: float
    features: dict[str, torch.Tensor] = field(default_factory=dict)  # kind -> (n, F) of the training pools

    @property
    def name(self) -> str:
        return self.model.name

    def positives(self, p_object: np.ndarray) -> list[np.ndarray]:
        """Per location (n, 3), the anchors within the positive radius (at least the nearest one)."""
        found = self.tree.query_ball_point(p_object, self.positive_radius_m)
        _, nearest = self.tree.query(p_object)
        return [np.asarray(f if len(f) else [n], dtype=np.int64) for f, n in zip(found, nearest, strict=True)]

    def pool(self, kind: str) -> ContactSet:
        return {"virtual": self.virtual_train, "real": self.real_train}[kind]


def load_object_sets(
    models: list[ObjectModel],
    real: dict[str, list[LabelledContact]],
    val: dict[str, list[LabelledContact]],
    config: DescriptorTrainConfig,
    workspace: str | Path | None,
    device: torch.device,
    progress: bool,
) -> list[ObjectSet]:
    grid = PolarGrid.of(config.network)
    sets = []
    for model in models:
        anchors = make_anchor_set(model, config.network)
        contacts = virtual_contacts(model, config.network, config.virtual, workspace, progress)
        train_index, val_index = split_virtual(
            len(contacts), config.val_fraction, config.val_max_per_object, None, config.seed
        )
        virtual = ContactSet(contacts.maps, contacts.p_object)
        anchor_maps = ContactSet(anchors.network_inputs(config.network), anchors.points_object)
        obj = ObjectSet(
            model=model,
            anchors=anchors,
            anchor_features=anchor_maps.features(device, config),
            tree=cKDTree(anchors.points_object),
            virtual_train=virtual.subset(train_index),
            virtual_val=virtual.subset(val_index),
            real_train=contact_set(real.get(model.name, []), grid, config),
            real_val=contact_set(val.get(model.name, []), grid, config),
            positive_radius_m=config.positive_radius_m,
        )
        obj.features = {kind: obj.pool(kind).features(device, config) for kind in ("virtual", "real")}
        sets.append(obj)
    return sets


# ------------------------------------------------------------------------------------------------ steps
def plan_epoch(
    objects: list[ObjectSet], stage: StageConfig, batch_size: int, rng: np.random.Generator, use_real: bool
) -> list[tuple[int, list[tuple[str, int]]]]:
    """The epoch's batches: (object index, [(kind, index), ...]), objects interleaved at random."""
    batches = []
    for obj_index, obj in enumerate(objects):
        count = len(obj.virtual_train)
        if stage.virtual_fraction < 1.0:
            chosen = rng.choice(count, size=max(1, int(round(stage.virtual_fraction * count))), replace=False)
        else:
            chosen = np.arange(count)
        pool = [("virtual", int(i)) for i in chosen]
        if use_real:
            pool += [("real", j) for j in range(len(obj.real_train))] * stage.real_oversample
        order = rng.permutation(len(pool))
        for chunk in np.array_split(order, max(1, int(np.ceil(len(pool) / batch_size)))):
            batches.append((obj_index, [pool[i] for i in chunk]))
    return [batches[i] for i in rng.permutation(len(batches))]


def epoch_batch_count(objects: list[ObjectSet], stage: StageConfig, batch_size: int, use_real: bool) -> int:
    total = 0
    for obj in objects:
        count = len(obj.virtual_train)
        if stage.virtual_fraction < 1.0:
            count = max(1, int(round(stage.virtual_fraction * count)))
        if use_real:
            count += len(obj.real_train) * stage.real_oversample
        total += max(1, int(np.ceil(count / batch_size)))
    return total


class DescriptorStep:
    """One optimisation step on one object's batch, and each object's bank of anchor descriptors (for mining)."""

    def __init__(
        self, net: DescriptorNet, objects: list[ObjectSet], config: DescriptorTrainConfig, device: torch.device
    ):
        self.net, self.objects, self.config, self.device = net, objects, config, device
        self.autocast_dtype: torch.dtype | None = None
        self.banks: dict[int, torch.Tensor] = {}
        self.steps_of: dict[int, int] = {}

    def bank(self, obj_index: int) -> torch.Tensor:
        """The object's anchor descriptors, re-described every `bank_refresh_every` of its steps."""
        steps = self.steps_of.get(obj_index, 0)
        if obj_index not in self.banks or steps % self.config.bank_refresh_every == 0:
            self.net.eval()
            self.banks[obj_index] = self.net.describe_many(self.objects[obj_index].anchor_features)
            self.net.train()
        self.steps_of[obj_index] = steps + 1
        return self.banks[obj_index]

    def new_epoch(self) -> None:
        self.banks.clear()
        self.steps_of.clear()

    def candidates(
        self, obj_index: int, features: torch.Tensor, positives: list[np.ndarray], rng: np.random.Generator
    ) -> np.ndarray:
        """The anchors a batch is scored against: its right anchors, each contact's hardest wrong ones by the bank,
        and random ones (sorted, unique)."""
        config = self.config
        bank = self.bank(obj_index)
        right = np.concatenate(positives)
        parts = [right, rng.integers(0, len(bank), size=config.random_negatives)]
        if config.hard_negatives > 0:
            with torch.no_grad():
                self.net.eval()
                scores = self.net.describe(features) @ bank.T
                self.net.train()
            count = min(config.hard_negatives + max(len(p) for p in positives), len(bank))
            parts.append(scores.topk(count, dim=1).indices.cpu().numpy().ravel())
        return np.unique(np.concatenate(parts))

    def __call__(
        self,
        obj_index: int,
        entries: list[tuple[str, int]],
        real_weight: float,
        rng: np.random.Generator,
        optimizer: torch.optim.Optimizer,
        scheduler: torch.optim.lr_scheduler.LRScheduler,
    ) -> dict[str, float]:
        obj = self.objects[obj_index]
        features = torch.stack([obj.features[kind][i] for kind, i in entries])
        locations = np.stack([obj.pool(kind).p_object[i] for kind, i in entries])
        weights = torch.tensor([real_weight if kind == "real" else 1.0 for kind, _ in entries], device=self.device)
        positives = obj.positives(locations)
        candidates = self.candidates(obj_index, features, positives, rng)
        column = np.full(len(obj.anchors), -1, dtype=np.int64)
        column[candidates] = np.arange(len(candidates))
        rows = np.repeat(np.arange(len(entries)), [len(p) for p in positives])
        mask = torch.zeros((len(entries), len(candidates)), dtype=torch.bool, device=self.device)
        mask[
            torch.from_numpy(rows).to(self.device), torch.from_numpy(column[np.concatenate(positives)]).to(self.device)
        ] = True
        with torch.autocast(
            self.device.type, dtype=self.autocast_dtype or torch.float32, enabled=self.autocast_dtype is not None
        ):
            descriptors = self.net.describe(features)
            anchors = self.net.describe(obj.anchor_features[torch.from_numpy(candidates).to(self.device)])
            logits = self.net.logits(descriptors, anchors).float()
            per_contact = torch.logsumexp(logits, 1) - torch.logsumexp(logits.masked_fill(~mask, float("-inf")), 1)
            loss = (weights * per_contact).sum() / weights.sum()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        return {"loss": float(loss.detach())}


# ------------------------------------------------------------------------------------------------ validation
def retrieval_metrics(
    net: DescriptorNet, obj: ObjectSet, contacts: ContactSet, anchor_descriptors: torch.Tensor
) -> dict[str, float]:
    """Recall@k (a right anchor among the best k) and the error of the best anchor, for one set of contacts."""
    device = anchor_descriptors.device
    descriptors = net.encode_many(torch.from_numpy(contacts.maps).to(device))
    scores = (descriptors @ anchor_descriptors.T).float().cpu().numpy()
    k = min(max(RECALL_AT), scores.shape[1])
    top = np.argpartition(-scores, k - 1, axis=1)[:, :k]
    top = np.take_along_axis(top, np.argsort(-np.take_along_axis(scores, top, axis=1), axis=1), axis=1)
    distances = np.linalg.norm(obj.anchors.points_object[top] - contacts.p_object[:, None], axis=2)
    metrics = {"count": float(len(contacts))}
    for at in RECALL_AT:
        metrics[f"recall_at_{at}"] = float((distances[:, :at].min(axis=1) <= RECALL_TOLERANCE_M).mean())
    metrics["top1_error_mean_mm"] = 1000.0 * float(distances[:, 0].mean())
    metrics["top1_error_median_mm"] = 1000.0 * float(np.median(distances[:, 0]))
    return metrics


def validate(net: DescriptorNet, objects: list[ObjectSet]) -> dict[str, Any]:
    """The epoch's validation record: val_{kind}_{object} metrics, and val_{kind}_{metric} pooled over objects."""
    net.eval()
    record: dict[str, Any] = {}
    for kind in ("virtual", "real"):
        pooled: dict[str, float] = {}
        total = 0.0
        for obj in objects:
            contacts = obj.virtual_val if kind == "virtual" else obj.real_val
            if not len(contacts):
                continue
            metrics = retrieval_metrics(net, obj, contacts, net.describe_many(obj.anchor_features))
            record[f"val_{kind}_{obj.name}"] = metrics
            for key, value in metrics.items():
                if key != "count":
                    pooled[key] = pooled.get(key, 0.0) + value * metrics["count"]
            total += metrics["count"]
        if total:
            record.update({f"val_{kind}_{key}": value / total for key, value in pooled.items()})
            record[f"val_{kind}_count"] = total
    net.train()
    return record


# ------------------------------------------------------------------------------------------------ the run
@dataclass
class DescriptorRun:
    """A run of the descriptor network in progress."""

    config: DescriptorTrainConfig
    run_dir: Path
    identity: dict[str, Any]
    net: DescriptorNet
    objects: list[ObjectSet]
    stages: list[tuple[str, StageConfig]]
    step: DescriptorStep
    progress: bool
    history: list[dict[str, Any]] = field(default_factory=list)
    steps_done: int = 0

    def train_stages(self, resumed: TrainingState | None, max_steps: int | None) -> bool:
        """Every stage from the resume point on; False when `max_steps` ran out first."""
        first_stage = resumed.stage_index if resumed is not None else 0
        for stage_index in range(first_stage, len(self.stages)):
            name, stage = self.stages[stage_index]
            use_real = name == "stage2"
            steps_per_epoch = epoch_batch_count(self.objects, stage, self.config.batch_size, use_real)
            optimizer, scheduler = make_optimizer(self.net, stage, self.config, steps_per_epoch * stage.epochs)
            for epoch in range(resume_stage(resumed, stage_index, optimizer, scheduler), stage.epochs):
                rng = np.random.default_rng([self.config.seed, stage_index, epoch])
                torch.manual_seed(self.config.seed * 1_000_003 + stage_index * 10_007 + epoch)
                plan = plan_epoch(self.objects, stage, self.config.batch_size, rng, use_real)
                self.step.new_epoch()
                tick, samples, loss_sum = time.perf_counter(), 0, 0.0
                bar = _progress(len(plan), f"{name} epoch {epoch + 1}/{stage.epochs}", self.progress)
                for obj_index, entries in plan:
                    parts = self.step(obj_index, entries, stage.real_weight, rng, optimizer, scheduler)
                    samples += len(entries)
                    loss_sum += parts["loss"] * len(entries)
                    bar.update(1)
                    bar.set_postfix(loss=f"{parts['loss']:.3f}", refresh=False)
                    self.steps_done += 1
                    if max_steps is not None and self.steps_done >= max_steps:
                        bar.close()
                        return False
                bar.close()
                elapsed = time.perf_counter() - tick
                record: dict[str, Any] = {
                    "stage": name,
                    "epoch": epoch + 1,
                    "step": scheduler.last_epoch,
                    "lr": optimizer.param_groups[0]["lr"],
                    "temperature": float(self.net.temperature.detach()),
                    "samples_per_s": samples / elapsed,
                    "epoch_time_s": elapsed,
                    "train_loss": loss_sum / max(samples, 1),
                    **validate(self.net, self.objects),
                }
                self.history.append(record)
                log_descriptor_epoch(record)
                TrainingState.after_epoch(
                    self.identity, stage_index, epoch, stage.epochs, self.net, optimizer, scheduler, self.history
                ).save(self.run_dir / "state.pt")
                write_logs(self.run_dir, self.history)
            if name == "stage1" and len(self.stages) > 1 and not (self.run_dir / "model_stage1.pt").exists():
                self.checkpoint(None).save(self.run_dir / "model_stage1.pt")
        return True

    def checkpoint(self, real_digest: str | None) -> LocalizerCheckpoint:
        return LocalizerCheckpoint(
            network_config=self.config.network,
            state_dict={k: v.detach().float().cpu() for k, v in self.net.state_dict().items()},
            objects=[TrainedObject(o.name, o.model.fingerprint, len(o.anchors)) for o in self.objects],
            train_config=self.config.to_dict(),
            seed=self.config.seed,
            versions=versions(),
            real_pairs=RealPairs(real_digest, sum(len(o.real_train) for o in self.objects)) if real_digest else None,
            metrics=dict(self.history[-1]) if self.history else {},
        )

    def finish(self, real_digest: str | None) -> Path:
        path = self.run_dir / "model.pt"
        self.checkpoint(real_digest).save(path)
        write_logs(self.run_dir, self.history)
        plot_descriptor_curves(self.run_dir, self.history)
        log.info("%s: written", path)
        return path


def train_descriptor(
    config: DescriptorTrainConfig,
    models: list[ObjectModel],
    run_dir: Path,
    identity: dict[str, Any],
    real: dict[str, list[LabelledContact]],
    val: dict[str, list[LabelledContact]],
    real_digest: str | None,
    workspace: str | Path | None,
    resume: bool,
    device: str | None,
    progress: bool,
    max_steps: int | None,
) -> Path:
    """Train the descriptor network in `run_dir` (called by yoto.training.train.train, which owns the folder)."""
    device_, autocast_dtype = device_and_autocast(config.precision, device)
    torch.manual_seed(config.seed)
    net = DescriptorNet(config.network).to(device_)
    objects = load_object_sets(models, real, val, config, workspace, device_, progress)
    use_real = any(len(o.real_train) for o in objects)
    step = DescriptorStep(net, objects, config, device_)
    step.autocast_dtype = autocast_dtype
    run = DescriptorRun(
        config=config,
        run_dir=run_dir,
        identity=identity,
        net=net,
        objects=objects,
        stages=[("stage1", config.stage1)] + ([("stage2", config.stage2)] if use_real else []),
        step=step,
        progress=progress,
    )
    resumed = None
    state_path = run_dir / "state.pt"
    if resume and state_path.exists():
        state = TrainingState.load(state_path)
        if state is not None and state.identity == identity:
            net.load_state_dict(state.net)
            run.history = list(state.history)
            resumed = state
            log.info("%s: resuming at stage %d epoch %d", run_dir, state.stage_index + 1, state.epoch + 1)
    write_json_atomic(run_dir / "run.json", identity)
    log.info(
        "training the anchor-descriptor network on %s (%s, %s)",
        ", ".join(
            f"{o.name} ({len(o.anchors)} anchors, {len(o.virtual_train)} virtual, {len(o.real_train)} real contacts)"
            for o in objects
        ),
        device_,
        "bf16" if autocast_dtype else "fp32",
    )
    if not objects:
        raise InputError("no objects to train on")
    if not run.train_stages(resumed, max_steps):
        log.info("stopped after %d steps (max_steps); no model written", run.steps_done)
        return state_path
    return run.finish(real_digest)


def _progress(total: int, description: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=description, unit="step", disable=not enabled, leave=False)
