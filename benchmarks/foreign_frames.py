"""Tactile frames written by another program: does `yoto track` close the loop on them as on YOTO's own frames?

Every closed-loop figure before used YOTO's simulated frames (contact points alone, every second pixel). This benchmark
simulates trajectories as `yoto simulate trajectory` does (same seed, same folder) and writes, beside each, copies whose
tactile frames (`left_tactile/`, `right_tactile/`, same file names) are rewritten as another simulator would write them,
from the truth alone: at each frame time the sensor's true pose on the object (the pose YOTO's own frame was pressed at,
slip and settling included: what the gel sees), a 320 x 240 grid of rays at 0.0634 mm through the pad into the mesh
(benchmarks/foreign_contacts.py's generator: Open3D ray casting, the penetration spread by an exponential kernel of 0.5
mm, not YOTO's Gaussian). Settings: `whole_pad` (every pixel, the untouched gel at z = 0, the gel's sink-in ring; 10 um
white noise), `contact_only` (the noise-free contact's pixels, the same noisy heights), `whole_pad_corr` /
`contact_only_corr` (the same with 30 um of noise correlated over 1 mm; new each frame, the two settings of a pair draw
the same fields), and `whole_pad_lift` / `contact_only_lift` (not run by default): the first two with the object leaving
the gel in some frames (the right sensor's frames from 40 to 55% of its frames, the grip slackening on one side, and
both sensors' last 10%): the object's front moved 0-50 um behind the gel plane (flat gel) or 20-100 um into it (a kiss),
one or the other at random, the other frames byte for byte the setting's without; the sensor streams and the truth
unchanged, so a lifted frame registered as a contact pulls the pose off by the press's depth. These frames carry no
fixed per-sensor error (YOTO's frames have a depth scale error and a smooth bias field drawn once per sensor): compare
the settings with each other for the handling, with `yoto` only loosely. The touch (`touch.json`, its clouds), the pose
streams and the truth stay YOTO's: the folders of a trajectory differ in their frames only. A frame whose pad misses the
object is written empty (contact points alone) or as the flat pad.

Each folder is tracked by the `yoto track` CLI, closed loop, with `--truth` and `--report`; prints one row per
trajectory and setting, from the report: the closed loop's final drift (mm / deg), its mean and peak error during the
motion, frames used of frames read, the median points per frame file, the closed loop's median time per instant (both
frames of an instant), and the CLI process's CPU seconds (model loading and the touch's pose included).

    python benchmarks/foreign_frames.py --out DIR                         # figurine, fruit, tool; seed 11, 2 each
    python benchmarks/foreign_frames.py --out DIR --objects bunny -n 1 --settings whole_pad contact_only
    python benchmarks/foreign_frames.py --out DIR -n 1 --settings whole_pad_lift contact_only_lift
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy import signal

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's yoto, not an installed one
sys.path.insert(0, str(Path(__file__).resolve().parent))

from foreign_contacts import SETTINGS, ForeignGenerator, _write_ply  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# The same gel and noise, 320 x 240, whole pad or contact points alone; and both with 30 um of noise correlated over
# 1 mm (new each frame; both settings of a pair draw the same noise fields).
FOREIGN = {
    "whole_pad": SETTINGS["whole_pad"],
    "contact_only": SETTINGS["gel"],
    "whole_pad_corr": SETTINGS["whole_pad_corr"],
    "contact_only_corr": dataclasses.replace(SETTINGS["whole_pad_corr"], whole_pad=False),
    "whole_pad_lift": SETTINGS["whole_pad"],
    "contact_only_lift": SETTINGS["gel"],
}


# Lift-off (`*_lift` settings): where the object leaves the gel, the frame shows it just behind the gel plane (the
# gel flat with its noise) or touching it over a few pixels (a kiss); the sensor poses and the truth stay as they are,
# so registering such a frame is wrong by the press's depth. Its front (deepest point) lies this far behind (+) or in
# (-) the gel plane, uniform.
LIFT_OFF_M = {"behind": (0.0, 5e-5), "kiss": (-1e-4, -2e-5)}
LIFT_WINDOW = (0.4, 0.55)  # share of the right sensor's frames (the grip slackens on one side) ...
LIFT_TAIL = 0.1  # ... and of both sensors' last frames (the end of the motion) written lifted off


def foreign_frame(
    generator: ForeignGenerator, T_mesh_sensor: np.ndarray, rng: np.random.Generator, front_m: float | None = None
) -> np.ndarray:
    """The cloud another simulator writes for a sensor at `T_mesh_sensor` (its gel plane z = 0, the object pressing
    in towards -z): the whole pad or the contact's pixels, per the generator's setting; with `front_m` the object's
    deepest point is moved (along the sensor's z) to that height: above 0 behind the gel plane, below it a kiss."""
    s = generator.setting
    start = -0.15
    rotation = T_mesh_sensor[:3, :3]
    local = np.stack([generator.grid_x.ravel(), generator.grid_y.ravel(), np.full(generator.grid_x.size, start)], 1)
    hits = generator.rays.cast(T_mesh_sensor[:3, 3] + local @ rotation.T, rotation[:, 2])
    z_object = np.where(hits.hit, start + hits.t_hit, np.inf).reshape(generator.grid_x.shape)
    if front_m is not None and np.isfinite(z_object).any():
        z_object = z_object - z_object.min() + front_m
    penetration = np.where(np.isfinite(z_object), np.maximum(-z_object, 0.0), 0.0)
    gel = penetration
    if generator.kernel is not None:
        reach = len(generator.kernel) // 2
        padded = np.pad(penetration, reach, mode="edge")
        gel = np.maximum(penetration, signal.fftconvolve(padded, generator.kernel, mode="valid"))
    touching = (penetration > s.contact_m) & (gel - penetration < 1e-7)
    heights = -gel + generator._noise(rng)
    keep = np.ones_like(touching) if s.whole_pad else touching
    return np.stack([generator.grid_x[keep], generator.grid_y[keep], heights[keep]], axis=1)


def lifted_off(count: int, side: str) -> np.ndarray:
    """Which of a sensor's `count` frames a `*_lift` setting writes lifted off: the last LIFT_TAIL of both sensors'
    and, for the right sensor, LIFT_WINDOW of them."""
    index = np.arange(count)
    lifted = index >= count * (1.0 - LIFT_TAIL)
    if side == "right":
        lifted |= (index >= count * LIFT_WINDOW[0]) & (index < count * LIFT_WINDOW[1])
    return lifted


def write_foreign_copy(source: Path, target: Path, trajectory, model, setting_name: str, seed: int) -> None:
    """`source`'s trajectory folder with its tactile frames rewritten by the foreign generator (same names)."""
    from yoto.trajectory import tactile_frame_name

    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("*_tactile"))
    generator = ForeignGenerator(model.mesh_vertices_mesh, model.mesh_faces, FOREIGN[setting_name])
    lift = setting_name.endswith("_lift")
    for number, side in enumerate(("left", "right")):
        folder = target / f"{side}_tactile"
        folder.mkdir()
        rng = np.random.default_rng([seed, number])
        lift_rng = np.random.default_rng([seed, number, 1])  # the noise of every frame as in the setting without
        frames = trajectory.tactile[side]
        for frame, lifted in zip(frames, lifted_off(len(frames), side) & lift, strict=True):
            front_m = lift_rng.uniform(*LIFT_OFF_M[lift_rng.choice(list(LIFT_OFF_M))]) if lifted else None
            cloud = foreign_frame(generator, model.T_mesh_object @ frame.T_object_sensor_true, rng, front_m)
            _write_ply(folder / tactile_frame_name(frame.timestamp_s), cloud, generator.setting.ply)


