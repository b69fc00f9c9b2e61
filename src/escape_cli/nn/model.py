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
from torch.nn import functional as F

from escape_cli.nn.config import ModelConfig


_HALF = (torch.bfloat16, torch.float16)


def full_precision(x: torch.Tensor) -> torch.Tensor:
    """A half-precision `x` (autocast's output) as float32; any other `x` as it is (no graph node in the export)."""
    return x.float() if x.dtype in _HALF else x


def linear_fp32(layer: nn.Linear, x: torch.Tensor) -> torch.Tensor:
    """`layer(x)` in float32 even under autocast: the output layers that write distances.

    Under `torch.autocast` (training with --precision bf16) a Linear would round its
    output to bfloat16 (8 significant bits, ~2e-3 at a distance of 0.5); these layers are
    small, so they keep full precision. Without autocast this is `layer(x)`.
    """
    if not torch.is_autocast_enabled(x.device.type):
        return layer(x)
    with torch.autocast(x.device.type, enabled=False):
        return layer(full_precision(x))


def knn_indices(centres: torch.Tensor, points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices of the k nearest rows of `points` for every centre (Euclidean in feature space).

    centres : (B, P, D), points : (B, N, D) -> (B, P, k) int64. Always in float32: under
    autocast the product would be rounded to bfloat16 and pick other neighbours.
    """
    if torch.is_autocast_enabled(points.device.type):
        with torch.autocast(points.device.type, enabled=False):
            return knn_indices(full_precision(centres), full_precision(points), k)
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


def embed_rows(features: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """`gather_rows` as an embedding lookup: the same values, a faster backward on the CPU (training only)."""
    b, n, c = features.shape
    offset = torch.arange(b, device=features.device).view(b, 1, 1) * n
    return F.embedding(index + offset, features.reshape(b * n, c))  # (B, P, k, C)


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
        if not self.training:  # the reference form: evaluation and the ONNX export
            neigh = gather_rows(features, idx)  # (B, P, k, C)
            centre = centre_feats.unsqueeze(2).expand_as(neigh)  # (B, P, k, C)
            edges = torch.cat([neigh - centre, centre], dim=-1)  # (B, P, k, 2C)
            return centre_coords, self.mlp(edges).amax(dim=2)  # (B, P, K), (B, P, C')
        return centre_coords, self._factored(features, centre_feats, idx)

    def _factored(self, features: torch.Tensor, centre_feats: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """The same edge MLP with its first layer applied before the gather (training).

        W [f_j - f_i, f_i] + b = W_n f_j + (W_c - W_n) f_i + b, with W = [W_n | W_c]: the
        first layer runs on the N points and P centres instead of the P k edges (k = 16
        times fewer rows), and no (B, P, k, 2C) edge tensor is built. Equal to the
        reference form to float rounding (tested with its gradients).
        """
        first, rest = self.mlp[0], self.mlp[1:]
        c = features.shape[-1]
        w_neigh, w_centre = first.weight[:, :c], first.weight[:, c:]  # (C', C) each
        neigh = embed_rows(F.linear(features, w_neigh), idx)  # (B, P, k, C')
        centre = F.linear(centre_feats, w_centre - w_neigh, first.bias)  # (B, P, C')
        return rest(neigh + centre.unsqueeze(2)).max(dim=2).values  # (B, P, C')


class RebuildHead(nn.Module):
    """Folds every query into F points: offsets = MLP(query feature, learned seed F), with the MLP's last features."""

    def __init__(self, dim: int, hidden: int, fold: int, anchors: int):
        super().__init__()
        self.seeds = nn.Parameter(torch.randn(fold, hidden) * 0.5)  # (F, H)
        self.query_proj = nn.Linear(dim + anchors, hidden)
        self.mlp = nn.Sequential(
            nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, anchors)
        )

    def forward(self, query_feats: torch.Tensor, coarse: torch.Tensor, seed_index: torch.Tensor | None = None):
        """query_feats : (B, Q, C), coarse : (B, Q, K) -> points (B, Q, F', K), their features (B, Q, F', H)."""
        seeds = self.seeds if seed_index is None else self.seeds[seed_index]  # (F', H)
        q = self.query_proj(torch.cat([query_feats, coarse], dim=-1))  # (B, Q, H)
        h = q.unsqueeze(2) + seeds.view(1, 1, seeds.shape[0], seeds.shape[1])  # (B, Q, F', H)
        hidden = self.mlp[:-1](h)  # (B, Q, F', H)
        return coarse.unsqueeze(2) + linear_fp32(self.mlp[-1], hidden), hidden  # (B, Q, F', K), (B, Q, F', H)


