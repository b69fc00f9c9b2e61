"""Nearest neighbours among a fixed cloud: the k nearest points, and all within a radius.

`NeighbourIndex` answers with the compiled grid kernel (`_kernels.knn`) where the package
was built with it, else with scipy's cKDTree: the same neighbours with the same
distances, ordered by (distance, row) by the kernel (cKDTree orders exact ties its own
way). The kernel needs no scipy, so `escape complete` does not import scipy.spatial
(about a third of a cold start).
"""

from __future__ import annotations

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.core.params import as_count
from escape_cli.core.threads import thread_map
from escape_cli.errors import ParameterError

try:  # built with the package where a C compiler was found (setup.py)
    from escape_cli.core import _kernels
except ImportError:  # pragma: no cover - a build without it uses scipy
    _kernels = None

_QUERY_CHUNK = 65536  # queries per kernel call on one thread
_MIN_SHARE = 1024  # fewer queries per thread are not worth a thread


class NeighbourIndex:
    """The points of a cloud, ready for neighbour queries.

    Parameters
    ----------
    points : (M, 3) float, M >= 1.
    """

    def __init__(self, points):
        self.points = np.ascontiguousarray(as_points(points, "points", min_points=1), dtype=np.float64)  # (M, 3)
        self._tree = None
        if _kernels is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.points)

    def query(self, queries, k: int, workers: int = 1, limit: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """The k nearest points of each query, nearest first.

        Parameters
        ----------
        queries : (Q, 3) float
        k : 1 <= k <= M.
        workers : threads (the same result with any number).
        limit : only points at most this far count (fast for far queries); missing
            neighbours have distance inf and row M, as with cKDTree's distance_upper_bound.

        Returns
        -------
        dist : (Q, k) float64
        rows : (Q, k) int64, rows of `points`.
        """
        q = np.ascontiguousarray(as_points(queries, "queries", min_points=0), dtype=np.float64)
        k = as_count(k, "k (neighbours)", minimum=1)
        if k > len(self.points):
            raise ParameterError(f"k (neighbours) = {k} is more than the {len(self.points)} points")
        if self._tree is not None:
            dist, rows = self._tree.query(q, k=k, workers=workers, distance_upper_bound=_upper_bound(limit))
            return dist.reshape(len(q), k), rows.reshape(len(q), k).astype(np.int64)
        dist = np.empty((len(q), k))
        rows = np.empty((len(q), k), dtype=np.int64)
        size = _QUERY_CHUNK if workers <= 1 else max(_MIN_SHARE, -(-len(q) // workers))  # equal shares per thread
        chunks = [slice(i, i + size) for i in range(0, len(q), size)]
        thread_map(lambda part: _kernels.knn(self.points, q[part], k, float(limit), dist[part], rows[part]), chunks, workers)
        return dist, rows

    def query_ball_point(self, x, radius: float) -> np.ndarray:
        """(L,) int64, ascending: the rows of the points within `radius` of the point x (3,)."""
        x = np.asarray(x, dtype=np.float64).reshape(3)
        d = self.points - x  # (M, 3)
        return np.flatnonzero(((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2]) <= radius * radius)


def _upper_bound(limit: float) -> float:
    """cKDTree's distance_upper_bound (strict) for our inclusive `limit`."""
    return float(np.nextafter(limit, np.inf)) if np.isfinite(limit) else np.inf
