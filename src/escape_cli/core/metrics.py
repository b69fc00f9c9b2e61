"""Point-cloud completion metrics (Chamfer L1/L2, F-Score, Fidelity), KD-tree based.

Every function returns the *raw* value in the clouds' own units; the community's
"x 1000" is the caller's business. Each fast function has a brute-force numpy
``*_naive`` twin beside it; the tests check that they agree.

Shapes: pred (M, 3), gt (G, 3), input (N, 3).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from escape_cli.core.checks import as_points
from escape_cli.core.params import as_number

__all__ = [
    "nearest_distances",
    "chamfer_l1",
    "chamfer_l2",
    "fscore",
    "fidelity",
    "point_metrics",
    "nearest_distances_naive",
    "chamfer_l1_naive",
    "chamfer_l2_naive",
    "fscore_naive",
    "fidelity_naive",
    "point_metrics_naive",
]

# Brute-force reference: at most this many pairwise differences per chunk (x3 floats).
_NAIVE_CHUNK_ELEMENTS = 1 << 21


# --------------------------------------------------------------------------- checks


def _check_threshold(threshold: float) -> float:
    return as_number(threshold, "the F-Score threshold", above=0.0)


# ------------------------------------------------------------------------ metrics


def nearest_distances(source, target) -> np.ndarray:
    """For every source point, the distance to its nearest target point (KD-tree).

    Parameters
    ----------
    source : (S, 3) float
    target : (T, 3) float

    Returns
    -------
    distances : (S,) float64
        min_y ||x - y|| for each x in source, y in target (unsquared).
    """
    src = as_points(source, "source")
    tgt = as_points(target, "target")
    return _query(src, tgt)


def _query(src: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    dist, _ = cKDTree(tgt).query(src, k=1)  # (S,)
    return np.asarray(dist, dtype=np.float64)


def nearest_distances_naive(source, target) -> np.ndarray:
    """Brute-force `nearest_distances`: all pairwise differences, chunked over source."""
    src = as_points(source, "source")
    tgt = as_points(target, "target")
    chunk = max(1, _NAIVE_CHUNK_ELEMENTS // len(tgt))
    out = np.empty(len(src), dtype=np.float64)
    for start in range(0, len(src), chunk):
        block = src[start : start + chunk]  # (c, 3)
        diff = block[:, None, :] - tgt[None, :, :]  # (c, T, 3)
        out[start : start + chunk] = np.sqrt((diff * diff).sum(axis=2)).min(axis=1)  # (c,)
    return out


# ------------------------------------------------------------------ from distances


def _cd_l1(d_pg: np.ndarray, d_gp: np.ndarray) -> float:
    return float((d_pg.mean() + d_gp.mean()) / 2.0)


def _cd_l2(d_pg: np.ndarray, d_gp: np.ndarray) -> float:
    return float(np.mean(d_pg * d_pg) + np.mean(d_gp * d_gp))


def _fscore(d_pg: np.ndarray, d_gp: np.ndarray, threshold: float) -> float:
    precision = float(np.mean(d_pg < threshold))
    recall = float(np.mean(d_gp < threshold))
    if precision + recall == 0.0:
        return 0.0
    return 2.0 * precision * recall / (precision + recall)


def _both_ways(pred, gt, naive: bool) -> tuple[np.ndarray, np.ndarray]:
    p = as_points(pred, "pred")
    g = as_points(gt, "gt")
    if naive:
        return nearest_distances_naive(p, g), nearest_distances_naive(g, p)
    return _query(p, g), _query(g, p)  # (M,), (G,)


# ------------------------------------------------------------------------- metrics


def chamfer_l1(pred, gt) -> float:
    """Chamfer distance with unsquared distances, the two directions averaged.

    CD-L1 = ( mean_{x in pred} min_{y in gt} ||x - y|| + mean_{y in gt} min_{x in pred} ||y - x|| ) / 2

    The paper's metric (it reports CD-L1 x 1000; this returns the raw value).

    Parameters
    ----------
    pred : (M, 3) float
    gt : (G, 3) float

    Returns
    -------
    float
    """
    return _cd_l1(*_both_ways(pred, gt, naive=False))


def chamfer_l1_naive(pred, gt) -> float:
    """Brute-force reference for `chamfer_l1` (same formula, no KD-tree)."""
    return _cd_l1(*_both_ways(pred, gt, naive=True))


def chamfer_l2(pred, gt) -> float:
    """Chamfer distance with squared distances, the two directions summed.

    CD-L2 = mean_{x in pred} min_{y in gt} ||x - y||^2 + mean_{y in gt} min_{x in pred} ||y - x||^2

    Parameters
    ----------
    pred : (M, 3) float
    gt : (G, 3) float

    Returns
    -------
    float
    """
    return _cd_l2(*_both_ways(pred, gt, naive=False))


def chamfer_l2_naive(pred, gt) -> float:
    """Brute-force reference for `chamfer_l2` (same formula, no KD-tree)."""
    return _cd_l2(*_both_ways(pred, gt, naive=True))


def fscore(pred, gt, threshold: float = 0.01) -> float:
    """F-Score at a distance threshold (unsquared distances).

    P = share of pred points x with min_y ||x - y|| < threshold (precision),
    R = share of gt points y with min_x ||y - x|| < threshold (recall),
    F = 2 P R / (P + R), and 0 when P = R = 0.

    Parameters
    ----------
    pred : (M, 3) float
    gt : (G, 3) float
    threshold : float
        0.01 is the community's F-Score@1% on PCN-scale shapes.

    Returns
    -------
    float in [0, 1]
    """
    t = _check_threshold(threshold)
    return _fscore(*_both_ways(pred, gt, naive=False), t)


def fscore_naive(pred, gt, threshold: float = 0.01) -> float:
    """Brute-force reference for `fscore` (same formula, no KD-tree)."""
    t = _check_threshold(threshold)
    return _fscore(*_both_ways(pred, gt, naive=True), t)


def fidelity(input_points, output_points) -> float:
    """Fidelity (KITTI): how well the output keeps the observed points.

    Fidelity = mean_{x in input} min_{y in output} ||x - y||

    Parameters
    ----------
    input_points : (N, 3) float
        The partial scan.
    output_points : (M, 3) float
        The completion.

    Returns
    -------
    float
    """
    src = as_points(input_points, "input")
    out = as_points(output_points, "output")
    return float(_query(src, out).mean())


def fidelity_naive(input_points, output_points) -> float:
    """Brute-force reference for `fidelity` (same formula, no KD-tree)."""
    return float(nearest_distances_naive(input_points, output_points).mean())


def point_metrics(pred, gt, threshold: float = 0.01) -> dict[str, float]:
    """CD-L1, CD-L2 and F-Score from one pair of KD-tree queries.

    Parameters
    ----------
    pred : (M, 3) float
    gt : (G, 3) float
    threshold : float
        F-Score threshold.

    Returns
    -------
    dict
        ``{"cd_l1": chamfer_l1, "cd_l2": chamfer_l2, "fscore": fscore}``, raw values
        (not x 1000), each as defined in the function of that name, and the two halves
        of CD-L1: ``"pred_to_gt"`` = mean_x min_y ||x - y|| (precision: are the predicted
        points on the shape?) and ``"gt_to_pred"`` = mean_y min_x ||y - x|| (recall: is
        the shape covered?); cd_l1 is their mean.
    """
    t = _check_threshold(threshold)
    return _point_metrics(*_both_ways(pred, gt, naive=False), t)  # (M,), (G,)


def point_metrics_naive(pred, gt, threshold: float = 0.01) -> dict[str, float]:
    """Brute-force reference for `point_metrics`."""
    t = _check_threshold(threshold)
    return _point_metrics(*_both_ways(pred, gt, naive=True), t)


def _point_metrics(d_pg: np.ndarray, d_gp: np.ndarray, threshold: float) -> dict[str, float]:
    return {"cd_l1": _cd_l1(d_pg, d_gp), "cd_l2": _cd_l2(d_pg, d_gp), "fscore": _fscore(d_pg, d_gp, threshold),
            "pred_to_gt": float(d_pg.mean()), "gt_to_pred": float(d_gp.mean())}