def query_neighbourhoods(coarse: torch.Tensor, query_feats: torch.Tensor, knn: int, training: bool) -> torch.Tensor:
    """[query feature, displacement from the query] of each query's `knn` nearest coarse points (in distance space).

    coarse : (B, Q, K), query_feats : (B, Q, C) -> (B, Q, k, C + K); what every
    `OffsetRefiner` reads (the queries do not move between refiners, so it is built once).
    """
    idx = knn_indices(coarse, coarse, min(knn, coarse.shape[1]))  # (B, Q, k)
    gather = embed_rows if training else gather_rows
    disp = gather(coarse, idx) - coarse.unsqueeze(2)  # (B, Q, k, K)
    return torch.cat([gather(query_feats, idx), disp], dim=-1)  # (B, Q, k, C + K)


class OffsetRefiner(nn.Module):
    """One coarse-to-fine step: every rebuilt point moves by a learned local offset.

    A point's offset is an MLP of its own feature, its displacement from its query's
    coarse point, and the neighbourhood of that query: the max over its nearest coarse
    points of [their query feature, their displacement from it] (`query_neighbourhoods`;
    SnowflakeNet's point deconvolution, with the fold as the split). The offset layer
    starts at zero, so a network grown by refiners computes what it did before.
    """

    def __init__(self, dim: int, hidden: int, anchors: int):
        super().__init__()
        self.neighbourhood = nn.Linear(dim + anchors, hidden)
        self.point_in = nn.Linear(hidden + anchors, hidden)
        self.mid = nn.Linear(hidden, hidden)
        self.offset = nn.Linear(hidden, anchors)
        nn.init.zeros_(self.offset.weight)
        nn.init.zeros_(self.offset.bias)

    def forward(self, points: torch.Tensor, hidden: torch.Tensor, coarse: torch.Tensor, neighbourhoods: torch.Tensor):
        # points : (B, Q, F', K), hidden : (B, Q, F', H), coarse : (B, Q, K), neighbourhoods : (B, Q, k, C + K)
        context = self.neighbourhood(neighbourhoods).amax(dim=2)  # (B, Q, H)
        x = self.point_in(torch.cat([hidden, points - coarse.unsqueeze(2)], dim=-1))  # (B, Q, F', H)
        x = F.gelu(self.mid(F.gelu(x + context.unsqueeze(2))))  # (B, Q, F', H)
        return points + linear_fp32(self.offset, x), hidden + x  # (B, Q, F', K), (B, Q, F', H)


