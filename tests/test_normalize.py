"""Tests for escape_cli.core.normalize: exact round trips, rotation invariance, KITTI boxes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from escape_cli.errors import DegenerateGeometryError, EscapeError, PointCloudError
from escape_cli.core.normalize import (
    BoxNormalization,
    Normalization,
    box_normalization,
    cloud_radius,
    cloud_radius_naive,
    fit_normalization,
)
from escape_cli.core.rotations import random_rotation

# ------------------------------------------------------------ centroid + radius


def test_fit_gives_target_radius_and_zero_centroid(rng):
    scan = rng.normal(size=(500, 3)) * [3.0, 1.0, 0.5] + [10.0, -4.0, 2.0]  # metres, off-centre
    norm = fit_normalization(scan, target_radius=0.35)
    out = norm.apply(scan)
    np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-14)
    assert cloud_radius(out) == pytest.approx(0.35, rel=1e-12)
    q = fit_normalization(scan, 0.35, quantile=0.95)
    assert cloud_radius(q.apply(scan), quantile=0.95) == pytest.approx(0.35, rel=1e-12)


def test_round_trip(rng):
    scan = rng.normal(size=(300, 3)) * 7.0 + 100.0
    norm = fit_normalization(scan, 0.4)
    np.testing.assert_allclose(norm.invert(norm.apply(scan)), scan, rtol=0, atol=1e-12)
    x = rng.normal(size=(50, 3))
    np.testing.assert_allclose(norm.apply(norm.invert(x)), x, rtol=0, atol=1e-14)


@settings(max_examples=50, deadline=None)
@given(
    arrays(np.float64, st.tuples(st.integers(2, 40), st.just(3)),
           elements=st.floats(-100, 100, allow_nan=False, allow_infinity=False, width=64)),
    st.floats(0.01, 10.0),
)
def test_property_round_trip(points, target):
    try:
        norm = fit_normalization(points, target)
    except DegenerateGeometryError:
        return  # all points equal (or nearly)
    back = norm.invert(norm.apply(points))
    np.testing.assert_allclose(back, points, rtol=0, atol=1e-12 * max(1.0, np.abs(points).max()))
    again = Normalization.from_dict(json.loads(json.dumps(norm.to_dict())))
    np.testing.assert_array_equal(again.center, norm.center)
    assert again.scale == norm.scale


@pytest.mark.parametrize("quantile", [None, 0.95])
def test_rotation_invariant(rng, quantile):
    scan = rng.normal(size=(400, 3)) * [2.0, 1.0, 0.3] + [5.0, 1.0, -2.0]
    norm = fit_normalization(scan, 0.3, quantile=quantile)
    for _ in range(10):
        rot, t = random_rotation(rng), rng.normal(size=3) * 10
        moved = fit_normalization(scan @ rot.T + t, 0.3, quantile=quantile)
        assert moved.scale == pytest.approx(norm.scale, rel=1e-12)
        np.testing.assert_allclose(moved.center, rot @ norm.center + t, atol=1e-12)
        # so the normalised clouds differ by the rotation alone
        np.testing.assert_allclose(moved.apply(scan @ rot.T + t), norm.apply(scan) @ rot.T, atol=1e-12)


def test_point_order_invariant(rng):
    scan = rng.normal(size=(100, 3))
    a, b = fit_normalization(scan, 1.0), fit_normalization(scan[::-1], 1.0)
    assert a.scale == pytest.approx(b.scale, rel=1e-14)
    np.testing.assert_allclose(a.center, b.center, atol=1e-15)


def test_cloud_radius_matches_naive(rng):
    pts = rng.normal(size=(200, 3)) + 3.0
    assert cloud_radius(pts) == pytest.approx(cloud_radius_naive(pts), rel=1e-12)


def test_identity_and_dict(rng):
    ident = Normalization.identity()
    x = rng.normal(size=(10, 3))
    np.testing.assert_array_equal(ident.apply(x), x)
    np.testing.assert_array_equal(ident.invert(x), x)
    assert ident.to_dict() == {"center": [0.0, 0.0, 0.0], "scale": 1.0}


def test_normalization_is_frozen():
    norm = Normalization([1.0, 2.0, 3.0], 2.0)
    with pytest.raises(Exception):
        norm.scale = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        norm.center[0] = 0.0


def test_degenerate_and_bad_inputs():
    with pytest.raises(DegenerateGeometryError, match="zero radius"):
        fit_normalization(np.ones((10, 3)) * 4.2, 0.3)
    with pytest.raises(PointCloudError, match="empty"):
        cloud_radius(np.zeros((0, 3)))
    with pytest.raises(PointCloudError, match=r"\(10, 2\)"):
        fit_normalization(np.zeros((10, 2)), 0.3)
    with pytest.raises(PointCloudError, match="NaN"):
        fit_normalization(np.array([[0.0, 0.0, np.inf], [1.0, 0.0, 0.0]]), 0.3)
    with pytest.raises(EscapeError, match="target_radius"):
        fit_normalization(np.eye(3), 0.0)
    with pytest.raises(EscapeError, match="quantile"):
        cloud_radius(np.eye(3), quantile=1.5)
    with pytest.raises(EscapeError, match="scale"):
        Normalization([0, 0, 0], -1.0)
    with pytest.raises(EscapeError, match="center"):
        Normalization([0, 0], 1.0)
    with pytest.raises(EscapeError, match="center"):
        Normalization.from_dict({"scale": 1.0})


# ------------------------------------------------------------------ KITTI boxes


def pcn_box(center, yaw, length, width, height, tilt=None) -> np.ndarray:
    """(8, 3) corners in PCN order: bottom 0-3 going round, top 4-7; 3-0 length, 4-0 up."""
    c, s = np.cos(yaw), np.sin(yaw)
    u = np.array([c, s, 0.0])  # length
    v = np.array([-s, c, 0.0])  # lateral
    w = np.array([0.0, 0.0, 1.0])  # up
    if tilt is not None:
        u, v, w = tilt @ u, tilt @ v, tilt @ w
    b0 = np.asarray(center) - (length * u + width * v + height * w) / 2
    bottom = [b0, b0 + width * v, b0 + width * v + length * u, b0 + length * u]
    return np.array(bottom + [p + height * w for p in bottom])


def pcn_reference(points, bbox):
    """PCN's own code (wentaoyuan/pcn test_kitti.py), copied for comparison."""
    bbox = np.array(bbox, dtype=np.float64)
    center = (bbox.min(0) + bbox.max(0)) / 2
    bbox -= center
    yaw = np.arctan2(bbox[3, 1] - bbox[0, 1], bbox[3, 0] - bbox[0, 0])
    rotation = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    bbox = np.dot(bbox, rotation)
    scale = bbox[3, 0] - bbox[0, 0]
    partial = np.dot(points - center, rotation) / scale
    return np.dot(partial, [[1, 0, 0], [0, 0, 1], [0, 1, 0]])


