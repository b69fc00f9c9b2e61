"""Benchmark: end-to-end `complete` of one 2048-point partial to 16384 points, per stage.

Run on demand (`make bench` or `.venv/bin/python bench/bench_complete.py [--model M]`).
Prints the time of each stage (anchors, encoding, ONNX inference, reconstruction, snap) warm,
the whole `complete()` call warm, and the whole `escape complete` command cold (a new
process: imports, model load and file I/O included), with each stage's share of the
warm total and the cold/warm ratio, all measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def timed(func, repeats: int):
    times = []
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = func()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    parser.add_argument("--input", default=str(REPO / "examples" / "chair.pcd"), help="partial cloud")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    from escape_cli.core.anchors import select_anchors
    from escape_cli.core.encoding import distance_matrix
    from escape_cli.inference import load_model
    from escape_cli.io import read_points
    from escape_cli.pipeline import complete
    from escape_cli.core.reconstruction import reconstruct
    from escape_cli.core.sampling import prepare_input
    from escape_cli.core.snap import snap_to_scan

    net = load_model(args.model)
    cloud = read_points(args.input)
    prepared, unique = prepare_input(cloud, net.input_points)
    print(f"input {args.input}: {len(cloud)} points -> {net.input_points} network rows; model {net.path.name}")

    t_prep, _ = timed(lambda: prepare_input(cloud, net.input_points), args.repeats)
    a = net.anchors
    t_anchor, anchors = timed(lambda: select_anchors(prepared[:unique], a.k, a.method, a.radius, a.knn), args.repeats)
    t_enc, feats = timed(lambda: distance_matrix(prepared, anchors.points), args.repeats)
    t_net, pred = timed(lambda: net.predict(feats[None].astype(np.float32)), args.repeats)
    pred = pred[0].astype(np.float64)
    t_rec, rec = timed(lambda: reconstruct(pred, anchors.points, reference_points=prepared[:unique]), args.repeats)
    t_snap, _ = timed(lambda: snap_to_scan(rec.points, prepared[:unique]), args.repeats)
    t_total, result = timed(lambda: complete(cloud, net), args.repeats)

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.ply"
        cmd = [str(Path(sys.executable).parent / "escape"), "complete", args.input, "-o", str(out), "--overwrite"]
        if args.model:
            cmd += ["--model", args.model]
        colds = []
        for _ in range(3):
            start = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            colds.append(time.perf_counter() - start)
        t_cold = statistics.median(colds)

    stages = [
        ("prepare input (FPS to N rows)", t_prep), ("anchors", t_anchor), ("encoding", t_enc),
        ("ONNX inference", t_net), ("reconstruction (batched LM)", t_rec), ("snap to scan", t_snap),
    ]
    print(f"\n{'stage':34s} {'ms (median)':>12s} {'share of warm total':>20s}")
    for name, t in stages:
        print(f"{name:34s} {1000 * t:12.1f} {100 * t / t_total:19.1f}%")
    print(f"{'complete() warm total':34s} {1000 * t_total:12.1f} {100.0:19.1f}%")
    print(f"{'escape complete, cold process':34s} {1000 * t_cold:12.1f} {'x%.1f of warm' % (t_cold / t_total):>20s}")
    print(f"\noutput: {len(result.points)} points")


if __name__ == "__main__":
    main()
