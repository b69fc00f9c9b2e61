"""Benchmark: `complete` of one partial scan, stage by stage, warm, cold and in batches.

Run on demand (`make bench` or `.venv/bin/python bench/bench_complete.py [--model M]`).
Every number is printed beside a reference measured in the same run, so that a busy
machine changes both alike:

- each stage and the warm `complete()` against the ONNX forward pass alone (measured
  alternately with them, medians of `--repeats`);
- farthest point sampling against its naive loop (`farthest_point_sampling_naive`) on the
  scan and on denser copies of it (a few thousand to 100k points down to 2048);
- the neighbour queries (`core.neighbours`, the compiled grid) against scipy's cKDTree;
- the cold `escape complete one.pcd` process against a process that only imports numpy,
  scipy.spatial and onnxruntime (alternately, medians);
- `complete_many` over `--scans` scans against a loop of `complete` over the same scans;
- warm `complete(anchor_sets=S)` for each S of `--anchor-sets` against one set
  (alternately, medians).

The reconstruction against scipy's per-point LM is in bench/bench_reconstruction.py.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def median_time(func, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def alternate(funcs: dict, repeats: int) -> dict:
    """Median seconds of each function, the functions called in turn `repeats` times."""
    times = {name: [] for name in funcs}
    for _ in range(repeats):
        for name, func in funcs.items():
            start = time.perf_counter()
            func()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}


def densified(cloud: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) a denser scan of the same surface: points of `cloud` jittered by 2 mm at PCN scale."""
    return cloud[rng.integers(0, len(cloud), n)] + rng.normal(scale=0.002, size=(n, 3))


def stages(cloud: np.ndarray, net, repeats: int) -> None:
    from escape_cli.core.anchors import select_anchors
    from escape_cli.core.encoding import distance_matrix
    from escape_cli.core.reconstruction import reconstruct
    from escape_cli.core.sampling import first_unique_rows
    from escape_cli.core.snap import snap_to_scan
    from escape_cli.pipeline import _network_input, complete

    net_in = _network_input(cloud, net, "auto")
    observed = net_in.observed
    anchors = select_anchors(observed, **net.anchors.to_dict())
    features = distance_matrix(net_in.rows, anchors.points)[None].astype(np.float32)
    predicted = net.predict(features)[0].astype(np.float64)
    rec = reconstruct(predicted, anchors.points, reference_points=observed)
    snap = snap_to_scan(rec.points, observed)

    def merge():  # observed points appended, a subset without repeats, back to the input frame
        from escape_cli.core.sampling import resample_rows

        out = np.concatenate([snap.points, observed])
        return net_in.normalization.invert(out[resample_rows(len(out), min(16384, len(out)))])

    funcs = {
        "ONNX forward alone": lambda: net.predict(features),
        "network input (FPS to N rows, frame)": lambda: _network_input(cloud, net, "auto"),
        "anchors": lambda: select_anchors(observed, **net.anchors.to_dict()),
        "encoding": lambda: distance_matrix(net_in.rows, anchors.points),
        "dedupe of repeated queries": lambda: first_unique_rows(predicted, predicted.shape[1]),
        "reconstruction (batched LM)": lambda: reconstruct(predicted, anchors.points, reference_points=observed),
        "snap to scan": lambda: snap_to_scan(rec.points, observed),
        "merge, subset, invert": merge,
        "complete() warm total": lambda: complete(cloud, net),
    }
    t = alternate(funcs, repeats)
    forward = t["ONNX forward alone"]
    print(f"\n{'stage (measured alternately)':40s} {'ms (median)':>12s} {'x ONNX forward':>15s}")
    for name, seconds in t.items():
        print(f"{name:40s} {1000 * seconds:12.1f} {seconds / forward:15.2f}")
    rest = sum(v for k, v in t.items() if k not in ("ONNX forward alone", "complete() warm total"))
    print(f"{'stages other than the network, summed':40s} {1000 * rest:12.1f} {rest / forward:15.2f}")
    ratio = t["complete() warm total"] / forward
    print(f"target: warm complete() <= 2.5 x the ONNX forward: x{ratio:.2f} -> {'met' if ratio <= 2.5 else 'NOT met'}")


def fps(cloud: np.ndarray, rng: np.random.Generator, sizes) -> None:
    from escape_cli.core.sampling import farthest_point_sampling, farthest_point_sampling_naive

    print(f"\n{'farthest point sampling':32s} {'naive ms':>10s} {'fast ms':>10s} {'speed-up':>9s}  same")
    for n in sizes:
        pts = cloud if n is None else densified(cloud, n, rng)
        count = min(len(pts), 2048)
        start = time.perf_counter()
        slow = farthest_point_sampling_naive(pts, count)
        t_slow = time.perf_counter() - start
        fast = None

        def run():
            nonlocal fast
            fast = farthest_point_sampling(pts, count)

        t_fast = median_time(run, 3)
        label = f"{len(pts)} -> {count}" + (" (the scan)" if n is None else "")
        print(f"{label:32s} {1000 * t_slow:10.1f} {1000 * t_fast:10.1f} {t_slow / t_fast:8.1f}x  {np.array_equal(slow, fast)}")


