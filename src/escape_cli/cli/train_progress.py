"""How `escape train` shows its progress: a bar on a terminal, plain lines in a log file.

A long run is started with ``nohup escape train ... > run.log 2>&1 &``; a progress bar
written there is a wall of redraws or nothing at all, so when stderr is not a terminal
the run writes one line every `LINE_EVERY` steps and one per validation instead:

    04:58:21 step 1100/7000  loss x1000 297.41  lr 1.9e-05  0.73 s/step
    05:05:40 step 1500/7000  validation: score 0.5897 (best)  synth-v1 15.46 / 30.86  modelnet40 16.20 / 23.88
"""

from __future__ import annotations

import contextlib
import sys

LINE_EVERY = 100  # steps between progress lines in a log


def format_validation(metrics: dict, best: float) -> str:
    """One validation's numbers: the score, and each set's xyz CD-L1 x1000 / its input copy's."""
    score = metrics["val_xyz_cd_l1_x1000"]
    mark = " (best)" if score <= best else ""
    sets = [key.split("@", 1)[1] for key in metrics if key.startswith("val_xyz_cd_l1_x1000@")]
    if not sets:  # one validation set: the score is its CD-L1
        return f"xyz CD-L1 x1000 {score:.2f}{mark} / input {metrics['val_input_cd_l1_x1000']:.2f}"
    parts = [f"{name} {metrics[f'val_xyz_cd_l1_x1000@{name}']:.2f} / {metrics[f'val_input_cd_l1_x1000@{name}']:.2f}"
             for name in sets]
    return f"score {score:.4f}{mark}  " + "  ".join(parts)


class ProgressLines:
    """The `Trainer.run` callback that writes plain progress lines to `stream` (see the module)."""

    def __init__(self, trainer, stream, every: int = LINE_EVERY):
        self.trainer = trainer
        self.stream = stream
        self.every = every
        self.metrics = trainer.last_metrics  # a new dict after each validation
        self.losses: list[float] = []
        self.seconds = 0.0  # of the steps since the last line, validations left out

    def __call__(self, step: int, total: int, loss: float, metrics: dict) -> None:
        self.losses.append(loss)
        self.seconds += self.trainer.last_step_seconds
        if step % self.every == 0 or step == total:
            self._write(
                f"step {step}/{total}  loss x1000 {1000 * sum(self.losses) / len(self.losses):.2f}  "
                f"lr {self.trainer.lr_at(step - 1):.1e}  {self.seconds / len(self.losses):.2f} s/step"
            )
            self.losses, self.seconds = [], 0.0
        if metrics is not self.metrics and metrics:
            self.metrics = metrics
            self._write(f"step {step}/{total}  validation: {format_validation(metrics, self.trainer.best)}")

    def _write(self, line: str) -> None:
        from escape_cli.nn.samples import log_line

        log_line(line, self.stream)


@contextlib.contextmanager
def train_progress(trainer, quiet: bool):
    """The callback for `trainer.run`: a bar on a terminal, `ProgressLines` otherwise, nothing when `quiet`."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    console = Console(stderr=True)
    if quiet:
        yield None
        return
    if not console.is_terminal:
        yield ProgressLines(trainer, sys.stderr, LINE_EVERY)
        return
    several = len(trainer.val_sets) > 1
    score_name, digits = ("xyz/input", 3) if several else ("CD-L1 x1000", 2)
    columns = [
        TextColumn("[bold]train"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn(),
    ]
    with Progress(*columns, transient=False, console=console) as progress:
        task = progress.add_task("train", total=None, info="")

        def report(step: int, total: int, loss: float, metrics: dict) -> None:
            val = metrics.get("val_xyz_cd_l1_x1000")
            info = f"loss x1000 {1000 * loss:.2f}" + (f"  val {score_name} {val:.{digits}f}" if val is not None else "")
            progress.update(task, completed=step, total=total, info=info)

        yield report
