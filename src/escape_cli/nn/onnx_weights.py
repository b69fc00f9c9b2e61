"""Recover the torch weights of an exported model, so a shipped `.onnx` can be fine-tuned.

`torch.onnx.export` keeps a parameter's name where the graph uses it as it is (biases,
layer norms, Gemm weights), or an Identity of an equal one. A `Linear` applied to a 3-D tensor becomes MatMul + Add: its
weight is stored transposed under a generated name, and the Add reads the named bias.
The rebuild seeds are folded with their reshape into one (1, 1, F, H) constant. Those
three rules recover every parameter; the result is then checked against onnxruntime.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from escape_cli.errors import ModelError
from escape_cli.inference import quiet_onnxruntime
from escape_cli.nn.config import ModelConfig
from escape_cli.nn.model import EscapeNet
from escape_cli.nn.parity import PARITY_TOLERANCE, sample_input

PREFIX = "net."  # the export wraps the network as `net`


def state_dict_from_onnx(onnx_path: Path, config: ModelConfig) -> dict[str, torch.Tensor]:
    """The `EscapeNet(config)` state dict stored in an exported ONNX graph.

    Raises ModelError when the graph does not hold exactly the network's parameters.
    """
    import onnx
    from onnx import numpy_helper

    try:
        graph = onnx.load(str(onnx_path)).graph
    except Exception as err:  # onnx raises protobuf errors of several kinds
        raise ModelError(f"cannot read {onnx_path} as ONNX: {str(err).splitlines()[0]}") from None
    stored = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    for node in graph.node:  # the exporter shares equal tensors (e.g. fresh biases) through Identity
        if node.op_type == "Identity" and node.input[0] in stored:
            stored[node.output[0]] = stored[node.input[0]]
    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)

    weights = {name[len(PREFIX):]: array for name, array in stored.items() if name.startswith(PREFIX)}
    for node in graph.node:
        if node.op_type != "MatMul" or node.input[1] not in stored or node.input[1].startswith(PREFIX):
            continue
        bias = _bias_added_to(node.output[0], consumers, stored)
        if bias is None:
            raise ModelError(f"{onnx_path}: cannot tell which layer the matrix {node.input[1]} belongs to")
        weights[bias[len(PREFIX):].removesuffix("bias") + "weight"] = stored[node.input[1]].T  # (out, in)
    seed_shape = (1, 1, config.fold, config.rebuild_hidden)
    seeds = [name for name, array in stored.items() if not name.startswith(PREFIX) and array.shape == seed_shape]
    if len(seeds) == 1:
        weights["rebuild.seeds"] = stored[seeds[0]].reshape(config.fold, config.rebuild_hidden)

    expected = EscapeNet(config).state_dict()
    missing = sorted(set(expected) - set(weights))
    unknown = sorted(set(weights) - set(expected))
    if missing or unknown:
        detail = f"missing {', '.join(missing[:3])}" if missing else f"unexpected {', '.join(unknown[:3])}"
        raise ModelError(f"{onnx_path} does not hold a network of its metadata's configuration ({detail})")
    state = {}
    for name, array in weights.items():
        if tuple(array.shape) != tuple(expected[name].shape):
            raise ModelError(f"{onnx_path}: {name} has shape {array.shape}, expected {tuple(expected[name].shape)}")
        state[name] = torch.from_numpy(np.array(array, dtype=np.float32))
    return state


def _bias_added_to(tensor: str, consumers: dict, stored: dict) -> str | None:
    """The named bias initializer of the single Add that reads `tensor`, if there is one."""
    adds = [node for node in consumers.get(tensor, []) if node.op_type == "Add"]
    if len(adds) != 1:
        return None
    names = [name for name in adds[0].input if name != tensor and name in stored]
    if len(names) != 1 or not names[0].startswith(PREFIX) or not names[0].endswith("bias"):
        return None
    return names[0]


def checkpoint_from_onnx(onnx_path: Path) -> tuple[EscapeNet, dict]:
    """An exported model as (network in eval mode, checkpoint-like dict) for `--init`.

    The dict carries what a training checkpoint does for lineage and export: config,
    steps, training seconds, options, the runs it came from. The recovered network must
    reproduce onnxruntime's output on a sample input to 1e-4.
    """
    import onnxruntime as ort

    from escape_cli.inference import read_metadata

    onnx_path = Path(onnx_path)
    meta = read_metadata(onnx_path)
    if "config" not in meta:
        raise ModelError(f"{onnx_path.with_suffix('.json')} lacks the network configuration")
    config = ModelConfig.from_dict(meta["config"])
    model = EscapeNet(config)
    model.load_state_dict(state_dict_from_onnx(onnx_path, config))
    model.eval()

    example = sample_input(config, batch=1)
    with torch.no_grad():
        want = model(torch.from_numpy(example))[0].numpy()
    try:
        quiet_onnxruntime(ort)
        session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
        got = session.run([meta.get("output_name", "distances")], {meta.get("input_name", "partial_distances"): example})[0]
    except Exception as err:
        raise ModelError(f"cannot run {onnx_path}: {str(err).splitlines()[0]}") from None
    diff = float(np.abs(got - want).max())
    if not diff <= PARITY_TOLERANCE:
        raise ModelError(f"weights recovered from {onnx_path} differ from onnxruntime by {diff:.2e}")

    training = meta.get("training", {})
    state = {
        "model": model.state_dict(),
        "config": config.to_dict(),
        "step": int(training.get("steps") or 0),
        "elapsed": float(training.get("train_seconds") or 0.0),
        "options": {
            "config": meta.get("config_name"), "lr": training.get("lr"), "xyz_weight": training.get("xyz_weight", 0.0),
            "recall_weight": training.get("recall_weight", 1.0), "data": training.get("data"), "seed": training.get("seed"),
        },
        "anchors": meta.get("anchors"),
        "input_radius": meta.get("normalization", {}).get("target_radius"),
        "frame": meta.get("frame") if (meta.get("frame") or {}).get("kind") == "partial" else None,
        "lineage": list(training.get("initialised_from", [])),
    }
    return model, state
