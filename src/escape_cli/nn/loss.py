"""Chamfer-L1 in distance space (DMCD, paper eq. 5), fast on CPU.

Nearest-neighbour *indices* come from KD-trees on detached values (scipy cKDTree in K
dimensions); the loss itself is a differentiable gather, so gradients flow exactly as
with the brute-force formula.
"""

from __future__ import annotations

import numpy as np
import torch


def nearest_indices(queries: np.ndarray, targets: np.ndarray, workers: int = 1) -> np.ndarray:
    """For each row of `queries` (B, P, K) the index of the nearest row of `targets` (B, G, K) -> (B, P).

    `workers` threads take the batch's samples in turn (the same indices with any number).
    """
    from scipy.spatial import cKDTree

    from escape_cli.core.threads import thread_map

    out = np.empty(queries.shape[:2], dtype=np.int64)

    def one(i: int) -> None:
        out[i] = cKDTree(targets[i]).query(queries[i], k=1)[1]

    thread_map(one, range(len(queries)), workers)
    return out


def _gather(points: torch.Tensor, index: np.ndarray) -> torch.Tensor:
    idx = torch.from_numpy(index).to(points.device)  # (B, P)
    return torch.gather(points, 1, idx.unsqueeze(-1).expand(-1, -1, points.shape[-1]))


def chamfer_l1(pred: torch.Tensor, gt: torch.Tensor, recall_weight: float = 1.0, workers: int = 1) -> torch.Tensor:
    """Chamfer-L1 per batch mean: (mean_p min_g ||p-g|| + w mean_g min_p ||g-p||) / (1 + w).

    pred : (B, P, K), gt : (B, G, K), recall_weight : w, the weight of the truth ->
    prediction term (1: the symmetric Chamfer distance), workers : threads for the
    nearest-neighbour queries (the same result with any number) -> scalar (mean over the batch)
    """
    p = pred.detach().cpu().float().numpy()
    g = gt.detach().cpu().float().numpy()
    to_gt = _gather(gt, nearest_indices(p, g, workers))  # (B, P, K)
    to_pred = _gather(pred, nearest_indices(g, p, workers))  # (B, G, K)
    d_pred = (pred - to_gt).norm(dim=-1).mean(dim=1)  # (B,)
    d_gt = (gt - to_pred).norm(dim=-1).mean(dim=1)  # (B,)
    return ((d_pred + recall_weight * d_gt) / (1.0 + recall_weight)).mean()


def chamfer_l1_naive(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Brute-force reference of `chamfer_l1` (O(P G) memory)."""
    d = torch.cdist(pred, gt)  # (B, P, G)
    return ((d.min(dim=2).values.mean(dim=1) + d.min(dim=1).values.mean(dim=1)) / 2).mean()


def reconstruct_differentiable(pred: torch.Tensor, anchors: torch.Tensor, references: np.ndarray,
                               damping: float = 1e-2, workers: int = 1) -> torch.Tensor:
    """Coordinates of predicted distance vectors, with gradients, for an xyz-space loss.

    The points are solved by the product's LM (`escape_cli.core.reconstruction.reconstruct`,
    no gradient); one damped Gauss-Newton step taken from that solution in torch then
    carries the gradient. Its value stays the LM solution (the step is ~0 at an optimum)
    and its derivative is the implicit one, d x / d d = (J^T J + lambda I)^-1 J^T,
    with lambda = `damping` * trace(J^T J) / 3 bounding it where anchors are flat.

    pred : (B, P, K) distances, anchors : (B, K, 3), references : (B, N, 3) the partials,
    workers : threads of the LM (the same points with any number) -> (B, P, 3)
    """
    from escape_cli.core.reconstruction import reconstruct

    d = pred.detach().cpu().double().numpy()
    a = anchors.detach().cpu().double().numpy()
    solved = np.stack([reconstruct(d[i], a[i], reference_points=references[i], workers=workers).points
                       for i in range(len(d))])
    x0 = torch.from_numpy(solved).to(pred)  # (B, P, 3)
    diff = x0.unsqueeze(2) - anchors.detach().unsqueeze(1)  # (B, P, K, 3)
    norm = diff.norm(dim=-1).clamp_min(1e-9)  # (B, P, K)
    jac = diff / norm.unsqueeze(-1)  # (B, P, K, 3)
    residual = norm - pred  # (B, P, K)
    jtj = jac.transpose(-1, -2) @ jac  # (B, P, 3, 3)
    lam = damping * jtj.diagonal(dim1=-2, dim2=-1).sum(-1) / 3  # (B, P)
    eye = torch.eye(3, dtype=pred.dtype, device=pred.device)
    jtr = jac.transpose(-1, -2) @ residual.unsqueeze(-1)  # (B, P, 3, 1)
    step = torch.linalg.solve(jtj + lam[..., None, None] * eye, jtr).squeeze(-1)  # (B, P, 3)
    return x0 - step
