"""The distance-space completion network (AdaPoinTr-style encoder-decoder on anchor distances).

Legend: B batch, N input points, K anchors, P centres, Q queries, F fold (points per
query), C channels. Inputs are distances, outputs are distances: nothing depends on
absolute coordinates, so the network is rotation and translation invariant by
construction. The input rows arrive in farthest-point order, so the first P rows are
the P-point FPS subset and grouping needs no sampling op in the graph.
"""

from __future__ import annotations

import torch
from torch import nn

from escape_cli.nn.config import ModelConfig


def knn_indices(centres: torch.Tensor, points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the k nearest rows of `points` for every centre (Euclidean in feature space).

    centres : (B, P, D), points : (B, N, D) -> (B, P, k) int64
    """
    sq = (
        centres.pow(2).sum(-1, keepdim=True)  # (B, P, 1)
        + points.pow(2).sum(-1).unsqueeze(1)  # (B, 1, N)
        - 2.0 * centres @ points.transpose(1, 2)  # (B, P, N)
    )
    return sq.topk(k, dim=-1, largest=False).indices  # (B, P, k)


def gather_rows(features: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """features : (B, N, C), index : (B, P, k) -> (B, P, k, C)."""
    b, n, c = features.shape
    offset = torch.arange(b, device=features.device).view(b, 1, 1) * n
    flat = features.reshape(b * n, c)
    return flat[(index + offset).reshape(-1)].reshape(index.shape[0], index.shape[1], index.shape[2], c)


class EdgeGrouping(nn.Module):
    """EdgeConv from all points to their first `centres` rows: max over kNN of MLP([f_j - f_i, f_i])."""

    def __init__(self, in_channels: int, out_channels: int, centres: int, k: int):
        super().__init__()
        self.centres = centres
        self.k = k
        self.mlp = nn.Sequential(
            nn.Linear(2 * in_channels, out_channels),
            nn.LayerNorm(out_channels),
            nn.GELU(),
            nn.Linear(out_channels, out_channels),
        )

    def forward(self, coords: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # coords : (B, N, K) distance vectors used for neighbourhoods; features : (B, N, C)
        centre_coords = coords[:, : self.centres]  # (B, P, K)
        centre_feats = features[:, : self.centres]  # (B, P, C)
        idx = knn_indices(centre_coords, coords, self.k)  # (B, P, k)
        neigh = gather_rows(features, idx)  # (B, P, k, C)
        centre = centre_feats.unsqueeze(2).expand_as(neigh)  # (B, P, k, C)
        edges = torch.cat([neigh - centre, centre], dim=-1)  # (B, P, k, 2C)
        return centre_coords, self.mlp(edges).amax(dim=2)  # (B, P, K), (B, P, C')


class RebuildHead(nn.Module):
    """Folds every query into F points: offsets = MLP(query feature, learned seed F)."""

    def __init__(self, dim: int, hidden: int, fold: int, anchors: int):
        super().__init__()
        self.seeds = nn.Parameter(torch.randn(fold, hidden) * 0.5)  # (F, H)
        self.query_proj = nn.Linear(dim + anchors, hidden)
        self.mlp = nn.Sequential(
            nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, anchors)
        )

    def forward(self, query_feats: torch.Tensor, coarse: torch.Tensor, seed_index: torch.Tensor | None = None):
        # query_feats : (B, Q, C), coarse : (B, Q, K) -> (B, Q * F', K)
        seeds = self.seeds if seed_index is None else self.seeds[seed_index]  # (F', H)
        q = self.query_proj(torch.cat([query_feats, coarse], dim=-1))  # (B, Q, H)
        h = q.unsqueeze(2) + seeds.view(1, 1, seeds.shape[0], seeds.shape[1])  # (B, Q, F', H)
        points = coarse.unsqueeze(2) + self.mlp(h)  # (B, Q, F', K)
        return points.reshape(points.shape[0], -1, points.shape[-1])  # (B, Q*F', K)


SOFTPLUS_SHARPNESS = 100.0


def sharp_softplus(x: torch.Tensor, beta: float = SOFTPLUS_SHARPNESS) -> torch.Tensor:
    """log(1 + exp(beta x)) / beta, written with ONNX-plain ops and stable for any x; >= 0.

    Within 7e-5 of x for x >= 0.05 (distances in the network's frame are 0.05-1.5).
    """
    return torch.relu(x) + torch.log(1.0 + torch.exp(-beta * x.abs())) / beta


def mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.GELU())
    return nn.Sequential(*layers)


class EscapeNet(nn.Module):
    """Distances of a partial cloud to K anchors -> distances of the complete shape.

    forward(partial (B, N, K)) -> (fine (B, Q*F, K), coarse (B, Q, K))
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        c = config
        if c.centres_coarse > c.centres_fine or c.centres_fine > c.input_points:
            raise ValueError("need centres_coarse <= centres_fine <= input_points")
        if c.input_queries > c.input_points:
            raise ValueError("input_queries must not exceed input_points")
        self.config = c
        self.point_embed = mlp([c.anchors, c.embed_dim, c.embed_dim])
        self.group_fine = EdgeGrouping(c.embed_dim, c.dim // 2, c.centres_fine, c.group_knn)
        self.group_coarse = EdgeGrouping(c.dim // 2, c.dim, c.centres_coarse, c.group_knn)
        self.pos_embed = mlp([c.anchors, c.dim, c.dim])
        ffn = int(c.dim * c.ffn_ratio)
        self.encoder = nn.ModuleList(
            nn.TransformerEncoderLayer(c.dim, c.heads, ffn, dropout=0.0, activation="gelu", batch_first=True, norm_first=True)
            for _ in range(c.encoder_depth)
        )
        self.global_head = mlp([c.dim, c.dim * 2, c.predicted_queries * c.anchors])
        self.query_embed = mlp([c.anchors + c.dim, c.dim, c.dim])
        self.decoder = nn.ModuleList(
            nn.TransformerDecoderLayer(c.dim, c.heads, ffn, dropout=0.0, activation="gelu", batch_first=True, norm_first=True)
            for _ in range(c.decoder_depth)
        )
        self.norm = nn.LayerNorm(c.dim)
        self.coarse_refine = nn.Linear(c.dim, c.anchors)
        self.rebuild = RebuildHead(c.dim, c.rebuild_hidden, c.fold, c.anchors)

    def forward(self, partial: torch.Tensor, seed_index: torch.Tensor | None = None):
        c = self.config
        b = partial.shape[0]
        feats = self.point_embed(partial)  # (B, N, E)
        coords1, feats1 = self.group_fine(partial, feats)  # (B, P1, K), (B, P1, C/2)
        coords2, tokens = self.group_coarse(coords1, feats1)  # (B, P2, K), (B, P2, C)
        tokens = tokens + self.pos_embed(coords2)  # (B, P2, C)
        for layer in self.encoder:
            tokens = layer(tokens)  # (B, P2, C)
        global_feat = tokens.amax(dim=1)  # (B, C)
        predicted = self.global_head(global_feat).view(b, c.predicted_queries, c.anchors)  # (B, Qp, K)
        observed = partial[:, : c.input_queries]  # (B, Qi, K): FPS rows of the input
        coarse = torch.cat([predicted, observed], dim=1)  # (B, Q, K)
        glob = global_feat.unsqueeze(1).expand(b, coarse.shape[1], global_feat.shape[-1])  # (B, Q, C)
        queries = self.query_embed(torch.cat([coarse, glob], dim=-1))  # (B, Q, C)
        for layer in self.decoder:
            queries = layer(queries, tokens)  # (B, Q, C)
        queries = self.norm(queries)
        coarse = coarse + self.coarse_refine(queries)  # (B, Q, K)
        fine = self.rebuild(queries, coarse, seed_index)  # (B, Q*F, K)
        if c.positive_output:
            return sharp_softplus(fine), sharp_softplus(coarse)
        return fine, coarse


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
