"""What decides a training run: `TrainConfig` (recorded in the checkpoint) and its named presets."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from yoto.errors import InputError
from yoto.network.presets import CPU_POINTS, PAPER, AnchorNetConfig, NetworkConfig
from yoto.training.augment import AugmentConfig
from yoto.training.losses import LossConfig
from yoto.training.press import PressPatchConfig
from yoto.training.virtual_contacts import VirtualContactConfig


@dataclass(frozen=True)
class StageConfig:
    """One training stage."""

    epochs: int  # passes over the stage's sample pool
    lr: float  # peak learning rate (OneCycle max_lr) of the heads and the temperature
    encoder_lr: float  # peak learning rate of the shared encoder
    real_oversample: int = 0  # each real contact appears this many times per epoch (paper stage 2: 10)
    real_weight: float = 1.0  # per-sample loss weight of real contacts (paper stage 2: 2.0)
    virtual_fraction: float = 1.0  # fraction of the virtual training patches drawn per epoch (fresh each epoch)


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides what `train` produces for the point network (recorded in the checkpoint)."""

    network: NetworkConfig = field(default_factory=NetworkConfig)  # architecture
    stage1: StageConfig = StageConfig(epochs=500, lr=2e-3, encoder_lr=1e-4)  # virtual pre-training
    stage2: StageConfig = StageConfig(  # fine-tuning on virtual + real contacts (runs only with real contacts)
        epochs=400, lr=4e-4, encoder_lr=1e-5, real_oversample=10, real_weight=2.0
    )
    batch_size: int = 32  # patches per step (all of one object)
    weight_decay: float = 0.01  # AdamW, on weight matrices (not on biases, norms or the temperature)
    pct_start: float = 0.1  # OneCycle warm-up fraction
    div_factor: float = 10.0  # OneCycle initial lr = max_lr / div_factor
    final_div_factor: float = 1000.0  # OneCycle final lr = initial lr / final_div_factor
    grad_clip_norm: float | None = None  # clip the gradient norm at this (None: no clipping)
    block_refresh_every: int = 1  # re-encode (with gradients) an object's blocks every n-th of its steps
    augment: AugmentConfig = AugmentConfig()  # per-step patch augmentations
    loss: LossConfig = LossConfig()  # loss weights
    precision: str = "auto"  # "auto": bf16 autocast on a GPU that supports it, else fp32; or "fp32", "bf16"
    seed: int = 0  # initialisation, data order and augmentation
    val_fraction: float = 0.05  # of each object's virtual patches, held out for validation
    val_max_per_object: int = 300  # at most this many virtual validation patches per object
    max_virtual_per_object: int | None = None  # use only this many virtual patches per object (None: all)
    press: PressPatchConfig = PressPatchConfig(count=0)  # press-shaped virtual patches per object (0: none)
    ball_patches: bool = True  # train on the paper's ball patches (False: press-shaped ones only)
    hypotheses: int = 4  # coarse hypotheses whose best candidates the localizer returns
    test_rotations: int = 1  # in-plane rotations averaged at validation and inference (1: none)
    merge_radius_m: float = 0.005  # candidates closer than this are merged into one

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        values = dict(values)
        augment = _lists_as_tuples(values.pop("augment", {}))
        loss = values.pop("loss", {})
        press = _lists_as_tuples(values.pop("press", {"count": 0}))
        return cls(
            network=NetworkConfig.from_dict(values.pop("network")),
            stage1=StageConfig(**values.pop("stage1")),
            stage2=StageConfig(**values.pop("stage2")),
            augment=AugmentConfig(**augment),
            loss=LossConfig(**loss),
            press=PressPatchConfig(**press),
            **values,
        )


