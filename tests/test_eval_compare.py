"""Paired comparison of two `escape eval --json` reports (`escape_cli.eval_compare`, scripts/compare_evals.py)."""

import json
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from escape_cli.errors import EscapeError
from escape_cli.eval_compare import paired_difference, read_report

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "compare_evals.py"


def _report(values, ids=None):
    ids = ids if ids is not None else [f"m{i}" for i in range(len(values))]
    return {"average": {}, "samples": [
        {"synset": "03001627", "category": "chair", "model_id": model_id, "view": 0, "input_points": 100 + i,
         "metrics": {"escape/cd_l1_x1000": float(v), "input/cd_l1_x1000": 30.0}}
        for i, (model_id, v) in enumerate(zip(ids, values))]}


def test_paired_difference_is_b_minus_a_sample_by_sample(rng):
    a = 10 + rng.random(50)
    b = a - 0.5 + 0.01 * rng.standard_normal(50)
    diff = paired_difference(_report(a), _report(b))
    want = b - a
    assert diff.count == 50 and diff.mean == pytest.approx(want.mean())
    assert diff.standard_error == pytest.approx(want.std(ddof=1) / np.sqrt(50))
    assert diff.better == 50 and diff.worse == 0 and diff.z < -2
    same = paired_difference(_report(a), _report(a))
    assert same.mean == 0 and same.z == 0 and same.better == same.worse == 0


def test_samples_are_matched_by_identity_not_order():
    a = _report([1.0, 2.0, 3.0], ["x", "y", "z"])
    b = _report([3.5, 1.5], ["z", "x"])  # reordered, one missing, other input sizes
    diff = paired_difference(a, b)
    assert diff.count == 2 and diff.mean == pytest.approx(0.5) and diff.worse == 2


def test_reports_without_shared_samples_or_records_are_refused(tmp_path):
    with pytest.raises(EscapeError, match="share no sample"):
        paired_difference(_report([1.0], ["x"]), _report([1.0], ["y"]))
    with pytest.raises(EscapeError, match="per-sample"):
        paired_difference({"average": {}}, _report([1.0]))
    (tmp_path / "indented.json").write_text(json.dumps(_report([1.0, 2.0]), indent=1) + "\n")  # as --json-out writes
    assert read_report(tmp_path / "indented.json") == _report([1.0, 2.0])
    (tmp_path / "bad.json").write_text("not json")
    with pytest.raises(EscapeError, match="cannot read"):
        read_report(tmp_path / "bad.json")


def test_the_script_prints_the_verdict_and_fails_cleanly(tmp_path, capsys, monkeypatch):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text("table on stderr\n" + json.dumps(_report([10.0, 11.0, 12.0, 13.0])))
    b.write_text(json.dumps(_report([9.0, 10.0, 11.0, 12.1])))
    monkeypatch.setattr(sys, "argv", ["compare_evals.py", str(a), str(b)])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "over 4 samples" in out and "4 better, 0 worse" in out and "B better" in out
    monkeypatch.setattr(sys, "argv", ["compare_evals.py", str(a), str(tmp_path / "missing.json")])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert done.value.code == 1
    err = capsys.readouterr().err
    assert err.startswith("compare_evals: error: cannot read") and len(err.strip().splitlines()) == 1
