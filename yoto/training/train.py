"""Two-stage training of the localization network (paper Sec. 3.3, App. C.2): `train(config, objects, ...)`.

`train` owns the run folder for both networks; the anchor-descriptor network's (`cpu` preset) stages run in
yoto.training.descriptor_train, the point network's (`paper`, `cpu-points`) below.

Stage 1 learns from the virtual patches of every object; stage 2 (when contact pairs with ground truth are
given) fine-tunes on virtual patches plus those "real" contacts, over-sampled and weighted up, at lower
learning rates. One network serves all the objects: each step draws one object's patches and scores them
against that object's blocks (the object is named at query time).

The run folder (hloc-style: importable, idempotent, resumable):
    state.pt     training state after the last finished epoch (yoto.training.state)
    model.pt     the trained localizer (yoto.network.checkpoint), written when training ends
    model_stage1.pt  the virtual-only localizer at the end of stage 1, when a stage 2 follows
    log.jsonl    one JSON record per epoch (losses, learning rates, validation metrics per object)
    log.csv      the same, flat, for spreadsheets and plotting
    curves.png   loss and validation curves
    run.json     what the run was asked to do (settings, objects, contacts)
A finished run whose recorded settings match is kept as it is; an interrupted one resumes from its last
finished epoch and, for a seed on the CPU, ends bitwise identical to an uninterrupted run.

The parts: config.py (TrainConfig and presets), data.py (objects, patches, contacts, augmented draws),
batches.py (an epoch's batches), step.py (one optimisation step), validation.py (metrics and the belief
temperature), state.py (resume point), logs.py, export.py (checkpoints and exported weights).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from yoto.errors import InputError
from yoto.io import read_json, write_json_atomic
from yoto.network.checkpoint import LocalizerCheckpoint
from yoto.network.model import ContactLocalizationNet, count_parameters
from yoto.objects.build import load_object_model
from yoto.objects.model import ObjectModel
from yoto.patches.virtual import VirtualPatchConfig
from yoto.training.batches import epoch_batch_count, plan_epoch
from yoto.training.config import AnyTrainConfig, DescriptorTrainConfig, StageConfig, TrainConfig
from yoto.training.data import (
    LabelledContact,
    ObjectData,
    contact_samples,
    load_labelled_contacts,
    load_objects,
    pair_files_digest,
)
from yoto.training.descriptor_train import train_descriptor
from yoto.training.export import localizer_checkpoint
from yoto.training.logs import log_epoch, plot_curves, write_logs
from yoto.training.state import TrainingState, resume_stage
from yoto.training.step import StepRunner, device_and_autocast, make_optimizer
from yoto.training.validation import EvalSet, make_eval_sets, validate
from yoto.workspace import runs_dir

log = logging.getLogger("yoto")

DEFAULT_RUN = "default"
RUN_FILES = ("model.pt", "model_stage1.pt", "state.pt", "log.jsonl", "log.csv", "curves.png", "run.json")


def train(
    config: AnyTrainConfig,
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

    config: a point-network config (`paper`, `cpu-points`) or the anchor-descriptor network's (`cpu`).
    objects: object names in the workspace (built-in objects are built on first use) or model files; their
    virtual patches (or contacts: `config.virtual`) are generated with `patch_config` if missing. real_pairs_dir:
    contact pairs with ground truth for stage 2 (stage 2 runs only with them). val_pairs_dir: held-out pairs
    validated every epoch (never the fine-tuning ones). max_steps: stop after this many steps in all (tests, speed
    checks); the result is then not a finished run and no model.pt is written. pair_objects: pair-file object name
    -> trained object name, for training a model of a scan with contacts recorded on the real object.
    """
    if not objects:
        raise InputError("name at least one object to train on")
    run_dir = Path(run_dir) if run_dir is not None else runs_dir(workspace) / DEFAULT_RUN
    models = [load_object_model(name, workspace) for name in objects]
    contacts = _load_contacts({m.name: m for m in models}, real_pairs_dir, val_pairs_dir, pair_objects)
    identity = _identity(config, models, patch_config, contacts)
    if overwrite:
        for name in RUN_FILES:
            (run_dir / name).unlink(missing_ok=True)
    if _is_finished(run_dir, identity):
        log.info("%s: up to date, kept (pass --overwrite to retrain)", run_dir / "model.pt")
        return run_dir / "model.pt"
    run_dir.mkdir(parents=True, exist_ok=True)
    if isinstance(config, DescriptorTrainConfig):
        return train_descriptor(
            config,
            models,
            run_dir,
            identity,
            contacts.real,
            contacts.val,
            contacts.real_digest,
            workspace,
            resume,
            device,
            progress,
            max_steps,
        )

    run = _start_run(config, objects, models, contacts, workspace, patch_config, device, run_dir, identity, progress)
    resumed = _resume(run, run_dir / "state.pt") if resume else None
    write_json_atomic(run_dir / "run.json", identity)
    run.log_start()
    if not run.train_stages(resumed, max_steps):
        log.info("stopped after %d steps (max_steps); no model written", run.steps_done)
        return run_dir / "state.pt"
    return run.finish(contacts.real_digest)