def _attention(mha: nn.MultiheadAttention, x: torch.Tensor, memory: torch.Tensor | None = None) -> torch.Tensor:
    """`mha(x, m, m, need_weights=False)[0]` for batch-first inputs, without its layout changes.

    nn.MultiheadAttention works in (L, B, E): a batch-first input is transposed and the
    packed projection copied twice before the attention, and the output copied back.
    Here the projections are applied to (B, L, E) as they are and the heads viewed out
    of them: the same products, the same attention kernel (training only).
    x : (B, L, E), memory : (B, S, E) or None (self-attention) -> (B, L, E)
    """
    b, length, e = x.shape
    h = mha.num_heads
    if memory is None:
        qkv = F.linear(x, mha.in_proj_weight, mha.in_proj_bias)  # (B, L, 3E)
        q, k, v = qkv.view(b, length, 3, h, e // h).permute(2, 0, 3, 1, 4)  # (B, H, L, E/H) each
    else:
        w_q, w_kv = mha.in_proj_weight.split([e, 2 * e])
        b_q, b_kv = mha.in_proj_bias.split([e, 2 * e])
        q = F.linear(x, w_q, b_q).view(b, length, h, e // h).transpose(1, 2)  # (B, H, L, E/H)
        kv = F.linear(memory, w_kv, b_kv)  # (B, S, 2E)
        k, v = kv.view(b, memory.shape[1], 2, h, e // h).permute(2, 0, 3, 1, 4)  # (B, H, S, E/H) each
    out = _scaled_dot_product(q, k, v)  # (B, H, L, E/H)
    return mha.out_proj(out.transpose(1, 2).reshape(b, length, e))  # (B, L, E)


def _scaled_dot_product(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """softmax(q k^T / sqrt(d)) v: torch's fused kernel, or for bfloat16 the plain products.

    On the CPU the fused (flash) kernel is slower in bfloat16 than in float32, and at
    these lengths (128-256) two bfloat16 products with a float32 softmax between them
    take about half its time. q : (B, H, L, d), k, v : (B, H, S, d) -> (B, H, L, d)
    """
    if q.dtype not in _HALF:
        return F.scaled_dot_product_attention(q, k, v)
    scores = torch.matmul(q, k.transpose(-1, -2))  # (B, H, L, S)
    weights = torch.softmax(scores.float() * q.shape[-1] ** -0.5, dim=-1)  # float32
    return torch.matmul(weights.to(v.dtype), v)


def _feed_forward(layer: nn.Module, x: torch.Tensor) -> torch.Tensor:
    return layer.linear2(F.gelu(layer.linear1(x)))


def encoder_layer(layer: nn.TransformerEncoderLayer, x: torch.Tensor) -> torch.Tensor:
    """`layer(x)` of a pre-norm, batch-first, dropout-free, GELU encoder layer (see `_attention`)."""
    if not layer.training:
        return layer(x)
    x = x + _attention(layer.self_attn, layer.norm1(x))
    return x + _feed_forward(layer, layer.norm2(x))


def decoder_layer(layer: nn.TransformerDecoderLayer, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
    """`layer(x, memory)` of a pre-norm, batch-first, dropout-free, GELU decoder layer (see `_attention`)."""
    if not layer.training:
        return layer(x, memory)
    x = x + _attention(layer.self_attn, layer.norm1(x))
    x = x + _attention(layer.multihead_attn, layer.norm2(x), memory)
    return x + _feed_forward(layer, layer.norm3(x))


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
        self.refine = nn.ModuleList(
            OffsetRefiner(c.dim, c.rebuild_hidden, c.anchors) for _ in range(c.refine_stages)
        )

    def forward(self, partial: torch.Tensor, seed_index: torch.Tensor | None = None):
        c = self.config
        b = partial.shape[0]
        feats = self.point_embed(partial)  # (B, N, E)
        coords1, feats1 = self.group_fine(partial, feats)  # (B, P1, K), (B, P1, C/2)
        coords2, tokens = self.group_coarse(coords1, feats1)  # (B, P2, K), (B, P2, C)
        tokens = full_precision(tokens) + self.pos_embed(coords2)  # (B, P2, C): the residual stream in float32
        for layer in self.encoder:
            tokens = encoder_layer(layer, tokens)  # (B, P2, C)
        global_feat = tokens.amax(dim=1)  # (B, C)
        hidden = self.global_head[:-1](global_feat)  # (B, 2C)
        predicted = linear_fp32(self.global_head[-1], hidden).view(b, c.predicted_queries, c.anchors)  # (B, Qp, K)
        observed = partial[:, : c.input_queries]  # (B, Qi, K): FPS rows of the input
        coarse = torch.cat([predicted, observed], dim=1)  # (B, Q, K)
        glob = global_feat.unsqueeze(1).expand(b, coarse.shape[1], global_feat.shape[-1])  # (B, Q, C)
        queries = full_precision(self.query_embed(torch.cat([coarse, glob], dim=-1)))  # (B, Q, C)
        for layer in self.decoder:
            queries = decoder_layer(layer, queries, tokens)  # (B, Q, C)
        queries = self.norm(queries)
        coarse = coarse + linear_fp32(self.coarse_refine, queries)  # (B, Q, K)
        points, hidden = self.rebuild(queries, coarse, seed_index)  # (B, Q, F, K), (B, Q, F, H)
        if len(self.refine):
            neighbourhoods = query_neighbourhoods(coarse, queries, c.refine_knn, self.training)  # (B, Q, k, C + K)
            for stage in self.refine:
                points, hidden = stage(points, hidden, coarse, neighbourhoods)
        fine = points.reshape(points.shape[0], -1, points.shape[-1])  # (B, Q*F, K)
        if c.positive_output:
            return sharp_softplus(fine), sharp_softplus(coarse)
        return fine, coarse


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
