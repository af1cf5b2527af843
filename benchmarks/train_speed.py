"""Training throughput of the localization network (samples per second of real training steps).

    python benchmarks/train_speed.py --preset cpu --objects tool fruit figurine --threads 2 --steps 30

Same as `yoto train --speed-test`, with overrides for measuring design choices, e.g.
`--network points_per_block=128 --batch-size 64`. See yoto/training/speed.py for what is timed.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace


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
        "--network", nargs="*", default=[], metavar="FIELD=VALUE", help="override network config fields (JSON values)"
    )
    parser.add_argument("--json", help="write the result here too")
    args = parser.parse_args()

    import torch

    from yoto.training.config import preset
    from yoto.training.speed import measure_training_speed

    torch.set_num_threads(args.threads)
    config = preset(args.preset)
    if args.batch_size:
        config = replace(config, batch_size=args.batch_size)
    if args.block_refresh_every:
        config = replace(config, block_refresh_every=args.block_refresh_every)
    if args.network:
        overrides = {k: json.loads(v) for k, v in (item.split("=", 1) for item in args.network)}
        config = replace(config, network=replace(config.network, **overrides))
    result = measure_training_speed(config, args.objects, args.workspace, args.steps, args.warmup)
    print(f"{args.preset}: {result.summary()}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({**result.to_dict(), "preset": args.preset, "network_overrides": args.network}, handle, indent=2)


if __name__ == "__main__":
    main()
