"""Benchmark: scans per second of one `escape complete` batch, local engine and Ray, on the same inputs.

Run on demand: `.venv/bin/python bench/bench_batch.py [--inputs 64] [--model M] [--no-ray]`.
Makes the inputs in a temporary folder (the 8 scans of examples/, each under
inputs/8 seeded random rotations), then runs one `escape complete IN -o OUT --json`
process per configuration: `--engine local` with 1 and 2 workers, `--engine ray` with 1
and 2 actors (a local Ray started by the command). Times are wall clock from process
start to exit, so start-up (imports, models, Ray) is included; "first" is the time to
the first JSON line. Every configuration's outputs are compared byte for byte with
those of the first.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
ESCAPE = Path(sys.executable).with_name("escape")


def make_inputs(folder: Path, count: int) -> None:
    """`count` partial scans: the example scans, each rotated by seeded random rotations."""
    from escape_cli.core.rotations import random_rotation
    from escape_cli.io import read_points, write_points

    scans = sorted(p for p in (REPO / "examples").iterdir() if p.suffix in (".ply", ".pcd"))
    folder.mkdir(parents=True)
    for i in range(count):
        scan = scans[i % len(scans)]
        rotation = random_rotation(np.random.default_rng(i))
        write_points(folder / f"{scan.stem}-{i:03d}.ply", read_points(scan) @ rotation.T)


def run_batch(inputs: Path, out: Path, options: list[str]) -> tuple[float, float, int]:
    """(wall seconds, seconds to the first JSON line, files completed) of one command."""
    command = [str(ESCAPE), "complete", str(inputs), "-o", str(out), "--json", *options]
    start = time.perf_counter()
    first = None
    done = 0
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        for line in proc.stdout:
            first = first or time.perf_counter() - start
            done += "error" not in json.loads(line)
        stderr = proc.stderr.read()
    wall = time.perf_counter() - start
    if proc.returncode:
        sys.exit(f"{' '.join(command)} failed ({proc.returncode}): {stderr.strip()}")
    return wall, first or wall, done


def same_bytes(a: Path, b: Path) -> bool:
    names = sorted(p.name for p in a.iterdir())
    return names == sorted(p.name for p in b.iterdir()) and all((a / n).read_bytes() == (b / n).read_bytes() for n in names)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=64, help="number of input scans (default 64)")
    parser.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    parser.add_argument("--no-ray", action="store_true", help="only the local engine")
    args = parser.parse_args()
    configs = [("local", 1), ("local", 2)]
    if not args.no_ray and importlib.util.find_spec("ray") is not None:
        configs += [("ray", 1), ("ray", 2)]
    with tempfile.TemporaryDirectory() as tmp:
        inputs = Path(tmp) / "in"
        make_inputs(inputs, args.inputs)
        extra = ["--model", args.model] if args.model else []
        print(f"{args.inputs} inputs, {', '.join(p.name for p in sorted((REPO / 'examples').glob('*.p*')))} rotated")
        print("| engine | workers/actors | wall s | first result s | scans/s | same bytes |")
        print("|---|---|---|---|---|---|")
        reference = None
        for engine, workers in configs:
            out = Path(tmp) / f"out-{engine}-{workers}"
            wall, first, done = run_batch(inputs, out, ["--engine", engine, "--workers", str(workers), *extra])
            reference = reference or out
            same = "yes" if same_bytes(reference, out) else "NO"
            print(f"| {engine} | {workers} | {wall:.1f} | {first:.1f} | {done / wall:.2f} | {same} |", flush=True)


if __name__ == "__main__":
    main()
