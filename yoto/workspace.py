"""Where YOTO keeps what it builds: object models, patch datasets, checkpoints, results.

The workspace is a folder (default `./yoto_workspace`, or $YOTO_WORKSPACE, or --workspace):
    objects/NAME.npz          object models            (yoto object build)
    patches/NAME.npz          virtual patch datasets    (yoto patches generate)
    pairs/NAME/pair_*.json    simulated contact pairs   (yoto simulate pairs)
    runs/RUN/                 training runs: checkpoints, logs
"""

from __future__ import annotations

import os
from pathlib import Path

DEFAULT_WORKSPACE = "yoto_workspace"


def workspace_dir(override: str | Path | None = None) -> Path:
    return Path(override or os.environ.get("YOTO_WORKSPACE") or DEFAULT_WORKSPACE)


def object_model_path(name: str, workspace: str | Path | None = None) -> Path:
    return workspace_dir(workspace) / "objects" / f"{name}.npz"


def patch_dataset_path(name: str, workspace: str | Path | None = None) -> Path:
    return workspace_dir(workspace) / "patches" / f"{name}.npz"


def pairs_dir(name: str, workspace: str | Path | None = None) -> Path:
    return workspace_dir(workspace) / "pairs" / name


def runs_dir(workspace: str | Path | None = None) -> Path:
    return workspace_dir(workspace) / "runs"
