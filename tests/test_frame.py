"""The scan's own frame: similarity equivariance end to end, one network input for training and use, UTM scale."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_runner import run_escape
from escape_cli import complete
from escape_cli.core.metrics import chamfer_l1
from escape_cli.core.normalize import PartialFrame, network_input
from escape_cli.core.rotations import random_rotation
from escape_cli.errors import ParameterError
from escape_cli.io import read_points, write_points
from tests_support import partial_cloud, write_tiny_pcn_tree


def random_similarity(rng):
    """R (3, 3), t (3,), s in [1e-3, 1e3] log-uniform."""
    scale = float(10 ** rng.uniform(-3, 3))
    return random_rotation(rng), rng.normal(scale=10.0 * scale, size=3), scale


def test_partial_frame_is_similarity_invariant(rng):
    cloud = partial_cloud(rng, 900)
    base = network_input(cloud, 512)
    for _ in range(10):
        r, t, s = random_similarity(rng)
        moved = network_input((s * cloud @ r.T + t)[rng.permutation(len(cloud))], 512)
        assert moved.unique == base.unique
        # the rows in the frame are the same points rotated (the frame removes t and s, not R)
        np.testing.assert_allclose(moved.rows, base.rows @ r.T, atol=1e-9)
        assert moved.normalization.scale == pytest.approx(s * base.normalization.scale, rel=1e-9)


def test_frame_statistic_is_the_documented_one(rng):
    cloud = partial_cloud(rng, 3000)
    frame = PartialFrame()
    net_in = network_input(cloud * 5.0 + 7.0, 2048, frame)
    head = net_in.rows[: frame.rows]
    rms = np.sqrt(((head - head.mean(axis=0)) ** 2).sum(axis=1).mean())
    assert rms == pytest.approx(frame.radius, rel=1e-12)
    np.testing.assert_allclose(head.mean(axis=0), 0.0, atol=1e-12)


@pytest.mark.parametrize("trial", range(6))
def test_complete_is_similarity_equivariant(tiny_model, trial):
    rng = np.random.default_rng(100 + trial)
    cloud = partial_cloud(rng, 500)
    base = complete(cloud, tiny_model, output_points=1000)
    r, t, s = random_similarity(rng)
    moved = complete((s * cloud @ r.T + t)[rng.permutation(len(cloud))], tiny_model, output_points=1000)
    back = (moved.points - t) @ r / s  # the moved output mapped back to the canonical pose and units
    size = np.ptp(cloud, axis=0).max()
    assert chamfer_l1(back, base.points) / size < 1e-6, f"s={s:.3g}"
    np.testing.assert_allclose((moved.anchors - t) @ r / s, base.anchors, atol=1e-7 * size)
    np.testing.assert_allclose(moved.residuals, s * base.residuals, rtol=1e-5, atol=1e-9 * s)


def test_cli_complete_is_similarity_equivariant(tiny_model, tmp_path):
    rng = np.random.default_rng(7)
    cloud = partial_cloud(rng, 400)
    write_points(tmp_path / "a.ply", cloud, coordinate_dtype=np.float64)
    r, t, s = random_rotation(rng), np.array([3.0, -2.0, 40.0]), 250.0
    write_points(tmp_path / "b.ply", s * cloud @ r.T + t, coordinate_dtype=np.float64)
    for name in ("a", "b"):
        res = run_escape("complete", tmp_path / f"{name}.ply", "-o", tmp_path / f"{name}_out.ply",
                         "--model", tiny_model, "--points", "800")
        assert res.exit_code == 0, res.stderr
    a = read_points(tmp_path / "a_out.ply")
    b = (read_points(tmp_path / "b_out.ply") - t) @ r / s
    # float32 files: compare to their rounding, in units of the object's size
    assert chamfer_l1(a, b) / np.ptp(cloud, axis=0).max() < 1e-5


def test_training_samples_use_the_completion_input(tmp_path, rng):
    """`escape train` and `complete` feed the network the same rows for the same partial."""
    pytest.importorskip("torch")
    from escape_cli.core.settings import AnchorSettings
    from escape_cli.data.pcn import list_samples, read_pcd
    from escape_cli.nn.samples import prepare_split

    write_tiny_pcn_tree(tmp_path / "pcn", objects=1, views=1)
    split = prepare_split(tmp_path / "pcn", "train", 256, AnchorSettings(), tmp_path / "cache", PartialFrame(), workers=1)
    for i, ref in enumerate(list_samples(tmp_path / "pcn", "train")):
        partial = read_pcd(ref.partial_path).astype(np.float64)
        want = network_input(partial, 256, PartialFrame())
        np.testing.assert_array_equal(split.inputs[i], want.rows.astype(np.float32))
        np.testing.assert_allclose(split.centers[i], want.normalization.center)
        assert split.scales[i] == want.normalization.scale
        # the complete cloud is mapped by the same similarity
        complete_cloud = read_pcd(ref.complete_path).astype(np.float64)
        np.testing.assert_allclose(split.complete_in_frame(i), want.normalization.apply(complete_cloud), atol=1e-6)


def test_utm_scale_scan_keeps_its_observed_points_to_the_millimetre(tiny_model, rng):
    cloud = partial_cloud(rng, 600) * 4.0  # an object a few metres across
    offset = np.array([512345.678, 4123456.789, 87.654])  # UTM metres
    far = cloud + offset
    near = complete(cloud, tiny_model, output_points=900)
    out = complete(far, tiny_model, output_points=900)
    observed = out.points[out.is_observed]
    gaps = np.min(np.linalg.norm(observed[:, None, :] - far[None, :, :], axis=2), axis=1)
    assert gaps.max() < 1e-3, f"observed points moved by up to {gaps.max():.2e} m"
    assert chamfer_l1(out.points - offset, near.points) < 1e-6  # completes as well as at the origin


def test_normalize_none_is_only_for_absolute_models(tiny_model, tiny_absolute_model, rng):
    cloud = partial_cloud(rng, 400)
    with pytest.raises(ParameterError, match="own frame"):
        complete(cloud, tiny_model, normalize="none")
    # an older model trained in absolute units keeps both behaviours
    plain = complete(cloud, tiny_absolute_model, normalize="none", output_points=800)
    assert plain.normalization.scale == 1.0
    auto = complete(cloud * 3.0, tiny_absolute_model, normalize="auto", output_points=800)
    assert auto.normalization.scale != 1.0


def test_model_metadata_records_the_frame(tiny_model, tiny_absolute_model):
    meta = json.loads(tiny_model.with_suffix(".json").read_text())
    assert meta["frame"] == {"kind": "partial", "rows": 256, "radius": 0.28}
    old = json.loads(tiny_absolute_model.with_suffix(".json").read_text())
    assert old["frame"] == {"kind": "absolute"} and old["normalization"]["target_radius"] == 0.25