def neighbours(cloud: np.ndarray, rng: np.random.Generator, repeats: int) -> None:
    """The neighbour queries of `complete` (anchors' curvature, the snap) against scipy's cKDTree."""
    from scipy.spatial import cKDTree

    from escape_cli.core.neighbours import NeighbourIndex

    completion = cloud[rng.integers(0, len(cloud), 16384)] + rng.normal(scale=0.05, size=(16384, 3))
    print(f"\n{'nearest neighbours (build + query)':40s} {'cKDTree ms':>10s} {'kernel ms':>10s} {'speed-up':>9s}  same distances")
    for label, queries, k in ((f"{len(cloud)} points, 24 of each", cloud, 24), ("16384 completion points, 10 each", completion, 10)):
        t = alternate({"tree": lambda: cKDTree(cloud).query(queries, k=k), "kernel": lambda: NeighbourIndex(cloud).query(queries, k)}, repeats)
        same = np.array_equal(cKDTree(cloud).query(queries, k=k)[0], NeighbourIndex(cloud).query(queries, k)[0])
        print(f"{label:40s} {1000 * t['tree']:10.1f} {1000 * t['kernel']:10.1f} {t['tree'] / t['kernel']:8.1f}x  {same}")


def cold(scan: str, model: str | None, repeats: int) -> None:
    escape = str(Path(sys.executable).parent / "escape")
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "out.ply")
        cmd = [escape, "-q", "complete", scan, "-o", out, "--overwrite"] + (["--model", model] if model else [])
        bare = [sys.executable, "-c", "import numpy, scipy.spatial, onnxruntime"]
        t = alternate({
            "bare imports (numpy, scipy.spatial, onnxruntime)": lambda: subprocess.run(bare, check=True),
            "escape complete one.pcd, cold process": lambda: subprocess.run(cmd, check=True, capture_output=True),
            "escape --help": lambda: subprocess.run([escape, "--help"], check=True, capture_output=True),
            "escape --version": lambda: subprocess.run([escape, "--version"], check=True, capture_output=True),
        }, repeats)
    base = t["bare imports (numpy, scipy.spatial, onnxruntime)"]
    print(f"\n{'process (measured alternately)':48s} {'ms (median)':>12s} {'x bare imports':>15s}")
    for name, seconds in t.items():
        print(f"{name:48s} {1000 * seconds:12.1f} {seconds / base:15.2f}")
    ratio = t["escape complete one.pcd, cold process"] / base
    print(f"target: cold escape complete <= 1.6 x the bare imports: x{ratio:.2f} -> {'met' if ratio <= 1.6 else 'NOT met'}")


def throughput(cloud: np.ndarray, net, scans: int, batch_size: int, rng: np.random.Generator) -> None:
    from escape_cli.core.rotations import random_rotation
    from escape_cli.pipeline import complete, complete_many

    clouds = [(cloud[rng.permutation(len(cloud))[: int(0.9 * len(cloud))]] @ random_rotation(rng).T) for _ in range(scans)]
    start = time.perf_counter()
    one_by_one = [complete(c, net) for c in clouds]
    t_loop = time.perf_counter() - start
    start = time.perf_counter()
    batched = complete_many(clouds, net, batch_size=batch_size)
    t_many = time.perf_counter() - start
    same = all(np.array_equal(a.points, b.points) for a, b in zip(one_by_one, batched))
    print(f"\nthroughput, {scans} scans: loop of complete() {scans / t_loop:.2f} scans/s, "
          f"complete_many(batch_size={batch_size}) {scans / t_many:.2f} scans/s: x{t_loop / t_many:.2f} "
          f"(results equal: {same})")


def anchor_set_times(cloud: np.ndarray, net, counts, repeats: int) -> None:
    from escape_cli.pipeline import complete

    runs = {count: (lambda count=count: complete(cloud, net, anchor_sets=count)) for count in sorted({1, *counts})}
    times = alternate(runs, repeats)
    print(f"\n{'warm complete(), anchor sets (alternately)':44s} {'ms (median)':>12s} {'x one set':>10s}")
    for count, seconds in times.items():
        print(f"{count:<44d} {1000 * seconds:12.1f} {seconds / times[1]:10.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    parser.add_argument("--input", default=str(REPO / "examples" / "chair.pcd"), help="partial cloud")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--scans", type=int, default=64, help="scans for the throughput measurement (0: skip)")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--anchor-sets", default="2,3,5", help="ensemble sizes to time against one set ('': none)")
    parser.add_argument("--fps-sizes", default="5000,20000,100000", help="denser copies of the scan for FPS ('': none)")
    args = parser.parse_args()
    logging.disable(logging.WARNING)  # "fewer points than asked" for scans the model cannot fill

    from escape_cli.inference import load_model
    from escape_cli.io import read_points

    rng = np.random.default_rng(0)
    net = load_model(args.model)
    cloud = read_points(args.input)
    print(f"input {args.input}: {len(cloud)} points -> {net.input_points} network rows; model {net.path.name} "
          f"({net.output_points} outputs); python {sys.version.split()[0]}, numpy {np.__version__}")
    stages(cloud, net, args.repeats)
    fps(cloud, rng, [None] + [int(s) for s in args.fps_sizes.split(",") if s])
    neighbours(cloud, rng, args.repeats)
    cold(args.input, args.model, max(3, args.repeats // 2))
    if args.scans:
        throughput(cloud, net, args.scans, args.batch_size, rng)
    if args.anchor_sets:
        anchor_set_times(cloud, net, [int(c) for c in args.anchor_sets.split(",")], args.repeats)


if __name__ == "__main__":
    main()
