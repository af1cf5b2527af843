"""`yoto demo`: the whole pipeline on the built-in objects, with the weights that ship in the package.

Builds the built-in object models (cached in the workspace), simulates dual GelSight contacts on each,
estimates the poses with YOTO and with the ICP baseline, prints a table against ground truth, and writes a
figure of predicted vs true contacts on the objects.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("yoto")

DEMO_SEED = 7  # the benchmark's evaluation seed; the shipped weights were fine-tuned on other seeds


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("demo", help="run the whole pipeline on the built-in objects (the main job)")
    parser.add_argument("-n", "--pairs", type=int, default=6, help="dual contacts per object for YOTO")
    parser.add_argument("--icp-pairs", type=int, default=2, help="of which ICP also runs on this many (ICP is slow)")
    parser.add_argument("--checkpoint", help="localizer weights (default: the weights shipped with YOTO)")
    parser.add_argument("--workspace", help="workspace folder (default: $YOTO_WORKSPACE or ./yoto_workspace)")
    parser.add_argument("--out", help="figure path (default: WORKSPACE/demo/demo.png)")
    parser.set_defaults(
        run=lambda args: run_demo(args.pairs, args.icp_pairs, args.checkpoint, args.workspace, args.out)
    )


def run_demo(
    pairs_per_object: int = 6,
    icp_pairs: int = 2,
    checkpoint: str | None = None,
    workspace: str | Path | None = None,
    out: str | Path | None = None,
) -> int:
    from yoto.contacts import SIDES
    from yoto.evaluation.metrics import pose_errors
    from yoto.localize import make_localizer
    from yoto.objects.build import load_object_model
    from yoto.objects.builtin import builtin_object_names
    from yoto.pose.pipeline import estimate_pose
    from yoto.simulate.scenarios import PairSimulator
    from yoto.workspace import workspace_dir

    started = time.perf_counter()
    yoto_localizer = make_localizer("yoto", checkpoint)
    icp_localizer = make_localizer("icp") if icp_pairs > 0 else None
    rows, figure_data = [], []
    for name in builtin_object_names():
        model = load_object_model(name, workspace)
        simulator = PairSimulator(model)
        truths, predictions, icp_predictions = [], [], []
        for index in range(pairs_per_object):
            simulated = simulator.pair(DEMO_SEED, index)
            pair = simulated.pair
            estimate = estimate_pose(pair, model, yoto_localizer)
            errors = pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model)
            contact_errors = [
                1000 * np.linalg.norm(estimate.contacts[side].p_object - simulated.p_object_true[side])
                for side in SIDES
            ]
            row = {
                "object": name,
                "pair": index,
                "contact_mm": contact_errors,
                "yoto": errors,
                "confidence": estimate.confidence,
                "yoto_ms": estimate.latency_ms["localize_left"] + estimate.latency_ms["localize_right"],
            }
            truths += [simulated.p_object_true[side] for side in SIDES]
            predictions += [estimate.contacts[side].p_object for side in SIDES]
            if icp_localizer is not None and index < icp_pairs:
                icp_estimate = estimate_pose(pair, model, icp_localizer)
                row["icp"] = pose_errors(icp_estimate.T_world_mesh, pair.T_world_mesh_true, model)
                row["icp_ms"] = icp_estimate.latency_ms["localize_left"] + icp_estimate.latency_ms["localize_right"]
                icp_predictions += [icp_estimate.contacts[side].p_object for side in SIDES]
            rows.append(row)
        figure_data.append((model, np.array(truths), np.array(predictions), np.array(icp_predictions).reshape(-1, 3)))

    print(format_table(rows))
    path = Path(out) if out else workspace_dir(workspace) / "demo" / "demo.png"
    plot_contacts(figure_data, path)
    print(f"\nFigure of predicted vs true contacts: {path}")
    print(f"Demo finished in {time.perf_counter() - started:.0f} s.")
    return 0


def format_table(rows: list[dict]) -> str:
    lines = [
        "object    pair  contact err L/R (mm)   YOTO pose (mm / deg)   conf   ICP pose (mm / deg)   YOTO ms   ICP ms",
        "-" * 108,
    ]
    for row in rows:
        icp = f"{row['icp']['translation_mm']:7.1f} / {row['icp']['rotation_deg']:6.1f}" if "icp" in row else " " * 16
        icp_ms = f"{row['icp_ms']:8.0f}" if "icp" in row else ""
        lines.append(
            f"{row['object']:<9} {row['pair']:>4}  {row['contact_mm'][0]:8.1f} / {row['contact_mm'][1]:6.1f}     "
            f"{row['yoto']['translation_mm']:7.1f} / {row['yoto']['rotation_deg']:6.1f}       "
            f"{row['confidence']:4.2f}   {icp}       {row['yoto_ms']:7.1f}  {icp_ms}"
        )
    contact = np.concatenate([row["contact_mm"] for row in rows])
    translation = np.array([row["yoto"]["translation_mm"] for row in rows])
    rotation = np.array([row["yoto"]["rotation_deg"] for row in rows])
    lines.append("-" * 108)
    lines.append(
        f"YOTO: contact error median {np.median(contact):.1f} mm, pose error median {np.median(translation):.1f} mm / "
        f"{np.median(rotation):.1f} deg over {len(rows)} pairs"
    )
    with_icp = [row for row in rows if "icp" in row]
    if with_icp:
        icp_t = np.median([row["icp"]["translation_mm"] for row in with_icp])
        icp_r = np.median([row["icp"]["rotation_deg"] for row in with_icp])
        speedup = np.median([row["icp_ms"] for row in with_icp]) / np.median([row["yoto_ms"] for row in with_icp])
        lines.append(
            f"ICP:  pose error median {icp_t:.1f} mm / {icp_r:.1f} deg over {len(with_icp)} pairs; "
            f"YOTO localizes {speedup:.0f}x faster"
        )
    return "\n".join(lines)


def plot_contacts(figure_data: list, path: Path) -> Path:
    """Parent cloud (grey), true contacts (red), YOTO's (blue) and ICP's (orange), two views per object."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from yoto.io import write_bytes_atomic

    figure = plt.figure(figsize=(4.2 * len(figure_data), 8.0))
    for column, (model, truths, predictions, icp_predictions) in enumerate(figure_data):
        cloud = model.points_object[:: max(1, len(model.points_object) // 6000)] * 1000
        for row, (elevation, azimuth) in enumerate(((25, -60), (-20, 120))):
            axis = figure.add_subplot(2, len(figure_data), 1 + column + row * len(figure_data), projection="3d")
            axis.scatter(*cloud.T, s=0.4, c="0.7", alpha=0.35, depthshade=False)
            axis.scatter(*(truths * 1000).T, s=60, c="red", label="true contact", depthshade=False)
            axis.scatter(*(predictions * 1000).T, s=30, c="royalblue", marker="^", label="YOTO", depthshade=False)
            if len(icp_predictions):
                axis.scatter(*(icp_predictions * 1000).T, s=30, c="orange", marker="x", label="ICP", depthshade=False)
            for true, predicted in zip(truths * 1000, predictions * 1000):
                axis.plot(*np.stack([true, predicted]).T, c="royalblue", lw=0.8)
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
