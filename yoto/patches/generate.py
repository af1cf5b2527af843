"""The virtual-patch stage: object model -> labelled virtual patch dataset file in the workspace."""

from __future__ import annotations

import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np

from yoto.errors import InputError
from yoto.objects.build import load_object_model
from yoto.patches.virtual import VirtualPatchConfig, VirtualPatchDataset, generate_virtual_patches
from yoto.workspace import patch_dataset_path

log = logging.getLogger("yoto")


def generate_patches(
    object_name: str,
    config: VirtualPatchConfig = VirtualPatchConfig(),
    workspace: str | Path | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Generate (or keep, if up to date) the virtual patch dataset of one object; returns its path."""
    model = load_object_model(object_name, workspace)
    path = patch_dataset_path(model.name, workspace)
    if path.exists() and not overwrite:
        try:
            existing = VirtualPatchDataset.load(path, model)
            if existing.meta.get("config") == {
                k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()
            }:
                log.info("%s: up to date, kept (pass --overwrite to regenerate)", path)
                return path
        except InputError as exc:
            log.info("%s: regenerating (%s)", path, exc.problem)
    dataset = generate_virtual_patches(model, config, workers=workers, progress=progress)
    dataset.save(path)
    return path


def statistics_table(object_names: list[str], workspace: str | Path | None = None) -> str:
    """Per-object dataset statistics as the paper's Table 6, in Markdown."""
    rows = [
        "| Object | Parent cloud N | Bbox (mm) | Valid blocks | Virtual patches | Patch radius (mm) |",
        "|---|---:|---|---|---:|---:|",
    ]
    total = 0
    for name in object_names:
        model = load_object_model(name, workspace)
        dataset = VirtualPatchDataset.load(patch_dataset_path(model.name, workspace), model)
        grid = int(np.prod(model.meta["build_config"]["grid_shape"]))
        bbox = " x ".join(f"{v * 1000:.1f}" for v in model.meta["bbox_object_m"])
        counts = dataset.counts()
        total += counts["accepted"]
        rows.append(
            f"| {model.name} | {len(model.points_object):,} | {bbox} | {model.num_blocks} / {grid} | "
            f"{counts['accepted']:,} / {counts['attempted']:,} | {np.median(dataset.radius_m) * 1000:.1f} |"
        )
    rows.append(f"| Total | | | | {total:,} | |")
    return "\n".join(rows)
