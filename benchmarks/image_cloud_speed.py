"""CPU time of GelSight image -> tactile cloud (`reconstruct`) on real presses and rendered contacts, and, with
`--against REV`, whether another revision's reconstruction gives the same clouds, timed interleaved with it.

Frames: the real presses in `--frames` (the ball presses of ../shared/data/gelsight_mini), and rendered ones through
the calibration's own optical model: `--contacts` simulated object contacts (the benchmark's pairs, seed 7, both
sides, over `--objects`) and `--balls` random ball presses (`yoto sensor bench`'s). All are reconstructed with the
calibration (`--calibration`, e.g. the fitted renderer's CAL_GAIN.npz, docs/sensor.md).
`--against REV` loads yoto/sensor/reconstruction.py as it is at git revision REV (the rest of yoto as it is now),
checks that height maps, masks and point clouds are bitwise equal on every frame (prints the largest difference
where not), then times both in alternating passes. Printed: median / p90 / mean CPU ms per frame (`process_time`,
one call per frame, after a warm-up pass), real and rendered apart. Run with one BLAS thread.

    OMP_NUM_THREADS=1 python benchmarks/image_cloud_speed.py --calibration CAL_GAIN.npz --against main --passes 10
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np


def load_revision(revision: str) -> ModuleType:
    """yoto/sensor/reconstruction.py at git `revision`, as its own module."""
    source = subprocess.run(
        ["git", "show", f"{revision}:yoto/sensor/reconstruction.py"], check=True, capture_output=True, text=True
    ).stdout
    path = Path(tempfile.mkdtemp()) / "reconstruction_at_revision.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("reconstruction_at_revision", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def rendered_frames(calibration, objects: list[str], contacts: int, balls: int) -> list[np.ndarray]:
    from yoto.evaluation.bench import resolve_object
    from yoto.sensor.bench import synthetic_frames
    from yoto.sensor.optical import render_image
    from yoto.simulate.scenarios import PairSimulator

    frames = []
    per_object = -(-contacts // max(1, len(objects)))
    for name in objects:
        simulator = PairSimulator(resolve_object(name, None))
        for k in range(per_object):
            if k % 2 == 0:
                simulated = simulator.pair(7, k // 2)
            press = simulated.contacts[("left", "right")[k % 2]].press
            frames.append(render_image(press.height_map_m, calibration, np.random.default_rng(1000 + len(frames))))
    return frames + synthetic_frames(calibration, balls, seed=3)


def outputs(module: ModuleType, frame: np.ndarray, calibration) -> list[np.ndarray]:
    r = module.reconstruct(frame, calibration)
    return [r.height_map_m, r.mask, r.core_mask, r.points_sensor]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calibration", required=True, help="calibration file (its optical model renders)")
    parser.add_argument("--frames", default="../shared/data/gelsight_mini/presses/6.310mm", help="real frames")
    parser.add_argument("--objects", nargs="+", default=["fruit", "figurine", "tool"])
    parser.add_argument("--contacts", type=int, default=48, help="rendered object contacts in all")
    parser.add_argument("--balls", type=int, default=12, help="rendered ball presses")
    parser.add_argument("--passes", type=int, default=5, help="timed passes over all frames (per revision)")
    parser.add_argument("--against", help="git revision whose reconstruction.py to compare with (e.g. main)")
    args = parser.parse_args()

    import yoto.sensor.reconstruction as current
    from yoto.sensor.calibration import load_calibration
    from yoto.sensor.presses import list_press_images, load_image

    calibration = load_calibration(args.calibration)
    real = [load_image(p, calibration.spec) for p in list_press_images(args.frames)]
    frames = real + rendered_frames(calibration, args.objects, args.contacts, args.balls)
    kinds = ["real"] * len(real) + ["rendered"] * (len(frames) - len(real))
    print(f"current: {current.__file__} (the installed yoto; PYTHONPATH=. for a worktree's)")
    versions = {"current": current}
    if args.against:
        versions[args.against] = load_revision(args.against)
        differing, worst = 0, 0.0
        for frame in frames:
            for a, b in zip(outputs(current, frame, calibration), outputs(versions[args.against], frame, calibration)):
                if a.shape != b.shape or not np.array_equal(a, b):
                    differing += 1
                    if a.shape == b.shape and a.dtype != bool:
                        worst = max(worst, float(np.abs(a.astype(np.float64) - b).max()))
                    elif a.shape != b.shape or a.dtype == bool:
                        worst = float("inf")
        print(
            f"{len(frames)} frames ({len(real)} real): {differing} of {4 * len(frames)} outputs (height, mask, core, "
            f"points) differ from {args.against}'s"
            + (f", by at most {worst:.3g} m" if differing else ": bitwise equal")
        )
    for module in versions.values():  # warm-up: caches, FFT plans
        for frame in frames:
            module.reconstruct(frame, calibration)
    times: dict[tuple[str, str], list[float]] = {(v, k): [] for v in versions for k in ("real", "rendered")}
    names = list(versions)
    for p in range(args.passes):
        for name in names if p % 2 == 0 else names[::-1]:  # alternate which goes first
            for frame, kind in zip(frames, kinds, strict=True):
                start = time.process_time()
                versions[name].reconstruct(frame, calibration)
                times[name, kind].append(time.process_time() - start)
    for (name, kind), values in times.items():
        ms = np.array(values) * 1e3
        print(
            f"{name:>10} {kind:>8}: median {np.median(ms):.3f} ms, p90 {np.percentile(ms, 90):.3f} ms, "
            f"mean {ms.mean():.3f} ms ({len(ms)} calls)"
        )


if __name__ == "__main__":
    main()
