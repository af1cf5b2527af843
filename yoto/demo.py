"""`yoto demo`: the whole pipeline on the built-in objects.

Builds the built-in object models (cached in the workspace), simulates dual GelSight contacts on each,
estimates the poses with the training-free matched filter, the YOTO network (the weights that ship in the
package) and the ICP baseline, prints a table against ground truth, and writes a figure of predicted vs
true contacts on the objects.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from yoto.localize.base import ContactLocalizer

log = logging.getLogger("yoto")

DEMO_SEED = 7  # the benchmark's evaluation seed; the shipped weights were fine-tuned on other seeds


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the whole pipeline on the built-in objects (the main job)")
    parser.add_argument("-n", "--pairs", type=int, default=6, help="dual contacts per object")
    parser.add_argument("--icp-pairs", type=int, default=2, help="of which ICP also runs on this many (ICP is slow)")
    parser.add_argument("--checkpoint", help="network weights (default: the weights shipped with YOTO)")
    parser.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")
    parser.add_argument("--out", help="figure path (default: WORKSPACE/demo/demo.png)")
    parser.set_defaults(
        run=lambda args: run_demo(args.pairs, args.icp_pairs, args.checkpoint, args.workspace, args.out)
    )


@dataclass
class DemoMethod:
    label: str
    localizer: ContactLocalizer
    max_pairs: int  # pairs per object this method runs on
    colour: str
    marker: str
    errors: list = field(default_factory=list)  # (object, pair) -> pose errors, in row order
    predictions: dict = field(default_factory=dict)  # object -> (K, 3) predicted contacts, object frame


def run_demo(
    pairs_per_object: int = 6,
    icp_pairs: int = 2,
    checkpoint: str | None = None,
    workspace: str | Path | None = None,
    out: str | Path | None = None,
) -> int:
    from yoto.contacts import SIDES
    from yoto.localize import make_localizer
    from yoto.metrics import pose_errors
    from yoto.objects.build import load_object_model
    from yoto.objects.builtin import builtin_object_names
    from yoto.pose.pipeline import estimate_pose
    from yoto.simulate.scenarios import PairSimulator
    from yoto.workspace import workspace_dir

    started = time.perf_counter()
    methods = [
        DemoMethod("matched filter", make_localizer("match"), pairs_per_object, "royalblue", "^"),
        DemoMethod("YOTO network", make_localizer("yoto", checkpoint), pairs_per_object, "seagreen", "s"),
    ]
    if icp_pairs > 0:
        methods.append(DemoMethod("ICP", make_localizer("icp"), icp_pairs, "orange", "x"))
    rows, figure_data = [], []
    for name in builtin_object_names():
        model = load_object_model(name, workspace)
        simulator = PairSimulator(model)
        truths = []
        for index in range(pairs_per_object):
            simulated = simulator.pair(DEMO_SEED, index)
            pair = simulated.pair
            truths += [simulated.p_object_true[side] for side in SIDES]
            results: dict[str, dict[str, float]] = {}
            row: dict[str, Any] = {"object": name, "pair": index, "results": results}
            for method in methods:
                if index >= method.max_pairs:
                    continue
                estimate = estimate_pose(pair, model, method.localizer)
                assert pair.T_world_mesh_true is not None  # simulated pairs carry their truth
                results[method.label] = {
                    **pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model),
                    "ms": estimate.latency_ms["localize_left"] + estimate.latency_ms["localize_right"],
                }
                found = [estimate.contacts[side].p_object for side in SIDES]
                method.predictions[name] = np.vstack([method.predictions.get(name, np.zeros((0, 3))), found])
            rows.append(row)
        figure_data.append((model, np.array(truths)))

    print(format_table(rows, [method.label for method in methods]))
    path = Path(out) if out else workspace_dir(workspace) / "demo" / "demo.png"
    plot_contacts(figure_data, methods, path)
    print(f"\nFigure of predicted vs true contacts: {path}")
    print(f"Demo finished in {time.perf_counter() - started:.0f} s.")
    return 0


def format_table(rows: list[dict], labels: list[str]) -> str:
    """Pose error (translation mm / rotation deg) and localization time (ms, both contacts) per pair and method."""
    header = f"{'object':<9} {'pair':>4}" + "".join(f"  {label + ' mm / deg, ms':>34}" for label in labels)
    lines = [header, "-" * len(header)]
    for row in rows:
        cells = []
        for label in labels:
            result = row["results"].get(label)
            cells.append(
                f"  {result['translation_mm']:10.1f} / {result['rotation_deg']:6.1f}, {result['ms']:7.0f}"
                if result
                else " " * 36
            )
        lines.append(f"{row['object']:<9} {row['pair']:>4}" + "".join(f"{cell:>36}" for cell in cells))
    lines.append("-" * len(header))
    for label in labels:
        results = [row["results"][label] for row in rows if label in row["results"]]
        translation = np.median([r["translation_mm"] for r in results])
        rotation = np.median([r["rotation_deg"] for r in results])
        good = np.mean([r["translation_mm"] < 5.0 and r["rotation_deg"] < 5.0 for r in results])
        ms = np.median([r["ms"] for r in results])
        lines.append(
            f"{label:<15} median pose error {translation:6.1f} mm / {rotation:5.1f} deg, {100 * good:3.0f}% of "
            f"{len(results)} pairs within 5 mm and 5 deg, {ms:5.0f} ms to localize both contacts"
        )
    return "\n".join(lines)


def plot_contacts(figure_data: list, methods: list[DemoMethod], path: Path) -> Path:
    """Parent cloud (grey), true contacts (red) and each method's chosen contacts, two views per object."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from yoto.io import write_bytes_atomic

    figure = plt.figure(figsize=(4.2 * len(figure_data), 8.0))
    for column, (model, truths) in enumerate(figure_data):
        cloud = model.points_object[:: max(1, len(model.points_object) // 6000)] * 1000
        for row, (elevation, azimuth) in enumerate(((25, -60), (-20, 120))):
            axis = figure.add_subplot(2, len(figure_data), 1 + column + row * len(figure_data), projection="3d")
            axis.scatter(*cloud.T, s=0.4, c="0.7", alpha=0.35, depthshade=False)
            axis.scatter(*(truths * 1000).T, s=60, c="red", label="true contact", depthshade=False)
            for method in methods:
                predictions = method.predictions.get(model.name, np.zeros((0, 3))) * 1000
                axis.scatter(
                    *predictions.T, s=30, c=method.colour, marker=method.marker, label=method.label, depthshade=False
                )
                for true, predicted in zip(truths * 1000, predictions):
                    axis.plot(*np.stack([true, predicted]).T, c=method.colour, lw=0.8)
            centre, radius = cloud.mean(axis=0), np.ptp(cloud, axis=0).max() / 2
            axis.set_xlim(centre[0] - radius, centre[0] + radius)
            axis.set_ylim(centre[1] - radius, centre[1] + radius)
            axis.set_zlim(centre[2] - radius, centre[2] + radius)
            axis.view_init(elevation, azimuth)
            axis.set_xlabel("x mm")
            axis.set_ylabel("y mm")
            if row == 0:
                axis.set_title(f"{model.name}: predicted vs true contacts")
            if row == 0 and column == 0:
                axis.legend(loc="upper left", fontsize=8)
    figure.tight_layout()
    import io

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90)
    plt.close(figure)
    return write_bytes_atomic(path, buffer.getvalue())
