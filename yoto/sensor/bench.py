"""Speed of image -> tactile point cloud on this machine, with a per-step breakdown.

Frames are rendered by the optical simulator from random ball presses (or given images), so the benchmark
needs nothing but a calibration. Every frame is reconstructed once untimed (warm-up), then the whole
pipeline is timed over `repeats` frames, and each step separately over the same frames. Reported: median
and p90 milliseconds, with the machine, versions and seed, as Markdown and as JSON.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from yoto.errors import InputError
from yoto.sensor.calibration import SensorCalibration
from yoto.sensor.optical import render_image
from yoto.sensor.reconstruction import (
    _pixel_xy,
    box_gradients,
    check_frame,
    contact_masks,
    integrate_box,
    reconstruct,
    touched_box,
)
from yoto.sensor.sphere import press_height_map

Item = TypeVar("Item")


@dataclass
class BenchResult:
    frames: int
    repeats: int
    total_ms: tuple[float, float]  # (median, p90) of the full image -> points call, checks included
    steps_ms: dict[str, tuple[float, float]] = field(default_factory=dict)  # (median, p90) per step
    environment: dict[str, Any] = field(default_factory=dict)

    def table(self) -> str:
        lines = ["| step | median ms | p90 ms |", "|---|---|---|"]
        for name, (median, p90) in self.steps_ms.items():
            lines.append(f"| {name} | {median:.3f} | {p90:.3f} |")
        lines.append(
            f"| **image -> point cloud (reconstruct)** | **{self.total_ms[0]:.3f}** | **{self.total_ms[1]:.3f}** |"
        )
        env = ", ".join(f"{k} {v}" for k, v in self.environment.items())
        return "\n".join(lines) + f"\n\n{self.repeats} timed frames after {self.frames} warm-up frames; {env}"

    def to_json(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "repeats": self.repeats,
            "total_ms": {"median": self.total_ms[0], "p90": self.total_ms[1]},
            "steps_ms": {k: {"median": m, "p90": p} for k, (m, p) in self.steps_ms.items()},
            "environment": self.environment,
        }


def synthetic_frames(
    calibration: SensorCalibration, count: int, seed: int = 0, ball_radius_m: float = 3.155e-3
) -> list[np.ndarray]:
    """Rendered frames of random ball presses (contact radius 0.6-2.0 mm), with sensor noise."""
    rng = np.random.default_rng(seed)
    spec = calibration.spec
    frames = []
    for _ in range(count):
        a_px = rng.uniform(0.6e-3, 2.0e-3) / spec.pixel_size_m
        cx = rng.uniform(a_px, spec.width_px - 1 - a_px)
        cy = rng.uniform(a_px, spec.height_px - 1 - a_px)
        frames.append(render_image(press_height_map(cx, cy, a_px, ball_radius_m, spec), calibration, rng))
    return frames


def _time(fn: Callable[[np.ndarray], Any], frames: list[np.ndarray], repeats: int) -> np.ndarray:
    out = np.empty(repeats)
    for k in range(repeats):
        frame = frames[k % len(frames)]
        start = time.perf_counter()
        fn(frame)
        out[k] = time.perf_counter() - start
    return out * 1e3


def run_benchmark(calibration: SensorCalibration, frames: list[np.ndarray], repeats: int = 300) -> BenchResult:
    """Time reconstruct() and each of its steps over `repeats` frames (cycling through `frames`)."""
    for frame in frames:  # warm-up: caches, allocator, FFT plans
        reconstruct(frame, calibration)
    spec = calibration.spec
    stats = lambda t: (float(np.median(t)), float(np.percentile(t, 90)))  # noqa: E731
    total = _time(lambda f: reconstruct(f, calibration), frames, repeats)

    # Per step, on precomputed inputs of the previous step.
    blocks = [check_frame(f, calibration) for f in frames]
    boxes = []
    for k, frame_blocks in enumerate(blocks):
        box = touched_box(frame_blocks, (spec.height_px, spec.width_px))
        if box is None:
            raise InputError(f"frame {k} shows no contact: the per-step timings need frames with a contact")
        boxes.append(box)
    gradients = [box_gradients(f, calibration, box) for f, box in zip(frames, boxes, strict=True)]
    heights = [
        integrate_box(gx, gy, box, b, spec.pixel_size_m)
        for (gx, gy, _), box, b in zip(gradients, boxes, blocks, strict=True)
    ]
    masks = [h <= 0.5 * h.min() for h in heights]
    index = {id(f): i for i, f in enumerate(frames)}

    def at(collection: list[Item]) -> Callable[[np.ndarray], Item]:
        return lambda f: collection[index[id(f)]]

    x, y = _pixel_xy(spec)
    steps = {
        "checks + touched blocks (8x8 means)": lambda f: touched_box(
            check_frame(f, calibration), (spec.height_px, spec.width_px)
        ),
        "gradients in the touched box (smoothing, table, gains)": lambda f: box_gradients(f, calibration, at(boxes)(f)),
        "Poisson integration in the box (DCT/DST, float32)": lambda f: integrate_box(
            *at(gradients)(f)[:2], at(boxes)(f), at(blocks)(f), spec.pixel_size_m
        ),
        "contact masks": lambda f: contact_masks(at(gradients)(f)[2], at(heights)(f), calibration.mask, at(boxes)(f)),
        "points (sensor frame)": lambda f: np.stack(
            [x[at(masks)(f)], y[at(masks)(f)], at(heights)(f)[at(masks)(f)]], 1
        ),
    }
    steps_ms = {name: stats(_time(fn, frames, repeats)) for name, fn in steps.items()}
    import scipy

    environment = {
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }
    return BenchResult(len(frames), repeats, stats(total), steps_ms, environment)