# ------------------------------------------------------------------------------------------- run folder
@dataclass
class _Contacts:
    """Contacts with ground truth by object name: for stage 2 (`real`) and for validation (`val`)."""

    real: dict[str, list[LabelledContact]]
    val: dict[str, list[LabelledContact]]
    real_digest: str | None  # of the pair files (None: no stage 2)
    val_digest: str | None


def _load_contacts(
    models: dict[str, ObjectModel],
    real_pairs_dir: str | Path | None,
    val_pairs_dir: str | Path | None,
    pair_objects: dict[str, str] | None,
) -> _Contacts:
    real: dict[str, list[LabelledContact]] = {}
    val: dict[str, list[LabelledContact]] = {}
    real_files: list[Path] = []
    val_files: list[Path] = []
    if real_pairs_dir is not None:
        real, real_files = load_labelled_contacts([real_pairs_dir], models, pair_objects)
    if val_pairs_dir is not None:
        val, val_files = load_labelled_contacts([val_pairs_dir], models, pair_objects)
    if real_files and val_files:
        overlap = {pair_files_digest([p]) for p in real_files} & {pair_files_digest([p]) for p in val_files}
        if overlap:
            raise InputError(f"{len(overlap)} validation pair(s) are also fine-tuning pairs; keep them apart")
    return _Contacts(
        real=real,
        val=val,
        real_digest=pair_files_digest(real_files) if real_files else None,
        val_digest=pair_files_digest(val_files) if val_files else None,
    )


def _identity(
    config: AnyTrainConfig, models: list[ObjectModel], patch_config: VirtualPatchConfig, contacts: _Contacts
) -> dict[str, Any]:
    """What decides the run's result (run.json): a run folder holding another identity is not reused."""
    return json.loads(
        json.dumps(
            {
                "train_config": config.to_dict(),
                "objects": [{"name": m.name, "fingerprint": m.fingerprint} for m in models],
                "patch_config": asdict(patch_config) if isinstance(config, TrainConfig) else None,
                "real_pairs": contacts.real_digest,
                "val_pairs": contacts.val_digest,
            }
        )
    )


def _is_finished(run_dir: Path, identity: dict[str, Any]) -> bool:
    """Whether the run folder holds this run's finished model; InputError when it holds another run's."""
    if not (run_dir / "model.pt").exists():
        return False
    recorded = read_json(run_dir / "run.json") if (run_dir / "run.json").exists() else None
    if recorded == identity:
        return True
    raise InputError(
        "this run folder holds a model trained with other settings, objects or contacts; choose another run "
        "name or pass --overwrite",
        run_dir,
    )


