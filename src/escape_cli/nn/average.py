"""Weight averaging of checkpoints from one run (stochastic weight averaging, applied after training).

Late checkpoints of a small-batch run scatter around a minimum; their mean usually sits
closer to it than any one of them. Averaging is done in float64 and rounded back.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from escape_cli.errors import EscapeError, OutputExistsError
from escape_cli.nn.checkpoint import load_checkpoint_model, save_checkpoint

log = logging.getLogger("escape")


def average_state_dicts(states: list[dict]) -> dict:
    """The element-wise mean of floating-point tensors; other entries (counters) come from the first."""
    if not states:
        raise EscapeError("nothing to average")
    keys = list(states[0])
    for state in states[1:]:
        if list(state) != keys:
            raise EscapeError("the checkpoints hold different networks")
    averaged = {}
    for key in keys:
        first = states[0][key]
        if first.is_floating_point():
            total = sum(state[key].double() for state in states)
            averaged[key] = (total / len(states)).to(first.dtype)
        else:
            averaged[key] = first.clone()
    return averaged


def average_checkpoints(paths: list[Path], output: Path, overwrite: bool = False, validate: bool = True) -> dict:
    """Write OUTPUT, a checkpoint whose weights are the mean of PATHS'; returns its metadata.

    The metadata of the latest checkpoint (by step) is kept, its optimizer state dropped.
    With `validate`, the averaged network is scored on the run's validation split (when the
    dataset is still where the run read it), so `export-onnx` records numbers that belong
    to it; without, the copied numbers are removed.
    """
    output = Path(output)
    if output.exists() and not overwrite:
        raise OutputExistsError(f"{output} exists (use --overwrite to replace it)")
    if len(paths) < 2:
        raise EscapeError(f"give at least two checkpoints to average, got {len(paths)}")
    loaded = [load_checkpoint_model(Path(p)) for p in paths]
    config = loaded[0][0].config
    for path, (model, _) in zip(paths, loaded):
        if model.config != config:
            raise EscapeError(f"{path} holds another network configuration than {paths[0]}")
    order = sorted(range(len(paths)), key=lambda i: loaded[i][1].get("step", 0))
    model, state = loaded[order[-1]]
    model.load_state_dict(average_state_dicts([loaded[i][0].state_dict() for i in order]))
    state = {key: value for key, value in state.items() if key not in ("optimizer", "metrics")}
    state["model"] = model.state_dict()
    state["averaged_from"] = [{"checkpoint": str(paths[i]), "step": loaded[i][1].get("step")} for i in order]
    if validate:
        metrics = _validate(model, state)
        if metrics:
            state["metrics"] = {"step": state.get("step"), **metrics}
    output.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(state, output)
    return state


def _validate(model, state: dict) -> dict | None:
    """The run's own validation of `model` (every set of its --val-data), or None when a dataset is gone."""
    from escape_cli.nn.train import TrainOptions, validate_sets, validation_sets

    raw = state.get("options", {})
    roots = raw.get("val_data") or [raw.get("data")]
    missing = [root for root in roots if not root or not (Path(root) / "val").is_dir()]
    if missing:
        log.warning("not validated: the run's dataset %s is not there", missing[0])
        return None
    options = TrainOptions.from_dict(raw)
    sets = validation_sets(options, model.config.input_points)
    return validate_sets(model, sets, options, torch.device("cpu"))
