"""`escape dataset from-shapes` (escape_cli.data.from_shapes, cloud_views): any shapes -> the PCN layout."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_runner import run_escape

from escape_cli.core.neighbours import NeighbourIndex
from escape_cli.data.cloud_views import SplatScanner, SplatSettings, densify, tangent_frames, view_coverage
from escape_cli.data.from_shapes import METADATA_FILE, ShapeSource, assign_splits, find_shapes
from escape_cli.data.meshes import read_mesh
from escape_cli.data.pcn import dataset_categories, list_samples, read_pcd
from escape_cli.data.surface import sample_triangles
from escape_cli.errors import DatasetError

SHARED = Path(__file__).resolve().parents[2] / "shared" / "shapes"
TEST_MESHES = SHARED / "test-meshes"
MODELNET = SHARED / "modelnet40"

needs_shapes = pytest.mark.skipif(not TEST_MESHES.is_dir() or not MODELNET.is_dir(),
                                  reason=f"third-party shapes not found at {SHARED}")


def _ellipsoid(rng: np.random.Generator, n: int = 600, axes=(1.0, 0.6, 0.4)) -> np.ndarray:
    """(n, 3) float32 points on an ellipsoid's surface: a small closed shape."""
    d = rng.normal(size=(n, 3))
    return (d / np.linalg.norm(d, axis=1, keepdims=True) * axes).astype(np.float32)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*.pcd"))}


def _cloud_from_mesh(name: str, points: int = 1024, seed: int = 5) -> np.ndarray:
    mesh = read_mesh(TEST_MESHES / name)
    return sample_triangles(mesh.vertices, mesh.triangles, points, np.random.default_rng(seed))[0].astype(np.float32)


