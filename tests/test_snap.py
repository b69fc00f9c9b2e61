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


def test_closed_form_plane_fits_match_eigh(rng):
    from escape_cli.core.snap import _plane_fits, _plane_fits_naive

    patches = rng.normal(size=(3000, 8, 3)) * rng.uniform(1e-4, 1.0, size=(3000, 1, 3))  # flat to round
    patches[:500, :, 2] = 0.0  # exactly flat
    patches = patches @ np.stack([random_rotation(rng) for _ in range(3000)]).transpose(0, 2, 1)
    offsets = patches - patches.mean(axis=1, keepdims=True)
    cov = offsets.transpose(0, 2, 1) @ offsets
    values, normal = _plane_fits(cov)
    ref_values, ref_normal = _plane_fits_naive(cov)
    scale = ref_values[:, 2:]
    # in units of the largest eigenvalue; near a double eigenvalue acos loses half the digits
    np.testing.assert_allclose(values / scale, ref_values / scale, atol=1e-8)
    np.testing.assert_allclose(values[:, 0] / scale[:, 0], ref_values[:, 0] / scale[:, 0], atol=1e-11)
    surface = ref_values[:, 0] <= 0.25 * ref_values[:, 1]  # where snapping uses the normal
    assert surface.sum() > 1000
    cosine = np.abs(np.einsum("pi,pi->p", normal, ref_normal))[surface]
    np.testing.assert_allclose(cosine, 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-12)


def test_snap_with_closed_form_fits_equals_snap_with_eigh(rng, monkeypatch):
    import escape_cli.core.snap as snap_module

    scan = plane_scan(rng, 1500)
    scan[:, 2] = 0.5 * scan[:, 0] ** 2 - 0.3 * scan[:, 1] ** 2  # a saddle
    points = scan[:400] + rng.normal(scale=0.03, size=(400, 3))
    fast = snap_to_scan(points, scan)

    def with_eigh(a00, a01, a02, a11, a12, a22):
        cov = np.stack([np.stack([a00, a01, a02], -1), np.stack([a01, a11, a12], -1), np.stack([a02, a12, a22], -1)], 1)
        return snap_module._plane_fits_naive(cov)

    monkeypatch.setattr(snap_module, "_plane_fits_entries", with_eigh)
    slow = snap_to_scan(points, scan)
    assert fast.moved.sum() > 300 and (fast.moved == slow.moved).all()
    np.testing.assert_allclose(fast.points, slow.points, atol=1e-12)
