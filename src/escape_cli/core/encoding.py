"""The rotation-invariant encoding: distances from every point to the anchors."""

from __future__ import annotations

import numpy as np

from escape_cli.core.checks import as_points


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
    pts = as_points(points, "points", min_points=0)
    anc = as_points(anchors, "anchors", min_points=1)
    return np.linalg.norm(pts[:, None, :] - anc[None, :, :], axis=2)  # (N, K)
