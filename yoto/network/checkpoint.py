"""The localizer checkpoint: a trained network and what the localizer needs besides its weights.

`yoto train` writes one (RUN/model.pt), the localizer reads one (`--checkpoint`, or the shipped
yoto/weights/default.pt). On disk it is a torch archive of plain containers (dicts, lists, numbers, strings,
tensors) with the keys of `LocalizerCheckpoint` plus `format` and `format_version`, loaded with
`weights_only=True` so that opening a checkpoint never runs code. Writes are atomic.
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from yoto.errors import InputError
from yoto.io import write_bytes_atomic
from yoto.network.presets import AnyNetworkConfig, network_config_from_dict

FORMAT_NAME = "yoto-localizer"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class TrainedObject:
    """An object the network was trained on: a model of another build (fingerprint) is not this one."""

    name: str
    fingerprint: str  # ObjectModel.fingerprint
    num_blocks: int  # its blocks (point network) or anchors (anchor-descriptor network)


@dataclass(frozen=True)
class RealPairs:
    """The contact pairs of the fine-tuning stage."""

    digest: str  # hash of the pair files and their clouds (yoto.training.data.pair_files_digest)
    count: int  # contacts (two per pair)


@dataclass(frozen=True)
class Calibration:
    """How candidate scores become beliefs and how many candidates are returned (fitted or set at training)."""

    temperature: float = 1.0  # softmax temperature of the candidates' combined scores
    merge_radius_m: float = 0.005  # candidates closer than this are merged into one
    hypotheses: int = 4  # coarse hypotheses whose best candidates are returned
    test_rotations: int = 1  # in-plane rotations averaged per contact (1: none)


@dataclass
class LocalizerCheckpoint:
    """A trained localizer: network architecture and weights, the objects it knows, how it was made."""

    network_config: AnyNetworkConfig  # architecture (its `kind` says which network)
    state_dict: dict[str, torch.Tensor]  # float32 weights on the CPU
    objects: list[TrainedObject] = field(default_factory=list)  # the objects it was trained on
    train_config: dict[str, Any] = field(default_factory=dict)  # yoto.training TrainConfig.to_dict()
    seed: int = 0  # the training seed
    versions: dict[str, str] = field(default_factory=dict)  # yoto, torch, numpy, python (yoto.provenance)
    real_pairs: RealPairs | None = None  # the stage-2 contacts, None: virtual patches only
    metrics: dict[str, Any] = field(default_factory=dict)  # validation metrics of the final epoch
    calibration: Calibration = Calibration()  # candidate beliefs

    def to_payload(self) -> dict[str, Any]:
        """The on-disk form: plain containers only."""
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "network_config": self.network_config.to_dict(),
            "state_dict": self.state_dict,
            "objects": [asdict(o) for o in self.objects],
            "train_config": self.train_config,
            "seed": self.seed,
            "versions": self.versions,
            "real_pairs": None if self.real_pairs is None else asdict(self.real_pairs),
            "metrics": self.metrics,
            "calibration": asdict(self.calibration),
        }

    @classmethod
    def from_payload(cls, payload: dict[str, Any], path: str | Path | None = None) -> LocalizerCheckpoint:
        """The checkpoint of an on-disk payload; InputError (naming `path`) when it is not a current one."""
        if payload.get("format") != FORMAT_NAME:
            raise InputError(f"not a YOTO localizer checkpoint (format is {payload.get('format')!r})", path)
        if payload.get("format_version") != FORMAT_VERSION:
            raise InputError(
                f"localizer checkpoint format version {payload.get('format_version')} is not supported by this "
                f"YOTO (expects {FORMAT_VERSION}); retrain it with `yoto train`",
                path,
            )
        try:
            real_pairs = payload.get("real_pairs")
            return cls(
                network_config=network_config_from_dict(payload["network_config"]),
                state_dict=dict(payload["state_dict"]),
                objects=[TrainedObject(**o) for o in payload.get("objects", [])],
                train_config=dict(payload.get("train_config", {})),
                seed=int(payload.get("seed", 0)),
                versions=dict(payload.get("versions", {})),
                real_pairs=None if real_pairs is None else RealPairs(**real_pairs),
                metrics=dict(payload.get("metrics", {})),
                calibration=Calibration(**(payload.get("calibration") or {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            problem = f"an incomplete or damaged localizer checkpoint ({exc.__class__.__name__}: {exc})"
            raise InputError(problem, path) from exc

    def save(self, path: str | Path) -> Path:
        return save_torch_atomic(path, self.to_payload())

    @classmethod
    def load(cls, path: str | Path) -> LocalizerCheckpoint:
        return cls.from_payload(load_torch(path, "localizer checkpoint"), path)


def save_torch_atomic(path: str | Path, payload: dict[str, Any]) -> Path:
    """torch.save `payload` to `path` atomically (a reader sees the old file or the new one, never a part)."""
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    return write_bytes_atomic(path, buffer.getvalue())


def load_torch(path: str | Path, kind: str) -> dict[str, Any]:
    """A torch archive of plain containers (`weights_only`: loading runs no code), on the CPU; InputError
    naming the file and the `kind` of file expected when it is missing, unreadable or not a dict."""
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
