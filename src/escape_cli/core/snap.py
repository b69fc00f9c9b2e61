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
from escape_cli.core.neighbours import NeighbourIndex
from escape_cli.core.params import as_count, as_number

__all__ = ["SNAP_RADIUS", "SNAP_NEIGHBOURS", "Snap", "check_snap_radius", "snap_to_scan"]

SNAP_RADIUS = 0.08  # in the network's units (PCN scale: objects span about 1)
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


def snap_to_scan(points, scan, radius: float = SNAP_RADIUS, neighbours: int = SNAP_NEIGHBOURS, *, tree=None,
                 workers: int = 1) -> Snap:
    """Pull predicted points near the scan onto the scan's local surface.

    Parameters
    ----------
    points : (M, 3) predicted points.
    scan : (N, 3) observed points in the same frame.
    radius : fade length of the pull; 0 turns snapping off.
    neighbours : scan points per fitted plane (at least 3).
    tree : a `NeighbourIndex` of `scan` already built (reused), or None.
    workers : threads of the neighbour query (the same result with any number).

    Returns
    -------
    Snap
    """
    pts = as_points(points, "points", min_points=0)
    ref = as_points(scan, "scan", min_points=0)
    radius = check_snap_radius(radius)
    neighbours = as_count(neighbours, "neighbours (scan points per plane)", minimum=MIN_SCAN_POINTS)
    unmoved = Snap(points=pts.copy(), moved=np.zeros(len(pts), dtype=bool))
    if radius == 0 or len(pts) == 0 or len(ref) < MIN_SCAN_POINTS:
        return unmoved

    if tree is None:
        tree = NeighbourIndex(ref)
    workers = as_count(workers, "workers", minimum=1)
    nearest, _ = tree.query(pts, 1, workers=workers, limit=2.0 * radius)  # (M, 1); inf beyond the reach
    near = np.flatnonzero(nearest[:, 0] < 2.0 * radius)
    if len(near) == 0:
        return unmoved
    dist, nbr = tree.query(pts[near], min(neighbours, len(ref)), workers=workers)  # (P, k) scan rows of each patch, nearest first
    gap = dist[:, 0]  # (P,)
    xs, ys, zs = (ref[:, c][nbr] for c in range(3))  # (P, k) each
    k = nbr.shape[1]
    centre = np.stack([np.einsum("pk->p", xs), np.einsum("pk->p", ys), np.einsum("pk->p", zs)], axis=1) / k  # (P, 3)
    xs, ys, zs = xs - centre[:, :1], ys - centre[:, 1:2], zs - centre[:, 2:]  # offsets from the patch centre

    def dot(u, v):
        return np.einsum("pk,pk->p", u, v)

    variance, normal = _plane_fits_entries(dot(xs, xs), dot(xs, ys), dot(xs, zs),
                                           dot(ys, ys), dot(ys, zs), dot(zs, zs))  # (P, 3) ascending, (P, 3)
    spread = variance[:, 2]
    is_surface = (spread > 0) & (variance[:, 1] > LINE_RATIO * spread) & (variance[:, 0] <= FLAT_RATIO * variance[:, 1])
    height = np.einsum("pi,pi->p", pts[near] - centre, normal)  # (P,)
    weight = np.exp(-((gap / radius) ** 2)) * is_surface  # (P,)

    out = pts.copy()
    out[near] -= np.where(is_surface, weight * height, 0.0)[:, None] * normal
    moved = np.zeros(len(pts), dtype=bool)
    moved[near] = weight > 0
    return Snap(points=out, moved=moved)


def _plane_fits(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues and the least-variance direction of symmetric 3x3 matrices, in closed form.

    The eigenvalues come from the trigonometric solution of the characteristic cubic
    (for A = q I + p B with q = tr(A) / 3, the eigenvalues are q + 2 p cos(phi + 2 pi j / 3),
    phi = acos(det(B) / 2) / 3); the unit eigenvector of the smallest is the largest of
    the three cross products of rows of A - lambda_min I. About 10x faster than
    ``numpy.linalg.eigh`` on (P, 3, 3) and as accurate where the smallest eigenvalue is
    well apart from the middle one (a surface patch); elsewhere the direction is
    whatever the cross products give (finite), which `snap_to_scan` does not use.

    Parameters
    ----------
    cov : (P, 3, 3) float64, symmetric positive semi-definite.

    Returns
    -------
    eigenvalues : (P, 3) float64, ascending.
    normal : (P, 3) float64, unit (zero where A is a multiple of I).
    """
    return _plane_fits_entries(cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2])


def _plane_fits_entries(a00, a01, a02, a11, a12, a22) -> tuple[np.ndarray, np.ndarray]:
    """`_plane_fits` of the matrices with these six entries, each (P,)."""
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    off = a01 * a01 + a02 * a02 + a12 * a12
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)  # (P,)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        half = np.where(p > 0, det / (2.0 * p * p * p), 0.0)
    phi = np.arccos(np.clip(half, -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    eigenvalues = np.stack([smallest, np.clip(middle, smallest, largest), largest], axis=1)  # (P, 3)
    # rows of A - lambda_min I (singular: they span the other two axes) and their cross products
    r0 = (a00 - smallest, a01, a02)
    r1 = (a01, a11 - smallest, a12)
    r2 = (a02, a12, a22 - smallest)
    cands = np.stack([_cross(r0, r1), _cross(r0, r2), _cross(r1, r2)])  # (3, 3, P): candidate, axis, point
    size = np.einsum("cip,cip->cp", cands, cands)  # (3, P)
    best = np.argmax(size, axis=0)  # (P,)
    cols = np.arange(len(q))
    normal = cands[best, :, cols]  # (P, 3)
    length = np.sqrt(size[best, cols])
    normal = np.where(length[:, None] > 0, normal / np.maximum(length, 1e-300)[:, None], 0.0)
    return eigenvalues, normal


def _cross(u, v) -> np.ndarray:
    """(3, P) cross products of vectors given as three (P,) components."""
    return np.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def _plane_fits_naive(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference for `_plane_fits`: ``numpy.linalg.eigh``."""
    variance, axes = np.linalg.eigh(cov)  # ascending
    return variance, axes[:, :, 0]