def test_box_matches_pcn_on_an_upright_box(rng):
    corners = pcn_box([4.0, -2.0, -0.9], yaw=0.7, length=3.9, width=1.6, height=1.5)
    pts = rng.uniform(-2, 2, size=(100, 3)) + [4.0, -2.0, -0.9]
    norm = box_normalization(corners)
    np.testing.assert_allclose(norm.apply(pts), pcn_reference(pts, corners), atol=1e-12)
    assert norm.scale == pytest.approx(3.9)
    np.testing.assert_allclose(norm.center, [4.0, -2.0, -0.9], atol=1e-12)
    assert np.linalg.det(norm.rotation) == pytest.approx(-1.0)  # PCN's y/z swap


def test_box_frame_puts_the_box_in_unit_range():
    corners = pcn_box([1.0, 2.0, 3.0], yaw=-2.1, length=4.0, width=1.8, height=1.4)
    for pcn_axes, up_axis in ((True, 1), (False, 2)):
        inside = box_normalization(corners, pcn_axes=pcn_axes).apply(corners)
        np.testing.assert_allclose(np.abs(inside[:, 0]), 0.5, atol=1e-12)  # length -> [-0.5, 0.5]
        np.testing.assert_allclose(np.abs(inside[:, up_axis]), 1.4 / 4.0 / 2, atol=1e-12)
        assert np.all(inside[4:, up_axis] > inside[:4, up_axis])  # corners 4-7 on top
    assert np.linalg.det(box_normalization(corners, pcn_axes=False).rotation) == pytest.approx(1.0)


