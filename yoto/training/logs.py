"""A run's logs for people and tools: log.jsonl, log.csv, curves.png, and a line per epoch."""

from __future__ import annotations

import csv
import io
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from yoto.io import write_bytes_atomic, write_text_atomic

log = logging.getLogger("yoto")


def write_logs(run_dir: Path, history: list[dict[str, Any]]) -> None:
    """log.jsonl (one record per epoch) and log.csv (their flat fields, for spreadsheets and plotting)."""
    write_text_atomic(run_dir / "log.jsonl", "".join(json.dumps(record) + "\n" for record in history))
    flat_rows = []
    for record in history:
        flat_rows.append({k: v for k, v in record.items() if not isinstance(v, dict | list)})
    columns: list[str] = []
    for row in flat_rows:
        columns.extend(c for c in row if c not in columns)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns)
    writer.writeheader()
    writer.writerows(flat_rows)
    write_text_atomic(run_dir / "log.csv", buffer.getvalue())


def plot_curves(run_dir: Path, history: list[dict[str, Any]]) -> Path | None:
    """curves.png: training loss, block recall and localization error per epoch."""
    if not history:
        return None
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    x = np.arange(1, len(history) + 1)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    axes[0].plot(x, [r["train_loss"] for r in history], label="total")
    for part in ("train_cls", "train_pos", "train_select"):
        axes[0].plot(x, [r[part] for r in history], label=part.removeprefix("train_"), alpha=0.7)
    axes[0].set(title="training loss", xlabel="epoch", yscale="log")
    for kind in ("virtual", "press", "real"):
        if f"val_{kind}_top1" in history[-1]:
            axes[1].plot(x, [r.get(f"val_{kind}_top1", np.nan) for r in history], label=f"{kind} top-1")
            axes[1].plot(x, [r.get(f"val_{kind}_topk", np.nan) for r in history], "--", label=f"{kind} top-K")
            axes[2].plot(x, [r.get(f"val_{kind}_error_mean_mm", np.nan) for r in history], label=f"{kind}")
    axes[1].set(title="block recall (validation)", xlabel="epoch", ylim=(0, 1))
    axes[2].set(title="localization error, mean (mm)", xlabel="epoch", yscale="log")
    stage_changes = [i + 1 for i in range(1, len(history)) if history[i]["stage"] != history[i - 1]["stage"]]
    for ax in axes:
        for change in stage_changes:
            ax.axvline(change - 0.5, color="grey", lw=0.8, ls=":")
        ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return write_bytes_atomic(run_dir / "curves.png", buffer.getvalue())


def log_epoch(record: dict[str, Any]) -> None:
    """One line per epoch: training loss and speed, validation metrics per kind."""
    text = (
        f"{record['stage']} epoch {record['epoch']}: loss {record['train_loss']:.3f} "
        f"({record['samples_per_s']:.0f} samples/s, tau {record['temperature']:.1f})"
    )
    for kind in ("virtual", "press", "real"):
        if f"val_{kind}_top1" in record:
            text += (
                f" | val {kind}: top-1 {record[f'val_{kind}_top1']:.2f}, top-K {record[f'val_{kind}_topk']:.2f}, "
                f"error {record[f'val_{kind}_error_mean_mm']:.1f} mm, <=5mm {record[f'val_{kind}_within_5mm']:.2f}"
            )
    log.info(text)


def log_descriptor_epoch(record: dict[str, Any]) -> None:
    """One line per epoch of the anchor-descriptor network: loss, speed, retrieval on the validation contacts."""
    text = (
        f"{record['stage']} epoch {record['epoch']}: loss {record['train_loss']:.3f} "
        f"({record['samples_per_s']:.0f} samples/s, tau {record['temperature']:.1f})"
    )
    for kind in ("virtual", "real"):
        if f"val_{kind}_recall_at_1" in record:
            recalls = ", ".join(
                f"@{key.rsplit('_', 1)[1]} {value:.2f}"
                for key, value in record.items()
                if key.startswith(f"val_{kind}_recall_at_")
            )
            text += f" | val {kind}: recall {recalls}, top-1 {record[f'val_{kind}_top1_error_mean_mm']:.1f} mm"
    log.info(text)


def plot_descriptor_curves(run_dir: Path, history: list[dict[str, Any]]) -> Path | None:
    """curves.png of the anchor-descriptor network: training loss, anchor recall and top-1 error per epoch."""
    if not history:
        return None
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    x = np.arange(1, len(history) + 1)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    axes[0].plot(x, [r["train_loss"] for r in history])
    axes[0].set(title="training loss", xlabel="epoch", yscale="log")
    for kind, style in (("virtual", "-"), ("real", "--")):
        keys = sorted(
            (k for k in history[-1] if k.startswith(f"val_{kind}_recall_at_")), key=lambda k: int(k.rsplit("_", 1)[1])
        )
        for key in keys:
            axes[1].plot(x, [r.get(key, np.nan) for r in history], style, label=f"{kind} @{key.rsplit('_', 1)[1]}")
        if f"val_{kind}_top1_error_mean_mm" in history[-1]:
            axes[2].plot(x, [r.get(f"val_{kind}_top1_error_mean_mm", np.nan) for r in history], style, label=kind)
    axes[1].set(title="a right anchor among the best k (validation)", xlabel="epoch", ylim=(0, 1))
    axes[2].set(title="best anchor's error, mean (mm)", xlabel="epoch", yscale="log")
    stage_changes = [i + 1 for i in range(1, len(history)) if history[i]["stage"] != history[i - 1]["stage"]]
    for ax in axes:
        for change in stage_changes:
            ax.axvline(change - 0.5, color="grey", lw=0.8, ls=":")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return write_bytes_atomic(run_dir / "curves.png", buffer.getvalue())
