"""Area-uniform point sampling of the *outer* surface of a union of convex parts.

Points are drawn area-uniformly on every part's triangles; those strictly inside
another part (buried where parts overlap) are dropped; a seeded subset of the
survivors is returned. Dropping buried points keeps the density uniform on the
union's outer surface.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import INSIDE_MARGIN, ConvexPart
from escape_cli.errors import DegenerateGeometryError


def sample_triangles(vertices: np.ndarray, triangles: np.ndarray, n_points: int,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Draw points area-uniformly on a triangle soup.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (F, 3) int64
    n_points : int
    rng : numpy.random.Generator

    Returns
    -------
    points : (n_points, 3) float64
    triangle_index : (n_points,) int64
        The triangle each point lies on.
    """
    tri = vertices[triangles]  # (F, 3, 3)
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)  # (F,)
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise DegenerateGeometryError("mesh has no surface area")
    index = rng.choice(len(tri), size=n_points, p=areas / total)
    u, v = rng.random(n_points), rng.random(n_points)
    outside = u + v > 1
    u[outside], v[outside] = 1 - u[outside], 1 - v[outside]
    t = tri[index]
    points = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return points, index


def buried_mask(parts: tuple[ConvexPart, ...] | list[ConvexPart], points: np.ndarray, owner: np.ndarray,
                margin: float = INSIDE_MARGIN) -> np.ndarray:
    """Which points lie strictly inside a part other than the one they were sampled on.

    Parameters
    ----------
    parts : sequence of ConvexPart
    points : (N, 3) float64
    owner : (N,) int64
        Index of the part each point lies on.

    Returns
    -------
    buried : (N,) bool
    """
    buried = np.zeros(len(points), dtype=bool)
    for k, part in enumerate(parts):
        candidates = np.flatnonzero((owner != k) & ~buried)
        if len(candidates):
            buried[candidates[part.contains_strictly(points[candidates], margin)]] = True
    return buried


def sample_outer_surface(parts: tuple[ConvexPart, ...] | list[ConvexPart], n_points: int,
                         rng: np.random.Generator, max_rounds: int = 20) -> np.ndarray:
    """Draw `n_points` area-uniform points on the outer surface of the union of `parts`.

    Parameters
    ----------
    parts : sequence of ConvexPart
    n_points : int
    rng : numpy.random.Generator
    max_rounds : int
        Oversampling rounds before giving up.

    Returns
    -------
    points : (n_points, 3) float64

    Raises
    ------
    DegenerateGeometryError
        When almost the whole surface is buried (cannot reach `n_points`).
    """
    vertices, triangles, owner_of_triangle, offset = [], [], [], 0
    for k, part in enumerate(parts):
        vertices.append(part.vertices)
        triangles.append(part.triangles + offset)
        owner_of_triangle.append(np.full(len(part.triangles), k))
        offset += len(part.vertices)
    vertices, triangles = np.concatenate(vertices), np.concatenate(triangles)
    owner_of_triangle = np.concatenate(owner_of_triangle)
    kept: list[np.ndarray] = []
    n_kept, batch = 0, int(1.6 * n_points)
    for _ in range(max_rounds):
        points, tri_index = sample_triangles(vertices, triangles, batch, rng)
        visible = points[~buried_mask(parts, points, owner_of_triangle[tri_index])]
        kept.append(visible)
        n_kept += len(visible)
        if n_kept >= n_points:
            break
    else:
        raise DegenerateGeometryError(f"only {n_kept} outer-surface points after {max_rounds} rounds")
    pool = np.concatenate(kept)
    return pool[np.sort(rng.choice(len(pool), size=n_points, replace=False))]
