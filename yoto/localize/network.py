"""The YOTO localizers: a trained network locates a tactile contact on an object model.

`load_localizer(checkpoint)` returns the localizer of the checkpoint's network: `NetworkLocalizer` below for the
paper's point network (`paper`, `cpu-points` presets), `DescriptorLocalizer` (yoto.localize.descriptor) for the
anchor-descriptor network (`cpu` preset).

The point network, per contact: prepare the sensor cloud (parent density, normals) -> canonicalize -> fixed
point sample -> encoder -> cosine scores against the object's cached block features -> fine head on the candidate
pools of the top few coarse blocks -> ranked candidates with beliefs (yoto.network.candidates). Block features are
computed once per object model (keyed by its fingerprint) and reused for every later contact.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch

from yoto.contacts import ContactEstimate
from yoto.errors import InputError
from yoto.network.candidates import candidates_of, rank_hypotheses, rotated_copies
from yoto.network.checkpoint import Calibration, LocalizerCheckpoint, TrainedObject
from yoto.network.inputs import BlockSet, inference_points, make_block_set
from yoto.network.model import ContactLocalizationNet
from yoto.network.presets import AnchorNetConfig, NetworkConfig
from yoto.objects.model import ObjectModel
from yoto.patches.canonical import canonicalize_patch, prepare_tactile_cloud

log = logging.getLogger("yoto")

DEFAULT_WEIGHTS = "default.pt"
TRAIN_COMMAND = "yoto train --objects tool fruit figurine --preset cpu --real-pairs DIR"


def default_checkpoint_path() -> Path:
    """Where the shipped default weights live (yoto/weights/default.pt)."""
    return Path(str(resources.files("yoto") / "weights" / DEFAULT_WEIGHTS))


class UnknownObjectWarning(UserWarning):
    """The object was not among the checkpoint's training objects."""


def is_trained_object(
    model: ObjectModel, trained_objects: list[TrainedObject], fallback: str, anchors: int | None = None
) -> bool:
    """Whether the localizer was trained on this model: this very build (its fingerprint), or, where `anchors` is
    given, a build of the same name with the same number of anchors (the fingerprint hashes every point's last bit,
    which another build of the same geometry can change; a changed surface changes its anchor count). Warns
    (UnknownObjectWarning) when not, saying what the localizer does instead (`fallback`)."""
    for trained in trained_objects:
        if trained.fingerprint == model.fingerprint:
            return True
        if anchors is not None and (trained.name, trained.num_blocks) == (model.name, anchors):
            return True
    names = sorted({trained.name for trained in trained_objects})
    warnings.warn(
        f"object {model.name!r} ({model.fingerprint}) is not one this localizer was trained on "
        f"({', '.join(names) or 'unknown'}): "
        + ("a model of that name but another build (rebuilt, other points or blocks); " if model.name in names else "")
        + f"{fallback}, but expect lower accuracy; train on it with `yoto train --objects ...`",
        UnknownObjectWarning,
        stacklevel=4,
    )
    return False


def checkpoint_path(path: str | Path | None) -> Path:
    """`path`, or the shipped default weights when None (InputError saying how to train them if absent)."""
    if path is not None:
        return Path(path)
    path = default_checkpoint_path()
    if not path.is_file():
        raise InputError(
            "no default localizer weights are installed with this copy of YOTO; train them with "
            f"`{TRAIN_COMMAND}` and pass the run's model.pt as --checkpoint (see docs/network.md)",
            path,
        )
    return path


def load_localizer(path: str | Path | None = None, **kwargs: Any) -> Any:
    """The localizer of a checkpoint written by `yoto train` (None: the weights shipped with YOTO): a
    `NetworkLocalizer` for the point network, a `DescriptorLocalizer` for the anchor-descriptor network."""
    path = checkpoint_path(path)
    checkpoint = LocalizerCheckpoint.load(path)
    if isinstance(checkpoint.network_config, AnchorNetConfig):
        from yoto.localize.descriptor import DescriptorLocalizer
        from yoto.network.descriptor import DescriptorNet

        descriptor_net = DescriptorNet(checkpoint.network_config)
        _load_weights(descriptor_net, checkpoint, path)
        return DescriptorLocalizer(descriptor_net, checkpoint, source=path, **kwargs)
    net = ContactLocalizationNet(checkpoint.network_config)
    _load_weights(net, checkpoint, path)
    return NetworkLocalizer(net, checkpoint, source=path, **kwargs)


def _load_weights(net: torch.nn.Module, checkpoint: LocalizerCheckpoint, path: Path) -> None:
    try:
        net.load_state_dict(checkpoint.state_dict)
    except RuntimeError as exc:
        raise InputError(f"checkpoint weights do not fit its network config ({exc})", path) from exc


@dataclass
class _ObjectCache:
    blocks: BlockSet
    tensors: dict[str, torch.Tensor]  # the blocks' entries of the network's input
    features: torch.Tensor  # (NB, D)
    trained: bool


