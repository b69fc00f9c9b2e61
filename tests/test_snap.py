"""`escape_cli.core.snap`: predicted points near the scan move onto its surface, nothing else moves."""

from __future__ import annotations

import numpy as np
import pytest

from escape_cli.core.rotations import random_rotation
from escape_cli.core.snap import SNAP_RADIUS, snap_to_scan


def plane_scan(rng, count: int = 400) -> np.ndarray:
    """(count, 3) points on the z = 0 plane, x and y in [-0.5, 0.5]."""
    return np.column_stack([rng.uniform(-0.5, 0.5, (count, 2)), np.zeros(count)])


def test_points_on_the_scan_land_on_its_plane(rng):
    scan = plane_scan(rng, 20000)  # spacing about 0.007
    above = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), rng.normal(scale=0.003, size=50)])
    snap = snap_to_scan(above, scan)
    assert snap.moved.all()
    # the pull is exp(-(d / r)^2) with d a few thousandths: nearly all the way down
    assert np.all(np.abs(snap.points[:, 2]) <= 0.05 * np.abs(above[:, 2]))
    assert np.allclose(snap.points[:, :2], above[:, :2], atol=1e-12), "only the normal component changes"


def test_pull_fades_with_distance_and_stops_beyond_two_radii(rng):
    scan = plane_scan(rng, 2000)
    heights = np.array([0.5, 1.0, 1.5, 2.5]) * SNAP_RADIUS
    points = np.column_stack([np.zeros((4, 2)), heights])
    snap = snap_to_scan(points, scan)
    gaps = np.array([np.linalg.norm(scan - p, axis=1).min() for p in points])
    want = heights * (1.0 - np.exp(-((gaps / SNAP_RADIUS) ** 2)) * (gaps < 2 * SNAP_RADIUS))
    assert np.allclose(snap.points[:, 2], want, atol=1e-9)
    assert snap.moved.tolist() == [True, True, True, False]


def test_snap_is_equivariant(rng):
    scan = plane_scan(rng, 1000)
    scan[:, 2] = 0.8 * (scan[:, 0] ** 2 + scan[:, 1] ** 2)  # a smooth bowl
    points = scan[:200] + rng.normal(scale=0.02, size=(200, 3))
    base = snap_to_scan(points, scan)
    assert base.moved.sum() > 150
    for _ in range(5):
        r = random_rotation(rng)
        t = rng.normal(scale=5.0, size=3)
        moved = snap_to_scan(points @ r.T + t, scan @ r.T + t)
        assert np.allclose(moved.points, base.points @ r.T + t, atol=1e-9)
        assert (moved.moved == base.moved).all()


@pytest.mark.parametrize(
    "scan",
    [
        np.zeros((50, 3)),  # one point repeated
        np.column_stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)]),  # a line
        np.zeros((2, 3)),  # too few points for a plane
    ],
    ids=["all-equal", "collinear", "two-points"],
)
def test_degenerate_scans_move_nothing(scan, rng):
    points = rng.normal(scale=0.01, size=(30, 3))
    snap = snap_to_scan(points, scan)
    assert not snap.moved.any()
    assert np.array_equal(snap.points, points)


def test_corners_are_left_alone(rng):
    # three orthogonal faces meeting at the origin: a neighbourhood there is no plane
    faces = [np.roll(np.column_stack([rng.uniform(0, 0.02, (30, 2)), np.zeros(30)]), i, axis=1) for i in range(3)]
    scan = np.concatenate(faces)
    snap = snap_to_scan(np.array([[0.004, 0.004, 0.004]]), scan, neighbours=60)
    assert not snap.moved.any()


def test_radius_zero_and_bad_arguments(rng):
    scan = plane_scan(rng)
    points = scan[:10] + 0.01
    off = snap_to_scan(points, scan, radius=0.0)
    assert np.array_equal(off.points, points) and not off.moved.any()
    with pytest.raises(ValueError):
        snap_to_scan(points, scan, radius=-1.0)
    with pytest.raises(ValueError):
        snap_to_scan(points, scan, neighbours=2)
    with pytest.raises(ValueError):
        snap_to_scan(points[:, :2], scan)


def test_inputs_are_not_modified(rng):
    scan = plane_scan(rng)
    points = scan[:100] + 0.005
    before = points.copy(), scan.copy()
    snap_to_scan(points, scan)
    assert np.array_equal(points, before[0]) and np.array_equal(scan, before[1])
