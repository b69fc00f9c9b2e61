"""`escape_cli.complete`: end-to-end equivariance, sizes, normalisation, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from escape_cli import complete
from escape_cli.errors import DegenerateGeometryError, PointCloudError
from escape_cli.core.metrics import chamfer_l1
from escape_cli.core.rotations import random_rotation
from tests_support import partial_cloud


def test_complete_is_equivariant(tiny_model, rng):
    cloud = partial_cloud(rng, 500)
    base = complete(cloud, tiny_model, output_points=1024)
    assert base.points.shape == (1024, 3)
    for i in range(10):
        r = random_rotation(rng)
        t = rng.normal(scale=3.0, size=3)
        moved = (cloud @ r.T + t)[rng.permutation(len(cloud))]
        out = complete(moved, tiny_model, output_points=1024)
        want = base.points @ r.T + t
        assert chamfer_l1(out.points, want) < 1e-4, f"rotation {i}"
        assert np.allclose(out.anchors, base.anchors @ r.T + t, atol=1e-6)


def test_output_in_input_frame_and_units(tiny_model, rng):
    cloud = partial_cloud(rng, 400)
    in_metres = cloud * 7.0 + np.array([100.0, -20.0, 3.0])
    a = complete(cloud, tiny_model, output_points=800)
    b = complete(in_metres, tiny_model, output_points=800)
    # auto normalisation is scale and translation covariant
    assert chamfer_l1(b.points, a.points * 7.0 + np.array([100.0, -20.0, 3.0])) < 1e-3
    assert np.allclose(b.residuals, a.residuals * 7.0, atol=1e-6)


@pytest.mark.parametrize("size", [16, 100, 5000])
def test_any_input_size(tiny_model, rng, size):
    cloud = partial_cloud(rng, size)
    out = complete(cloud, tiny_model, output_points=300)
    assert out.points.shape == (300, 3) and np.all(np.isfinite(out.points))


def test_keep_input_merges_observed_points(tiny_model, rng):
    cloud = partial_cloud(rng, 300)
    kept = complete(cloud, tiny_model, output_points=2000, keep_input=True)
    assert kept.is_observed.sum() > 0
    observed = kept.points[kept.is_observed]
    assert np.min(np.linalg.norm(observed[:, None] - cloud[None], axis=2), axis=1).max() < 1e-9
    alone = complete(cloud, tiny_model, output_points=2000, keep_input=False)
    assert alone.is_observed.sum() == 0


def test_too_small_and_degenerate_inputs(tiny_model):
    with pytest.raises(PointCloudError):
        complete(np.zeros((0, 3)), tiny_model)
    with pytest.raises(PointCloudError, match="distinct"):
        complete(np.random.default_rng(0).random((10, 3)), tiny_model)
    with pytest.raises(PointCloudError):
        complete(np.full((100, 3), np.nan), tiny_model)
    with pytest.raises(DegenerateGeometryError):
        complete(np.outer(np.linspace(0, 1, 100), [1.0, 2.0, 3.0]), tiny_model)


def test_snap_radius_controls_snapping(tiny_model, rng):
    cloud = partial_cloud(rng, 400)
    off = complete(cloud, tiny_model, output_points=1000, snap_radius=0.0)
    assert not off.is_snapped.any() and off.summary()["snapped"] == 0
    wide = complete(cloud, tiny_model, output_points=1000, snap_radius=10.0)
    assert wide.is_snapped.any()
    assert not (wide.is_snapped & wide.is_observed).any(), "observed points are never snapped"
    # snapping moves points towards the scan, never away from it
    gap = lambda pts: np.min(np.linalg.norm(pts[:, None] - cloud[None], axis=2), axis=1)  # noqa: E731
    assert gap(wide.points).mean() <= gap(off.points).mean() + 1e-9
    with pytest.raises(ValueError, match="snap_radius"):
        complete(cloud, tiny_model, snap_radius=-1.0)


# ------------------------------------------------------------------ complete_many


def _same_completion(a, b):
    """The same completion up to float32 rounding: onnxruntime may round a batch's rows differently."""
    size = np.ptp(b.points, axis=0).max()
    np.testing.assert_allclose(a.points, b.points, rtol=0, atol=1e-7 * size)
    np.testing.assert_allclose(a.residuals, b.residuals, rtol=1e-5, atol=1e-9 * size)
    np.testing.assert_array_equal(a.is_observed, b.is_observed)
    np.testing.assert_array_equal(a.is_snapped, b.is_snapped)
    np.testing.assert_array_equal(a.anchor_indices, b.anchor_indices)
    assert a.summary().keys() == b.summary().keys()
    for key, value in b.summary().items():
        assert a.summary()[key] == pytest.approx(value, rel=1e-5, abs=1e-9), key


