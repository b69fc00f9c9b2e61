"""Tests for escape_cli.core.metrics: KD-tree metrics agree with brute force, match the
formulas on hand-made cases, and have the expected symmetries."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from escape_cli.errors import EscapeError, PointCloudError
from escape_cli.core.metrics import (
    chamfer_l1,
    chamfer_l1_naive,
    chamfer_l2,
    chamfer_l2_naive,
    fidelity,
    fidelity_naive,
    fscore,
    fscore_naive,
    nearest_distances,
    nearest_distances_naive,
    point_metrics,
    point_metrics_naive,
)

coords = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False, width=64)


def clouds(max_points: int = 60):
    return st.integers(1, max_points).flatmap(lambda n: arrays(np.float64, (n, 3), elements=coords))


def test_hand_computed_example():
    pred = np.array([[0.0, 0.0, 0.0]])
    gt = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    # pred -> gt: 1; gt -> pred: 1 and 2 (mean 1.5)
    assert chamfer_l1(pred, gt) == pytest.approx((1.0 + 1.5) / 2)
    assert chamfer_l2(pred, gt) == pytest.approx(1.0 + (1.0 + 4.0) / 2)
    assert fidelity(gt, pred) == pytest.approx(1.5)
    assert fidelity(pred, gt) == pytest.approx(1.0)
    assert fscore(pred, gt, threshold=1.5) == pytest.approx(2 * 1.0 * 0.5 / 1.5)
    assert fscore(pred, gt, threshold=0.5) == 0.0


def test_fscore_counts_shares():
    gt = np.zeros((4, 3))
    gt[:, 0] = [0.0, 1.0, 2.0, 3.0]
    pred = gt[:2] + [0.0, 0.005, 0.0]  # two predicted points, both near gt
    # P = 2/2, R = 2/4 -> F = 2 * 1 * 0.5 / 1.5
    assert fscore(pred, gt) == pytest.approx(2.0 / 3.0)


@pytest.mark.parametrize("m, g", [(1, 1), (7, 300), (500, 40), (1200, 1500)])
def test_agree_with_brute_force(rng, m, g):
    pred = rng.normal(size=(m, 3)) * 0.3
    gt = rng.normal(size=(g, 3)) * 0.3
    np.testing.assert_allclose(nearest_distances(pred, gt), nearest_distances_naive(pred, gt),
                               rtol=1e-12, atol=1e-15)
    assert chamfer_l1(pred, gt) == pytest.approx(chamfer_l1_naive(pred, gt), rel=1e-12)
    assert chamfer_l2(pred, gt) == pytest.approx(chamfer_l2_naive(pred, gt), rel=1e-12)
    for t in (0.01, 0.05, 0.2):
        assert fscore(pred, gt, t) == pytest.approx(fscore_naive(pred, gt, t), abs=1e-12)
    assert fidelity(pred, gt) == pytest.approx(fidelity_naive(pred, gt), rel=1e-12)
    fast, slow = point_metrics(pred, gt, 0.05), point_metrics_naive(pred, gt, 0.05)
    assert fast.keys() == slow.keys() == {"cd_l1", "cd_l2", "fscore", "pred_to_gt", "gt_to_pred"}
    for key in fast:
        assert fast[key] == pytest.approx(slow[key], rel=1e-12, abs=1e-15)


def test_point_metrics_match_single_functions(rng):
    pred, gt = rng.uniform(size=(300, 3)), rng.uniform(size=(500, 3))
    out = point_metrics(pred, gt, threshold=0.05)
    assert out["cd_l1"] == chamfer_l1(pred, gt)
    assert out["cd_l2"] == chamfer_l2(pred, gt)
    assert out["fscore"] == fscore(pred, gt, threshold=0.05)
    assert out["pred_to_gt"] == pytest.approx(nearest_distances(pred, gt).mean(), rel=1e-12)
    assert out["gt_to_pred"] == pytest.approx(nearest_distances(gt, pred).mean(), rel=1e-12)
    assert out["cd_l1"] == pytest.approx((out["pred_to_gt"] + out["gt_to_pred"]) / 2, rel=1e-12)
    assert all(isinstance(v, float) for v in out.values())


@settings(max_examples=40, deadline=None)
@given(clouds(), clouds())
def test_property_agree_and_symmetric(pred, gt):
    assert chamfer_l1(pred, gt) == pytest.approx(chamfer_l1_naive(pred, gt), rel=1e-9, abs=1e-12)
    assert chamfer_l2(pred, gt) == pytest.approx(chamfer_l2_naive(pred, gt), rel=1e-9, abs=1e-12)
    assert chamfer_l1(pred, gt) == pytest.approx(chamfer_l1(gt, pred), rel=1e-12, abs=1e-15)
    assert chamfer_l2(pred, gt) == pytest.approx(chamfer_l2(gt, pred), rel=1e-12, abs=1e-15)
    assert fscore(pred, gt, 0.3) == pytest.approx(fscore(gt, pred, 0.3), abs=1e-12)
    assert 0.0 <= fscore(pred, gt, 0.3) <= 1.0
    assert chamfer_l1(pred, gt) >= 0.0 and chamfer_l2(pred, gt) >= 0.0


@settings(max_examples=30, deadline=None)
@given(clouds(), st.data())
def test_property_zero_on_equal_sets(cloud, data):
    order = data.draw(st.permutations(range(len(cloud))))
    shuffled = cloud[list(order)]
    assert chamfer_l1(cloud, shuffled) == 0.0
    assert chamfer_l2(cloud, shuffled) == 0.0
    assert fscore(cloud, shuffled) == 1.0
    assert fidelity(cloud, shuffled) == 0.0


def test_fidelity_zero_when_input_inside_output(rng):
    output = rng.uniform(size=(400, 3))
    assert fidelity(output[:50], output) == 0.0
    assert fidelity(output, output[:50]) > 0.0


def test_invariant_under_rigid_motion(rng):
    from escape_cli.core.rotations import random_rotation

    pred, gt = rng.normal(size=(200, 3)), rng.normal(size=(300, 3))
    rot, t = random_rotation(rng), rng.normal(size=3)
    before = point_metrics(pred, gt, 0.1)
    after = point_metrics(pred @ rot.T + t, gt @ rot.T + t, 0.1)
    for key in before:
        assert after[key] == pytest.approx(before[key], rel=1e-9)


def test_cross_check_point_cloud_utils(rng):
    pcu = pytest.importorskip("point_cloud_utils")
    pred, gt = rng.uniform(size=(200, 3)), rng.uniform(size=(300, 3))
    # pcu returns the *sum* of the two means: 2 x CD-L1 (DESIGN.md "Metrics")
    assert pcu.chamfer_distance(pred, gt) == pytest.approx(2.0 * chamfer_l1(pred, gt), rel=1e-6)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((0, 3)), "empty"),
        (np.zeros((5, 2)), r"\(5, 2\)"),
        (np.zeros(3), r"\(3,\)"),
        (np.array([[0.0, np.nan, 0.0]]), "NaN"),
    ],
)
def test_bad_clouds_rejected(bad, match):
    ok = np.zeros((4, 3))
    for fn in (chamfer_l1, chamfer_l2, fscore, fidelity, point_metrics, chamfer_l1_naive):
        with pytest.raises(PointCloudError, match=match):
            fn(bad, ok)
        with pytest.raises(PointCloudError, match=match):
            fn(ok, bad)


@pytest.mark.parametrize("threshold", [0.0, -0.1, float("nan")])
def test_bad_threshold_rejected(threshold):
    with pytest.raises(EscapeError, match="threshold"):
        fscore(np.zeros((2, 3)), np.ones((2, 3)), threshold)
