"""Sizes of the contact localization network (paper App. C.1), as named presets.

`paper` is the paper's network, for a GPU. `cpu` keeps the paper's structure (shared encoder with
multi-scale kNN aggregation, cosine coarse matching, 9-block candidate pool, MLP fine head) at sizes
chosen by measurement so that training and inference are fast on a 2-core CPU (docs/network.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any


@dataclass(frozen=True)
class NetworkConfig:
    """Architecture of the shared point encoder and the coarse/fine heads."""

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
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> NetworkConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown network config keys {unknown}")
        tuples = {"knn_scales", "fine_dims"}
        typed: dict[str, Any] = {k: tuple(v) if k in tuples else v for k, v in values.items()}
        return cls(**typed)


PRESETS: dict[str, NetworkConfig] = {
    # The paper's network (App. C.1): 256-D point MLP, k in {8,16,32,64}, 256 fusion, 512 pre-pool, 512-D features,
    # 512 points per patch and per block, fine MLP 1024 -> 512 -> 256.
    "paper": NetworkConfig(),
    # Fast on a 2-core CPU: fewer points and narrower layers; same scales, shared kNN, per-point linear edge terms.
    "cpu": NetworkConfig(
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
    ),
}
