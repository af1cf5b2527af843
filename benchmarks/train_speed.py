"""Training throughput of the localization network: samples per second of real training steps.

Each timed step is a full optimisation step of `yoto train`: draw and augment a batch of virtual patches,
encode them and all the object's blocks (with gradients), compute the loss, backward, AdamW step. Steps
cycle over the objects as training does. Warm-up steps are excluded; the median and spread of the rest
are reported, as wall-clock and as process CPU time (the machine may be shared: CPU time per step shows
what the code costs when wall time is inflated by other processes).

    python benchmarks/train_speed.py --preset cpu --objects tool fruit figurine --threads 2 --steps 30
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from dataclasses import replace

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu", help="training preset (cpu or paper)")
    parser.add_argument("--objects", nargs="+", default=["tool", "fruit", "figurine"])
    parser.add_argument("--workspace", help="workspace holding (or to hold) the object models and patches")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--steps", type=int, default=30, help="timed steps")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps first")
    parser.add_argument("--batch-size", type=int, help="override the preset's batch size")
    parser.add_argument("--block-refresh-every", type=int, help="override: re-encode blocks every n-th step")
    parser.add_argument(
        "--network", nargs="*", default=[], metavar="FIELD=VALUE", help="override network config fields (measurements)"
    )
    parser.add_argument("--json", help="write the result here too")
    args = parser.parse_args()

    import torch

    from yoto.network.model import ContactLocalizationNet, count_parameters
    from yoto.objects.build import load_object_model
    from yoto.patches.virtual import VirtualPatchConfig
    from yoto.training.train import StepRunner, _load_objects, _optimizer, plan_epoch, preset

    torch.set_num_threads(args.threads)
    config = preset(args.preset)
    if args.batch_size:
        config = replace(config, batch_size=args.batch_size)
    if args.network:
        overrides = {}
        for item in args.network:
            key, value = item.split("=", 1)
            overrides[key] = json.loads(value)
        config = replace(config, network=replace(config.network, **overrides))
    if args.block_refresh_every:
        config = replace(config, block_refresh_every=args.block_refresh_every)
    models = [load_object_model(name, args.workspace) for name in args.objects]
    data = _load_objects(args.objects, models, args.workspace, config, VirtualPatchConfig(), progress=False)
    torch.manual_seed(0)
    net = ContactLocalizationNet(config.network)
    runner = StepRunner(net, data, config, torch.device("cpu"), None)
    rng = np.random.default_rng(0)
    plan = plan_epoch(data, config.stage1, config.batch_size, rng, use_real=False)
    optimizer, scheduler = _optimizer(net, config.stage1, config, len(plan))

    wall, cpu, sizes = [], [], []
    for i, (obj_index, entries) in enumerate(plan[: args.warmup + args.steps]):
        tick, cpu_tick = time.perf_counter(), time.process_time()
        runner.step(obj_index, entries, rng, 1.0, optimizer, scheduler)
        if i >= args.warmup:
            wall.append(time.perf_counter() - tick)
            cpu.append(time.process_time() - cpu_tick)
            sizes.append(len(entries))
    wall_a, cpu_a, sizes_a = np.array(wall), np.array(cpu), np.array(sizes)
    batch = float(np.median(sizes_a))
    result = {
        "preset": args.preset,
        "objects": args.objects,
        "blocks": [o.blocks.num_blocks for o in data],
        "parameters": count_parameters(net),
        "network_overrides": args.network,
        "batch_size": config.batch_size,
        "block_refresh_every": config.block_refresh_every,
        "threads": args.threads,
        "steps": len(wall),
        "step_ms_median": 1000 * float(np.median(wall_a)),
        "step_ms_p10_p90": [1000 * float(np.percentile(wall_a, 10)), 1000 * float(np.percentile(wall_a, 90))],
        "samples_per_s_median": batch / float(np.median(wall_a)),
        "samples_per_s_best_decile": batch / float(np.percentile(wall_a, 10)),
        "cpu_ms_per_step_median": 1000 * float(np.median(cpu_a)),
        "samples_per_cpu_s": batch / float(np.median(cpu_a)),
        "load_average": os.getloadavg(),
        "cpu": platform.processor() or platform.machine(),
        "torch": torch.__version__,
    }
    print(
        f"{args.preset}: {result['parameters']:,} parameters, batch {config.batch_size}, {args.threads} threads: "
        f"median step {result['step_ms_median']:.0f} ms -> {result['samples_per_s_median']:.0f} samples/s "
        f"(best decile {result['samples_per_s_best_decile']:.0f}/s; {result['samples_per_cpu_s']:.0f} samples per "
        f"CPU-second; load average {result['load_average'][0]:.1f})"
    )
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=2)


if __name__ == "__main__":
    main()