def _write_off(path: Path, mesh) -> None:
    lines = [f"OFF\n{len(mesh.vertices)} {len(mesh.triangles)} 0\n"]
    lines += [f"{float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in mesh.vertices]
    lines += [f"3 {a} {b} {c}\n" for a, b, c in mesh.triangles]
    path.write_text("".join(lines))


def _write_binary_stl(path: Path, mesh) -> None:
    corners = mesh.vertices[mesh.triangles]
    record = np.zeros(len(corners), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    record["v"] = corners
    path.write_bytes(b"binary stl".ljust(80, b" ") + np.uint32(len(corners)).tobytes() + record.tobytes())


@pytest.fixture(scope="module")
def mixed_folder(tmp_path_factory) -> Path:
    """ModelNet clouds, OBJ, OFF, binary STL, the tristrips PLY, a broken OBJ and an all-NaN cloud."""
    if not TEST_MESHES.is_dir() or not MODELNET.is_dir():
        pytest.skip(f"third-party shapes not found at {SHARED}")
    folder = tmp_path_factory.mktemp("mixed") / "shapes"
    folder.mkdir()
    shutil.copy(MODELNET / "sofa" / "train" / "sofa_0001.npy", folder)
    shutil.copy(MODELNET / "bathtub" / "train" / "bathtub_0001.npy", folder)
    shutil.copy(TEST_MESHES / "spot.obj", folder)
    shutil.copy(TEST_MESHES / "igea.ply", folder)
    _write_off(folder / "cow.off", read_mesh(TEST_MESHES / "cow.obj"))
    _write_binary_stl(folder / "teapot.stl", read_mesh(TEST_MESHES / "teapot.obj"))
    (folder / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 9\n")
    np.save(folder / "nan.npy", np.full((100, 3), np.nan, dtype=np.float32))
    return folder


@pytest.fixture(scope="module")
def mixed_runs(mixed_folder, tmp_path_factory):
    """The mixed folder made into datasets with 1 and with 2 workers."""
    out = tmp_path_factory.mktemp("mixed_out")
    runs = {}
    for workers in (1, 2):
        runs[workers] = (out / f"w{workers}", run_escape(
            "dataset", "from-shapes", str(mixed_folder), "-o", str(out / f"w{workers}"), "--views", "2",
            "--eval-views", "1", "--val-fraction", "0.34", "--seed", "3", "--workers", str(workers)))
    return runs


GOOD = ("sofa_0001", "bathtub_0001", "spot", "igea", "cow", "teapot")


def test_mixed_folder_names_each_bad_file_and_writes_the_rest(mixed_runs):
    root, res = mixed_runs[1]
    assert res.exit_code == 1
    errors = [line for line in res.stderr_lines if line.startswith("escape: error:")]
    assert len(errors) == 3, res.stderr  # one per bad file, then the count
    assert any("broken.obj" in line for line in errors) and any("nan.npy" in line for line in errors)
    assert "2 of 8 shapes" in errors[-1]
    refs = list_samples(root, "train") + list_samples(root, "val")
    assert sorted({r.model_id for r in refs}) == sorted(GOOD)
    views = {r.model_id: 0 for r in refs}
    for r in refs:
        views[r.model_id] += 1
    split = {r.model_id: r.split for r in refs}
    assert all(views[m] == (2 if split[m] == "train" else 1) for m in GOOD)
    assert sum(s == "val" for s in split.values()) == 2  # round(0.34 x 6)
    meta = json.loads((root / METADATA_FILE).read_text())
    assert meta["totals"]["failed"] == 2 and meta["totals"]["written"] == 6
    assert meta["notes"]["tristrips triangulated"] == [str(Path(meta["sources"][0]) / "igea.ply")]
    assert not list(root.rglob("*.tmp"))


def test_views_lie_on_the_surface_and_show_one_side(mixed_runs):
    root, _ = mixed_runs[1]
    for ref in list_samples(root, "train") + list_samples(root, "val"):
        complete, view = read_pcd(ref.complete_path).astype(np.float64), read_pcd(ref.partial_path).astype(np.float64)
        diagonal = np.linalg.norm(np.ptp(complete, axis=0))
        dist, _ = NeighbourIndex(complete).query(view, 1)
        assert np.quantile(dist[:, 0], 0.99) <= 0.03 * diagonal, ref.model_id
        assert view_coverage(complete, view) <= 0.85, ref.model_id
        assert len(complete) == 16384 and len(view) >= 256


def test_same_bytes_with_one_or_two_workers(mixed_runs):
    (one, _), (two, _) = mixed_runs[1], mixed_runs[2]
    assert _files(one) == _files(two)
    assert (one / "PCN.json").read_bytes() == (two / "PCN.json").read_bytes()
    strip = lambda p: {k: v for k, v in json.loads(p.read_text()).items() if k != "timing"}  # noqa: E731
    assert strip(one / METADATA_FILE) == strip(two / METADATA_FILE)


@needs_shapes
@pytest.mark.parametrize("name", ["spot", "cow"])
def test_views_of_a_sparse_cloud_cover_like_depth_renders_of_its_mesh(tmp_path, name):
    meshes, clouds = tmp_path / "mesh", tmp_path / "cloud"
    meshes.mkdir()
    clouds.mkdir()
    shutil.copy(TEST_MESHES / f"{name}.obj", meshes)
    np.save(clouds / f"{name}.npy", _cloud_from_mesh(f"{name}.obj"))
    coverage = {}
    for kind, folder in (("mesh", meshes), ("cloud", clouds)):
        out = tmp_path / f"out-{kind}"
        res = run_escape("dataset", "from-shapes", str(folder), "-o", str(out), "--views", "8", "--val-fraction", "0", "--seed", "1")
        assert res.exit_code == 0, res.stderr
        refs = list_samples(out, "train")
        assert len(refs) == 8
        complete = read_pcd(refs[0].complete_path)
        coverage[kind] = np.mean([view_coverage(complete, read_pcd(r.partial_path)) for r in refs])
    assert coverage["cloud"] <= 1.25 * coverage["mesh"], coverage
    assert coverage["cloud"] >= 0.6 * coverage["mesh"], coverage  # one side, not a sliver


@needs_shapes
def test_densified_cloud_is_closer_to_the_surface_than_its_source():
    mesh = read_mesh(TEST_MESHES / "spot.obj")
    truth = sample_triangles(mesh.vertices, mesh.triangles, 16384, np.random.default_rng(0))[0]
    source = _cloud_from_mesh("spot.obj").astype(np.float64)
    dense, parent = densify(source, tangent_frames(source), 16384, np.random.default_rng(1))
    assert dense.shape == (16384, 3) and parent.shape == (16384,)
    np.testing.assert_array_equal(dense[:1024], source)

    def one_way(a, b):  # mean distance from a to b
        return NeighbourIndex(b).query(a, 1)[0].mean()
    # every new point stays near the surface; the denser cloud covers it better than its source
    assert one_way(dense, truth) < 0.01 * np.linalg.norm(np.ptp(truth, axis=0))
    assert one_way(truth, dense) < 0.7 * one_way(truth, source)


def _far_side_share(splat_scale: float) -> tuple[float, int]:
    """A hollow box's six faces, sparsely sampled, seen from a corner: the share of the view on the 3 far faces."""
    rng = np.random.default_rng(0)
    faces = []
    for axis in range(3):
        for side in (-0.3, 0.3):
            p = rng.uniform(-0.3, 0.3, (170, 3))
            p[:, axis] = side
            faces.append(p)
    source = np.concatenate(faces)
    frames = tangent_frames(source)
    dense, parent = densify(source, frames, 8192, rng)
    scanner = SplatScanner(source, frames, dense, parent, settings=SplatSettings(splat_scale=splat_scale))
    view = scanner.scan(np.array([1.0, 1.2, 0.8]), np.array([0.0, 1.0, 0.0]))
    far = near = 0
    for axis in range(3):
        interior = (np.abs(np.delete(view, axis, axis=1)) < 0.25).all(axis=1)  # away from edges shared with a seen face
        far += np.sum(interior & (np.abs(view[:, axis] + 0.3) < 1e-9))
        near += np.sum(interior & (np.abs(view[:, axis] - 0.3) < 1e-9))
    return far / len(view), near


def test_a_plain_point_z_buffer_would_see_through_but_splats_do_not():
    far, near = _far_side_share(SplatSettings().splat_scale)
    assert far < 0.01 and near > 300
    see_through, _ = _far_side_share(0.01)  # splats of no size: a plain point z-buffer
    assert see_through > 0.1


@pytest.mark.parametrize("outliers", [0, 12])
def test_the_z_buffer_is_the_naive_one_exactly(outliers):
    """Discs tried on their own reach (fast) or on the largest one's (naive): the same buffer, bit for bit."""
    from escape_cli.data.depth_views import DepthCamera, draw_viewpoint

    rng = np.random.default_rng(outliers)
    source = np.concatenate([_ellipsoid(rng, 700).astype(np.float64), rng.normal(size=(outliers, 3)) * 0.4])
    frames = tangent_frames(source)
    dense, parent = densify(source, frames, 4096, rng)
    scanner = SplatScanner(source, frames, dense, parent)
    grids = []

    def keep(method):
        def run(*args):
            grids.append(method(scanner, *args))
            return grids[-1]
        return run

    for _ in range(4):
        eye, up = draw_viewpoint(rng, DepthCamera())
        for method in (SplatScanner._zbuffer, SplatScanner._zbuffer_naive):
            scanner._zbuffer = keep(method)
            grids.append(scanner.scan(eye, up))
        fast_grid, fast_view, naive_grid, naive_view = grids[-4:]
        np.testing.assert_array_equal(fast_grid, naive_grid)
        np.testing.assert_array_equal(fast_view, naive_view)
        assert np.isfinite(fast_grid).sum() > 1000


def test_layouts_and_categories(tmp_path):
    rng = np.random.default_rng(0)
    cloud = lambda: rng.normal(size=(300, 3)).astype(np.float32)  # noqa: E731
    modelnet = tmp_path / "mn"
    for cat in ("chair", "bathtub"):
        for split in ("train", "test"):
            (modelnet / cat / split).mkdir(parents=True)
            for i in range(3):
                np.save(modelnet / cat / split / f"{cat}_{i:04d}.npy", cloud())
    (modelnet / "README.txt").write_text("not a shape")
    shapes, skipped = find_shapes([modelnet])
    assert skipped == 1 and len(shapes) == 12
    assert {s.category for s in shapes} == {"03001627", "bathtub"}  # PCN names become their synsets
    assert {s.split for s in shapes} == {"train", "test"}
    flat = tmp_path / "parts"
    flat.mkdir()
    for name in ("a.npy", "a.xyz", "b.npy"):
        (flat / name).write_bytes(b"")
    (flat / "LICENSE").write_text("x")
    shapes, skipped = find_shapes([flat], category="bolts")
    assert [s.model_id for s in shapes] == ["a", "a_xyz", "b"] and skipped == 1  # a stem met twice: its extension
    assert {s.category for s in shapes} == {"bolts"}
    assert find_shapes([flat])[0][0].category == "parts"
    with pytest.raises(DatasetError, match="no shape files"):
        find_shapes([_empty(tmp_path)])


def _empty(tmp_path: Path) -> Path:
    folder = tmp_path / "empty"
    folder.mkdir()
    return folder


def test_validation_carved_deterministically():
    shapes = [ShapeSource(Path(f"{i}.npy"), "c", f"s{i}", "train") for i in range(40)]
    first = assign_splits(shapes, 0.1, 0.0)
    assert first.count("val") == 4 and first.count("train") == 36
    assert assign_splits(list(reversed(shapes)), 0.1, 0.0) == list(reversed(first))  # not the order found in
    free = [ShapeSource(Path(f"{i}.npy"), "c", f"s{i}") for i in range(40)]
    splits = assign_splits(free, 0.1, 0.25)
    assert splits.count("test") == 10 and splits.count("val") == 3  # round(0.1 x 30)


def test_seed_changes_the_views_not_the_split(tmp_path):
    folder = tmp_path / "src"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for i in range(3):
        np.save(folder / f"s{i}.npy", _ellipsoid(rng))
    outs = {}
    for seed in (0, 0, 1):
        out = tmp_path / f"out{len(outs)}"
        assert run_escape("dataset", "from-shapes", str(folder), "-o", str(out), "--views", "1", "--seed", str(seed),
                          "--val-fraction", "0.34").exit_code == 0
        outs[len(outs)] = out
    assert _files(outs[0]) == _files(outs[1])
    assert _files(outs[0]).keys() == _files(outs[2]).keys() and _files(outs[0]) != _files(outs[2])


def test_cli_refusals(tmp_path):
    empty = _empty(tmp_path)
    res = run_escape("dataset", "from-shapes", str(empty), "-o", str(tmp_path / "o"))
    assert res.exit_code == 1 and "no shape files" in res.stderr and len(res.stderr_lines) == 1
    res = run_escape("dataset", "from-shapes", str(tmp_path / "missing"), "-o", str(tmp_path / "o"))
    assert res.exit_code == 1 and "no such file or folder" in res.stderr
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    np.save(empty / "s.npy", np.random.default_rng(0).normal(size=(100, 3)))
    res = run_escape("dataset", "from-shapes", str(empty), "-o", str(tmp_path / "full"))
    assert res.exit_code == 1 and "--overwrite" in res.stderr
    res = run_escape("dataset", "from-shapes", str(empty), "-o", str(tmp_path / "o"), "--val-fraction", "1.5")
    assert res.exit_code == 2


def test_a_source_that_overwrite_would_remove_is_refused(tmp_path):
    """An earlier dataset's clouds made into a new dataset in its place: --overwrite would delete them first."""
    old = tmp_path / "ds" / "train" / "complete" / "bolt"
    old.mkdir(parents=True)
    np.save(old / "s.npy", _ellipsoid(np.random.default_rng(0)))
    for source in (old, old / "s.npy", tmp_path / "ds" / "train"):
        res = run_escape("dataset", "from-shapes", str(source), "-o", str(tmp_path / "ds"), "--overwrite")
        assert res.exit_code == 1 and len(res.stderr_lines) == 1, res.stderr
        assert "is inside the output folder" in res.stderr and (old / "s.npy").is_file()


def test_train_info_and_eval_take_the_dataset_categories(tmp_path, tiny_model):
    pytest.importorskip("torch")
    rng = np.random.default_rng(2)
    src = tmp_path / "src"
    for cat in ("bathtub", "guitar"):
        for split in ("train", "test"):
            (src / cat / split).mkdir(parents=True)
            for i in range(2 if split == "test" else 4):
                np.save(src / cat / split / f"{cat}_{i}.npy", _ellipsoid(rng))
    data = tmp_path / "ds"
    assert run_escape("dataset", "from-shapes", str(src), "-o", str(data), "--views", "2", "--val-fraction", "0.25").exit_code == 0
    assert dataset_categories(data) == {"bathtub": "bathtub", "guitar": "guitar"}
    info = run_escape("dataset", "info", str(data), "--json")
    assert info.exit_code == 0 and set(json.loads(info.stdout)["train"]) == {"bathtub", "guitar"}
    res = run_escape("eval", "--dataset", "pcn", "--root", str(data), "--model", str(tiny_model), "--json")
    assert res.exit_code == 0, res.stderr
    report = json.loads(res.stdout.decode().splitlines()[-1])
    assert set(report["categories"]) == {"bathtub", "guitar"}
    res = run_escape("train", "--data", str(data), "--out", str(tmp_path / "run"), "--config", "tiny", "--max-steps", "2",
                     "--batch", "2", "--categories", "guitar", "--workers", "1")
    assert res.exit_code == 0, res.stderr
