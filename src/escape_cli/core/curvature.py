"""Rotation-invariant curvature of a point cloud: surface variation of kNN neighbourhoods."""

from __future__ import annotations

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.core.neighbours import NeighbourIndex
from escape_cli.core.params import as_count

# Neighbours whose distance is within this relative tolerance of the k-th one are all
# kept, so that exact ties (grid-like scans) cannot change the neighbourhood under rotation.
NEIGHBOUR_TIE_RTOL = 1e-7


def tie_stable_neighbours(points: np.ndarray, k: int, *, tree=None) -> tuple[np.ndarray, np.ndarray]:
    """kNN neighbourhoods that include every point tied with the k-th neighbour.

    Parameters
    ----------
    points : (N, 3) float64
    k : neighbours per point, the point itself included.
    tree : a `NeighbourIndex` of `points` already built (reused), or None.

    Returns
    -------
    indices : (N, L) int64, L >= k, padded with the point itself.
    mask : (N, L) bool, True for real neighbours.
    """
    points = as_points(points, "points", min_points=1)
    n = len(points)
    k = min(as_count(k, "k (neighbours)", minimum=1), n)
    extra = min(n, k + 8)
    if tree is None:
        tree = NeighbourIndex(points)
    dist, idx = tree.query(points, extra)  # (N, L)
    kth = dist[:, k - 1 : k]  # (N, 1)
    mask = dist <= kth * (1.0 + NEIGHBOUR_TIE_RTOL) + 1e-15
    idx = np.where(mask, idx, np.arange(n)[:, None])
    return idx, mask


def surface_variation(points, k: int = 16, *, tree=None) -> np.ndarray:
    """Curvature as surface variation, kappa_i = lambda_min / (lambda_1 + lambda_2 + lambda_3).

    The eigenvalues are those of the covariance of point i's k nearest neighbours. It
    needs no normals, so it has no sign ambiguity, and eigenvalues are exactly rotation
    invariant. Flat regions give ~0, edges and corners up to 1/3.

    Parameters
    ----------
    points : (N, 3) float64
    k : neighbourhood size (the point itself included).
    tree : a `NeighbourIndex` of `points` already built (reused), or None.

    Returns
    -------
    curvature : (N,) float64 in [0, 1/3].
    """
    pts = as_points(points, "points", min_points=1)
    k = as_count(k, "k (neighbours)", minimum=1)
    idx, mask = tie_stable_neighbours(pts, k, tree=tree)
    weights = mask / mask.sum(axis=1, keepdims=True)  # (N, L)
    neigh = pts[idx]  # (N, L, 3)
    mean = np.einsum("nl,nlc->nc", weights, neigh)  # (N, 3)
    centred = (neigh - mean[:, None, :]) * np.sqrt(weights)[:, :, None]  # (N, L, 3)
    cov = np.einsum("nla,nlb->nab", centred, centred)  # (N, 3, 3)
    eig = np.linalg.eigvalsh(cov)  # (N, 3) ascending
    total = eig.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        kappa = np.where(total > 0, eig[:, 0] / total, 0.0)
    return np.clip(kappa, 0.0, 1.0 / 3.0)
