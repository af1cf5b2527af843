"""Checkpoint files: the trained localizer (model.pt) and the resumable training state (state.pt).

Both are torch archives of plain containers (dicts, lists, numbers, strings, tensors), loaded with
`weights_only=True` so that opening a checkpoint never runs code. Writes are atomic.

A localizer checkpoint holds:
    format, format_version                "yoto-localizer", 1
    network_config                        NetworkConfig as a dict
    state_dict                            float32 weights
    objects                               [{"name", "fingerprint", "num_blocks"}] the objects it was trained on
    train_config, seed, versions          how it was made (TrainConfig dict, seed, yoto/torch/numpy/python)
    real_pairs                            {"digest", "count"} of the stage-2 contacts, or None
    metrics                               validation metrics of the final epoch
    calibration                           {"temperature", "merge_radius_m", "hypotheses"} for candidate beliefs
"""

from __future__ import annotations

import io
import platform
from pathlib import Path
from typing import Any

import numpy as np

from yoto import __version__
from yoto.errors import InputError, require_torch
from yoto.io import write_bytes_atomic

FORMAT_NAME = "yoto-localizer"
FORMAT_VERSION = 1
STATE_FORMAT_NAME = "yoto-training-state"


def versions() -> dict[str, str]:
    torch = require_torch("reading versions")
    return {
        "yoto": __version__,
        "torch": str(torch.__version__),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def save_torch_atomic(path: str | Path, payload: dict[str, Any]) -> Path:
    torch = require_torch("saving a checkpoint")
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return write_bytes_atomic(path, buffer.getvalue())


def load_torch(path: str | Path, kind: str) -> dict[str, Any]:
    torch = require_torch("loading a checkpoint")
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{kind} not found", path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for corrupt or foreign files
        raise InputError(f"not a readable {kind} ({exc.__class__.__name__}: {exc})", path) from exc
    if not isinstance(payload, dict):
        raise InputError(f"not a YOTO {kind}", path)
    return payload


def load_localizer_checkpoint(path: str | Path) -> dict[str, Any]:
    payload = load_torch(path, "localizer checkpoint")
    if payload.get("format") != FORMAT_NAME:
        raise InputError(f"not a YOTO localizer checkpoint (format is {payload.get('format')!r})", path)
    if payload.get("format_version") != FORMAT_VERSION:
        raise InputError(
            f"localizer checkpoint format version {payload.get('format_version')} is not supported by this YOTO "
            f"(expects {FORMAT_VERSION}); retrain it with `yoto train`",
            path,
        )
    return payload
