"""One optimisation step, and what steps need: the device and precision, AdamW with a OneCycle schedule."""

from __future__ import annotations

import numpy as np
import torch

from yoto.errors import InputError
from yoto.network.model import ContactLocalizationNet
from yoto.training.batches import Entry, collate
from yoto.training.config import AnyTrainConfig, StageConfig, TrainConfig
from yoto.training.data import ObjectData, draw_patch
from yoto.training.losses import localization_loss


def device_and_autocast(precision: str, device: str | None) -> tuple[torch.device, torch.dtype | None]:
    """The device (default: cuda when available) and the autocast dtype (None: fp32) of `precision`."""
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if precision not in ("auto", "fp32", "bf16"):
        raise InputError(f"precision must be auto, fp32 or bf16, not {precision!r}")
    use_bf16 = precision == "bf16" or (precision == "auto" and dev.type == "cuda" and torch.cuda.is_bf16_supported())
    return dev, (torch.bfloat16 if use_bf16 else None)


def make_optimizer(
    net: torch.nn.Module, stage: StageConfig, config: AnyTrainConfig, total_steps: int
) -> tuple[torch.optim.AdamW, torch.optim.lr_scheduler.OneCycleLR]:
    """AdamW with weight decay on weight matrices only, the encoder (parameters named encoder.*) at its own learning
    rate, under a OneCycle schedule of `total_steps` steps."""
    groups: dict[str, list[torch.nn.Parameter]] = {
        "encoder_decay": [],
        "encoder_plain": [],
        "head_decay": [],
        "head_plain": [],
    }
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


class StepRunner:
    """One optimisation step on one object's batch: draw and augment patches, encode them and the object's
    blocks, take the loss and step. Holds each object's blocks as tensors (with their fixed kNN)."""

    def __init__(
        self,
        net: ContactLocalizationNet,
        data: list[ObjectData],
        config: TrainConfig,
        device: torch.device,
        autocast_dtype: torch.dtype | None,
    ):
        self.net, self.data, self.config = net, data, config
        self.device, self.autocast_dtype = device, autocast_dtype
        self.block_tensors: list[dict[str, torch.Tensor]] = []
        for obj in data:
            tensors = {k: v.to(device) for k, v in obj.blocks.tensors().items()}
            tensors["block_knn"] = net.encoder.neighbours(tensors["block_points"])
            self.block_tensors.append(tensors)
        self.new_epoch()

    def new_epoch(self) -> None:
        self.block_cache: dict[int, torch.Tensor] = {}
        self.object_steps = [0] * len(self.data)
        self.net.train()

    def step(
        self,
        obj_index: int,
        entries: list[Entry],
        rng: np.random.Generator,
        real_weight: float,
        optimizer: torch.optim.Optimizer,
        scheduler: torch.optim.lr_scheduler.LRScheduler | None,
    ) -> dict[str, float]:
        """Train on the batch `entries` of object `obj_index`; returns the loss and its parts."""
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