def test_box_round_trip_and_unpacking(rng):
    corners = pcn_box([10.0, 5.0, -1.0], yaw=1.2, length=3.5, width=1.7, height=1.5)
    norm = box_normalization(corners)
    rotation, center, scale = norm
    assert rotation.shape == (3, 3) and center.shape == (3,) and isinstance(scale, float)
    pts = rng.normal(size=(200, 3)) * 2 + [10.0, 5.0, -1.0]
    np.testing.assert_allclose(norm.invert(norm.apply(pts)), pts, atol=1e-12)
    again = BoxNormalization.from_dict(json.loads(json.dumps(norm.to_dict())))
    np.testing.assert_allclose(again.apply(pts), norm.apply(pts), atol=0)


def test_box_equivariant(rng):
    tilt = random_rotation(rng)
    corners = pcn_box([0.0, 0.0, 0.0], yaw=0.3, length=4.0, width=1.7, height=1.5, tilt=tilt)
    pts = rng.normal(size=(100, 3))
    base = box_normalization(corners).apply(pts)
    for _ in range(10):
        rot, t = random_rotation(rng), rng.normal(size=3) * 20
        moved = box_normalization(corners @ rot.T + t).apply(pts @ rot.T + t)
        np.testing.assert_allclose(moved, base, atol=1e-12)


def test_box_rejects_bad_corners(rng):
    corners = pcn_box([0.0, 0.0, 0.0], yaw=0.3, length=4.0, width=1.7, height=1.5)
    with pytest.raises(EscapeError, match=r"\(7, 3\)"):
        box_normalization(corners[:7])
    with pytest.raises(DegenerateGeometryError, match="PCN order"):
        box_normalization(corners[[0, 2, 1, 3, 4, 5, 6, 7]])
    flat = corners.copy()
    flat[4:] = flat[:4]
    with pytest.raises(DegenerateGeometryError, match="flat"):
        box_normalization(flat)
    with pytest.raises(DegenerateGeometryError, match="zero length"):
        box_normalization(np.zeros((8, 3)))


def _read_ascii_pcd(path) -> np.ndarray:
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("DATA")) + 1
    return np.array([[float(v) for v in line.split()[:3]] for line in lines[start:] if line.strip()])


def test_kitti_boxes(realdata_dir):
    kitti = realdata_dir / "kitti_cars"
    boxes = sorted((kitti / "bboxes").glob("*.txt"))
    if not boxes:
        pytest.skip(f"no KITTI boxes under {kitti}")
    for box_file in boxes:
        corners = np.loadtxt(box_file)
        cloud = _read_ascii_pcd(kitti / "cars" / (box_file.stem + ".pcd"))
        norm = box_normalization(corners)
        car = norm.apply(cloud)
        # The car's LiDAR points lie in its box (PCN frame: x length, y up, z lateral).
        half = np.abs(norm.apply(corners)).max(axis=0)
        assert half[0] == pytest.approx(0.5, abs=1e-5)  # corners are stored to 1e-6
        assert np.mean(np.all(np.abs(car) <= half + 0.05, axis=1)) > 0.95
        # Close to PCN's own (yaw-only) formula: these boxes are tilted by ~0.01 rad.
        assert np.abs(car - pcn_reference(cloud, corners)).max() < 0.02
        np.testing.assert_allclose(norm.invert(car), cloud, atol=1e-9)
