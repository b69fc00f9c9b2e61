"""Tests for escape_cli.core.rotations: orthonormal, det +1, seeded, the paper's composition."""

from __future__ import annotations

import numpy as np
import pytest

from escape_cli.errors import EscapeError
from escape_cli.core.rotations import is_rotation, paper_rotation, random_rotation, rotation_about_axis


@pytest.mark.parametrize("make", [random_rotation, paper_rotation])
def test_orthonormal_det_one(make):
    for seed in range(200):
        rot = make(seed)
        assert rot.shape == (3, 3) and rot.dtype == np.float64
        np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-13)
        assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-13)
        assert is_rotation(rot)


@pytest.mark.parametrize("make", [random_rotation, paper_rotation])
def test_seeded(make):
    np.testing.assert_array_equal(make(42), make(42))
    np.testing.assert_array_equal(make(np.random.default_rng(3)), make(np.random.default_rng(3)))
    assert not np.allclose(make(42), make(43))
    gen = np.random.default_rng(5)
    assert not np.allclose(make(gen), make(gen))  # a Generator advances


def test_random_rotation_is_uniform_in_mean():
    # Under the Haar measure E[R] = 0 and E[trace R] = 0.
    gen = np.random.default_rng(0)
    rots = np.stack([random_rotation(gen) for _ in range(4000)])
    assert np.abs(rots.mean(axis=0)).max() < 0.05
    assert abs(np.trace(rots, axis1=1, axis2=2).mean()) < 0.05


def test_paper_rotation_composition_matches_scipy():
    from scipy.spatial.transform import Rotation

    for seed in range(20):
        angles = np.random.default_rng(seed).uniform(0.0, 180.0, size=3)
        expected = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
        np.testing.assert_allclose(paper_rotation(seed), expected, atol=1e-13)


def test_rotation_about_axis():
    np.testing.assert_allclose(rotation_about_axis([0, 0, 1], np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rotation_about_axis([1, 0, 0], np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    axis = np.array([1.0, -2.0, 0.5])
    rot = rotation_about_axis(axis * 7.0, 1.234)  # the axis length does not matter
    np.testing.assert_allclose(rot @ axis, axis, atol=1e-14)
    assert is_rotation(rot)
    np.testing.assert_allclose(rotation_about_axis(axis, 0.4) @ rotation_about_axis(axis, 0.8),
                               rotation_about_axis(axis, 1.2), atol=1e-14)
    assert np.trace(rot) == pytest.approx(1 + 2 * np.cos(1.234))


def test_rotation_about_axis_rejects_bad_axis():
    with pytest.raises(EscapeError, match="non-zero"):
        rotation_about_axis([0, 0, 0], 1.0)
    with pytest.raises(EscapeError, match="shape"):
        rotation_about_axis([1, 0], 1.0)


def test_is_rotation_rejects_reflections():
    assert not is_rotation(np.diag([1.0, 1.0, -1.0]))
    assert not is_rotation(2 * np.eye(3))
    assert not is_rotation(np.eye(2))
