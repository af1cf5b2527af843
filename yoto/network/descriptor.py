"""The `cpu` network: a roll-invariant descriptor of a polar height map, in one file.

    polar map (B, 2, R, T): heights (in height_unit_m, 0 off the surface) and coverage, R rings x T sectors
      -> angular spectrum of each ring: H_r(k), C_r(k) for k = 0..K (heights and coverage)          exact roll
      -> invariants: |H_r(k)|, |C_r(k)|, H_r(k) conj H_r+1(k), H_r(k) conj C_r(k), C_r(k) conj C_r+1(k)   invariance
      -> signed square root, LayerNorm, MLP                                                          (B, D)
      -> unit descriptor q;   coarse logits a_i = tau cos(q, b_i) against the anchors' descriptors b_i

Rolling the sensor by s sectors multiplies every coefficient of harmonic k by exp(-2 pi i k s / T): magnitudes and
products of one coefficient with the conjugate of another of the same harmonic do not change. The products tie
neighbouring rings (and heights to coverage) together, so the features keep the relative phase of the rings, which
magnitudes alone lose. The same network describes contacts and anchors (the paper's shared encoder); cost per map
is one small FFT and a ~0.2 M multiply-add MLP, so all anchors of an object are described in a fraction of a second.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from yoto.network.presets import AnchorNetConfig


def invariant_feature_count(config: AnchorNetConfig) -> int:
    rings, harmonics = config.rings, config.harmonics
    return 2 * rings * (harmonics + 1) + 2 * harmonics * (2 * (rings - 1) + rings)


def invariant_features(maps: torch.Tensor, harmonics: int) -> torch.Tensor:
    """(B, F) roll-invariant features of polar maps (B, 2, R, T) (module docstring), signed square roots."""
    angles = maps.shape[-1]
    coverage = maps[:, 1].float()
    spectra = torch.fft.rfft(torch.stack([maps[:, 0].float() * coverage, coverage], dim=1), dim=-1) / angles
    heights, cover = spectra[:, 0, :, : harmonics + 1], spectra[:, 1, :, : harmonics + 1]
    h, c = heights[..., 1:], cover[..., 1:]  # the mean (k = 0) has no phase: its magnitude says it all
    parts = [
        heights.abs(),
        cover.abs(),
        torch.view_as_real(h[:, :-1] * h[:, 1:].conj()),
        torch.view_as_real(h * c.conj()),
        torch.view_as_real(c[:, :-1] * c[:, 1:].conj()),
    ]
    features = torch.cat([part.flatten(1) for part in parts], dim=1)
    return features.sign() * features.abs().sqrt()


class DescriptorNet(nn.Module):
    """Roll-invariant features -> MLP -> unit descriptor; cosine logits with a learnable temperature."""

    def __init__(self, config: AnchorNetConfig):
        super().__init__()
        self.config = config
        layers: list[nn.Module] = [nn.LayerNorm(invariant_feature_count(config))]
        width = invariant_feature_count(config)
        for hidden in config.hidden_dims:
            layers += [nn.Linear(width, hidden), nn.GELU()]
            width = hidden
        layers.append(nn.Linear(width, config.feature_dim))
        self.encoder = nn.Sequential(*layers)
        self.log_temperature = nn.Parameter(torch.tensor(math.log(config.initial_temperature)))

    @property
    def temperature(self) -> torch.Tensor:
        return self.log_temperature.exp().clamp(max=self.config.max_temperature)

    def features(self, maps: torch.Tensor) -> torch.Tensor:
        """(B, F) roll-invariant features of polar maps (B, 2, R, T): fixed, nothing learnt (training caches them)."""
        return invariant_features(maps, self.config.harmonics)

    def describe(self, features: torch.Tensor) -> torch.Tensor:
        """Unit descriptors (B, D) of invariant features (B, F): the learnt part."""
        return F.normalize(self.encoder(features), dim=-1)

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        """Unit descriptors (B, D) of polar maps (B, 2, R, T) (yoto.network.polar: heights and coverage)."""
        return self.describe(self.features(maps))

    def describe_many(self, features: torch.Tensor, batch: int = 8192) -> torch.Tensor:
        """describe() in batches (all anchors of an object), without gradients."""
        with torch.no_grad():
            return torch.cat([self.describe(features[i : i + batch]) for i in range(0, len(features), batch)])

    def encode_many(self, maps: torch.Tensor, batch: int = 8192) -> torch.Tensor:
        """forward() in batches, without gradients."""
        with torch.no_grad():
            return torch.cat([self(maps[i : i + batch]) for i in range(0, len(maps), batch)])

    def logits(self, descriptors: torch.Tensor, anchor_descriptors: torch.Tensor) -> torch.Tensor:
        """tau * cos: (B, D) x (A, D) -> (B, A)."""
        return self.temperature * descriptors @ anchor_descriptors.T
