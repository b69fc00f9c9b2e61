"""Training checkpoints on disk: atomic saving, and loading a network from a checkpoint or an exported model."""

from __future__ import annotations

from pathlib import Path

import torch

from escape_cli.errors import EscapeError
from escape_cli.nn.config import ModelConfig
from escape_cli.nn.model import EscapeNet


def save_checkpoint(state: dict, path: Path) -> None:
    """torch.save to a hidden temporary beside PATH, then rename: a reader never sees half a file."""
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def load_checkpoint_model(path: Path) -> tuple[EscapeNet, dict]:
    """Rebuild the network of a checkpoint in eval mode; returns (model, checkpoint dict).

    An exported `.onnx` (with its metadata beside it) works too: its weights are recovered
    from the graph, so a shipped model can be fine-tuned with `escape train --init`.
    """
    if Path(path).suffix.lower() == ".onnx":
        from escape_cli.nn.onnx_weights import checkpoint_from_onnx

        return checkpoint_from_onnx(Path(path))
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
        model = EscapeNet(ModelConfig.from_dict(state["config"]))
        model.load_state_dict(state["model"])
    except FileNotFoundError:
        raise EscapeError(f"checkpoint {path} does not exist") from None
    except Exception as err:  # torch raises many kinds for a bad file
        raise EscapeError(f"cannot load checkpoint {path}: {err}") from None
    model.eval()
    return model, state
