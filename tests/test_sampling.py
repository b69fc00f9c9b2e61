"""Farthest point sampling: both fast paths (compiled and numpy) equal the naive loop, index for index, and are equivariant."""

from __future__ import annotations

import numpy as np
import pytest

from escape_cli.core import sampling
from escape_cli.core.rotations import random_rotation
from escape_cli.core.sampling import farthest_point_sampling, farthest_point_sampling_naive
from escape_cli.errors import DegenerateGeometryError
from tests_support import kernel_or_fallback, partial_cloud


def lattice(n_side: int, spacing: float = 0.1) -> np.ndarray:
    """(n_side^3, 3) a regular grid: many exact and near-exact distance ties."""
    axis = np.arange(n_side) * spacing
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def clouds():
    rng = np.random.default_rng(5)
    sphere = rng.normal(size=(6000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    scan = partial_cloud(rng, 1800)
    plane = rng.uniform(-0.5, 0.5, size=(3000, 3)) * [1.0, 1.0, 0.0]
    u, v = np.meshgrid(np.arange(40) * 0.01, np.arange(40) * 0.01, indexing="ij")
    image = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)  # a depth image's pixel grid
    return {
        "sphere": (sphere, 2048),
        "partial scan": (scan, 1800),  # every point: the full ordering
        "plane": (plane, 1024),
        "lattice": (lattice(12), 1728),
        "pixel grid": (image, 1600),
        "duplicated points": (np.concatenate([scan, scan[:700], scan[:50]]), 1800),
        "blob, a few": (rng.normal(size=(5000, 3)), 40),
    }


@pytest.fixture(params=["compiled", "numpy"])
def fast_path(request, monkeypatch):
    """Every test runs on the compiled kernel and on the numpy path (the kernel hidden)."""
    return kernel_or_fallback(request, monkeypatch, sampling, "numpy")


@pytest.mark.parametrize("name", list(clouds()))
def test_fast_fps_equals_naive(name, fast_path):
    cloud, count = clouds()[name]
    fast = farthest_point_sampling(cloud, count)
    assert fast.dtype == np.int64 and fast.shape == (count,)
    assert np.array_equal(fast, farthest_point_sampling_naive(cloud, count))


def test_fast_fps_equals_naive_from_a_given_start(fast_path):
    cloud, _ = clouds()["sphere"]
    for start in (0, 17, len(cloud) - 1):
        assert np.array_equal(farthest_point_sampling(cloud, 700, start=start),
                              farthest_point_sampling_naive(cloud, 700, start=start))


def test_fast_fps_raises_like_naive_when_points_run_out(fast_path):
    rng = np.random.default_rng(2)
    few = rng.normal(size=(300, 3))
    cloud = few[rng.integers(0, 300, size=1200)]  # 300 distinct points (at most), each repeated
    distinct = len(np.unique(cloud, axis=0))
    messages = []
    for fps in (farthest_point_sampling, farthest_point_sampling_naive):
        with pytest.raises(DegenerateGeometryError) as err:
            fps(cloud, distinct + 1)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and f"only {distinct} distinct" in messages[0]
    assert np.array_equal(farthest_point_sampling(cloud, distinct), farthest_point_sampling_naive(cloud, distinct))


@pytest.mark.parametrize("name", ["sphere", "partial scan"])
def test_fast_fps_is_equivariant(name, fast_path):
    cloud, count = clouds()[name]
    rng = np.random.default_rng(8)
    base = farthest_point_sampling(cloud, count)
    for _ in range(3):
        r, t, s = random_rotation(rng), rng.normal(scale=3.0, size=3), float(rng.uniform(0.01, 100.0))
        perm = rng.permutation(len(cloud))
        moved = (s * cloud @ r.T + t)[perm]
        assert np.array_equal(perm[farthest_point_sampling(moved, count)], base)


def test_first_unique_rows_equals_numpy_unique():
    from escape_cli.core.sampling import count_distinct, first_unique_rows

    rng = np.random.default_rng(4)
    base = rng.normal(size=(300, 8)).round(2)
    rows = np.concatenate([base, base[:120], -0.0 * base[:5], base[rng.integers(0, 300, 200)]])
    rows[rows == 0.0] = -0.0  # signed zeros count as equal, as in numpy
    rows = rows[rng.permutation(len(rows))]
    assert np.array_equal(first_unique_rows(rows, 8), np.sort(np.unique(rows, axis=0, return_index=True)[1]))
    cloud = rows[:, :3]
    assert count_distinct(cloud) == len(np.unique(cloud, axis=0))
    assert count_distinct(cloud * 1e-200) == count_distinct(cloud) == count_distinct(cloud * 1e100)  # any scale


# ------------------------------------------------------------------ huge clouds


def test_thinning_is_equivariant_and_even(rng):
    from escape_cli.core.sampling import thin_by_radius

    cloud = partial_cloud(rng, 60000)
    cloud = np.concatenate([cloud, cloud[:500], lattice(10, 0.01)])  # duplicates and exact ties too
    base = thin_by_radius(cloud, 5000)
    assert 2500 <= len(base) <= 5600 and np.all(np.diff(base) > 0)
    for _ in range(4):
        r, t, s = random_rotation(rng), rng.normal(scale=100.0, size=3), float(rng.uniform(1e-3, 1e3))
        perm = rng.permutation(len(cloud))
        got = thin_by_radius((s * cloud @ r.T + t)[perm], 5000)
        assert np.array_equal(np.sort(perm[got]), base)
    # even: the kept points cover the cloud about as a random 1-in-s subset does
    from scipy.spatial import cKDTree

    gaps = cKDTree(cloud[base]).query(cloud)[0]
    random_gaps = cKDTree(cloud[rng.choice(len(cloud), len(base), replace=False)]).query(cloud)[0]
    assert gaps.max() < 2.0 * random_gaps.max()
    assert np.array_equal(thin_by_radius(cloud[:3000], 5000), np.arange(3000))


def test_prepare_input_thins_huge_clouds_equivariantly(rng, monkeypatch):
    import escape_cli.core.sampling as sampling

    monkeypatch.setattr(sampling, "THIN_ABOVE", 20000)
    monkeypatch.setattr(sampling, "THIN_TO", 8000)
    cloud = partial_cloud(rng, 50000)
    prepared, unique = sampling.prepare_input(cloud, 2048)
    assert unique == 2048
    kept = sampling.thin_by_radius(cloud, 8000)
    assert np.array_equal(prepared, cloud[kept][farthest_point_sampling(cloud[kept], 2048)])
    r, t = random_rotation(rng), rng.normal(size=3)
    moved, _ = sampling.prepare_input((cloud @ r.T + t)[rng.permutation(len(cloud))], 2048)
    np.testing.assert_allclose(moved, prepared @ r.T + t, atol=1e-9)


# ---------------------------------------------------------------- keeping the confident points


def test_select_confident_rows_keeps_distinct_rows_in_order_and_is_repeatable():
    residuals = np.random.default_rng(0).random(500)
    rows = sampling.select_confident_rows(residuals, 420)
    assert rows.shape == (420,) and len(np.unique(rows)) == 420 and np.all(np.diff(rows) > 0)
    assert np.array_equal(rows, sampling.select_confident_rows(residuals, 420))
    assert np.array_equal(sampling.select_confident_rows(residuals, 500), np.arange(500))


def test_select_confident_rows_leaves_out_the_unsure_points_first():
    residuals = np.concatenate([np.full(900, 0.01), np.full(100, 1.0), np.zeros(50)])  # sure, unsure, observed
    rows = sampling.select_confident_rows(residuals, 950)
    left_out = np.setdiff1d(np.arange(1050), rows)
    assert np.all(left_out < 1000)  # the observed points (residual 0) all stay
    assert np.mean(left_out >= 900) > 0.9  # nearly all left-out points are the unsure ones
    # only when nothing with a residual is left do observed points go, uniformly
    rows = sampling.select_confident_rows(residuals, 20)
    assert np.all(rows >= 1000)


def test_select_confident_rows_ignores_the_residuals_scale():
    residuals = np.random.default_rng(1).random(300)
    rows = sampling.select_confident_rows(residuals, 200)
    for scale in (1e-3, 7.0, 1e3):
        assert np.array_equal(sampling.select_confident_rows(residuals * scale, 200), rows)


def test_select_confident_rows_refuses_bad_requests():
    from escape_cli.errors import PointCloudError

    with pytest.raises(PointCloudError):
        sampling.select_confident_rows(np.ones(10), 11)
    with pytest.raises(PointCloudError):
        sampling.select_confident_rows(-np.ones(10), 5)
    assert np.array_equal(sampling.select_confident_rows(np.zeros(10), 10), np.arange(10))
    assert len(np.unique(sampling.select_confident_rows(np.zeros(10), 4))) == 4
