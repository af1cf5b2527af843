"""The localization networks' architectures, as named presets.

`paper` is the paper's network (App. C.1; shared point encoder over tactile patches and 54 surface blocks,
cosine coarse matching, a fine head regressing offsets), for a GPU. `cpu-points` is the same network at sizes
chosen for a 2-core CPU. `cpu` is ours (docs/network.md, each change measured): a roll-invariant descriptor of
the contact's height map on polar cells, matched against the same descriptor of anchors every 2 mm on the
object surface (`AnchorNetConfig`); a geometric fine stage then places the contact (yoto.localize.network).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar


@dataclass(frozen=True)
class NetworkConfig:
    """Architecture of the shared point encoder and the coarse/fine heads (the paper's network)."""

    kind: ClassVar[str] = "points"
    coordinate_scale_m: float = 0.01  # point coordinates are divided by this before the encoder (1 cm -> 1.0)
    points_per_patch: int = 512  # tactile points the encoder sees per patch (sub-sampled, repeat-padded)
    points_per_block: int = 512  # surface points the encoder sees per block
    point_dim: int = 256  # width of the point-wise MLP (6-D coordinates + normals in)
    knn_scales: tuple[int, ...] = (8, 16, 32, 64)  # neighbourhood sizes of the multi-scale aggregation
    rotation_invariant: bool = False  # cylindrical point inputs and height-only edge offsets: exactly invariant
    #   to turning the patch about its canonical z axis (the sensor's unknown roll); False: the paper's xyz + normals
    centre_fraction: float = 1.0  # fraction of the points at which neighbourhoods are aggregated (1: every point)
    max_gathered_neighbours: int | None = None  # larger scales are dilated to this many neighbours (None: all)
    edge_dim: int = 256  # output width of each scale's edge function
    fusion_dim: int = 256  # width of the fusion MLP over [point feature, scale features]
    prepool_dim: int = 512  # width of the projection before max+mean pooling
    feature_dim: int = 512  # dimension of a patch or block feature (the matching space)
    fine_feature_dim: int = 0  # >0: a separate projection of this size feeds the fine head (0: the matching feature)
    fine_interaction: bool = False  # fine head input [b, q, b*q, |b-q|] instead of the paper's [b, q]
    initial_temperature: float = 10.0  # tau of the cosine logits at initialisation (learnable)
    max_temperature: float = 100.0  # upper clamp of tau
    candidates: int = 9  # K_nbr: blocks in the candidate pool (the top block and its nearest block centres)
    fine_dims: tuple[int, int] = (512, 256)  # hidden widths of the two-layer fine MLP
    fine_dropout: float = 0.2  # dropout in the fine MLP
    offset_scale_m: float = 0.01  # the fine head's offset output is in units of this (metres)
    fine_encoder_gradient: float = 0.1  # scale of the fine head's gradient into the shared encoder trunk (1: joint)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, **asdict(self)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> NetworkConfig:
        return _from_dict(cls, values, {"knn_scales", "fine_dims"})


@dataclass(frozen=True)
class AnchorNetConfig:
    """The `cpu` network: a descriptor of a contact's height map on polar cells that does not change with the
    sensor's roll, compared by cosine with the descriptors of anchors on the object surface."""

    kind: ClassVar[str] = "anchors"
    rings: int = 8  # polar cells: rings around the contact centre ...
    angles: int = 32  # ... each cut into this many sectors (also the roll step of the fine stage: 360 / angles deg)
    ring_width_m: float = 0.00125  # radial width of a ring (8 rings cover a disc of 10 mm radius)
    harmonics: int = 8  # angular harmonics of each ring that the roll-invariant features keep
    hidden_dims: tuple[int, ...] = (256, 256)  # widths of the MLP over the invariant features
    feature_dim: int = 64  # descriptor dimension (the matching space)
    initial_temperature: float = 20.0  # tau of the cosine logits at initialisation (learnable)
    max_temperature: float = 100.0  # upper clamp of tau
    height_unit_m: float = 0.001  # heights enter the network in this unit
    contact_pixel_m: float = 0.0002  # pixel of the tactile cloud's height image (coarser for sparser clouds)
    contact_erode_px: int = 1  # the height image's rim is eroded by this many pixels (the rim is gel, not object)
    anchor_spacing_m: float = 0.002  # anchors: one parent point per voxel of this size
    anchor_normal_neighbours: int = 50  # k of an anchor's aggregated normal (smooth, stable)
    press_depth_m: float = 0.001  # an anchor's descriptor sees the cells a press this deep along its normal touches
    ray_start_m: float = 0.005  # anchor height rays start this far in front of the anchor's tangent plane
    ray_reach_m: float = 0.005  # surface further than this behind the tangent plane counts as absent

    def __post_init__(self):
        if self.rings < 2 or self.angles < 8 or not 1 <= self.harmonics <= self.angles // 2:
            raise ValueError("need rings >= 2, angles >= 8 and 1 <= harmonics <= angles / 2")

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, **asdict(self)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> AnchorNetConfig:
        return _from_dict(cls, values, {"hidden_dims"})


AnyNetworkConfig = NetworkConfig | AnchorNetConfig


def _from_dict(cls: Any, values: dict[str, Any], tuples: set[str]) -> Any:
    values = {k: v for k, v in values.items() if k != "kind"}
    unknown = sorted(set(values) - {f.name for f in fields(cls)})
    if unknown:
        raise ValueError(f"unknown network config keys {unknown}")
    return cls(**{k: tuple(v) if k in tuples else v for k, v in values.items()})


def network_config_from_dict(values: dict[str, Any]) -> AnyNetworkConfig:
    """The config of a stored dict, by its `kind` (stored configs without one are the point network's)."""
    kinds: dict[str, Any] = {"points": NetworkConfig, "anchors": AnchorNetConfig}
    kind = values.get("kind", "points")
    if kind not in kinds:
        raise ValueError(f"unknown network kind {kind!r} (known: {', '.join(kinds)})")
    return kinds[kind].from_dict(values)


# The paper's network (App. C.1): 256-D point MLP, k in {8,16,32,64}, 256 fusion, 512 pre-pool, 512-D features,
# 512 points per patch and per block, fine MLP 1024 -> 512 -> 256.
PAPER = NetworkConfig()
# The paper's network made fast on a 2-core CPU (the previous `cpu` preset, the first row of the ablation): fewer
# points and narrower layers; same scales, shared kNN, per-point linear edge terms.
CPU_POINTS = NetworkConfig(
    rotation_invariant=True,
    points_per_patch=128,
    points_per_block=256,
    centre_fraction=0.25,
    max_gathered_neighbours=16,
    point_dim=64,
    edge_dim=32,
    fusion_dim=128,
    prepool_dim=128,
    feature_dim=128,
    fine_dims=(256, 128),
)
# Ours, for a 2-core CPU (docs/network.md): polar height maps, roll-invariant features, descriptors over anchors.
CPU = AnchorNetConfig()

PRESETS: dict[str, AnyNetworkConfig] = {"paper": PAPER, "cpu": CPU, "cpu-points": CPU_POINTS}
