"""Is model B better than model A? Paired difference of two `escape eval` reports.

Usage: `.venv/bin/python scripts/compare_evals.py A.json B.json [--metric escape/cd_l1_x1000]`

Prints B minus A sample by sample: the mean difference, its standard error, z, and how
many samples got better or worse. Both reports must score the same samples (the same
dataset, split and --limit). A report is a `--json-out` file or the captured stdout of
`--json`.
"""

from __future__ import annotations

import argparse
import sys

from escape_cli.errors import EscapeError
from escape_cli.eval_compare import DEFAULT_METRIC, paired_difference, read_report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", help="report of the reference model")
    parser.add_argument("b", help="report of the candidate")
    parser.add_argument("--metric", default=DEFAULT_METRIC, help=f"per-sample metric (default {DEFAULT_METRIC})")
    args = parser.parse_args(argv)
    try:
        diff = paired_difference(read_report(args.a), read_report(args.b), args.metric)
    except EscapeError as err:
        print(f"compare_evals: error: {err}", file=sys.stderr)
        return 1
    verdict = "within noise" if abs(diff.z) < 2 else ("B better" if diff.mean < 0 else "B worse")
    print(f"{diff.metric}, B - A over {diff.count} samples: mean {diff.mean:+.4f} +- {diff.standard_error:.4f} "
          f"(z {diff.z:+.2f}), {diff.better} better, {diff.worse} worse: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
