"""The shared point-cloud encoder (paper Sec. 3.2, App. C.1): tactile patches and surface blocks -> features.

    points + normals (B, N, 6)
      -> point-wise MLP                                   f_j            (B, N, P)   every point
      -> per scale k in {8, 16, 32, 64}, at each centre i:
            e_i^k = max_{j in kNN_k(i)} relu(W_k [f_j ; x_j - x_i] + b_k)                   (B, C, E) each
      -> fusion MLP over [f_i, e_i^8, e_i^16, e_i^32, e_i^64], pre-pool projection          (B, C, Q)
      -> [max over centres, mean over centres] -> linear                                  (B, D)

The centres are every point in the paper's network (centre_fraction = 1); the `cpu` preset aggregates at a
random quarter of the points (PointNet++'s set abstraction), their neighbours still drawn from all points,
and may dilate the large scales (every 2nd / 4th of the 32 / 64 nearest). Two further choices make the
encoder fast without changing what it computes:
- One kNN search (the largest k, sorted by distance) serves every scale: the k nearest are a prefix of it.
- The edge function's linear part is computed once per point, before the neighbour gather:
  W [f_j ; x_j - x_i] = (W_f f_j + W_x x_j) - W_x x_i, and since relu is monotone,
  max_j relu(u_j - v_i + b) = relu(max_j u_j - v_i + b). The gather then moves E numbers per neighbour
  instead of a (P + 3)-wide edge vector, and no (N, k, P + 3) edge tensor is ever built.
  `reference_edge_features` is the slow, obviously-correct version; the tests check that they agree.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from yoto.network.presets import NetworkConfig


def knn_indices(queries: torch.Tensor, points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices into `points` of each query's k nearest points, sorted by distance.

    queries (B, C, 3), points (B, N, 3). Returns (B, C, min(k, N)) int64.
    """
    k = min(k, points.shape[1])
    squared = (
        queries.square().sum(-1).unsqueeze(2)
        + points.square().sum(-1).unsqueeze(1)
        - 2.0 * queries @ points.transpose(1, 2)
    )
    return squared.topk(k, dim=-1, largest=False, sorted=True).indices


