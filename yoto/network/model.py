"""The coarse-to-fine contact localization network (paper Sec. 3.2, App. C.1), in one file.

    tactile patch --phi--> q          surface blocks --phi--> b_1 .. b_NB      (same encoder weights)
    coarse:  a_i = tau * cos(q, b_i) over the valid blocks of the queried object
    pool:    the top block and its nearest blocks by centre distance (K_nbr = 9 candidates)
    fine:    per candidate k, MLP([b_k, q]) -> offset d_k (block frame) and confidence gamma_k
             p_k = c_k + R_k^T d_k  (object frame);   answer: argmax_k (a_k + gamma_k)

The offset is predicted in the candidate block's standardised frame (the frame its points were encoded
in: R_k (x - c_k)) and rotated back to the object frame, so one head serves blocks of any orientation.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from yoto.network.encoder import PointEncoder, scale_gradient
from yoto.network.presets import NetworkConfig


class FineHead(nn.Module):
    """Two-layer MLP over [block feature, tactile feature] -> 3-D offset and a scalar confidence."""

    def __init__(self, config: NetworkConfig):
        super().__init__()
        hidden, out = config.fine_dims
        self.interaction = config.fine_interaction
        width = config.fine_feature_dim or config.feature_dim
        self.mlp = nn.Sequential(
            nn.Linear((4 if config.fine_interaction else 2) * width, hidden),
            nn.LayerNorm(hidden),
            nn.GELU(),
            nn.Dropout(config.fine_dropout),
            nn.Linear(hidden, out),
            nn.LayerNorm(out),
            nn.GELU(),
            nn.Dropout(config.fine_dropout),
        )
        self.offset = nn.Linear(out, 3)
        self.confidence = nn.Linear(out, 1)

    def forward(self, block_features: torch.Tensor, patch_features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """block_features (..., D), patch_features (..., D) -> offsets (..., 3), confidences (...)."""
        parts = [block_features, patch_features]
        if self.interaction:
            parts += [block_features * patch_features, (block_features - patch_features).abs()]
        hidden = self.mlp(torch.cat(parts, dim=-1))
        return self.offset(hidden), self.confidence(hidden).squeeze(-1)


class ContactLocalizationNet(nn.Module):
    """Shared point encoder, cosine block matching with a learnable temperature, and the fine head."""

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        self.encoder = PointEncoder(config)
        self.log_temperature = nn.Parameter(torch.tensor(math.log(config.initial_temperature)))
        self.fine = FineHead(config)

    # ------------------------------------------------------------------------------------------- parts
    @property
    def temperature(self) -> torch.Tensor:
        return self.log_temperature.exp().clamp(max=self.config.max_temperature)

    def encode(self, points: torch.Tensor, normals: torch.Tensor, knn: torch.Tensor | None = None) -> torch.Tensor:
        """Features (B, D) of point clouds (B, N, 3) with normals (B, N, 3); knn (B, N, k) is optional."""
        return self.encoder(points, normals, knn)

    def coarse_logits(
        self, patch_features: torch.Tensor, block_features: torch.Tensor, block_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """tau * cosine similarity, (B, D) x (NB, D) -> (B, NB); blocks outside `block_mask` (B, NB) get -inf."""
        dim = self.config.feature_dim
        patch_features, block_features = patch_features[..., :dim], block_features[..., :dim]
        logits = self.temperature * F.normalize(patch_features, dim=-1) @ F.normalize(block_features, dim=-1).T
        if block_mask is not None:
            logits = logits.masked_fill(~block_mask, float("-inf"))
        return logits

    def fine_predictions(
        self,
        patch_features: torch.Tensor,
        block_features: torch.Tensor,
        candidates: torch.Tensor,
        block_centres: torch.Tensor,
        block_rotations: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Positions (B, K, 3; object frame), offsets (B, K, 3; block frames), confidences (B, K) of candidates."""
        if self.config.fine_feature_dim > 0:  # its own projection; the encoder already scaled the trunk's gradient
            scale = 1.0
            patch_features = patch_features[..., self.config.feature_dim :]
            block_features = block_features[..., self.config.feature_dim :]
        else:
            scale = self.config.fine_encoder_gradient
            patch_features = patch_features[..., : self.config.feature_dim]
            block_features = block_features[..., : self.config.feature_dim]
        candidate_features = scale_gradient(block_features, scale)[candidates]  # (B, K, D)
        expanded = scale_gradient(patch_features, scale).unsqueeze(1).expand_as(candidate_features)
        offsets, confidence = self.fine(candidate_features, expanded)
        offsets = offsets * self.config.offset_scale_m
        # p = c + R^T d: (R^T d)_a = sum_b R_ba d_b
        positions = block_centres[candidates] + torch.einsum("bkji,bkj->bki", block_rotations[candidates], offsets)
        return positions, offsets, confidence

    # -------------------------------------------------------------------------------------------- forward
    def forward(self, data: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Localize a batch of tactile patches among the blocks of their objects.

        Inputs (B patches, N points per patch, NB blocks, M points per block, K = config.candidates):
            patch_points     (B, N, 3)   canonical patch coordinates, metres (centroid at 0, concave dir +z)
            patch_normals    (B, N, 3)   outward unit normals in the same frame
            patch_knn        (B, N, k)   optional: nearest-neighbour indices, sorted, k >= max(knn_scales)
            block_points     (NB, M, 3)  each block's points in its standardised frame R_i (x - c_i), metres;
                                         omit when block_features is given
            block_normals    (NB, M, 3)  their normals in the same frame
            block_knn        (NB, M, k)  optional, like patch_knn
            block_features   (NB, D)     optional: precomputed block features (inference cache)
            block_centres    (NB, 3)     c_i, object frame, metres
            block_rotations  (NB, 3, 3)  R_i, the standardising rotations
            block_neighbours (NB, K)     int64: each block's K nearest blocks by centre distance, itself first
            block_mask       (B, NB)     optional bool: the blocks each patch may match (its object's blocks)
            force_block      (B,)        optional int64: put this block in the candidate pool if the coarse
                                         stage left it out (training: the ground-truth block), -1 for none
        Outputs:
            patch_features   (B, D)
            block_features   (NB, D)
            coarse_logits    (B, NB)     a_i = tau cos(q, b_i); -inf outside block_mask
            candidates       (B, K)      block indices of the candidate pool (pool of the top coarse block)
            offsets          (B, K, 3)   predicted offsets in each candidate's block frame, metres
            positions        (B, K, 3)   predicted contact location per candidate, object frame, metres
            confidence       (B, K)      gamma_k
            scores           (B, K)      a_{i_k} + gamma_k, the ranking score
            best             (B,)        index into the candidates of the answer
            p_object         (B, 3)      the answer's contact location, object frame
        """
        patch_features = self.encode(data["patch_points"], data["patch_normals"], data.get("patch_knn"))
        block_features = data.get("block_features")
        if block_features is None:
            block_features = self.encode(data["block_points"], data["block_normals"], data.get("block_knn"))
        logits = self.coarse_logits(patch_features, block_features, data.get("block_mask"))
        candidates = data["block_neighbours"][logits.argmax(dim=1)]  # (B, K)
        force = data.get("force_block")
        if force is not None:
            missing = (force >= 0) & ~(candidates == force.unsqueeze(1)).any(dim=1)
            candidates = candidates.clone()
            candidates[missing, -1] = force[missing]
        positions, offsets, confidence = self.fine_predictions(
            patch_features, block_features, candidates, data["block_centres"], data["block_rotations"]
        )
        scores = logits.gather(1, candidates) + confidence
        best = scores.argmax(dim=1)
        return {
            "patch_features": patch_features,
            "block_features": block_features,
            "coarse_logits": logits,
            "candidates": candidates,
            "offsets": offsets,
            "positions": positions,
            "confidence": confidence,
            "scores": scores,
            "best": best,
            "p_object": positions[torch.arange(len(best)), best],
        }


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
