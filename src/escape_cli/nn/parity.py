"""What export and weight recovery check a network with: a realistic sample input and the torch/onnxruntime tolerance."""

from __future__ import annotations

import numpy as np

PARITY_TOLERANCE = 1e-4
"""Largest |onnxruntime - torch| accepted for an exported or recovered network."""


def sample_input(config, batch: int = 2, seed: int = 0) -> np.ndarray:
    """A realistic (B, N, K) float32 input: distances of a half-ellipsoid patch to its anchors."""
    from escape_cli.core.anchors import select_anchors
    from escape_cli.core.encoding import distance_matrix
    from escape_cli.core.sampling import prepare_input

    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(batch):
        pts = rng.normal(size=(3000, 3))
        pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        pts *= rng.uniform(0.15, 0.45, size=3)
        pts = pts[pts[:, 0] > -0.05]
        prepared, unique = prepare_input(pts, config.input_points)
        anchors = select_anchors(prepared[:unique], config.anchors)
        rows.append(distance_matrix(prepared, anchors.points))
    return np.stack(rows).astype(np.float32)


