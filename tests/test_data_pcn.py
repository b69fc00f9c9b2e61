"""The PCN layout reader and writer (escape_cli.data.pcn) on hand-made trees and real files."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from escape_cli.data.pcn import (
    CATEGORIES,
    PCNDataset,
    SampleRef,
    complete_path,
    list_samples,
    partial_path,
    read_pcd,
    read_sample,
    read_split_file,
    resample_points,
    resolve_categories,
    write_model,
    write_pcd,
    write_split_file,
)
from escape_cli.errors import DatasetError, InputFileError, PointCloudError

CHAIR, TABLE, CAR = "03001627", "04379243", "02958343"
PCD_HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {type}\n"
    "COUNT {count}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
)


def _cloud(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.5, 0.5, size=(n, 3)).astype(np.float32)


# --------------------------------------------------------------------------- categories


def test_resolve_categories_accepts_names_synsets_and_comma_lists():
    assert resolve_categories(None) == sorted(CATEGORIES)
    assert resolve_categories([]) == sorted(CATEGORIES)
    assert resolve_categories(["Chair", TABLE]) == [CHAIR, TABLE]
    assert resolve_categories(["table,chair", "chair"]) == [CHAIR, TABLE]


@pytest.mark.parametrize("bad", [["bicycle"], ["0300162"], [","]])
def test_resolve_categories_rejects_unknown(bad):
    with pytest.raises(DatasetError):
        resolve_categories(bad)


# --------------------------------------------------------------------------- PCD files


def test_write_pcd_read_pcd_round_trip_is_exact(tmp_path):
    points = _cloud(100)
    write_pcd(tmp_path / "a.pcd", points)
    back = read_pcd(tmp_path / "a.pcd")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, points)
    header = (tmp_path / "a.pcd").read_bytes().split(b"DATA binary\n")[0].decode()
    assert "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100\nHEIGHT 1" in header


def test_read_ascii_pcd_with_extra_fields_and_nans(tmp_path):
    body = "1 2 3 9\n4 5 6 9\nnan 0 0 9\n"
    path = tmp_path / "a.pcd"
    path.write_text(PCD_HEADER.format(fields="x y z rgb", size="4 4 4 4", type="F F F F", count="1 1 1 1",
                                      n=3, data="ascii") + body)
    np.testing.assert_array_equal(read_pcd(path), [[1, 2, 3], [4, 5, 6]])


def test_read_binary_pcd_with_fields_in_another_order(tmp_path):
    rows = np.array([(7.0, 1.0, 2.0, 3.0), (8.0, 4.0, 5.0, 6.0)], dtype=[("i", "<f4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    path = tmp_path / "b.pcd"
    path.write_bytes(PCD_HEADER.format(fields="intensity x y z", size="4 4 4 4", type="F F F F", count="1 1 1 1",
                                       n=2, data="binary").encode() + rows.tobytes())
    np.testing.assert_array_equal(read_pcd(path), [[1, 2, 3], [4, 5, 6]])


def test_read_binary_compressed_pcd(tmp_path):
    # Column-major x x y y z z as float32; LZF stream: one literal run of all 24 bytes, except that the
    # z column repeats y and is coded as a back reference (length 8, offset 8).
    x, y = np.array([1, 2], "<f4").tobytes(), np.array([3, 4], "<f4").tobytes()
    literal = x + y
    stream = bytes([len(literal) - 1]) + literal + bytes([(8 - 2) << 5 | 0, 8 - 1])
    path = tmp_path / "c.pcd"
    path.write_bytes(PCD_HEADER.format(fields="x y z", size="4 4 4", type="F F F", count="1 1 1", n=2,
                                       data="binary_compressed").encode()
                     + struct.pack("<II", len(stream), 24) + stream)
    np.testing.assert_array_equal(read_pcd(path), [[1, 3, 3], [2, 4, 4]])


def test_read_pcd_errors_are_input_file_errors(tmp_path):
    with pytest.raises(InputFileError, match="no such file"):
        read_pcd(tmp_path / "missing.pcd")
    (tmp_path / "junk.pcd").write_bytes(b"not a pcd at all")
    with pytest.raises(InputFileError, match="corrupt PCD header"):
        read_pcd(tmp_path / "junk.pcd")
    truncated = PCD_HEADER.format(fields="x y z", size="4 4 4", type="F F F", count="1 1 1", n=10, data="binary")
    (tmp_path / "short.pcd").write_bytes(truncated.encode() + b"\0" * 12)
    with pytest.raises(InputFileError, match="truncated"):
        read_pcd(tmp_path / "short.pcd")


def test_read_pcn_demo_partials(realdata_dir):
    for path in sorted((realdata_dir / "pcn_demo").glob("*.pcd")):
        points = read_pcd(path)
        assert points.ndim == 2 and points.shape[1] == 3 and len(points) > 100
        assert np.abs(points).max() < 0.6  # PCN frame: inside [-0.5, 0.5]^3 give or take


def test_real_pcn_split_file_parses(realdata_dir):
    ids = read_split_file(realdata_dir / "pointr_demo" / "PCN.json")
    train_counts = {"02691156": 3795, "02933112": 1322, "02958343": 5677, "03001627": 5750,
                    "03636649": 2068, "04256520": 2923, "04379243": 5750, "04530566": 1689}
    assert {s: len(v["train"]) for s, v in ids.items()} == train_counts
    for synset, splits in ids.items():
        assert (len(splits["val"]), len(splits["test"])) == (100, 150), CATEGORIES[synset]
        assert all(isinstance(i, str) and i for i in splits["test"])


# --------------------------------------------------------------------------- a hand-made tree


@pytest.fixture
def tiny_tree(tmp_path) -> Path:
    """train: 2 chairs (2 views each) + 1 table (3 views); test: 1 chair (1 view); no PCN.json."""
    root = tmp_path / "PCN"
    write_model(root, "train", CHAIR, "chair_b", _cloud(64, 1), [_cloud(10, 2), _cloud(12, 3)])
    write_model(root, "train", CHAIR, "chair_a", _cloud(64, 4), [_cloud(11, 5), _cloud(13, 6)])
    write_model(root, "train", TABLE, "table_a", _cloud(64, 7), [_cloud(20, 8), _cloud(21, 9), _cloud(22, 10)])
    write_model(root, "test", CHAIR, "chair_t", _cloud(64, 11), [_cloud(30, 12)])
    return root


def test_layout_paths_are_pcn_paths(tmp_path):
    assert partial_path(tmp_path, "train", CHAIR, "m", 3) == tmp_path / "train/partial/03001627/m/03.pcd"
    assert complete_path(tmp_path, "val", CHAIR, "m") == tmp_path / "val/complete/03001627/m.pcd"


def test_list_samples_without_split_file_walks_the_folders(tiny_tree):
    refs = list_samples(tiny_tree, "train")
    assert [(r.synset, r.model_id, r.view) for r in refs] == [
        (CHAIR, "chair_a", 0), (CHAIR, "chair_a", 1), (CHAIR, "chair_b", 0), (CHAIR, "chair_b", 1),
        (TABLE, "table_a", 0), (TABLE, "table_a", 1), (TABLE, "table_a", 2)]
    assert refs[0].partial_path == tiny_tree / "train/partial/03001627/chair_a/00.pcd"
    assert refs[0].complete_path == tiny_tree / "train/complete/03001627/chair_a.pcd"
    first = list_samples(tiny_tree, "train", categories=["table"], views="first")
    assert [(r.model_id, r.view) for r in first] == [("table_a", 0)]


def test_list_samples_with_split_file_uses_its_ids_that_exist(tiny_tree):
    write_split_file(tiny_tree, {CHAIR: {"train": ["chair_b", "chair_missing"], "test": ["chair_t"]},
                                 TABLE: {"train": []}})
    refs = list_samples(tiny_tree, "train")
    assert [(r.model_id, r.view) for r in refs] == [("chair_b", 0), ("chair_b", 1)]
    entries = json.loads((tiny_tree / "PCN.json").read_text())
    assert entries[0] == {"taxonomy_id": CHAIR, "taxonomy_name": "chair", "train": ["chair_b", "chair_missing"],
                          "val": [], "test": ["chair_t"]}
    with pytest.raises(DatasetError, match="no train samples listed in PCN.json"):
        list_samples(tiny_tree, "train", categories=["table"])


@pytest.mark.parametrize("kwargs, message", [
    ({"split": "valid"}, "unknown split"),
    ({"split": "val"}, "no val/partial"),
    ({"split": "test", "categories": ["car"]}, "no test samples"),
    ({"split": "train", "views": "some"}, "views must be"),
])
def test_list_samples_explains_a_wrong_layout(tiny_tree, kwargs, message):
    with pytest.raises(DatasetError, match=message):
        list_samples(tiny_tree, **kwargs)


def test_list_samples_on_a_missing_root(tmp_path):
    with pytest.raises(DatasetError, match="not a folder"):
        list_samples(tmp_path / "nope")


def test_bad_split_file_is_a_dataset_error(tiny_tree):
    (tiny_tree / "PCN.json").write_text('{"not": "a list"}')
    with pytest.raises(DatasetError, match="list of categories"):
        list_samples(tiny_tree, "train")


def test_read_sample_reads_what_was_written(tiny_tree):
    ref = list_samples(tiny_tree, "test")[0]
    sample = read_sample(ref, n_points=None)
    np.testing.assert_array_equal(sample.partial, _cloud(30, 12))
    np.testing.assert_array_equal(sample.complete, _cloud(64, 11))
    assert (sample.synset, sample.category, sample.model_id, sample.view) == (CHAIR, "chair", "chair_t", 0)


def test_read_sample_resamples_pcn_style_and_deterministically(tiny_tree):
    ref = list_samples(tiny_tree, "test")[0]  # 30 partial points
    up = read_sample(ref, n_points=64, seed=0)
    assert up.partial.shape == (64, 3) and up.partial.dtype == np.float32
    assert {tuple(p) for p in up.partial} == {tuple(p) for p in _cloud(30, 12)}  # all points, some repeated
    down = read_sample(ref, n_points=16, seed=0)
    assert len({tuple(p) for p in down.partial}) == 16  # a subset without repeats
    np.testing.assert_array_equal(read_sample(ref, 16, seed=0).partial, down.partial)
    assert not np.array_equal(read_sample(ref, 16, seed=1).partial, down.partial)


def test_resample_points_rejects_empty():
    with pytest.raises(PointCloudError):
        resample_points(np.zeros((0, 3)), 8, np.random.default_rng(0))


def test_pcn_dataset_indexes_samples(tiny_tree):
    dataset = PCNDataset(tiny_tree, "train", categories=["chair"], n_points=32, seed=3)
    assert len(dataset) == 4
    sample = dataset[2]
    assert sample.model_id == "chair_b" and sample.view == 0 and sample.partial.shape == (32, 3)
    assert isinstance(dataset.refs[0], SampleRef)
    np.testing.assert_array_equal(dataset[2].partial, sample.partial)


def test_point_files_are_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """write_pcd goes through a temporary file that an interrupt would remove (tracked while it exists)."""
    import escape_cli.interrupts as interrupts
    from escape_cli.errors import OutputFileError
    from escape_cli.io import files

    seen = []
    real_replace = files.os.replace

    def replace(src, dst):
        seen.append((Path(src).name, set(interrupts._temporary) == {str(src)}))
        real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", replace)
    target = tmp_path / "a" / "00.pcd"
    write_pcd(target, _cloud(20, 1))
    write_pcd(target, _cloud(30, 2))  # an existing file is replaced
    assert len(read_pcd(target)) == 30 and sorted(p.name for p in target.parent.iterdir()) == ["00.pcd"]
    assert [tracked for _, tracked in seen] == [True, True] and all(name.endswith(".tmp") for name, _ in seen)
    assert not interrupts._temporary
    monkeypatch.setattr(files.os, "replace", lambda src, dst: (_ for _ in ()).throw(OSError(28, "No space left on device")))
    with pytest.raises(OutputFileError, match="cannot write .*00.pcd: No space left on device"):
        write_pcd(target, _cloud(40, 3))
    assert len(read_pcd(target)) == 30 and sorted(p.name for p in target.parent.iterdir()) == ["00.pcd"]
    assert not interrupts._temporary
