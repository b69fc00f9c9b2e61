"""Export a training checkpoint to ONNX with its metadata, and check onnxruntime against torch."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from escape_cli.core.settings import AnchorSettings
from escape_cli.errors import ModelError, OutputExistsError
from escape_cli.inference import quiet_onnxruntime
from escape_cli.nn.checkpoint import load_checkpoint_model
from escape_cli.nn.parity import PARITY_TOLERANCE, sample_input

MODEL_FORMAT = "escape-model/1"


class _Exportable(torch.nn.Module):
    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, partial_distances: torch.Tensor):
        return self.net(partial_distances)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def export_onnx(checkpoint: Path, output: Path, overwrite: bool = False, opset: int = 17) -> dict:
    """Write OUTPUT (.onnx) and OUTPUT.json; returns the metadata.

    Fails (and writes nothing) when onnxruntime and torch differ by more than 1e-4.
    """
    import onnxruntime as ort

    output = Path(output)
    meta_path = output.with_suffix(".json")
    for path in (output, meta_path):
        if path.exists() and not overwrite:
            raise OutputExistsError(f"{path} exists (use --overwrite to replace it)")
    net, state = load_checkpoint_model(Path(checkpoint))
    config = net.config
    example = torch.from_numpy(sample_input(config))
    output.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(suffix=".onnx", dir=output.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        with warnings.catch_warnings():  # tracer notes about Python-level shape checks
            warnings.simplefilter("ignore")
            torch.onnx.export(
                _Exportable(net), (example,), str(tmp), input_names=["partial_distances"],
                output_names=["distances", "coarse"], opset_version=opset, dynamo=False,
                dynamic_axes={"partial_distances": {0: "batch"}, "distances": {0: "batch"}, "coarse": {0: "batch"}},
            )
        with torch.no_grad():
            want = net(example)[0].numpy()
        quiet_onnxruntime(ort)
        session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        single = example[:1].numpy()
        got = session.run(["distances"], {"partial_distances": example.numpy()})[0]
        got_single = session.run(["distances"], {"partial_distances": single})[0]
        diff = float(max(np.abs(got - want).max(), np.abs(got_single - want[:1]).max()))
        if not diff <= PARITY_TOLERANCE:
            raise ModelError(f"onnxruntime differs from torch by {diff:.2e} (> {PARITY_TOLERANCE:g}); not exported")
        meta = _metadata(state, output.name, file_sha256(tmp), diff)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it private
        tmp.replace(output)
    finally:
        tmp.unlink(missing_ok=True)
    tmp_meta = meta_path.with_suffix(".json.tmp")
    tmp_meta.write_text(json.dumps(meta, indent=2) + "\n")
    tmp_meta.replace(meta_path)
    return meta


def _dataset_summary(data_root: str | None) -> dict | None:
    """Generator version, seed and counts of a dataset made by `escape dataset synth`, if it is one."""
    if not data_root:
        return None
    path = Path(data_root) / "escape_synth.json"
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    keys = ("generator_version", "seed", "objects_per_category", "views_per_object", "totals")
    return {key: info[key] for key in keys if key in info}


def _metadata(state: dict, onnx_name: str, sha256: str, parity: float) -> dict:
    config = state["config"]
    options = state.get("options", {})
    queries = config["predicted_queries"] + config["input_queries"]
    lineage = state.get("lineage", [])  # earlier runs this one was initialised from
    return {
        "format": MODEL_FORMAT,
        "onnx": onnx_name,
        "sha256": sha256,
        "k": config["anchors"],
        "input_points": config["input_points"],
        "output_points": queries * config["fold"],
        "input_name": "partial_distances",
        "output_name": "distances",
        "anchors": state.get("anchors") or AnchorSettings(k=config["anchors"]).to_dict(),
        "merge_observed": bool(options.get("include_observed", True)),
        "frame": state.get("frame") or {"kind": "absolute"},
        "normalization": {"method": "centroid + rms radius", "target_radius": state.get("input_radius")},
        "config_name": options.get("config"),
        "config": config,
        "parameters": state.get("parameters"),
        "training": {
            "data": options.get("data"),
            "dataset": _dataset_summary(options.get("data")),
            "extra_data": [{"data": root, "dataset": _dataset_summary(root)} for root in options.get("extra_data") or ()],
            "views_per_object": options.get("views_per_object"),
            "seed": options.get("seed"),
            "train_samples": state.get("train_samples"),
            "train_objects": state.get("train_objects"),
            "steps": state.get("step"),
            "epochs": round(state.get("step", 0) / max(1, state.get("steps_per_epoch", 1)), 3),
            "batch": options.get("batch"),
            "train_seconds": round(state.get("elapsed", 0.0), 1),
            "lr": options.get("lr"),
            "xyz_weight": options.get("xyz_weight", 0.0),
            "recall_weight": options.get("recall_weight", 1.0),
            "initialised_from": lineage,
            "averaged_from": state.get("averaged_from", []),
            "total_steps": state.get("step", 0) + sum(run["steps"] for run in lineage),
            "total_train_seconds": round(state.get("elapsed", 0.0) + sum(run["train_seconds"] for run in lineage), 1),
        },
        "validation": state.get("metrics", {}),
        "onnx_parity_max_abs": parity,
    }
