"""`escape eval`: tables and JSON on a tiny PCN tree (checked by brute force), pairs, KITTI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cli_runner import run_escape
from escape_cli.data.pcn import read_pcd
from escape_cli.evaluation import Perturbation
from escape_cli.io import read_points, write_points
from escape_cli.core.metrics import chamfer_l1_naive, chamfer_l2_naive, fscore_naive
from tests_support import write_tiny_pcn_tree


@pytest.fixture(scope="module")
def tiny_tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("pcn_eval")
    write_tiny_pcn_tree(root, seed=3)
    return root


def test_pcn_table_and_json_match_brute_force(tiny_tree, tiny_model, tmp_path):
    report_path, saved = tmp_path / "report.json", tmp_path / "saved"
    res = run_escape("eval", "--dataset", "pcn", "--root", tiny_tree, "--model", tiny_model, "--rotate",
                     "--json-out", report_path, "--save", saved)
    assert res.exit_code == 0, res.stderr
    table = res.stdout.decode()
    for word in ("chair", "table", "average", "CD-L1", "rot gap"):
        assert word in table
    report = json.loads(report_path.read_text())
    assert set(report["categories"]) == {"chair", "table"}
    assert report["average"]["count"] == 4
    for sample in report["samples"]:
        truth = read_pcd(tiny_tree / "test" / "complete" / sample["synset"] / f"{sample['model_id']}.pcd")
        out = read_points(saved / sample["synset"] / f"{sample['model_id']}_00_escape.ply")
        m = sample["metrics"]
        assert m["escape/cd_l1_x1000"] == pytest.approx(1000 * chamfer_l1_naive(out, truth), rel=1e-4)
        assert m["escape/cd_l2_x1000"] == pytest.approx(1000 * chamfer_l2_naive(out, truth), rel=1e-3)
        assert m["escape/fscore_1pct"] == pytest.approx(fscore_naive(out, truth, 0.01), abs=2e-3)
        partial = read_pcd(tiny_tree / "test" / "partial" / sample["synset"] / sample["model_id"] / "00.pcd")
        assert m["input/cd_l1_x1000"] == pytest.approx(1000 * chamfer_l1_naive(partial, truth), rel=1e-4)
        # equivariant: the rotated score equals the canonical one
        assert m["rotated/escape/cd_l1_x1000"] == pytest.approx(m["escape/cd_l1_x1000"], rel=1e-3)
    chair = report["categories"]["chair"]
    rows = [s for s in report["samples"] if s["category"] == "chair"]
    assert chair["escape/cd_l1_x1000_mean"] == pytest.approx(np.mean([s["metrics"]["escape/cd_l1_x1000"] for s in rows]))
    means = [c["escape/cd_l1_x1000_mean"] for c in report["categories"].values()]
    assert report["average"]["escape/cd_l1_x1000_mean"] == pytest.approx(np.mean(means))


def test_limit_noise_and_drop(tiny_tree, tiny_model, tmp_path):
    res = run_escape("eval", "--root", tiny_tree, "--model", tiny_model, "--limit", "1", "--noise", "0.002",
                     "--drop", "0.25", "--categories", "chair", "--json-out", tmp_path / "r.json", "--no-baseline")
    assert res.exit_code == 0, res.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    assert list(report["categories"]) == ["chair"] and report["average"]["count"] == 1
    assert report["samples"][0]["input_points"] < 600


def test_perturbation_is_seeded():
    pts = np.random.default_rng(0).random((1000, 3))
    a = Perturbation(noise=0.01, drop=0.5).apply(pts, np.random.default_rng(1))
    b = Perturbation(noise=0.01, drop=0.5).apply(pts, np.random.default_rng(1))
    assert np.array_equal(a, b) and 400 < len(a) < 600


def test_bad_dataset_root_is_one_line(tmp_path, tiny_model):
    res = run_escape("eval", "--root", tmp_path, "--model", tiny_model)
    assert res.exit_code != 0 and len(res.stderr_lines) == 1 and "escape: error:" in res.stderr


def test_pair_on_p2c_chair(realdata_dir, tiny_model):
    res = run_escape("eval", "--dataset", "pair", "--root", realdata_dir / "p2c_chair", "--model", tiny_model, "--rotate")
    assert res.exit_code == 0, res.stderr
    assert "p2c_chair" in res.stdout.decode()


def test_kitti_fidelity_and_mmd(realdata_dir, tiny_model, tmp_path):
    refs = tmp_path / "refs"
    refs.mkdir()
    rng = np.random.default_rng(0)
    box = rng.uniform(-0.5, 0.5, size=(2000, 3)) * [1.0, 0.35, 0.45]
    from escape_cli.io import write_points

    write_points(refs / "box_car.ply", box)
    res = run_escape("eval", "--dataset", "kitti", "--root", realdata_dir / "kitti_cars", "--model", tiny_model,
                     "--reference", refs, "--json-out", tmp_path / "k.json")
    assert res.exit_code == 0, res.stderr
    report = json.loads((tmp_path / "k.json").read_text())
    assert len(report["cars"]) == 6
    for car in report["cars"]:
        assert "input/fidelity_x1000" not in car["metrics"]  # the copy predicts no point
        assert car["metrics"]["escape/fidelity_x1000"] > 0  # the predicted points alone
        assert car["metrics"]["escape/mmd_cd_l2_x1000"] > 0 and car["metrics"]["input/mmd_cd_l2_x1000"] > 0


BOX = [[0, 0, 0], [0, 0, 1], [2, 0, 1], [2, 0, 0], [0, 1, 0], [0, 1, 1], [2, 1, 1], [2, 1, 0]]  # PCN corner order


@pytest.fixture
def kitti_root(tmp_path, rng):
    """A KITTI layout of two cars: one of 400 points, one of 40 (a far, sparse car)."""
    root = tmp_path / "kitti"
    (root / "cars").mkdir(parents=True)
    (root / "bboxes").mkdir()
    for name, n in (("near", 400), ("far", 40)):
        write_points(root / "cars" / f"{name}.pcd", rng.uniform(0, 1, size=(n, 3)) * [2.0, 1.0, 0.1])
        np.savetxt(root / "bboxes" / f"{name}.txt", np.array(BOX, float))
    return root


def test_kitti_without_reference_says_what_it_cannot_score(kitti_root, tiny_model, tmp_path):
    res = run_escape("eval", "--dataset", "kitti", "--root", kitti_root, "--model", tiny_model, "--json-out", tmp_path / "k.json")
    assert res.exit_code == 0, res.stderr
    warnings = [line for line in res.stderr_lines if line.startswith("escape: WARNING: ")]
    assert "no --reference folder of complete cars: MMD is not scored, nor is the input copy" in warnings[0]
    assert all(line.startswith(("escape: WARNING: far: ", "escape: WARNING: near: ")) for line in warnings[1:]), warnings
    report = json.loads((tmp_path / "k.json").read_text())
    for car in report["cars"]:
        assert list(car["metrics"]) == ["escape/fidelity_x1000"]
        assert car["metrics"]["escape/fidelity_x1000"] > 0  # the observed points merged in would make it 0


def test_kitti_fidelity_leaves_the_observed_points_out(kitti_root, tiny_model):
    from escape_cli.core.metrics import fidelity_naive
    from escape_cli.evaluation import evaluate_kitti
    from escape_cli.pipeline import complete

    outputs = []

    def completer(points):
        outputs.append((points, complete(points, str(tiny_model), output_points=1280)))
        return outputs[-1][1]

    report = evaluate_kitti(kitti_root, {"escape": completer})
    for car, (scan, result) in zip(report["cars"], outputs):
        assert result.is_observed.any()
        expected = 1000 * fidelity_naive(scan, result.points[~result.is_observed])
        assert car["metrics"]["escape/fidelity_x1000"] == pytest.approx(expected)


@pytest.mark.parametrize("reference", ["missing", "file"])
def test_kitti_reference_that_is_no_folder_is_one_line_before_any_work(kitti_root, tiny_model, tmp_path, monkeypatch, reference):
    def no_work(*args, **kwargs):
        raise AssertionError("the model was loaded before --reference was checked")

    monkeypatch.setattr("escape_cli.inference.load_model", no_work)
    path = tmp_path / "refs"
    if reference == "file":
        path.write_text("not a folder")
    res = run_escape("eval", "--dataset", "kitti", "--root", kitti_root, "--model", tiny_model, "--reference", path)
    assert res.exit_code == 1
    expected = "no such folder" if reference == "missing" else "is a file; give the folder of complete reference cars"
    assert len(res.stderr_lines) == 1 and f"escape: error: --reference {path}" in res.stderr and expected in res.stderr, res.stderr


def test_json_report_is_not_overwritten_without_flag(tiny_tree, tiny_model, tmp_path):
    report = tmp_path / "r.json"
    report.write_text("keep")
    args = ["eval", "--root", tiny_tree, "--model", tiny_model, "--limit", "1", "-c", "chair", "--json-out", report]
    res = run_escape(*args)
    assert res.exit_code != 0 and "--overwrite" in res.stderr and report.read_text() == "keep"
    assert run_escape(*args, "--overwrite").exit_code == 0
    assert json.loads(report.read_text())["average"]["count"] == 1


def test_pairs_folder_scores_every_pair_with_its_ratio(tiny_model, tmp_path, rng):
    from tests_support import ellipsoid_surface

    folder = tmp_path / "pairs"
    folder.mkdir()
    for name, radii in (("box_a", (0.3, 0.2, 0.1)), ("box_b", (0.2, 0.4, 0.3)), ("cup", (0.25, 0.25, 0.4))):
        complete_cloud = ellipsoid_surface(rng, 2048, radii)
        write_points(folder / f"{name}_complete.ply", complete_cloud)
        write_points(folder / f"{name}_partial.pcd", complete_cloud[complete_cloud[:, 0] > 0][:500])
    (folder / "notes.txt").write_text("not a cloud pair\n")  # other files are ignored
    res = run_escape("eval", "--dataset", "pairs", "--root", folder, "--model", tiny_model, "--json-out", tmp_path / "r.json")
    assert res.exit_code == 0, res.stderr
    assert "escape / input" in res.stdout.decode()
    report = json.loads((tmp_path / "r.json").read_text())
    assert list(report["categories"]) == ["box_a", "box_b", "cup"]
    ratios = []
    for name, stats in report["categories"].items():
        ratio = stats["escape/cd_l1_x1000_mean"] / stats["input/cd_l1_x1000_mean"]
        assert stats["escape/ratio_to_input"] == pytest.approx(ratio)
        ratios.append(ratio)
    assert report["average"]["escape/ratio_to_input"] == pytest.approx(np.mean(ratios))  # mean of the ratios
    for sample in report["samples"]:  # the two halves of CD-L1 average to it
        m = sample["metrics"]
        assert (m["escape/pred_to_gt_x1000"] + m["escape/gt_to_pred_x1000"]) / 2 == pytest.approx(m["escape/cd_l1_x1000"])


def test_pairs_folder_needs_complete_pairs(tiny_model, tmp_path):
    folder = tmp_path / "pairs"
    folder.mkdir()
    write_points(folder / "lonely_partial.ply", np.random.default_rng(0).random((100, 3)))
    res = run_escape("eval", "--dataset", "pairs", "--root", folder, "--model", tiny_model)
    assert res.exit_code == 1 and len(res.stderr_lines) == 1
    assert "lonely_partial.ply has no lonely_complete" in res.stderr


def test_json_flag_prints_the_report_as_one_line(tiny_tree, tiny_model, tmp_path):
    """--json is the same flag as in every command: JSON lines on stdout (the table moves to stderr)."""
    out = tmp_path / "r.json"
    res = run_escape("eval", "--root", tiny_tree, "--model", tiny_model, "--limit", "1", "-c", "chair",
                     "--json", "--json-out", out)
    assert res.exit_code == 0, res.stderr
    lines = res.stdout.decode().splitlines()
    assert len(lines) == 1 and json.loads(lines[0]) == json.loads(out.read_text())
    assert "CD-L1" in res.stderr
    quiet = run_escape("-q", "eval", "--root", tiny_tree, "--model", tiny_model, "--limit", "1", "-c", "chair", "--json")
    assert quiet.exit_code == 0 and quiet.stderr == "" and len(quiet.stdout.decode().splitlines()) == 1


def test_reference_cars_are_put_in_the_box_frame_both_ways_round(rng):
    from escape_cli.core.normalize import car_in_box_frame

    # a ModelNet-like car: z up, its length along y, off centre and 3 units long
    car = rng.uniform(-0.5, 0.5, size=(500, 3)) * [1.2, 3.0, 0.9] + [5.0, -2.0, 1.0]
    car[0] = [5.6, 1.4, 1.1]  # a nose at one end: the two ways round differ
    ahead, behind = car_in_box_frame(car, "z")
    for boxed in (ahead, behind):
        np.testing.assert_allclose(boxed.max(0) - boxed.min(0), np.ptp(car, axis=0)[[1, 2, 0]] / np.ptp(car[:, 1]))
        np.testing.assert_allclose((boxed.max(0) + boxed.min(0)) / 2, 0, atol=1e-12)
    np.testing.assert_allclose(behind, ahead * [-1, 1, -1])
    assert ahead[0, 0] > 0.49 and behind[0, 0] < -0.49
    with pytest.raises(Exception, match="no length"):
        car_in_box_frame(np.ones((10, 3)), "y")


def test_kitti_mmd_against_modelnet_cars_in_the_box_frame(realdata_dir, shapes_dir, tiny_model, tmp_path):
    refs = tmp_path / "modelnet-cars"
    refs.mkdir()
    for path in sorted((shapes_dir / "modelnet40" / "car" / "test").glob("*.npy"))[:3]:
        (refs / path.name).write_bytes(path.read_bytes())
    scores = {}
    for up in (None, "z"):
        out = tmp_path / f"k-{up}.json"
        extra = ("--reference-up", up) if up else ()
        res = run_escape("eval", "--dataset", "kitti", "--root", realdata_dir / "kitti_cars", "--model", tiny_model,
                         "--reference", refs, *extra, "--json-out", out)
        assert res.exit_code == 0, res.stderr
        report = json.loads(out.read_text())
        assert report["settings"]["reference_up"] == up
        scores[up] = report["average"]["input/mmd_cd_l2_x1000_mean"]
    # unit-sphere cars lying along y are far from length-1 cars along x; in the box frame they are near
    assert scores["z"] < 0.5 * scores[None], scores
