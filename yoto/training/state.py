"""The resumable training state (RUN/state.pt): where an interrupted run goes on.

A torch archive of plain containers like the localizer checkpoint (yoto.network.checkpoint), written
atomically after every finished epoch and loaded with `weights_only=True`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch

from yoto.errors import InputError
from yoto.network.checkpoint import load_torch, save_torch_atomic

FORMAT_NAME = "yoto-training-state"


@dataclass
class TrainingState:
    """A run after its last finished epoch."""

    identity: dict[str, Any]  # the settings, objects and contacts of the run; another run's state is not resumed
    stage_index: int  # the stage to go on with (the number of stages: every stage is done)
    epoch: int  # epochs of that stage done
    net: dict[str, torch.Tensor]  # network weights
    optimizer: dict[str, Any]  # optimizer state of the stage
    scheduler: dict[str, Any]  # learning-rate schedule of the stage
    history: list[dict[str, Any]]  # one record per finished epoch (log.jsonl)

    @classmethod
    def after_epoch(
        cls,
        identity: dict[str, Any],
        stage_index: int,
        epoch: int,
        stage_epochs: int,
        net: torch.nn.Module,
        optimizer: torch.optim.Optimizer,
        scheduler: Any,
        history: list[dict[str, Any]],
    ) -> TrainingState:
        """The state after `epoch` (0-based) of stage `stage_index` finished; the stage's last epoch moves it on."""
        stage_done = epoch + 1 == stage_epochs
        return cls(
            identity=identity,
            stage_index=stage_index + 1 if stage_done else stage_index,
            epoch=0 if stage_done else epoch + 1,
            net=net.state_dict(),
            optimizer=optimizer.state_dict(),
            scheduler=scheduler.state_dict(),
            history=history,
        )

    def save(self, path: str | Path) -> Path:
        return save_torch_atomic(
            path,
            {
                "format": FORMAT_NAME,
                "identity": self.identity,
                "stage_index": self.stage_index,
                "epoch": self.epoch,
                "net": self.net,
                "optimizer": self.optimizer,
                "scheduler": self.scheduler,
                "history": self.history,
            },
        )

    @classmethod
    def load(cls, path: str | Path) -> TrainingState | None:
        """The state in `path`; None when the file is another kind of torch archive."""
        payload = load_torch(path, "training state")
        if payload.get("format") != FORMAT_NAME:
            return None
        try:
            return cls(**{f.name: payload[f.name] for f in fields(cls)})
        except KeyError as exc:
            raise InputError(f"an incomplete training state (no {exc})", path) from exc


def resume_stage(resumed: TrainingState | None, stage_index: int, optimizer: Any, scheduler: Any) -> int:
    """The first epoch of stage `stage_index` to train: mid-stage in a resumed run, with its optimizer and
    learning-rate schedule restored; 0 otherwise."""
    if resumed is None or stage_index != resumed.stage_index or resumed.epoch == 0:
        return 0
    optimizer.load_state_dict(resumed.optimizer)
    scheduler.load_state_dict(resumed.scheduler)
    return resumed.epoch
