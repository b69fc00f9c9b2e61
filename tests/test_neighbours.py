"""Nearest neighbours: the compiled grid kernel finds what scipy's cKDTree finds, with the same distances."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from escape_cli.core import neighbours
from escape_cli.core.neighbours import NeighbourIndex
from escape_cli.core.rotations import random_rotation
from escape_cli.errors import ParameterError
from tests_support import kernel_or_fallback, partial_cloud


def cases():
    rng = np.random.default_rng(3)
    scan = partial_cloud(rng, 1500)
    return {
        "scan, itself": (scan, scan, 24, np.inf),
        "scan, a completion around it": (scan, scan[rng.integers(0, 1500, 4000)] + rng.normal(scale=0.1, size=(4000, 3)), 10, np.inf),
        "scan, within a limit": (scan, scan[rng.integers(0, 1500, 3000)] + rng.normal(scale=0.2, size=(3000, 3)), 3, 0.05),
        "flat": (rng.uniform(size=(2000, 3)) * [1.0, 1.0, 0.0], rng.uniform(size=(500, 3)), 16, np.inf),
        "a line": (np.outer(np.linspace(0.0, 1.0, 400), [1.0, 2.0, 3.0]), rng.normal(size=(100, 3)), 7, np.inf),
        "far queries": (rng.normal(size=(300, 3)), rng.normal(size=(50, 3)) * 1e6, 5, np.inf),
        "k = every point": (rng.normal(size=(20, 3)), rng.normal(size=(30, 3)), 20, np.inf),
        "one point": (np.zeros((1, 3)), rng.normal(size=(4, 3)), 1, np.inf),
        "repeated points": (np.repeat(rng.normal(size=(50, 3)), 3, axis=0), rng.normal(size=(100, 3)), 9, np.inf),
        "a grid (ties)": (np.stack(np.meshgrid(*[np.arange(8) * 0.1] * 3, indexing="ij"), -1).reshape(-1, 3), rng.uniform(size=(200, 3)), 6, np.inf),
    }


@pytest.fixture(params=["compiled", "scipy"])
def path(request, monkeypatch):
    """Every test runs on the compiled kernel and on the cKDTree path (the kernel hidden)."""
    return kernel_or_fallback(request, monkeypatch, neighbours, "scipy")


@pytest.mark.parametrize("name", list(cases()))
def test_query_finds_what_ckdtree_finds(name, path):
    ref, queries, k, limit = cases()[name]
    dist, rows = NeighbourIndex(ref).query(queries, k, limit=limit)
    want_dist, want_rows = cKDTree(ref).query(queries, k=k, distance_upper_bound=np.nextafter(limit, np.inf))
    want_dist, want_rows = want_dist.reshape(len(queries), k), want_rows.reshape(len(queries), k)
    assert dist.shape == rows.shape == (len(queries), k) and rows.dtype == np.int64
    assert np.array_equal(dist, want_dist)  # the same floats, in the same order
    for got, want in zip(rows, want_rows):  # the same rows, up to the order of exact ties
        assert sorted(got) == sorted(want)
    if path == "compiled":  # ties ordered by row
        tied = (dist[:, 1:] == dist[:, :-1]) & np.isfinite(dist[:, 1:])  # missing neighbours (inf) aside
        assert np.all(rows[:, 1:][tied] > rows[:, :-1][tied])


def test_query_with_several_threads_is_the_same(path):
    ref, queries, k, _ = cases()["scan, a completion around it"]
    index = NeighbourIndex(ref)
    many = np.concatenate([queries] * 5)  # more than one chunk
    one = index.query(many, k, workers=1)
    two = index.query(many, k, workers=2)
    assert np.array_equal(one[0], two[0]) and np.array_equal(one[1], two[1])


def test_ball_query_is_ckdtree_sorted(path):
    ref, _, _, _ = cases()["scan, itself"]
    index, tree = NeighbourIndex(ref), cKDTree(ref)
    for row in (0, 10, 700):
        got = index.query_ball_point(ref[row], 0.075)
        assert np.array_equal(got, np.sort(tree.query_ball_point(ref[row], 0.075)))


def test_neighbours_are_equivariant(path):
    ref, queries, k, _ = cases()["scan, a completion around it"]
    rng = np.random.default_rng(4)
    dist, rows = NeighbourIndex(ref).query(queries, k)
    for _ in range(3):
        r, t, s = random_rotation(rng), rng.normal(scale=5.0, size=3), float(rng.uniform(1e-3, 1e3))
        moved_dist, moved_rows = NeighbourIndex(s * ref @ r.T + t).query(s * queries @ r.T + t, k)
        assert np.allclose(moved_dist, s * dist, rtol=1e-9, atol=0)
        same = np.all(np.abs(np.diff(dist, axis=1)) > 1e-9 * dist[:, 1:], axis=1)  # rows without near-ties
        assert np.array_equal(moved_rows[same], rows[same])


def test_k_larger_than_the_cloud_is_refused(path):
    with pytest.raises(ParameterError, match="more than the 5 points"):
        NeighbourIndex(np.random.default_rng(0).normal(size=(5, 3))).query(np.zeros((1, 3)), 6)


def test_thread_map_keeps_the_order_and_reuses_its_threads():
    from escape_cli.core import threads

    assert threads.thread_map(lambda x: x * x, range(7), workers=3) == [x * x for x in range(7)]
    pool = threads._POOLS[3]
    assert threads.thread_map(lambda x: -x, [1, 2, 3], workers=3) == [-1, -2, -3]
    assert threads._POOLS[3] is pool  # one pool per worker count, kept
    assert threads.thread_map(str, [5], workers=4) == ["5"]  # one item: no thread
