"""The rotation-invariant encoding: distances from every point to the anchors."""

from __future__ import annotations

import numpy as np

from escape_cli.errors import PointCloudError


def distance_matrix(points, anchors) -> np.ndarray:
    """Euclidean distances from points to anchors, D[i, j] = ||p_i - a_j||.

    Parameters
    ----------
    points : (N, 3) float
    anchors : (K, 3) float

    Returns
    -------
    distances : (N, K) float64
    """
    pts = np.asarray(points, dtype=np.float64)
    anc = np.asarray(anchors, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PointCloudError(f"points must have shape (N, 3), got {pts.shape}")
    if anc.ndim != 2 or anc.shape[1] != 3 or len(anc) == 0:
        raise PointCloudError(f"anchors must have shape (K, 3) with K >= 1, got {anc.shape}")
    return np.linalg.norm(pts[:, None, :] - anc[None, :, :], axis=2)  # (N, K)