class NetworkLocalizer:
    """Locates a tactile contact with the trained network; implements yoto.localize.ContactLocalizer."""

    name = "yoto"
    needs_ground_truth = False

    def __init__(
        self,
        net: ContactLocalizationNet,
        checkpoint: LocalizerCheckpoint | None = None,
        hypotheses: int | None = None,
        rotations: int | None = None,
        temperature: float | None = None,
        merge_radius_m: float | None = None,
        source: str | Path | None = None,
    ):
        self.net = net.eval()
        self.config: NetworkConfig = net.config
        calibration = checkpoint.calibration if checkpoint is not None else Calibration()
        self.hypotheses = int(hypotheses or calibration.hypotheses)
        self.rotations = max(1, int(rotations or calibration.test_rotations))
        self.temperature = float(temperature or calibration.temperature)
        self.merge_radius_m = float(merge_radius_m or calibration.merge_radius_m)
        self.trained_objects = list(checkpoint.objects) if checkpoint is not None else []
        self.source = source
        self._cache: dict[str, _ObjectCache] = {}

    # ------------------------------------------------------------------------------------------ loading
    @classmethod
    def from_checkpoint(cls, path: str | Path | None = None, **kwargs: Any) -> NetworkLocalizer:
        """Load a point-network checkpoint written by `yoto train`; None loads the weights shipped with YOTO."""
        localizer = load_localizer(path, **kwargs)
        if not isinstance(localizer, cls):
            raise InputError(
                "this checkpoint holds the anchor-descriptor network (`cpu` preset), not the point network; "
                "load it with yoto.localize.network.load_localizer",
                checkpoint_path(path),
            )
        return localizer

    # ------------------------------------------------------------------------------------------- blocks
    def prepare_object(self, model: ObjectModel) -> _ObjectCache:
        """Encode the object's blocks once; later calls for the same model (fingerprint) reuse them."""
        cached = self._cache.get(model.fingerprint)
        if cached is not None:
            return cached
        trained = is_trained_object(model, self.trained_objects, "its blocks are encoded by the shared encoder")
        blocks = make_block_set(model, self.config)
        tensors = blocks.tensors()
        with torch.inference_mode():
            features = self.net.encode(tensors["block_points"], tensors["block_normals"])
        cached = _ObjectCache(blocks=blocks, tensors=tensors, features=features, trained=trained)
        self._cache[model.fingerprint] = cached
        return cached

    # ------------------------------------------------------------------------------------------ localize
    def canonical_patch(self, points_sensor: np.ndarray, model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
        """A tactile cloud prepared (parent density, normals) and canonicalized: points and normals."""
        points, normals = prepare_tactile_cloud(np.asarray(points_sensor, dtype=np.float64), model.point_spacing_m)
        canonical = canonicalize_patch(points, normals)
        return canonical.points, canonical.normals

    def canonical_input(self, points_sensor: np.ndarray, model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
        """The network's input for a tactile cloud: prepared, canonicalized, sampled to a fixed size."""
        return inference_points(*self.canonical_patch(points_sensor, model), self.config.points_per_patch)

    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        """Candidate contacts on `model` (object frame), best first (see yoto.network.candidates)."""
        return self.localize_many([points_sensor], model)[0]

    def localize_many(self, clouds: list[np.ndarray], model: ObjectModel) -> list[list[ContactEstimate]]:
        """`localize` for several tactile clouds of one object, in one network pass."""
        cache = self.prepare_object(model)
        patches = [self.canonical_patch(cloud, model) for cloud in clouds]
        inputs = [
            rotated_copies(*inference_points(p, n, self.config.points_per_patch), self.rotations) for p, n in patches
        ]
        points = torch.from_numpy(np.concatenate([i[0] for i in inputs]))
        normals = torch.from_numpy(np.concatenate([i[1] for i in inputs]))
        with torch.inference_mode():
            features = self.net.encode(points, normals).reshape(len(clouds), self.rotations, -1)
            ranking = rank_hypotheses(self.net, features, cache.features, cache.tensors, self.hypotheses)
        results = []
        for index in range(len(clouds)):
            top = np.argsort(-ranking["logits"][index])[: self.config.candidates]
            details_common = {
                "coarse_top_blocks": [int(b) for b in top],
                "coarse_top_logits": [round(float(ranking["logits"][index, b]), 4) for b in top],
                "temperature": round(float(self.net.temperature.detach()), 4),
                "trained_object": cache.trained,
            }
            found = candidates_of(ranking, index, self.temperature, self.merge_radius_m)
            estimates = []
            for candidate in found:
                estimates.append(
                    ContactEstimate(
                        p_object=candidate.p_object,
                        n_object=model.aggregated_normal(candidate.p_object, 20),
                        block=candidate.block,
                        score=candidate.score,
                        probability=candidate.probability,
                        details={
                            "coarse_score": round(candidate.coarse, 4),
                            "fine_confidence": round(candidate.confidence, 4),
                            "hypothesis": candidate.hypothesis,
                            **details_common,
                        },
                    )
                )
            results.append(estimates)
        return results


def measure_latency(
    localizer: NetworkLocalizer, clouds: list[np.ndarray], model: ObjectModel, warmup: int = 1, repeats: int = 1
) -> dict[str, float]:
    """Per-contact latency the paper's way: each call timed end to end (prepare, canonicalize, network,
    candidates), the first `warmup` calls (and the block encoding) excluded. Returns median, p90, mean (ms)."""
    localizer.prepare_object(model)
    for cloud in clouds[:warmup]:
        localizer.localize(cloud, model)
    times = []
    for _ in range(repeats):
        for cloud in clouds:
            tick = time.perf_counter()
            localizer.localize(cloud, model)
            times.append(1000.0 * (time.perf_counter() - tick))
    array = np.array(times)
    return {
        "calls": len(times),
        "median_ms": float(np.median(array)),
        "p90_ms": float(np.percentile(array, 90)),
        "mean_ms": float(array.mean()),
    }
