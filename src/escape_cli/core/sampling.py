"""Deterministic farthest point sampling and the fixed-size network input.

Everything here is equivariant: the chosen indices do not change when the cloud is
rotated, translated or permuted (up to exact ties, which are broken by an equivariant
rule first and by index only when the geometry itself is symmetric).
"""

from __future__ import annotations

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.core.params import as_count
from escape_cli.errors import DegenerateGeometryError, PointCloudError

# Values within this relative tolerance of the best are treated as tied.
TIE_RTOL = 1e-9


def farthest_from_centroid(points: np.ndarray) -> int:
    """Index of the point farthest from the centroid (ties: lowest index).

    Parameters
    ----------
    points : (N, 3) float64
    """
    points = as_points(points, "points", min_points=1)
    radius = np.linalg.norm(points - points.mean(axis=0), axis=1)  # (N,)
    return int(np.flatnonzero(radius >= radius.max() * (1.0 - TIE_RTOL))[0])


def farthest_point_sampling(points, count: int, start: int | None = None) -> np.ndarray:
    """Deterministic farthest point sampling.

    The first point is the one farthest from the centroid (or `start`); each next point
    is the one farthest from those chosen. Near-ties are broken by the larger distance
    to the centroid, then by index, so the result is rotation, translation and
    permutation invariant for any cloud without exact symmetries.

    Parameters
    ----------
    points : (N, 3) float64
    count : number of points to choose, at most the number of distinct points.

    Returns
    -------
    indices : (count,) int64, in the order chosen.
    """
    pts = as_points(points)
    n = len(pts)
    if count > n:
        raise PointCloudError(f"cannot choose {count} points from a cloud of {n}")
    radius = np.linalg.norm(pts - pts.mean(axis=0), axis=1)  # (N,)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = farthest_from_centroid(pts) if start is None else start
    min_dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)  # (N,)
    for i in range(1, count):
        best = min_dist.max()
        if best <= 0.0:
            raise DegenerateGeometryError(f"the cloud has only {i} distinct points; {count} are needed")
        tied = np.flatnonzero(min_dist >= best * (1.0 - TIE_RTOL))
        nxt = tied[0] if len(tied) == 1 else tied[np.argmax(radius[tied])]
        chosen[i] = nxt
        np.minimum(min_dist, np.linalg.norm(pts - pts[nxt], axis=1), out=min_dist)
    return chosen


def count_distinct(points: np.ndarray, decimals: int = 12) -> int:
    """Number of distinct points (coordinates compared after rounding)."""
    points = as_points(points, "points", min_points=0)
    return len(np.unique(np.round(points, decimals), axis=0))


def prepare_input(points, size: int = 2048) -> tuple[np.ndarray, int]:
    """Make the fixed-size, farthest-point-ordered network input from a cloud of any size.

    Larger clouds are subsampled by farthest point sampling; smaller ones are put in
    farthest-point order and repeated cyclically (PCN repeats points too). Either way
    the first `q` rows are the `q`-point FPS subset for every `q`, which the network
    uses as its centres, and the result is equivariant.

    Parameters
    ----------
    points : (N, 3) float64, N >= 1 distinct points.
    size : number of output rows.

    Returns
    -------
    prepared : (size, 3) float64
    unique_count : number of leading rows that are distinct points (min(N, size)).
    """
    pts = as_points(points)
    distinct = np.unique(pts, axis=0)  # duplicates carry no information and break FPS
    if len(distinct) < len(pts):
        pts = distinct
    count = min(len(pts), size)
    order = farthest_point_sampling(pts, count)
    chosen = pts[order]  # (count, 3)
    if count < size:
        chosen = chosen[np.arange(size) % count]
    return chosen, count


def resample_rows(count: int, size: int, seed: int = 0) -> np.ndarray:
    """Deterministic rows to turn `count` points into `size`: a seeded subset, or all plus repeats.

    Depends only on the counts, so it commutes with any rotation of the points. The
    one resampling rule of the package (the network input, PCN-style fixed-size
    samples, completions).

    Returns
    -------
    rows : (size,) int64
    """
    count = as_count(count, "count", minimum=1)
    size = as_count(size, "size", minimum=1)
    if size == count:
        return np.arange(count)
    rng = np.random.default_rng(seed)
    if size < count:
        return np.sort(rng.choice(count, size, replace=False))
    extra = rng.choice(count, size - count, replace=size - count > count)
    return np.concatenate([np.arange(count), extra])
