"""Paired comparison of two `escape eval --json` reports on the same samples.

    from escape_cli.eval_compare import paired_difference
    diff = paired_difference(report_a, report_b)   # B minus A, sample by sample
    diff.mean, diff.standard_error, diff.better, diff.worse

Two models scored on the same objects differ by less than the objects' spread; the
difference sample by sample, with its standard error, says whether a change in the
averages is more than noise (the model card's rule for shipping a stage).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from escape_cli.errors import EscapeError

DEFAULT_METRIC = "escape/cd_l1_x1000"


@dataclass(frozen=True)
class PairedDifference:
    """B minus A over the samples both reports scored (lower metric is better)."""

    metric: str
    count: int
    mean: float
    standard_error: float  # of the mean difference (0 with one sample)
    better: int  # samples where B is lower
    worse: int  # samples where B is higher

    @property
    def z(self) -> float:
        """mean / standard_error (0 when both are 0); |z| < 2 is within noise."""
        if self.standard_error == 0:
            return 0.0 if self.mean == 0 else float(np.sign(self.mean) * np.inf)
        return self.mean / self.standard_error


def read_report(path: str | Path) -> dict:
    """An `escape eval` report: a `--json-out` file (indented JSON) or captured `--json` output (its last line)."""
    try:
        text = Path(path).read_text().strip()
        try:
            return json.loads(text)
        except ValueError:
            return json.loads(text.splitlines()[-1])
    except (OSError, IndexError, ValueError) as err:
        raise EscapeError(f"cannot read an escape eval report from {path}: {err}") from None


def _by_sample(report: dict, metric: str) -> dict[tuple, float]:
    """{sample identity: metric} of a report's samples (identity: every field but its metrics)."""
    samples = report.get("samples")
    if not isinstance(samples, list):
        raise EscapeError("the report has no per-sample records (run escape eval with --json)")
    values = {}
    for sample in samples:
        key = tuple(sorted((k, str(v)) for k, v in sample.items() if k not in ("metrics", "input_points")))
        if metric in sample.get("metrics", {}):
            values[key] = float(sample["metrics"][metric])
    return values


def paired_difference(a: dict, b: dict, metric: str = DEFAULT_METRIC) -> PairedDifference:
    """B minus A, sample by sample, over the samples both reports hold `metric` for."""
    first, second = _by_sample(a, metric), _by_sample(b, metric)
    shared = sorted(first.keys() & second.keys())
    if not shared:
        raise EscapeError(f"the two reports share no sample with {metric!r}")
    diff = np.array([second[k] - first[k] for k in shared])  # (n,)
    error = float(diff.std(ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else 0.0
    return PairedDifference(metric, len(diff), float(diff.mean()), error, int((diff < 0).sum()), int((diff > 0).sum()))
