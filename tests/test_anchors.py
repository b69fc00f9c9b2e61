"""Anchors and encoding: equivariance under rotation, translation and permutation; bad input."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import realdata_clouds, realdata_id
from escape_cli.core.anchors import METHODS, anchor_sets, select_anchors
from escape_cli.core.curvature import surface_variation
from escape_cli.core.encoding import distance_matrix
from escape_cli.errors import DegenerateGeometryError, PointCloudError
from escape_cli.core.rotations import random_rotation
from escape_cli.core.sampling import farthest_point_sampling, prepare_input
from tests_support import ellipsoid_surface, partial_cloud

MAX_REAL_POINTS = 6000  # larger real scans are thinned (fixed stride) to keep the test fast


def assert_equivariant(cloud: np.ndarray, rng: np.random.Generator, method: str, trials: int = 20) -> None:
    base = select_anchors(cloud, method=method)
    assert len(np.unique(base.points, axis=0)) == len(base.points), "anchors must be distinct points"
    for i in range(trials):
        r = random_rotation(rng)
        t = rng.normal(scale=2.0, size=3)
        perm = rng.permutation(len(cloud))
        moved = (cloud @ r.T + t)[perm]
        got = select_anchors(moved, method=method)
        assert np.array_equal(perm[got.indices], base.indices), f"{method}, trial {i}: other anchors chosen"
        np.testing.assert_allclose(got.points, base.points @ r.T + t, atol=1e-6)


def synthetic_clouds():
    rng = np.random.default_rng(7)
    box = rng.uniform(-0.4, 0.4, size=(3000, 3))
    box[np.arange(3000), rng.integers(0, 3, 3000)] = rng.choice([-0.4, 0.4], 3000)  # box surface
    return {
        "ellipsoid": ellipsoid_surface(rng, 2048, [0.45, 0.3, 0.15]),
        "half_ellipsoid": partial_cloud(rng, 1500),
        "box_surface": box,
        "noisy_blob": rng.normal(scale=0.2, size=(800, 3)),
    }


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", list(synthetic_clouds()))
def test_anchors_equivariant_on_synthetic_clouds(name, method):
    assert_equivariant(synthetic_clouds()[name], np.random.default_rng(3), method)


@pytest.mark.parametrize("path", realdata_clouds(), ids=realdata_id)
def test_anchors_equivariant_on_real_scans(path, realdata_dir):
    from escape_cli.io import read_points

    cloud = read_points(path)
    if len(cloud) > MAX_REAL_POINTS:
        cloud = cloud[:: int(np.ceil(len(cloud) / MAX_REAL_POINTS))]
    cloud = np.unique(cloud, axis=0)
    rng = np.random.default_rng(11)
    for method in METHODS:
        assert_equivariant(cloud, rng, method)


@pytest.mark.parametrize("method", METHODS)
def test_anchor_sets_are_equivariant_and_start_with_the_usual_set(method):
    rng = np.random.default_rng(5)
    cloud = synthetic_clouds()["half_ellipsoid"]
    base = anchor_sets(cloud, 8, method=method)
    assert len(base) == 8
    assert np.array_equal(base[0].indices, select_anchors(cloud, method=method).indices)
    assert len({tuple(sorted(a.indices)) for a in base}) > 4, "restarted sets differ"
    for i in range(5):
        r, t, perm = random_rotation(rng), rng.normal(scale=2.0, size=3), rng.permutation(len(cloud))
        got = anchor_sets((cloud @ r.T + t)[perm], 8, method=method)
        for j, (a, b) in enumerate(zip(got, base)):
            assert np.array_equal(perm[a.indices], b.indices), f"{method}, trial {i}, set {j}"
            np.testing.assert_allclose(a.points, b.points @ r.T + t, atol=1e-6)


@pytest.mark.parametrize("count", [0, 9, 1.5, True])
def test_anchor_set_count_is_checked(count):
    from escape_cli.errors import ParameterError

    with pytest.raises(ParameterError, match="anchor sets"):
        anchor_sets(synthetic_clouds()["half_ellipsoid"], count)


def test_realdata_present_or_skipped_with_message(realdata_dir):
    assert realdata_clouds(), f"no clouds found under {realdata_dir}"


def test_prepare_input_is_equivariant_and_fps_ordered(rng):
    cloud = partial_cloud(rng, 3000)
    prepared, unique = prepare_input(cloud, 2048)
    assert prepared.shape == (2048, 3) and unique == 2048
    head = farthest_point_sampling(prepared, 128, start=0)
    assert np.array_equal(head, np.arange(128)), "the first rows must be their own FPS order"
    r, t = random_rotation(rng), rng.normal(size=3)
    moved, _ = prepare_input((cloud @ r.T + t)[rng.permutation(len(cloud))], 2048)
    np.testing.assert_allclose(moved, prepared @ r.T + t, atol=1e-9)
    small, count = prepare_input(cloud[:100], 2048)
    assert count == 100 and small.shape == (2048, 3)
    assert np.array_equal(small[100:200], small[:100])


def test_curvature_is_rotation_invariant_and_high_on_edges(rng):
    cloud = synthetic_clouds()["box_surface"]
    kappa = surface_variation(cloud)
    r = random_rotation(rng)
    np.testing.assert_allclose(surface_variation(cloud @ r.T), kappa, atol=1e-9)
    on_edge = (np.abs(np.abs(cloud) - 0.4) < 0.02).sum(axis=1) >= 2
    assert kappa[on_edge].mean() > 3 * kappa[~on_edge].mean()


def test_encoding_is_invariant(rng):
    cloud = partial_cloud(rng, 500)
    anchors = select_anchors(cloud)
    d = distance_matrix(cloud, anchors.points)
    assert d.shape == (500, 8)
    r, t = random_rotation(rng), rng.normal(size=3)
    np.testing.assert_allclose(distance_matrix(cloud @ r.T + t, anchors.points @ r.T + t), d, atol=1e-12)
    brute = np.array([[np.sqrt(((p - a) ** 2).sum()) for a in anchors.points] for p in cloud[:20]])
    np.testing.assert_allclose(d[:20], brute, atol=1e-12)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(PointCloudError):
        select_anchors(np.zeros((5, 2)))
    with pytest.raises(PointCloudError):
        select_anchors(np.zeros((3, 3)))
    with pytest.raises(PointCloudError, match="NaN"):
        select_anchors(np.full((20, 3), np.nan))
    with pytest.raises(DegenerateGeometryError, match="distinct"):
        select_anchors(np.zeros((50, 3)))
    with pytest.raises(DegenerateGeometryError, match="line"):
        select_anchors(np.outer(np.linspace(0, 1, 50), [1.0, 2.0, 3.0]))
    with pytest.raises(ValueError):
        select_anchors(np.random.default_rng(0).random((50, 3)), method="magic")
