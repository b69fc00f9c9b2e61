"""Tests for escape_cli.core.reconstruction: exact recovery, agreement with scipy, no explosion
on noisy near-planar anchors, equivariance, degenerate anchors and input checks."""

from __future__ import annotations

import numpy as np
import pytest

from escape_cli.errors import DegenerateGeometryError, EscapeError, PointCloudError
from escape_cli.core.reconstruction import (
    PLANAR_RATIO,
    Reconstruction,
    check_anchors,
    linear_multilateration,
    linear_multilateration_naive,
    plane_normal,
    reconstruct,
    rms_residuals,
)
from escape_cli.core.rotations import random_rotation

HALF = np.array([0.3, 0.2, 0.25])  # half extents of a PCN-sized box


def box_surface(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points uniform-ish on the surface of the box [-HALF, HALF]."""
    p = rng.uniform(-1.0, 1.0, (n, 3))
    face = rng.integers(0, 3, n)
    p[np.arange(n), face] = np.sign(p[np.arange(n), face])
    return p * HALF


def encode(points: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """(M, K) distances, D[i, j] = ||p_i - a_j||."""
    return np.sqrt(((points[:, None, :] - anchors[None, :, :]) ** 2).sum(axis=2))


SPREAD_ANCHORS = np.array(
    [[0.3, 0.2, 0.25], [-0.3, -0.2, 0.25], [0.3, -0.2, -0.25], [-0.3, 0.2, -0.25],
     [0.1, 0.0, 0.25], [0.0, 0.2, 0.1], [-0.3, 0.0, 0.0], [0.3, 0.1, 0.0]]
)


def flat_anchors(rng: np.random.Generator, ratio: float = 1e-3) -> np.ndarray:
    """8 anchors on the box's front face z = 0.25 with s_min / s_max = `ratio` exactly."""
    a = np.column_stack([rng.uniform(-0.3, 0.3, 8), rng.uniform(-0.2, 0.2, 8), rng.normal(0, 1, 8)])
    xy = a[:, :2] - a[:, :2].mean(axis=0)  # (8, 2)
    z = a[:, 2] - a[:, 2].mean()
    z -= xy @ np.linalg.lstsq(xy, z, rcond=None)[0]  # orthogonal to the in-plane directions
    s = np.linalg.svd(xy, compute_uv=False)
    a[:, 2] = z * (ratio * s[0] / np.linalg.norm(z)) + HALF[2]
    return a


def front_partial(points: np.ndarray) -> np.ndarray:
    """A partial view of the box: its front face plus a sliver of one side face."""
    front = points[points[:, 2] > HALF[2] - 1e-9]
    side = points[(points[:, 0] > HALF[0] - 1e-9) & (points[:, 2] > 0.1)]
    return np.concatenate([front, side])


# ------------------------------------------------------------------- recovery


def test_exact_distances_recover_cloud(rng):
    points = box_surface(2000, rng)
    rec = reconstruct(encode(points, SPREAD_ANCHORS), SPREAD_ANCHORS)
    assert isinstance(rec, Reconstruction)
    assert rec.points.shape == (2000, 3) and rec.points.dtype == np.float64
    assert rec.residuals.shape == (2000,)
    assert not rec.near_planar
    np.testing.assert_allclose(rec.points, points, atol=1e-6)
    assert rec.residuals.max() < 1e-9


def test_encoding_module_round_trip(rng):
    encoding = pytest.importorskip("escape_cli.core.encoding")
    points = box_surface(500, rng)
    rec = reconstruct(encoding.distance_matrix(points, SPREAD_ANCHORS), SPREAD_ANCHORS)
    np.testing.assert_allclose(rec.points, points, atol=1e-6)


def test_anchors_taken_from_the_cloud(rng):
    points = box_surface(1000, rng)
    anchors = points[rng.choice(len(points), 8, replace=False)]
    rec = reconstruct(encode(points, anchors), anchors)
    np.testing.assert_allclose(rec.points, points, atol=1e-6)


def test_exact_distances_near_planar_recover_cloud(rng):
    points = box_surface(1000, rng)
    anchors = flat_anchors(rng)
    rec = reconstruct(encode(points, anchors), anchors)
    assert rec.near_planar
    np.testing.assert_allclose(rec.points, points, atol=1e-5)


def test_linear_start_exact_on_exact_distances(rng):
    points = box_surface(300, rng)
    est = linear_multilateration(encode(points, SPREAD_ANCHORS), SPREAD_ANCHORS)
    np.testing.assert_allclose(est, points, atol=1e-12)


@pytest.mark.parametrize("flat", [False, True])
def test_linear_start_matches_naive(rng, flat):
    points = box_surface(200, rng)
    anchors = flat_anchors(rng, 0.01) if flat else SPREAD_ANCHORS
    dist = encode(points, anchors) + 0.01 * rng.standard_normal((200, 8))
    np.testing.assert_allclose(
        linear_multilateration(dist, anchors), linear_multilateration_naive(dist, anchors), atol=1e-12
    )


def test_residuals_are_rms_misfit(rng):
    points = box_surface(300, rng)
    dist = encode(points, SPREAD_ANCHORS) + 0.005 * rng.standard_normal((300, 8))
    rec = reconstruct(dist, SPREAD_ANCHORS)
    np.testing.assert_allclose(rec.residuals, rms_residuals(rec.points, dist, SPREAD_ANCHORS), atol=1e-15)
    assert 0.001 < np.median(rec.residuals) < 0.01  # of the order of the noise


def test_singular_values_reported(rng):
    rec = reconstruct(encode(box_surface(10, rng), SPREAD_ANCHORS), SPREAD_ANCHORS)
    expected = np.linalg.svd(SPREAD_ANCHORS - SPREAD_ANCHORS.mean(axis=0), compute_uv=False)
    np.testing.assert_allclose(rec.anchor_singular_values, expected)
    assert np.all(np.diff(rec.anchor_singular_values) <= 0)


# ------------------------------------------------------------- batched vs scipy


def test_batched_agrees_with_scipy_on_noisy_well_conditioned(rng):
    points = box_surface(300, rng)
    dist = encode(points, SPREAD_ANCHORS) + 0.005 * rng.standard_normal((300, 8))
    fast = reconstruct(dist, SPREAD_ANCHORS, method="batched")
    ref = reconstruct(dist, SPREAD_ANCHORS, method="scipy")
    np.testing.assert_allclose(fast.points, ref.points, atol=1e-6)
    np.testing.assert_allclose(fast.residuals, ref.residuals, atol=1e-9)
    assert np.all(fast.residuals <= ref.residuals + 1e-12)  # batched is never worse


def test_scipy_near_planar_is_bounded_and_mostly_agrees(rng):
    points = box_surface(200, rng)
    anchors = flat_anchors(rng)
    dist = encode(points, anchors) + 0.005 * rng.standard_normal((200, 8))
    ref_pts = front_partial(points)
    fast = reconstruct(dist, anchors, reference_points=ref_pts)
    ref = reconstruct(dist, anchors, method="scipy", reference_points=ref_pts)
    assert ref.near_planar
    assert np.linalg.norm(ref.points - points, axis=1).max() < 0.3
    agree = np.linalg.norm(fast.points - ref.points, axis=1) < 1e-3
    assert agree.mean() > 0.9


# --------------------------------------------------------- noisy, near-planar


@pytest.mark.parametrize("noise", [0.005, 0.01])
def test_noisy_near_planar_does_not_explode(noise):
    rng = np.random.default_rng(7)
    points = box_surface(3000, rng)
    anchors = flat_anchors(rng, 1e-3)
    s = np.linalg.svd(anchors - anchors.mean(axis=0), compute_uv=False)
    assert s[2] / s[0] == pytest.approx(1e-3, rel=1e-6)
    dist = encode(points, anchors) + noise * rng.standard_normal(points.shape[:1] + (8,))
    rec = reconstruct(dist, anchors, reference_points=front_partial(points))
    assert rec.near_planar
    err = np.linalg.norm(rec.points - points, axis=1)
    assert err.max() < 0.3  # no explosion (the box's diagonal is 0.86)
    assert np.mean(err > 0.1) < 0.02  # few mirrored points
    assert np.median(err) < 0.03


def test_noisy_near_planar_without_reference_is_bounded():
    rng = np.random.default_rng(8)
    points = box_surface(2000, rng)
    anchors = flat_anchors(rng, 1e-3)
    dist = encode(points, anchors) + 0.01 * rng.standard_normal((2000, 8))
    rec = reconstruct(dist, anchors)
    # Without the partial the side is a coin flip per shape: mirrored at worst.
    err = np.linalg.norm(rec.points - points, axis=1)
    assert err.max() < 1.2
    assert np.linalg.norm(rec.points - anchors.mean(axis=0), axis=1).max() < 1.0


def test_garbage_distances_stay_bounded(rng):
    anchors = flat_anchors(rng, 1e-3)
    dist = rng.uniform(0.0, 1.0, (2000, 8))  # no point fits these
    rec = reconstruct(dist, anchors)
    radius = np.linalg.norm(rec.points - anchors.mean(axis=0), axis=1)
    assert np.all(np.isfinite(rec.points))
    assert radius.max() < 2.0


def test_negative_distances_are_clipped(rng):
    points = box_surface(50, rng)
    dist = encode(points, SPREAD_ANCHORS)
    dist[:, 0] = -1e-3  # a network may predict slightly negative values
    rec = reconstruct(dist, SPREAD_ANCHORS)
    clipped = np.maximum(dist, 0.0)
    np.testing.assert_allclose(rec.residuals, rms_residuals(rec.points, clipped, SPREAD_ANCHORS), atol=1e-15)


def test_point_on_an_anchor(rng):
    points = np.concatenate([SPREAD_ANCHORS[:3], box_surface(5, rng)])
    rec = reconstruct(encode(points, SPREAD_ANCHORS), SPREAD_ANCHORS)
    np.testing.assert_allclose(rec.points, points, atol=1e-6)


def test_empty_input():
    rec = reconstruct(np.zeros((0, 8)), SPREAD_ANCHORS)
    assert rec.points.shape == (0, 3) and rec.residuals.shape == (0,)


# --------------------------------------------------------------- equivariance


def _check_equivariant(dist, anchors, reference, rng, method="batched", atol=1e-9):
    base = reconstruct(dist, anchors, method, reference_points=reference)
    for _ in range(20):
        rot = random_rotation(rng)
        t = rng.normal(0.0, 3.0, 3)
        moved = reconstruct(dist, anchors @ rot.T + t, method,
                            reference_points=None if reference is None else reference @ rot.T + t)
        assert moved.near_planar == base.near_planar
        np.testing.assert_allclose(moved.points, base.points @ rot.T + t, atol=atol)
        np.testing.assert_allclose(moved.residuals, base.residuals, atol=atol)


def test_equivariant_well_spread(rng):
    points = box_surface(400, rng)
    dist = encode(points, SPREAD_ANCHORS) + 0.005 * rng.standard_normal((400, 8))
    _check_equivariant(dist, SPREAD_ANCHORS, None, rng)


@pytest.mark.parametrize("with_reference", [True, False])
def test_equivariant_near_planar(rng, with_reference):
    points = box_surface(400, rng)
    anchors = flat_anchors(rng, 1e-3)
    dist = encode(points, anchors) + 0.005 * rng.standard_normal((400, 8))
    _check_equivariant(dist, anchors, front_partial(points) if with_reference else None, rng)


def test_equivariant_exactly_planar(rng):
    """Anchors in one plane: only the geometric side rule can choose, and it must turn too."""
    points = box_surface(300, rng)
    anchors = flat_anchors(rng, 1e-3)
    anchors[:, 2] = HALF[2]
    dist = encode(points, anchors) + 0.005 * rng.standard_normal((300, 8))
    _check_equivariant(dist, anchors, None, rng)


def test_equivariant_scipy_reference(rng):
    points = box_surface(40, rng)
    dist = encode(points, SPREAD_ANCHORS) + 0.005 * rng.standard_normal((40, 8))
    base = reconstruct(dist, SPREAD_ANCHORS, "scipy")
    rot, t = random_rotation(rng), rng.normal(0.0, 3.0, 3)
    moved = reconstruct(dist, SPREAD_ANCHORS @ rot.T + t, "scipy")
    np.testing.assert_allclose(moved.points, base.points @ rot.T + t, atol=1e-7)


def test_plane_normal_equivariant(rng):
    points = box_surface(500, rng)
    anchors = flat_anchors(rng, 1e-3)
    ref = front_partial(points)
    n = plane_normal(anchors, ref)
    assert n[2] < -0.99  # the partial extends behind its front face
    n0 = plane_normal(anchors)
    exact = anchors.copy()
    exact[:, 2] = 0.0
    n1 = plane_normal(exact)  # decided by the anchors' order alone
    for _ in range(20):
        rot, t = random_rotation(rng), rng.normal(0.0, 3.0, 3)
        np.testing.assert_allclose(plane_normal(anchors @ rot.T + t, ref @ rot.T + t), rot @ n, atol=1e-12)
        np.testing.assert_allclose(plane_normal(anchors @ rot.T + t), rot @ n0, atol=1e-12)
        np.testing.assert_allclose(plane_normal(exact @ rot.T + t), rot @ n1, atol=1e-12)


def test_point_order_does_not_matter(rng):
    points = box_surface(300, rng)
    anchors = flat_anchors(rng, 1e-3)
    dist = encode(points, anchors) + 0.005 * rng.standard_normal((300, 8))
    ref = front_partial(points)
    base = reconstruct(dist, anchors, reference_points=ref)
    perm = rng.permutation(300)
    again = reconstruct(dist[perm], anchors, reference_points=ref[rng.permutation(len(ref))])
    np.testing.assert_allclose(again.points, base.points[perm], atol=1e-12)


# ------------------------------------------------------------ errors and checks


def test_three_anchors_rejected(rng):
    with pytest.raises(DegenerateGeometryError, match="at least 4 anchors"):
        check_anchors(SPREAD_ANCHORS[:3])
    with pytest.raises(DegenerateGeometryError):
        reconstruct(np.ones((5, 3)), SPREAD_ANCHORS[:3])


def test_duplicated_anchors_rejected():
    anchors = np.repeat(SPREAD_ANCHORS[:3], [3, 3, 2], axis=0)  # 8 anchors, 3 distinct
    with pytest.raises(DegenerateGeometryError, match="distinct"):
        check_anchors(anchors)
    with pytest.raises(DegenerateGeometryError):
        reconstruct(np.ones((5, 8)), anchors)


def test_collinear_anchors_rejected(rng):
    line = np.outer(rng.uniform(-1, 1, 8), [1.0, 2.0, -0.5]) + [3.0, 0.0, 1.0]
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        check_anchors(line)
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        check_anchors(line + 1e-7 * rng.standard_normal(line.shape))


def test_non_finite_anchors_rejected():
    bad = SPREAD_ANCHORS.copy()
    bad[2, 1] = np.nan
    with pytest.raises(PointCloudError, match="NaN"):
        check_anchors(bad)


def test_planar_anchors_accepted():
    square = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    check_anchors(square)


def test_distance_shape_must_match_anchors():
    with pytest.raises(PointCloudError, match=r"\(10, 7\)"):
        reconstruct(np.ones((10, 7)), SPREAD_ANCHORS)
    with pytest.raises(PointCloudError, match=r"\(8,\)"):
        reconstruct(np.ones(8), SPREAD_ANCHORS)
    with pytest.raises(PointCloudError, match=r"\(8, 2\)"):
        reconstruct(np.ones((10, 8)), SPREAD_ANCHORS[:, :2])


def test_non_finite_distances_rejected():
    dist = np.ones((4, 8))
    dist[1, 3] = np.inf
    with pytest.raises(PointCloudError, match="NaN or infinite"):
        reconstruct(dist, SPREAD_ANCHORS)


def test_bad_reference_points_rejected():
    with pytest.raises(PointCloudError, match=r"\(5, 2\)"):
        reconstruct(np.ones((4, 8)), SPREAD_ANCHORS, reference_points=np.ones((5, 2)))


def test_bad_method_and_iterations_rejected():
    with pytest.raises(EscapeError, match="method"):
        reconstruct(np.ones((4, 8)), SPREAD_ANCHORS, method="gauss")
    with pytest.raises(EscapeError, match="max_iter"):
        reconstruct(np.ones((4, 8)), SPREAD_ANCHORS, max_iter=0)


def test_planar_threshold_documented():
    assert 0.0 < PLANAR_RATIO < 1.0


def test_batched_3x3_cholesky_matches_numpy(rng):
    from escape_cli.core.reconstruction import _cholesky_solve3

    g = rng.normal(size=(500, 3, 3))
    spd = g @ g.transpose(0, 2, 1) + 1e-3 * np.eye(3)
    b = rng.normal(size=(500, 3))
    x, ok = _cholesky_solve3(spd, b)
    assert ok.all()
    np.testing.assert_allclose(x, np.linalg.solve(spd, b[:, :, None])[:, :, 0], rtol=1e-8, atol=1e-10)
    indefinite = spd.copy()
    indefinite[:, 2, 2] = -1.0
    assert not _cholesky_solve3(indefinite, b)[1].any()


# --------------------------------------------------- fast batched vs its reference


@pytest.mark.parametrize("case", ["spread", "near-planar", "exactly planar", "garbage"])
def test_batched_equals_its_reference_on_noisy_input(rng, case):
    points = box_surface(9000, rng)  # more than one batch of the fast solver
    anchors = {"spread": SPREAD_ANCHORS, "near-planar": flat_anchors(rng, 1e-3),
               "exactly planar": flat_anchors(rng, 0.0), "garbage": SPREAD_ANCHORS}[case]
    dist = encode(points, anchors) + rng.normal(scale=0.01, size=(len(points), len(anchors)))
    if case == "garbage":
        dist = rng.uniform(0.0, 2.0, size=dist.shape)
    reference = front_partial(points) if case != "spread" else None
    fast = reconstruct(dist, anchors, "batched", reference_points=reference)
    slow = reconstruct(dist, anchors, "batched-naive", reference_points=reference)
    np.testing.assert_allclose(fast.points, slow.points, atol=1e-6)
    np.testing.assert_allclose(fast.residuals, slow.residuals, atol=1e-9)
    assert fast.near_planar == slow.near_planar
    wrong = lambda rec: int((np.linalg.norm(rec.points - points, axis=1) > 0.1).sum())  # noqa: E731
    assert wrong(fast) <= wrong(slow), "no more mirrored points than the reference"


def test_batched_result_does_not_depend_on_workers(rng):
    points = box_surface(10000, rng)
    dist = encode(points, SPREAD_ANCHORS) + rng.normal(scale=0.01, size=(len(points), 8))
    one = reconstruct(dist, SPREAD_ANCHORS, workers=1)
    two = reconstruct(dist, SPREAD_ANCHORS, workers=3)
    np.testing.assert_array_equal(one.points, two.points)
    np.testing.assert_array_equal(one.residuals, two.residuals)
    assert one.iterations == two.iterations