def test_complete_many_equals_complete_of_each(tiny_model, rng):
    from escape_cli import complete_many

    clouds = [partial_cloud(rng, n) for n in (120, 400, 256, 900, 60)]
    clouds[2] = clouds[2] * 30.0 + 5.0  # other units
    many = complete_many((c for c in clouds), tiny_model, batch_size=2, output_points=700)
    assert len(many) == len(clouds)
    for cloud, got in zip(clouds, many):
        _same_completion(got, complete(cloud, tiny_model, output_points=700))


def test_complete_many_isolates_bad_clouds(tiny_model, rng):
    from escape_cli import complete_many

    good = partial_cloud(rng, 300)
    clouds = [good, np.zeros((10, 3)), good[:, :2], good * 2.0]
    with pytest.raises(PointCloudError):
        complete_many(clouds, tiny_model, output_points=500)
    many = complete_many(clouds, tiny_model, batch_size=3, return_exceptions=True, output_points=500)
    assert isinstance(many[1], PointCloudError) and "distinct" in str(many[1])
    assert isinstance(many[2], PointCloudError)
    _same_completion(many[0], complete(good, tiny_model, output_points=500))
    _same_completion(many[3], complete(good * 2.0, tiny_model, output_points=500))
    assert complete_many([], tiny_model) == []


def test_complete_many_checks_its_options_first(tiny_model, rng):
    from escape_cli import complete_many
    from escape_cli.errors import ParameterError

    with pytest.raises(ParameterError, match="batch_size"):
        complete_many([partial_cloud(rng, 100)], tiny_model, batch_size=0, return_exceptions=True)
    with pytest.raises(ParameterError, match="normalize"):
        complete_many([partial_cloud(rng, 100)], tiny_model, normalize="bogus", return_exceptions=True)


# ------------------------------------------------------------------ anchor-set ensembles


def test_anchor_set_ensemble_is_equivariant(tiny_model, rng):
    cloud = partial_cloud(rng, 500)
    base = complete(cloud, tiny_model, output_points=1024, anchor_sets=3)
    assert base.points.shape == (1024, 3) and base.available > 2 * 1024
    for i in range(4):
        r = random_rotation(rng)
        t = rng.normal(scale=3.0, size=3)
        moved = (cloud @ r.T + t)[rng.permutation(len(cloud))]
        out = complete(moved, tiny_model, output_points=1024, anchor_sets=3)
        assert chamfer_l1(out.points, base.points @ r.T + t) < 1e-4, f"rotation {i}"
        np.testing.assert_array_equal(out.is_observed, base.is_observed)