def track(folder: Path, workspace: Path) -> dict:
    """`yoto track` closed loop on a trajectory folder: the report's figures and the process's CPU time."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    command = [
        sys.executable, "-c", "import sys; from yoto.cli import main; sys.exit(main())", "track", "touch.json",
        "--left", "left.tum", "--right", "right.tum", "--left-tactile", "left_tactile", "--right-tactile",
        "right_tactile", "--truth", "object_true.tum", "--report", "report.json", "--out", "tracked.tum",
        "--workspace", str(workspace),
    ]  # fmt: skip
    run = subprocess.run(command, cwd=folder, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
                         text=True)  # fmt: skip
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if run.returncode != 0:
        return {"failed": (run.stderr or run.stdout).strip().splitlines()[-1:], "cpu_s": cpu}
    (folder / "track.log").write_text(run.stdout + run.stderr)
    return {"report": json.loads((folder / "report.json").read_text()), "cpu_s": cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--objects", nargs="+", default=["figurine", "fruit", "tool"])
    parser.add_argument("-n", type=int, default=2, help="trajectories per object")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument(
        "--settings", nargs="+", default=[name for name in FOREIGN if not name.endswith("_lift")], choices=list(FOREIGN)
    )
    parser.add_argument("--out", required=True, help="the folders are written here (about 0.2 GB a trajectory)")
    parser.add_argument("--workspace", default=os.environ.get("YOTO_WORKSPACE", str(ROOT / "yoto_workspace")))
    args = parser.parse_args()

    from yoto.evaluation.bench import resolve_object
    from yoto.simulate.trajectory import TrajectorySimulator, trajectory_folder_name, write_trajectory

    out = Path(args.out)
    rows = []
    for spec in args.objects:
        model = resolve_object(spec, args.workspace)
        simulator = TrajectorySimulator(model)
        for index in range(args.n):
            trajectory = simulator.trajectory(args.seed, index)
            base = out / model.name / trajectory_folder_name(index)
            write_trajectory(trajectory, model, base / "yoto")
            for name in args.settings:
                write_foreign_copy(base / "yoto", base / name, trajectory, model, name, args.seed)
            for name in ("yoto", *args.settings):
                result = track(base / name, Path(args.workspace))
                rows.append(row(model.name, index, name, base / name, result))
                print(rows[-1], flush=True)
    print(f"\nClosed-loop tracking, seed {args.seed}, frames rewritten by another simulator (yoto: YOTO's own)")
    print(
        "| trajectory | frames | final drift mm / deg | during motion mean | peak | frames used / read | points per "
        "frame | ms per instant (median) | CLI CPU s |\n|---|---|---|---|---|---|---|---|---|"
    )
    print("\n".join(rows))


def row(name: str, index: int, setting: str, folder: Path, result: dict) -> str:
    files = [p for side in ("left", "right") for p in (folder / f"{side}_tactile").iterdir()]
    points = int(np.median([int(p.read_bytes()[:200].split(b"element vertex ")[1].split(b"\n")[0]) for p in files]))
    if "report" not in result:
        return f"| {name} #{index} | {setting} | failed: {result['failed']} | | | | {points} | |"
    report = result["report"]
    errors, loop = report["errors"]["closed_loop"], report["closed_loop"]

    def pair(key: str) -> str:
        return f"{errors[key]['mm']:.2f} / {errors[key]['deg']:.2f}"

    return (
        f"| {name} #{index} | {setting} | {pair('final_drift')} | {pair('motion_mean')} | {pair('motion_peak')} | "
        f"{loop['frames_used']} / {loop['frames']} | {points} | {loop['latency_median_ms']:.1f} | "
        f"{result['cpu_s']:.1f} |"
    )


if __name__ == "__main__":
    main()