class _NeighbourMax(torch.autograd.Function):
    """max over each centre's neighbours of per-point values; the backward pass routes gradients to the argmax.

    Autograd through gather + amax would keep the (B, C, k, E) gathered tensor and spread the gradient with
    several passes over it; this keeps only the (B, C, E) winning source indices.
    """

    @staticmethod
    def forward(ctx, values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        batch, points, channels = values.shape
        centres, k = index.shape[1:]
        offsets = torch.arange(batch, device=values.device).view(batch, 1, 1) * points
        flat = index + offsets
        gathered = values.reshape(batch * points, channels).index_select(0, flat.reshape(-1))
        maxima, winner = gathered.view(batch, centres, k, channels).max(dim=2)
        ctx.save_for_backward(flat.gather(2, winner))  # (B, C, E) flat source index of each maximum
        ctx.shape = values.shape
        return maxima

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (source,) = ctx.saved_tensors
        batch, points, channels = ctx.shape
        grad_values = torch.zeros(batch * points, channels, dtype=grad.dtype, device=grad.device)
        grad_values.scatter_add_(0, source.reshape(-1, channels), grad.reshape(-1, channels))
        return grad_values.view(batch, points, channels), None


def cylindrical_inputs(coords: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Per-point inputs that do not change when the cloud turns about its z axis: radius r = |(x, y)|, height z,
    and the normal's radial, tangential and z components -> (B, N, 5)."""
    radius = torch.linalg.vector_norm(coords[..., :2], dim=-1, keepdim=True)
    radial = coords[..., :2] / radius.clamp_min(1e-6)
    normal_radial = (normals[..., :2] * radial).sum(-1, keepdim=True)
    normal_tangential = normals[..., 1:2] * radial[..., :1] - normals[..., :1] * radial[..., 1:2]
    return torch.cat([radius, coords[..., 2:3], normal_radial, normal_tangential, normals[..., 2:3]], dim=-1)


def scale_gradient(tensor: torch.Tensor, scale: float) -> torch.Tensor:
    """The tensor unchanged in the forward pass, its gradient multiplied by `scale` in the backward pass."""
    if scale == 1.0:
        return tensor
    detached = tensor.detach()
    return detached if scale == 0.0 else detached + scale * (tensor - detached)


def neighbour_max(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """values (B, N, E), index (B, C, k) into N -> (B, C, E): each channel's max over each centre's neighbours."""
    return _NeighbourMax.apply(values, index)


def scale_neighbours(knn: torch.Tensor, scales: tuple[int, ...], max_gathered: int | None) -> list[torch.Tensor]:
    """Each scale's neighbour list: the k nearest (a prefix of the sorted kNN), dilated to at most
    `max_gathered` entries (every (k / max_gathered)-th neighbour, nearest first) when that is set."""
    lists = []
    for k in scales:
        k = min(k, knn.shape[-1])
        stride = 1 if max_gathered is None else max(1, k // max_gathered)
        lists.append(knn[..., :k:stride])
    return lists


class MultiScaleEdge(nn.Module):
    """Multi-scale kNN aggregation: per scale, max over neighbours of relu(W [f_j ; x_j - x_i] + b)."""

    def __init__(
        self, in_dim: int, edge_dim: int, scales: tuple[int, ...], max_gathered: int | None = None, offset_dim: int = 3
    ):
        super().__init__()
        self.scales = tuple(scales)
        self.edge_dim = edge_dim
        self.max_gathered = max_gathered
        # One linear layer per scale, stored stacked: rows s*E:(s+1)*E belong to scale s.
        self.weight_feature = nn.Parameter(torch.empty(len(scales) * edge_dim, in_dim))
        self.weight_offset = nn.Parameter(torch.empty(len(scales) * edge_dim, offset_dim))
        self.bias = nn.Parameter(torch.zeros(len(scales) * edge_dim))
        fan_in = in_dim + offset_dim
        for weight in (self.weight_feature, self.weight_offset):
            nn.init.uniform_(weight, -(fan_in**-0.5), fan_in**-0.5)

    def forward(
        self, features: torch.Tensor, coords: torch.Tensor, centre_coords: torch.Tensor, knn: torch.Tensor
    ) -> torch.Tensor:
        """features (B, N, P), coords (B, N, 3), centre_coords (B, C, 3), knn (B, C, k_max) -> (B, C, S * E)."""
        per_point = features @ self.weight_feature.T + coords @ self.weight_offset.T  # W_f f_j + W_x x_j
        centre_term = centre_coords @ self.weight_offset.T - self.bias  # W_x x_i - b
        outputs = []
        for s, neighbours in enumerate(scale_neighbours(knn, self.scales, self.max_gathered)):
            channels = slice(s * self.edge_dim, (s + 1) * self.edge_dim)
            pooled = neighbour_max(per_point[..., channels].contiguous(), neighbours)
            outputs.append(F.relu(pooled - centre_term[..., channels]))
        return torch.cat(outputs, dim=-1)


def reference_edge_features(
    edge: MultiScaleEdge, features: torch.Tensor, coords: torch.Tensor, centre_coords: torch.Tensor, knn: torch.Tensor
) -> torch.Tensor:
    """The edge function computed literally: build [f_j ; x_j - x_i] per edge, apply W, relu, max. Slow."""
    outputs = []
    batch_index = torch.arange(features.shape[0]).view(-1, 1, 1)
    for s, neighbours in enumerate(scale_neighbours(knn, edge.scales, edge.max_gathered)):
        channels = slice(s * edge.edge_dim, (s + 1) * edge.edge_dim)
        neighbour_features = features[batch_index, neighbours]  # (B, C, k, P)
        relative = coords[batch_index, neighbours] - centre_coords.unsqueeze(2)  # (B, C, k, 3)
        edges = torch.cat([neighbour_features, relative], dim=-1)
        weight = torch.cat([edge.weight_feature[channels], edge.weight_offset[channels]], dim=1)
        outputs.append(F.relu(F.linear(edges, weight, edge.bias[channels])).amax(dim=2))
    return torch.cat(outputs, dim=-1)


class PointEncoder(nn.Module):
    """Shared encoder phi: a point cloud with normals -> one feature vector (paper's three-stage module)."""

    def __init__(self, config: NetworkConfig):
        super().__init__()
        self.config = config
        self.point_mlp = nn.Sequential(
            nn.Linear(5 if config.rotation_invariant else 6, config.point_dim),
            nn.LayerNorm(config.point_dim),
            nn.ReLU(),
            nn.Linear(config.point_dim, config.point_dim),
            nn.LayerNorm(config.point_dim),
            nn.ReLU(),
        )
        self.edge = MultiScaleEdge(
            config.point_dim,
            config.edge_dim,
            config.knn_scales,
            config.max_gathered_neighbours,
            offset_dim=1 if config.rotation_invariant else 3,
        )
        fused_in = config.point_dim + len(config.knn_scales) * config.edge_dim
        self.fusion = nn.Sequential(
            nn.Linear(fused_in, config.fusion_dim),
            nn.LayerNorm(config.fusion_dim),
            nn.ReLU(),
            nn.Linear(config.fusion_dim, config.prepool_dim),
        )
        self.project = nn.Linear(2 * config.prepool_dim, config.feature_dim)
        if config.fine_feature_dim > 0:
            self.project_fine = nn.Linear(2 * config.prepool_dim, config.fine_feature_dim)

    def num_centres(self, num_points: int) -> int:
        return max(1, min(num_points, round(self.config.centre_fraction * num_points)))

    def neighbours(self, points: torch.Tensor) -> torch.Tensor:
        """The kNN the encoder uses for a cloud (B, N, 3) in metres: (B, C, k_max) indices of each centre's
        nearest points, the centres being the first C points."""
        coords = points / self.config.coordinate_scale_m
        centres = coords[:, : self.num_centres(points.shape[1])]
        return knn_indices(centres, coords, max(self.config.knn_scales))

    def forward(self, points: torch.Tensor, normals: torch.Tensor, knn: torch.Tensor | None = None) -> torch.Tensor:
        """points (B, N, 3) metres, normals (B, N, 3), knn (B, C, >= max scale) from `neighbours` or None
        -> features (B, D + F): the matching feature, then the fine feature if the config has one. The first
        C = centre_fraction * N points are the aggregation centres (the input order is random, so they are a
        random subset)."""
        coords = points / self.config.coordinate_scale_m
        if knn is None:
            knn = self.neighbours(points)
        centres = knn.shape[1]
        if self.config.rotation_invariant:
            point_features = self.point_mlp(cylindrical_inputs(coords, normals))
            heights = coords[..., 2:3]  # the edge's relative term keeps only the height difference
            edge_features = self.edge(point_features, heights, heights[:, :centres], knn)
        else:
            point_features = self.point_mlp(torch.cat([coords, normals], dim=-1))
            edge_features = self.edge(point_features, coords, coords[:, :centres], knn)
        fused = self.fusion(torch.cat([point_features[:, :centres], edge_features], dim=-1))
        pooled = torch.cat([fused.amax(dim=1), fused.mean(dim=1)], dim=-1)
        if self.config.fine_feature_dim > 0:
            fine = self.project_fine(scale_gradient(pooled, self.config.fine_encoder_gradient))
            return torch.cat([self.project(pooled), fine], dim=-1)
        return self.project(pooled)
