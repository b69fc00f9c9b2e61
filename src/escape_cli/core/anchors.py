"""Anchor points on a partial cloud: deterministic FPS, refined towards high curvature.

Methods (paper section 3.1 and its ablation):

- ``fps``: deterministic farthest point sampling started from the point farthest from
  the centroid.
- ``ball`` (default): each FPS anchor moves to the highest-curvature point within
  `radius` of it.
- ``cluster``: each point joins its nearest FPS anchor; each cluster's highest-curvature
  point becomes the anchor.

All three are rotation, translation and permutation equivariant: near-ties in curvature
are broken by distance to the FPS anchor, then by distance to the centroid.

`anchor_sets` gives further, equally equivariant sets for an ensemble: set j restarts
the FPS from the j-th anchor of the first set's FPS order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from escape_cli.core.checks import as_points, check_not_collinear
from escape_cli.core.curvature import surface_variation
from escape_cli.core.neighbours import NeighbourIndex
from escape_cli.core.sampling import count_distinct, farthest_point_sampling
from escape_cli.core.settings import DEFAULTS, METHODS, AnchorSettings
from escape_cli.errors import DegenerateGeometryError, ParameterError

__all__ = ["Anchors", "AnchorSettings", "DEFAULTS", "METHODS", "anchor_sets", "select_anchors"]

# Curvatures within this absolute tolerance of the best candidate are treated as tied.
CURVATURE_TIE_ATOL = 1e-6


@dataclass(frozen=True)
class Anchors:
    """Anchors chosen on a cloud.

    Attributes
    ----------
    indices : (K,) int64, rows of the input cloud.
    points : (K, 3) float64, the anchor coordinates.
    """

    indices: np.ndarray
    points: np.ndarray


def select_anchors(
    points,
    k: int = DEFAULTS.k,
    method: str = DEFAULTS.method,
    radius: float = DEFAULTS.radius,
    knn: int = DEFAULTS.knn,
    *,
    tree=None,
) -> Anchors:
    """Choose `k` distinct anchor points on a cloud.

    Parameters
    ----------
    points : (N, 3) float, N >= k distinct points, not all on one line.
    k : number of anchors (>= 4 for a 3D reconstruction).
    method : "ball", "fps" or "cluster".
    radius : search radius of the "ball" refinement, in the cloud's units.
    knn : neighbourhood size of the curvature estimate.
    tree : a `NeighbourIndex` of `points` already built (reused), or None.

    Returns
    -------
    Anchors with indices (K,) and points (K, 3).
    """
    return anchor_sets(points, 1, k, method, radius, knn, tree=tree)[0]


def anchor_sets(
    points,
    count: int,
    k: int = DEFAULTS.k,
    method: str = DEFAULTS.method,
    radius: float = DEFAULTS.radius,
    knn: int = DEFAULTS.knn,
    *,
    tree=None,
) -> list[Anchors]:
    """`count` anchor sets on a cloud; the first is `select_anchors`'s.

    Set j (j >= 1) runs the same method from a farthest point sampling restarted at the
    j-th seed of the first set's FPS order, so every set is as equivariant as the first.
    Sets may coincide on small or symmetric clouds.

    Parameters
    ----------
    points, k, method, radius, knn, tree : as in `select_anchors`.
    count : number of sets, 1 <= count <= k.

    Returns
    -------
    list of `count` Anchors, each with indices (K,) and points (K, 3).
    """
    AnchorSettings(k, method, radius, knn)  # checks the parameters
    if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or not 1 <= count <= k:
        raise ParameterError(f"the number of anchor sets must be an integer from 1 to {k} (the anchors), got {count!r}")
    pts = as_points(points, "the cloud", min_points=k)
    distinct = count_distinct(pts)
    if distinct < k:
        raise DegenerateGeometryError(f"the cloud has only {distinct} distinct points; {k} anchors need at least {k}")
    check_not_collinear(pts, "the cloud's points")

    first = farthest_point_sampling(pts, k)  # (K,)
    seed_sets = [first] + [farthest_point_sampling(pts, k, start=int(first[j])) for j in range(1, count)]
    if method == "fps":
        chosen_sets = seed_sets
    else:
        if tree is None:
            tree = NeighbourIndex(pts)
        curvature = surface_variation(pts, knn, tree=tree)  # (N,)
        centroid_dist = np.linalg.norm(pts - pts.mean(axis=0), axis=1)  # (N,)
        refine = _refine_in_balls if method == "ball" else _refine_in_clusters
        extra = (radius, tree) if method == "ball" else ()
        chosen_sets = [refine(pts, seeds, curvature, centroid_dist, *extra) for seeds in seed_sets]
    return [Anchors(indices=chosen.astype(np.int64), points=pts[chosen].copy()) for chosen in chosen_sets]


def _best_candidate(candidates, curvature, seed_point, pts, centroid_dist) -> int:
    """Highest curvature; near-ties -> nearest the FPS seed, then farthest from the centroid."""
    kappa = curvature[candidates]
    tied = candidates[kappa >= kappa.max() - CURVATURE_TIE_ATOL]
    if len(tied) == 1:
        return int(tied[0])
    to_seed = np.linalg.norm(pts[tied] - seed_point, axis=1)
    near = tied[to_seed <= to_seed.min() * (1 + 1e-9) + 1e-12]
    return int(near[np.argmax(centroid_dist[near])])


def _is_free(pts, chosen: list[int]) -> np.ndarray:
    """(N,) bool: points whose coordinates differ from every anchor chosen so far."""
    free = np.ones(len(pts), dtype=bool)
    for c in chosen:
        free &= np.any(pts != pts[c], axis=1)
    return free


def _refine_in_balls(pts, seeds, curvature, centroid_dist, radius, tree) -> np.ndarray:
    chosen: list[int] = []
    for seed in seeds:
        free = _is_free(pts, chosen)
        ball = np.asarray(tree.query_ball_point(pts[seed], radius), dtype=np.int64)
        candidates = ball[free[ball]] if len(ball) else ball
        if len(candidates) == 0:  # the whole ball is taken: nearest free point
            candidates = np.flatnonzero(free)
            d = np.linalg.norm(pts[candidates] - pts[seed], axis=1)
            candidates = candidates[d <= d.min() * (1 + 1e-9) + 1e-12]
        chosen.append(_best_candidate(candidates, curvature, pts[seed], pts, centroid_dist))
    return np.asarray(chosen)


def _refine_in_clusters(pts, seeds, curvature, centroid_dist) -> np.ndarray:
    to_seeds = np.linalg.norm(pts[:, None, :] - pts[seeds][None, :, :], axis=2)  # (N, K)
    cluster = np.argmin(to_seeds, axis=1)  # (N,)
    chosen: list[int] = []
    for j, seed in enumerate(seeds):
        members = np.flatnonzero(cluster == j)
        chosen.append(_best_candidate(members, curvature, pts[seed], pts, centroid_dist))
    return np.asarray(chosen)