def _lists_as_tuples(values: dict[str, Any]) -> dict[str, Any]:
    """JSON turned the tuple fields (ranges, sizes) into lists; turn them back."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}


@dataclass(frozen=True)
class DescriptorTrainConfig:
    """Everything that decides what `train` produces for the anchor-descriptor network (`cpu` preset)."""

    network: AnchorNetConfig = field(default_factory=AnchorNetConfig)  # architecture and its inputs
    stage1: StageConfig = StageConfig(epochs=20, lr=2e-3, encoder_lr=2e-3)  # virtual pre-training
    stage2: StageConfig = StageConfig(  # fine-tuning on virtual + real contacts (runs only with real contacts)
        epochs=5, lr=5e-4, encoder_lr=5e-4, real_oversample=10, real_weight=2.0, virtual_fraction=0.25
    )
    batch_size: int = 256  # contacts per step (all of one object)
    weight_decay: float = 1e-4  # AdamW, on weight matrices
    pct_start: float = 0.1  # OneCycle warm-up fraction
    div_factor: float = 10.0  # OneCycle initial lr = max_lr / div_factor
    final_div_factor: float = 100.0  # OneCycle final lr = initial lr / final_div_factor
    positive_radius_m: float = 0.0025  # anchors this close to the true contact location are right answers
    hard_negatives: int = 8  # per contact, the wrong anchors it scores highest join the step's candidate set ...
    random_negatives: int = 512  # ... with this many anchors drawn at random
    bank_refresh_every: int = 10  # steps of an object between re-describing all of its anchors (to find the hardest)
    virtual: VirtualContactConfig = VirtualContactConfig()  # the virtual contacts of stage 1
    precision: str = "auto"  # "auto": bf16 autocast on a GPU that supports it, else fp32; or "fp32", "bf16"
    seed: int = 0  # initialisation, data order
    val_fraction: float = 0.05  # of each object's virtual contacts, held out for validation
    val_max_per_object: int = 300  # at most this many virtual validation contacts per object

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DescriptorTrainConfig:
        values = dict(values)
        return cls(
            network=AnchorNetConfig.from_dict(values.pop("network")),
            stage1=StageConfig(**values.pop("stage1")),
            stage2=StageConfig(**values.pop("stage2")),
            virtual=VirtualContactConfig(**_lists_as_tuples(values.pop("virtual"))),
            **values,
        )


AnyTrainConfig = TrainConfig | DescriptorTrainConfig


PRESETS: dict[str, AnyTrainConfig] = {
    # Every number from the paper (App. C.2): 500 + 400 epochs, batch 32, lr 2e-3 / 1e-4 (encoder), then
    # 4e-4 / 1e-5, real contacts over-sampled 10x and weighted 2.0, bf16 on a GPU.
    "paper": TrainConfig(network=PAPER),
    # Ours, for a 2-core CPU (docs/network.md): descriptors of polar height maps over anchors.
    "cpu": DescriptorTrainConfig(),
    # The paper's network at CPU sizes (the previous `cpu` preset); sizes and rates chosen by measurement.
    "cpu-points": TrainConfig(
        network=CPU_POINTS,
        stage1=StageConfig(epochs=14, lr=2e-3, encoder_lr=1e-3),
        stage2=StageConfig(
            epochs=4, lr=4e-4, encoder_lr=2e-4, real_oversample=10, real_weight=2.0, virtual_fraction=0.25
        ),
        batch_size=128,
        # The 0.2 mm voxel grid removes ~8% of a virtual patch's points (near-duplicates of a 0.45 mm-spaced
        # cloud); with 128 of ~900 points sampled that changes nothing measurable but costs 0.3 ms a patch.
        augment=AugmentConfig(voxel_size_m=0.0, rotation_prob=1.0, rotation_max_rad=3.141592653589793),
        # Press-shaped virtual patches instead of balls: on held-out simulated contacts of the fruit they gave
        # the best block recall and error of the patch kinds measured (docs/network.md).
        press=PressPatchConfig(count=8700),
        ball_patches=False,
    ),
}


def preset(name: str) -> AnyTrainConfig:
    if name not in PRESETS:
        raise InputError(f"unknown training preset {name!r} (presets: {', '.join(PRESETS)})")
    return PRESETS[name]


def with_overrides(config: AnyTrainConfig, **stage_epochs: int | None) -> AnyTrainConfig:
    """A copy with stage epochs replaced where given (CLI --stage1-epochs / --stage2-epochs)."""
    for key in ("stage1", "stage2"):
        epochs = stage_epochs.get(f"{key}_epochs")
        if epochs is not None:
            config = replace(config, **{key: replace(getattr(config, key), epochs=int(epochs))})
    return config
