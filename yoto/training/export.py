"""What a run hands on: the localizer checkpoint of the trained network, and its export with a JSON card."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import torch

from yoto.errors import InputError
from yoto.io import write_json_atomic
from yoto.network.checkpoint import Calibration, LocalizerCheckpoint, RealPairs, TrainedObject
from yoto.network.model import ContactLocalizationNet
from yoto.provenance import versions
from yoto.training.config import TrainConfig
from yoto.training.data import ObjectData
from yoto.training.validation import EvalSet, calibrate

CARD_KEYS = ("objects", "real_pairs", "seed", "versions", "network_config", "train_config", "calibration")


def localizer_checkpoint(
    net: ContactLocalizationNet,
    data: list[ObjectData],
    block_tensors: list[dict[str, torch.Tensor]],
    eval_sets: dict[tuple[int, str], EvalSet],
    config: TrainConfig,
    history: list[dict[str, Any]],
    real_digest: str | None,
) -> LocalizerCheckpoint:
    """The localizer checkpoint of the network as it is now, its candidate beliefs calibrated on `eval_sets`."""
    temperature = calibrate(net, block_tensors, eval_sets, config)
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
        **{key: checkpoint[key] for key in CARD_KEYS},
        "validation": {k: v for k, v in metrics.items() if k.startswith("val_")},
        "final_epoch": {k: v for k, v in metrics.items() if not k.startswith("val_")},
    }
    card_path = write_json_atomic(destination.with_suffix(".json"), card)
    return destination, card_path
