"""Helpers shared by several test modules (not fixtures)."""

from __future__ import annotations

import numpy as np


def with_moving_refiners(net):
    """`net` with its refiners' offset layers random (std 0.05) instead of zero, so they move points."""
    import torch

    for stage in net.refine:
        torch.nn.init.normal_(stage.offset.weight, std=0.05)
    return net


def write_tiny_checkpoint(path, seed: int = 0, partial_frame: bool = True):
    """A checkpoint in the layout `escape train` writes, for an untrained tiny network.

    `partial_frame`: the model works in each scan's own frame (today's models); False
    makes one of the older kind, trained in absolute units (radius 0.25 for --normalize auto).
    """
    import torch

    from escape_cli.nn.config import get_preset
    from escape_cli.nn.model import EscapeNet

    torch.manual_seed(seed)
    config = get_preset("tiny")
    net = EscapeNet(config).eval()
    torch.save(
        {
            "model": net.state_dict(), "config": config.to_dict(), "step": 0, "elapsed": 0.0,
            "options": {"config": "tiny", "seed": seed, "include_observed": True},
            "anchors": {"k": 8, "method": "ball", "radius": 0.075, "knn": 16},
            "parameters": sum(p.numel() for p in net.parameters()),
            "input_radius": None if partial_frame else 0.25,
            "frame": {"kind": "partial", "rows": 256, "radius": 0.28} if partial_frame else None,
        },
        path,
    )
    return net


def partial_cloud(rng: np.random.Generator, n: int = 600) -> np.ndarray:
    """(n, 3) points on one side of a random ellipsoid: a stand-in for a partial scan."""
    pts = rng.normal(size=(n * 3, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    pts *= rng.uniform(0.2, 0.5, size=3)
    return pts[pts[:, 0] > 0][:n]


def ellipsoid_surface(rng: np.random.Generator, n: int, radii) -> np.ndarray:
    """(n, 3) points on an ellipsoid surface."""
    pts = rng.normal(size=(n, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    return pts * np.asarray(radii)


def write_tiny_pcn_tree(root, seed: int = 0, objects: int = 2, views: int = 2, complete_points: int = 2048) -> dict:
    """A small PCN-layout tree of ellipsoids (two categories), written with the project's writer.

    Partials are the half of the surface facing a random direction. Returns
    {split: [(synset, model_id), ...]}.
    """
    from escape_cli.data.pcn import write_model, write_split_file

    rng = np.random.default_rng(seed)
    ids: dict[str, dict[str, list[str]]] = {}
    made: dict[str, list] = {}
    for split in ("train", "val", "test"):
        for synset in ("03001627", "04379243"):
            for j in range(objects):
                model_id = f"{split}{j:03d}"
                radii = rng.uniform(0.15, 0.45, size=3)
                complete = ellipsoid_surface(rng, complete_points, radii)
                partials = []
                for _ in range(views if split == "train" else 1):
                    direction = rng.normal(size=3)
                    dense = ellipsoid_surface(rng, 1200, radii)
                    partials.append(dense[dense @ direction > 0])
                write_model(root, split, synset, model_id, complete, partials)
                ids.setdefault(synset, {}).setdefault(split, []).append(model_id)
                made.setdefault(split, []).append((synset, model_id))
    write_split_file(root, ids)
    return made


def kernel_or_fallback(request, monkeypatch, module, fallback: str) -> str:
    """Body of a fixture with params ["compiled", fallback]: the compiled kernels, or `module` without them.

    Fails when the kernels were not built: the tests insist on them (setup.py needs a C compiler).
    """
    assert module._kernels is not None, "escape_cli.core._kernels was not built (setup.py needs a C compiler)"
    if request.param == fallback:
        monkeypatch.setattr(module, "_kernels", None)
    return request.param


def worker_job(job):
    """A job for `escape_cli.data.workers.run_in_workers` tests: ``(folder, n, action)``.

    Writes a temporary file in `folder` named as a stopped writer leaves one
    (`io.files.temporary_name`, this process's id), then: "ok" removes it and returns
    n * n, "die" exits the process at once, "raise" removes it and raises ValueError,
    "sleep" prints a line and sleeps.
    """
    import os
    import time
    from pathlib import Path

    from escape_cli.io.files import temporary_name

    folder, n, action = job
    temporary = Path(folder) / temporary_name(f"{n}.pcd", os.getpid(), 0)
    temporary.write_bytes(b"half")
    if action == "die":
        os._exit(3)
    if action == "raise":
        temporary.unlink()  # as a writer does on an error
        raise ValueError(f"job {n} failed")
    if action == "sleep":
        os.write(2, f"job {n} started\n".encode())  # one write: the workers' lines never interleave
        time.sleep(120)
    temporary.unlink()
    return n * n