def _resume(run: _Run, state_path: Path) -> TrainingState | None:
    """Load the run's last finished epoch into `run`, if `state_path` holds one of this run."""
    if not state_path.exists():
        return None
    state = TrainingState.load(state_path)
    if state is None or state.identity != run.identity:
        log.info("%s: its training state belongs to other settings; starting afresh", state_path)
        return None
    run.net.load_state_dict(state.net)
    run.history = list(state.history)
    stage_name = run.stages[min(state.stage_index, len(run.stages) - 1)][0]
    log.info("%s: resuming at %s epoch %d", run.run_dir, stage_name, state.epoch + 1)
    return state


# ------------------------------------------------------------------------------------------------ stages
@dataclass
class _EpochTotals:
    """An epoch's training steps, summed."""

    sums: dict[str, float] = field(default_factory=dict)  # each loss part, summed over the samples
    samples: int = 0
    elapsed_s: float = 0.0


@dataclass
class _Run:
    """A run in progress: its folder, the network, the data and the record so far."""

    config: TrainConfig
    run_dir: Path
    identity: dict[str, Any]
    net: ContactLocalizationNet
    data: list[ObjectData]
    stages: list[tuple[str, StageConfig]]  # ("stage1", ...) and, with real contacts, ("stage2", ...)
    runner: StepRunner
    eval_sets: dict[tuple[int, str], EvalSet]
    progress: bool  # progress bars
    history: list[dict[str, Any]] = field(default_factory=list)  # one record per finished epoch
    steps_done: int = 0  # in this call

    def log_start(self) -> None:
        log.info(
            "training %s on %s (%d parameters, %s, %s)",
            "stage 1" + (" + stage 2" if len(self.stages) > 1 else ""),
            ", ".join(
                f"{o.name} ({len(o.virtual_train)} ball, {len(o.press_train)} press, {len(o.real_train)} real)"
                for o in self.data
            ),
            count_parameters(self.net),
            self.runner.device,
            "bf16" if self.runner.autocast_dtype else "fp32",
        )

    def train_stages(self, resumed: TrainingState | None, max_steps: int | None) -> bool:
        """Train every stage from the resume point on; False when `max_steps` ran out first."""
        first_stage = resumed.stage_index if resumed is not None else 0
        for stage_index in range(first_stage, len(self.stages)):
            name, stage = self.stages[stage_index]
            steps_per_epoch = epoch_batch_count(self.data, stage, self.config.batch_size, name == "stage2")
            optimizer, scheduler = make_optimizer(self.net, stage, self.config, steps_per_epoch * stage.epochs)
            for epoch in range(resume_stage(resumed, stage_index, optimizer, scheduler), stage.epochs):
                totals = self.train_epoch(stage_index, epoch, optimizer, scheduler, max_steps)
                if totals is None:
                    return False
                self.end_epoch(stage_index, epoch, totals, optimizer, scheduler)
            if name == "stage1" and len(self.stages) > 1 and not (self.run_dir / "model_stage1.pt").exists():
                # The virtual-only network, for comparisons with the fine-tuned one (the paper's "virtual only").
                self.checkpoint(None).save(self.run_dir / "model_stage1.pt")
        return True

    def train_epoch(
        self,
        stage_index: int,
        epoch: int,
        optimizer: torch.optim.Optimizer,
        scheduler: torch.optim.lr_scheduler.LRScheduler,
        max_steps: int | None,
    ) -> _EpochTotals | None:
        """One pass over the stage's sample pool (seeded by stage and epoch); None when `max_steps` ran out."""
        name, stage = self.stages[stage_index]
        seed = self.config.seed
        rng = np.random.default_rng([seed, stage_index, epoch])
        torch.manual_seed(seed * 1_000_003 + stage_index * 10_007 + epoch)
        plan = plan_epoch(self.data, stage, self.config.batch_size, rng, name == "stage2")
        self.runner.new_epoch()
        totals = _EpochTotals()
        tick = time.perf_counter()
        bar = _progress(len(plan), f"{name} epoch {epoch + 1}/{stage.epochs}", self.progress)
        for obj_index, entries in plan:
            parts = self.runner.step(obj_index, entries, rng, stage.real_weight, optimizer, scheduler)
            totals.samples += len(entries)
            for key, value in parts.items():
                totals.sums[key] = totals.sums.get(key, 0.0) + value * len(entries)
            bar.update(1)
            bar.set_postfix(loss=f"{parts['loss']:.3f}", refresh=False)
            self.steps_done += 1
            if max_steps is not None and self.steps_done >= max_steps:
                bar.close()
                return None
        bar.close()
        totals.elapsed_s = time.perf_counter() - tick
        return totals

    def end_epoch(
        self,
        stage_index: int,
        epoch: int,
        totals: _EpochTotals,
        optimizer: torch.optim.Optimizer,
        scheduler: torch.optim.lr_scheduler.LRScheduler,
    ) -> None:
        """Validate, log, and save the resume point."""
        name, stage = self.stages[stage_index]
        record: dict[str, Any] = {
            "stage": name,
            "epoch": epoch + 1,
            "step": scheduler.last_epoch,
            "lr": optimizer.param_groups[-1]["lr"],
            "encoder_lr": optimizer.param_groups[0]["lr"],
            "temperature": float(self.net.temperature.detach()),
            "samples_per_s": totals.samples / totals.elapsed_s,
            "epoch_time_s": totals.elapsed_s,
            **{f"train_{k}": v / max(totals.samples, 1) for k, v in totals.sums.items()},
        }
        record.update(validate(self.net, self.data, self.runner.block_tensors, self.eval_sets, self.config))
        self.history.append(record)
        log_epoch(record)
        TrainingState.after_epoch(
            self.identity, stage_index, epoch, stage.epochs, self.net, optimizer, scheduler, self.history
        ).save(self.run_dir / "state.pt")
        write_logs(self.run_dir, self.history)

    def checkpoint(self, real_digest: str | None) -> LocalizerCheckpoint:
        return localizer_checkpoint(
            self.net, self.data, self.runner.block_tensors, self.eval_sets, self.config, self.history, real_digest
        )

    def finish(self, real_digest: str | None) -> Path:
        """Write the trained localizer (model.pt), the logs and the curves; returns model.pt."""
        path = self.run_dir / "model.pt"
        checkpoint = self.checkpoint(real_digest)
        checkpoint.save(path)
        write_logs(self.run_dir, self.history)
        plot_curves(self.run_dir, self.history)
        log.info("%s: written (score temperature %.2f)", path, checkpoint.calibration.temperature)
        return path