def test_anchor_set_ensemble_pools_every_set_and_keeps_the_scan(tiny_model, rng):
    cloud = partial_cloud(rng, 300)
    one = complete(cloud, tiny_model, output_points=1000)  # of 1024 predicted + the 256 rows observed
    assert np.array_equal(complete(cloud, tiny_model, output_points=1000, anchor_sets=1).points, one.points)
    pooled = complete(cloud, tiny_model, output_points=1000, anchor_sets=4)
    assert pooled.points.shape == (1000, 3) and pooled.available == 4 * 1024 + 256
    np.testing.assert_array_equal(pooled.anchors, one.anchors)  # the first set is the usual one
    assert pooled.is_observed.sum() == one.is_observed.sum() == 256, "every observed row kept"
    predicted_one = one.points[~one.is_observed]
    gap = np.min(np.linalg.norm(pooled.points[~pooled.is_observed][:, None] - predicted_one[None], axis=2), axis=1)
    assert (gap > 1e-6).sum() > 0.5 * len(gap), "most pooled points come from the other sets"
    alone = complete(cloud, tiny_model, output_points=1000, anchor_sets=4, keep_input=False)
    assert alone.points.shape == (1000, 3) and not alone.is_observed.any()


def test_anchor_set_ensemble_solves_only_the_share_the_output_needs(tiny_model, rng, monkeypatch):
    import escape_cli.core.reconstruction as reconstruction

    solved_rows = []
    original = reconstruction.reconstruct

    def counting(predicted, *args, **kwargs):
        solved_rows.append(len(predicted))
        return original(predicted, *args, **kwargs)

    monkeypatch.setattr(reconstruction, "reconstruct", counting)
    cloud = partial_cloud(rng, 300)  # 256 observed rows, 1024 predicted per set
    out = complete(cloud, tiny_model, output_points=1000, anchor_sets=4)
    assert solved_rows == [207] * 4, "ceil((1000 - 256) / (4 * 0.9)) rows of each set"
    assert out.points.shape == (1000, 3) and out.available == 4 * 1024 + 256
    solved_rows.clear()
    everything = complete(cloud, tiny_model, output_points=4 * 1024 + 256, anchor_sets=4)
    assert solved_rows == [1024] * 4 and len(everything.points) == 4 * 1024 + 256
    solved_rows.clear()
    few = complete(cloud, tiny_model, output_points=100, anchor_sets=3)  # fewer than the observed points
    assert solved_rows == [1] * 3 and few.is_observed.all() and len(few.points) == 100


def test_complete_many_with_anchor_sets_equals_complete(tiny_model, rng):
    from escape_cli import complete_many

    clouds = [partial_cloud(rng, n) for n in (200, 500, 90)]
    many = complete_many(clouds, tiny_model, batch_size=2, output_points=600, anchor_sets=3)
    for cloud, got in zip(clouds, many):
        _same_completion(got, complete(cloud, tiny_model, output_points=600, anchor_sets=3))


@pytest.mark.parametrize("count", [0, 9, -1, 2.5])
def test_bad_anchor_set_counts_are_refused(tiny_model, rng, count):
    from escape_cli import complete_many
    from escape_cli.errors import ParameterError

    with pytest.raises(ParameterError, match="anchor_sets"):
        complete(partial_cloud(rng, 100), tiny_model, anchor_sets=count)
    with pytest.raises(ParameterError, match="anchor_sets"):
        complete_many([partial_cloud(rng, 100)], tiny_model, anchor_sets=count, return_exceptions=True)


def test_pooled_rows_leave_out_the_least_sure_share_and_draw_the_rest(rng):
    from escape_cli.pipeline import ENSEMBLE_DROP, pooled_rows

    residuals = rng.random(1000)
    rows = pooled_rows(residuals, 500)
    assert len(rows) == 500 and np.all(np.diff(rows) > 0)
    worst = np.argsort(residuals)[-int(ENSEMBLE_DROP * 1000):]
    assert not np.isin(worst, rows).any()
    assert np.array_equal(pooled_rows(residuals, 500), rows), "a fixed draw"
    assert np.array_equal(pooled_rows(residuals, 1000), np.arange(1000))
    assert np.isin(worst, pooled_rows(residuals, 950)).sum() == 50, "never more left out than the surplus"
    assert len(pooled_rows(residuals, 0)) == 0
