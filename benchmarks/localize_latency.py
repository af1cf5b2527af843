"""Per-contact latency of the YOTO localizer, the paper's way (App. C.3): every call timed end to end, the
first call (and the once-per-object block encoding) excluded as warm-up; median and p90.

"end to end" here is `NetworkLocalizer.localize`: prepare the sensor cloud (voxel grid at the parent's
spacing, PCA normals), canonicalize, sample, encode, score against the cached blocks, fine head, candidates.
The network part alone (encode + score + fine head) is timed separately.

    python benchmarks/localize_latency.py --pairs PAIRS/tool PAIRS/fruit PAIRS/figurine --threads 1
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", help="localizer checkpoint (default: the shipped weights)")
    parser.add_argument("--pairs", nargs="+", required=True, help="pair files or folders (their clouds are used)")
    parser.add_argument("--workspace", help="workspace holding the object models")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=1, help="passes over the clouds")
    parser.add_argument("--json", help="write results here")
    args = parser.parse_args()

    import torch

    from yoto.contacts import SIDES, read_contact_pair
    from yoto.localize.network import NetworkLocalizer, measure_latency
    from yoto.network.candidates import rank_hypotheses
    from yoto.objects.build import load_object_model
    from yoto.provenance import run_info
    from yoto.training.data import find_pair_files_recursive

    torch.set_num_threads(args.threads)
    localizer = NetworkLocalizer.from_checkpoint(args.checkpoint)
    clouds: dict[str, list[np.ndarray]] = defaultdict(list)
    for path in find_pair_files_recursive(args.pairs):
        pair = read_contact_pair(path)
        clouds[pair.object_name] += [pair.contact(side).points_sensor for side in SIDES]
    results = {**run_info(), "threads": args.threads, "load_average": os.getloadavg(), "objects": {}}
    for name, object_clouds in clouds.items():
        model = load_object_model(name, args.workspace)
        tick = time.perf_counter()
        localizer.prepare_object(model)
        block_ms = 1000 * (time.perf_counter() - tick)
        full = measure_latency(localizer, object_clouds, model, warmup=1, repeats=args.repeats)
        cache = localizer.prepare_object(model)
        inputs = [localizer.canonical_input(cloud, model) for cloud in object_clouds]
        network_ms = []
        for points, normals in inputs:
            tick = time.perf_counter()
            with torch.inference_mode():
                features = localizer.net.encode(torch.from_numpy(points[None]), torch.from_numpy(normals[None]))
                rank_hypotheses(localizer.net, features, cache.features, cache.tensors, localizer.hypotheses)
            network_ms.append(1000 * (time.perf_counter() - tick))
        network_ms = network_ms[1:]
        results["objects"][name] = {
            "contacts": len(object_clouds),
            "block_encoding_ms": block_ms,
            "per_contact_ms": full,
            "network_only_ms": {"median": float(np.median(network_ms)), "p90": float(np.percentile(network_ms, 90))},
        }
        print(
            f"{name:9s} {full['calls']} calls: per contact median {full['median_ms']:.1f} ms, "
            f"p90 {full['p90_ms']:.1f} ms (network alone median {np.median(network_ms):.1f} ms, "
            f"p90 {np.percentile(network_ms, 90):.1f}); "
            f"block encoding once {block_ms:.0f} ms"
        )
    print(f"load average {results['load_average'][0]:.1f}, {args.threads} thread(s)")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=2)


if __name__ == "__main__":
    main()
