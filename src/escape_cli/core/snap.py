"""Snapping predicted points onto the scanned surface where the scan saw it.

Near the observed part of an object the network's points scatter a few thousandths
around the true surface, while the scan lies on it. Each predicted point close to the
scan moves towards the plane fitted (local PCA) to its nearest scan points: all the
way when it sits on the scan, fading with distance d as exp(-(d / radius)^2), and not
at all beyond 2 * radius. Points whose scan neighbourhood is not a surface patch (a
corner, a line, a single point) stay where they are.

Every step (nearest neighbours, PCA planes, distances) commutes with rotations and
translations, so the completion stays equivariant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.core.params import as_count, as_number

__all__ = ["SNAP_RADIUS", "SNAP_NEIGHBOURS", "Snap", "check_snap_radius", "snap_to_scan"]

SNAP_RADIUS = 0.05  # in the network's units (PCN scale: objects span about 1)
SNAP_NEIGHBOURS = 8
FLAT_RATIO = 0.25  # a surface patch: smallest PCA variance <= FLAT_RATIO * middle one (a cube corner is 0.39)
LINE_RATIO = 1e-3  # ... and middle variance > LINE_RATIO * largest (not a line)
MIN_SCAN_POINTS = 3


def check_snap_radius(radius) -> float:
    """The radius as a float; ParameterError unless it is finite and >= 0."""
    return as_number(radius, "snap_radius", minimum=0.0)


@dataclass(frozen=True)
class Snap:
    """The result of `snap_to_scan`.

    Attributes
    ----------
    points : (M, 3) float64, the predicted points after snapping.
    moved : (M,) bool, True for points that moved towards the scan.
    """

    points: np.ndarray
    moved: np.ndarray


def snap_to_scan(points, scan, radius: float = SNAP_RADIUS, neighbours: int = SNAP_NEIGHBOURS) -> Snap:
    """Pull predicted points near the scan onto the scan's local surface.

    Parameters
    ----------
    points : (M, 3) predicted points.
    scan : (N, 3) observed points in the same frame.
    radius : fade length of the pull; 0 turns snapping off.
    neighbours : scan points per fitted plane (at least 3).

    Returns
    -------
    Snap
    """
    from scipy.spatial import cKDTree

    pts = as_points(points, "points", min_points=0)
    ref = as_points(scan, "scan", min_points=0)
    radius = check_snap_radius(radius)
    neighbours = as_count(neighbours, "neighbours (scan points per plane)", minimum=MIN_SCAN_POINTS)
    unmoved = Snap(points=pts.copy(), moved=np.zeros(len(pts), dtype=bool))
    if radius == 0 or len(pts) == 0 or len(ref) < MIN_SCAN_POINTS:
        return unmoved

    dist, rows = cKDTree(ref).query(pts, k=min(neighbours, len(ref)))  # (M, k), nearest first
    gap = dist[:, 0]  # (M,)
    near = np.flatnonzero(gap < 2.0 * radius)
    if len(near) == 0:
        return unmoved
    patch = ref[rows[near]]  # (P, k, 3)
    centre = patch.mean(axis=1)  # (P, 3)
    offsets = patch - centre[:, None]
    variance, axes = np.linalg.eigh(offsets.transpose(0, 2, 1) @ offsets)  # ascending
    normal = axes[:, :, 0]  # (P, 3)
    spread = variance[:, 2]
    is_surface = (spread > 0) & (variance[:, 1] > LINE_RATIO * spread) & (variance[:, 0] <= FLAT_RATIO * variance[:, 1])
    height = np.einsum("pi,pi->p", pts[near] - centre, normal)  # (P,)
    weight = np.exp(-((gap[near] / radius) ** 2)) * is_surface  # (P,)

    out = pts.copy()
    out[near] -= (weight * height)[:, None] * normal
    moved = np.zeros(len(pts), dtype=bool)
    moved[near] = weight > 0
    return Snap(points=out, moved=moved)
