"""Training throughput: samples per second of real training steps (`yoto train --speed-test`).

Each timed step is a full optimisation step of `yoto train`: draw and augment a batch of virtual patches,
encode them and all of the object's blocks (with gradients), loss, backward, AdamW step. Steps cycle over
the objects as training does. Warm-up steps are excluded; the median and spread of the rest are reported
as wall-clock and as process CPU time (on a shared machine, CPU time per step shows what the code costs
when the wall clock is inflated by other processes).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from yoto.network.model import ContactLocalizationNet, count_parameters
from yoto.objects.build import load_object_model
from yoto.patches.virtual import VirtualPatchConfig
from yoto.provenance import run_info
from yoto.training.batches import plan_epoch
from yoto.training.config import AnyTrainConfig, DescriptorTrainConfig
from yoto.training.data import load_objects
from yoto.training.step import StepRunner, device_and_autocast, make_optimizer


@dataclass
class SpeedResult:
    """Timings of training steps."""

    step_s: np.ndarray  # wall-clock seconds per timed step
    cpu_s: np.ndarray  # process CPU seconds per timed step
    batch_sizes: np.ndarray  # samples per timed step
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def samples_per_s(self) -> float:
        return float(np.median(self.batch_sizes) / np.median(self.step_s))

    def to_dict(self) -> dict[str, Any]:
        batch = float(np.median(self.batch_sizes))
        return {
            **self.info,
            "steps": len(self.step_s),
            "step_ms_median": 1000 * float(np.median(self.step_s)),
            "step_ms_p10_p90": [1000 * float(np.percentile(self.step_s, q)) for q in (10, 90)],
            "samples_per_s_median": self.samples_per_s,
            "samples_per_s_best_decile": batch / float(np.percentile(self.step_s, 10)),
            "cpu_ms_per_step_median": 1000 * float(np.median(self.cpu_s)),
            "samples_per_cpu_s": batch / float(np.median(self.cpu_s)),
        }

    def summary(self) -> str:
        d = self.to_dict()
        return (
            f"{d['parameters']:,} parameters, batch {d['batch_size']}, {d['threads']} threads, {d['steps']} steps: "
            f"median step {d['step_ms_median']:.0f} ms -> {d['samples_per_s_median']:.0f} training samples/s "
            f"(best decile {d['samples_per_s_best_decile']:.0f}/s; {d['samples_per_cpu_s']:.0f} samples per CPU-second;"
            f" load average {d['load_average'][0]:.1f} on {d['cpu_count']} CPUs)"
        )


def measure_training_speed(
    config: AnyTrainConfig,
    objects: list[str],
    workspace: str | Path | None = None,
    steps: int = 30,
    warmup: int = 5,
    device: str | None = "cpu",
    patch_config: VirtualPatchConfig = VirtualPatchConfig(),
) -> SpeedResult:
    """Time `steps` training steps (after `warmup` untimed ones) of `config` on `objects`, on `device` (None: cuda
    when available) with the config's precision; the point network trains on virtual patches of `patch_config`."""
    if isinstance(config, DescriptorTrainConfig):
        return _descriptor_speed(config, objects, workspace, steps, warmup)
    models = [load_object_model(name, workspace) for name in objects]
    data = load_objects(objects, models, workspace, config, patch_config, progress=False)
    torch.manual_seed(config.seed)
    device_, autocast_dtype = device_and_autocast(config.precision, device)
    net = ContactLocalizationNet(config.network).to(device_)
    runner = StepRunner(net, data, config, device_, autocast_dtype)
    rng = np.random.default_rng(config.seed)
    plan = plan_epoch(data, config.stage1, config.batch_size, rng, use_real=False)
    optimizer, scheduler = make_optimizer(net, config.stage1, config, len(plan))

    def run(obj_index: int, entries: Any) -> None:
        runner.step(obj_index, entries, rng, 1.0, optimizer, scheduler)
        if device_.type == "cuda":
            torch.cuda.synchronize(device_)

    wall, cpu, sizes = _time_steps(plan, warmup, steps, run)
    info = {
        **run_info(),
        "objects": list(objects),
        "blocks": [o.blocks.num_blocks for o in data],
        "parameters": count_parameters(net),
        "batch_size": config.batch_size,
        "block_refresh_every": config.block_refresh_every,
        "device": str(device_),
        "precision": "bf16" if autocast_dtype is not None else "fp32",
        "threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
    }
    return SpeedResult(wall, cpu, sizes, info)


def _descriptor_speed(
    config: DescriptorTrainConfig, objects: list[str], workspace: str | Path | None, steps: int, warmup: int
) -> SpeedResult:
    """measure_training_speed for the anchor-descriptor network (its virtual contacts are made if missing)."""
    from yoto.network.descriptor import DescriptorNet
    from yoto.training.descriptor_train import DescriptorStep, load_object_sets
    from yoto.training.descriptor_train import plan_epoch as plan_descriptor_epoch

    models = [load_object_model(name, workspace) for name in objects]
    device = torch.device("cpu")
    sets = load_object_sets(models, {}, {}, config, workspace, device, progress=False)
    torch.manual_seed(config.seed)
    net = DescriptorNet(config.network)
    step = DescriptorStep(net, sets, config, device)
    rng = np.random.default_rng(config.seed)
    plan = plan_descriptor_epoch(sets, config.stage1, config.batch_size, rng, use_real=False)
    optimizer, scheduler = make_optimizer(net, config.stage1, config, len(plan))
    wall, cpu, sizes = _time_steps(
        plan, warmup, steps, lambda obj_index, entries: step(obj_index, entries, 1.0, rng, optimizer, scheduler)
    )
    info = {
        **run_info(),
        "objects": list(objects),
        "anchors": [len(o.anchors) for o in sets],
        "parameters": count_parameters(net),
        "batch_size": config.batch_size,
        "threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
    }
    return SpeedResult(wall, cpu, sizes, info)


def _time_steps(
    plan: list, warmup: int, steps: int, run: Callable[[int, Any], Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wall and CPU seconds and batch sizes of `steps` training steps `run(obj_index, entries)` of an epoch plan,
    after `warmup` untimed ones."""
    wall, cpu, sizes = [], [], []
    for i, (obj_index, entries) in enumerate(plan[: warmup + steps]):
        tick, cpu_tick = time.perf_counter(), time.process_time()
        run(obj_index, entries)
        if i >= warmup:
            wall.append(time.perf_counter() - tick)
            cpu.append(time.process_time() - cpu_tick)
            sizes.append(len(entries))
    return np.array(wall), np.array(cpu), np.array(sizes)
