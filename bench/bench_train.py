"""Benchmark: seconds per training step in float32 and with `--precision bf16`, and what each trains to.

Run on demand: `.venv/bin/python bench/bench_train.py [--data DIR] [--steps 150]`.
Without `--data` it makes a small dataset with `escape dataset synth` in a temporary
folder. Two `Trainer`s with the same options, seed and initial weights (the `small`
preset, batch 8, 2 threads by default), one per precision, take their steps in turn (a
busy machine slows both alike; which goes first alternates), sharing one `--cache` of
the prepared data. Printed:

- seconds per step of each (median over the steps after the first 3), and the stages of
  a step (sample, forward, DMCD loss, xyz term, backward, optimizer), medians;
- after `--steps` steps of each (a warm-up + cosine schedule of that length, no
  validation before the end): the run's validation metrics, measured in float32 as
  every validation is;
- last, `bf16/fp32 R`: R the ratio of the median step times (target: <= 0.70 with a
  validation no worse than float32's).

"No worse" is judged against the run-to-run noise of training itself: a third run,
float32 with the next seed (other data order, augmentation and dropout; the same initial
weights), sets the band. bf16 is no worse when its validation loss (`val_dmcd_x1000`,
the loss training minimises) is at most float32's plus the gap between the two float32
runs; the xyz CD-L1 (24 reconstructed samples, noisier) is printed beside its own band
(`--no-noise-run` drops the third run and asks for bf16 <= float32 outright).

`--reference` adds a third run, float32 with the network's reference forms in training
(the EdgeConv edge tensor, the nn.Transformer layers, amax: the training network as it
was before the training-only forms), to show what those bought and that they train the
same to float rounding.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import sys
import tempfile
import types
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

STAGES = ("sample", "forward", "loss", "xyz", "backward", "optimizer")
METRICS = ("val_dmcd_x1000", "val_xyz_cd_l1_x1000", "val_input_cd_l1_x1000")


def make_dataset(folder: Path, train: int, val: int, views: int) -> None:
    """A small synthetic PCN-layout dataset (all 8 categories) in FOLDER."""
    subprocess.run(
        [sys.executable, "-m", "escape_cli", "-q", "dataset", "synth", "--out", str(folder), "--train", str(train),
         "--val", str(val), "--test", "0", "--views", str(views), "--seed", "0", "--workers", "2"],
        check=True,
    )


def reference_forms(trainer) -> None:
    """Train with the network's reference forms: its evaluation mode (no dropout, so the same network)."""
    model = trainer.model
    model.train = types.MethodType(lambda self, mode=True: torch.nn.Module.train(self, False), model)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=None, help="PCN-layout dataset (default: made by `escape dataset synth`)")
    parser.add_argument("--train-objects", type=int, default=40, help="synthetic training objects per category")
    parser.add_argument("--val-objects", type=int, default=10, help="synthetic validation objects per category")
    parser.add_argument("--views", type=int, default=4, help="synthetic views per training object")
    parser.add_argument("--steps", type=int, default=150, help="training steps of each precision")
    parser.add_argument("--config", default="small")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--warmup", type=int, default=30, help="warm-up steps of the schedule")
    parser.add_argument("--xyz-weight", type=float, default=0.0, help="as `escape train --xyz-weight`")
    parser.add_argument("--init", default=None, help="start both from this checkpoint or .onnx (default: the seed's weights)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reference", action="store_true", help="also train float32 with the network's reference forms")
    parser.add_argument("--no-noise-run", action="store_true", help="no float32 run with the next seed (the noise band)")
    args = parser.parse_args()

    from escape_cli.nn.train import Trainer, TrainOptions

    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="bench-train-") as tmp:
        tmp = Path(tmp)
        data = Path(args.data) if args.data else tmp / "data"
        if not args.data:
            make_dataset(data, args.train_objects, args.val_objects, args.views)
        base = TrainOptions(
            data=str(data), out=str(tmp / "fp32"), config=args.config, batch=args.batch, lr=args.lr, seed=args.seed,
            warmup_steps=args.warmup, epochs=10_000, max_steps=args.steps, xyz_weight=args.xyz_weight,
            threads=args.threads, workers=2, checkpoint_every=10**9, cache=str(tmp / "cache"), init=args.init,
        )
        runs = {"fp32": Trainer(base), "bf16": Trainer(replace(base, out=str(tmp / "bf16"), precision="bf16"))}
        if not args.no_noise_run:  # the same start, the next seed's data order and randomness
            noise = Trainer(replace(base, out=str(tmp / "noise"), seed=args.seed + 1))
            noise.model.load_state_dict(runs["fp32"].model.state_dict())
            runs[f"fp32, seed {args.seed + 1}"] = noise
        if args.reference:
            runs["fp32, reference forms"] = Trainer(replace(base, out=str(tmp / "reference")))
            reference_forms(runs["fp32, reference forms"])
        first = runs["fp32"]
        for name, trainer in runs.items():  # the same start
            for key, value in first.model.state_dict().items():
                assert torch.equal(value, trainer.model.state_dict()[key]), (name, key)
            trainer.stage_times = {}
        print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, {args.threads} threads, "
              f"bf16 native: {bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())}")
        print(f"data {data}: {len(first.train_data)} training samples, {len(first.val_data)} validation samples; "
              f"config {args.config}, batch {args.batch}, xyz weight {args.xyz_weight}, "
              f"init {args.init or f'seed {args.seed}'}; {args.steps} steps of each, taken in turn")

        seconds = {name: [] for name in runs}
        losses = {name: [] for name in runs}
        stages = {name: {stage: [] for stage in STAGES} for name in runs}
        names = list(runs)
        for step in range(args.steps):
            turn = names[step % len(names):] + names[: step % len(names)]
            for name in turn:
                trainer = runs[name]
                trainer.stage_times.clear()
                trainer.run(lambda step, total, loss, metrics, name=name: losses[name].append(loss), steps=1)
                seconds[name].append(trainer.last_step_seconds)
                for stage in STAGES:
                    stages[name][stage].append(trainer.stage_times.get(stage, 0.0))

        warm = slice(3, None)
        median = {name: statistics.median(s[warm]) for name, s in seconds.items()}
        print(f"\n{'seconds per step (median)':24s} {'step':>7s} " + " ".join(f"{s:>9s}" for s in STAGES) + "  x fp32")
        for name in runs:
            parts = " ".join(f"{statistics.median(stages[name][s][warm]):9.3f}" for s in STAGES)
            print(f"{name:24s} {median[name]:7.3f} {parts}  {median[name] / median['fp32']:6.3f}")

        print(f"\nafter {args.steps} steps (validation in float32; x1000)")
        print(f"{'':24s} " + " ".join(f"{m:>22s}" for m in METRICS) + f" {'train loss, last 20':>20s}")
        for name, trainer in runs.items():
            metrics = trainer.last_metrics
            tail = 1000 * float(np.mean(losses[name][-20:]))
            print(f"{name:24s} " + " ".join(f"{metrics[m]:22.3f}" for m in METRICS) + f" {tail:20.3f}")
        fp32, bf16 = runs["fp32"].last_metrics, runs["bf16"].last_metrics
        ratio = median["bf16"] / median["fp32"]
        other = runs.get(f"fp32, seed {args.seed + 1}")
        band = {m: abs(other.last_metrics[m] - fp32[m]) if other else 0.0 for m in METRICS[:2]}
        loss = METRICS[0]  # the validation loss: the distance-space loss training minimises
        no_worse = bf16[loss] <= fp32[loss] + band[loss]
        gaps = ", ".join(f"{m} bf16 - fp32 {bf16[m] - fp32[m]:+.3f} (seed noise {band[m]:.3f})" for m in METRICS[:2])
        print(f"\n{gaps}")
        print(f"target: bf16/fp32 <= 0.70 with no worse validation loss: x{ratio:.3f}, validation loss "
              f"{'no worse' if no_worse else 'WORSE'} -> {'met' if ratio <= 0.70 and no_worse else 'NOT met'}")
        print(f"bf16/fp32 {ratio:.3f}")


if __name__ == "__main__":
    main()