def _start_run(
    config: TrainConfig,
    objects: list[str],
    models: list[ObjectModel],
    contacts: _Contacts,
    workspace: str | Path | None,
    patch_config: VirtualPatchConfig,
    device: str | None,
    run_dir: Path,
    identity: dict[str, Any],
    progress: bool,
) -> _Run:
    """The seeded network and everything the steps and validation use."""
    device_, autocast_dtype = device_and_autocast(config.precision, device)
    torch.manual_seed(config.seed)
    net = ContactLocalizationNet(config.network).to(device_)
    data = load_objects(objects, models, workspace, config, patch_config, progress)
    for obj in data:
        obj.real_train = contact_samples(contacts.real.get(obj.name, []), obj.model)
        obj.real_val = contact_samples(contacts.val.get(obj.name, []), obj.model)
    use_real = any(obj.real_train for obj in data)
    return _Run(
        config=config,
        run_dir=run_dir,
        identity=identity,
        net=net,
        data=data,
        stages=[("stage1", config.stage1)] + ([("stage2", config.stage2)] if use_real else []),
        runner=StepRunner(net, data, config, device_, autocast_dtype),
        eval_sets=make_eval_sets(data, config.network.points_per_patch),
        progress=progress,
    )


def _progress(total: int, description: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc=description, unit="step", disable=not enabled, leave=False)
