"""Procedural cabinets (ShapeNet 02933112): door cupboards, chests of drawers, open shelves, hutches.

Units are metres before normalisation; y up, the doors face +x.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import beam, box, frustum
from escape_cli.data.shapes.base import draw_subtype

SUBTYPES = ("doors", "drawers", "shelves", "hutch")


def _base(rng: np.random.Generator, depth: float, width: float) -> tuple[float, list[np.ndarray]]:
    """What the carcass stands on (plinth, legs or nothing); returns its height and parts."""
    style = rng.choice(3)
    if style == 0:
        h = rng.uniform(0.05, 0.12)
        return h, [box([-0.02, h / 2 + 0.005, 0], (depth - 0.06, h + 0.01, width - 0.04))]
    if style == 1:
        h = rng.uniform(0.08, 0.25)
        parts = []
        for sx in (-1, 1):
            for sz in (-1, 1):
                p = np.array([sx * (depth / 2 - 0.04), 0, sz * (width / 2 - 0.04)])
                if rng.random() < 0.5:
                    parts.append(beam(p, p + [0, h + 0.01, 0], 0.035))
                else:
                    parts.append(frustum(p, p + [0, h + 0.01, 0], 0.012, 0.02, 10))
        return h, parts
    return 0.0, []


def _handle(rng_round: bool, centre: np.ndarray, vertical: bool, length: float) -> np.ndarray:
    if rng_round:
        return frustum(centre - [0.02, 0, 0], centre + [0.015, 0, 0], 0.012, 0.012, 10)
    size = (0.03, length, 0.015) if vertical else (0.03, 0.015, length)
    return box(centre, size)


def _carcass(rng: np.random.Generator, tall: bool, max_height: float = 2.0
             ) -> tuple[float, float, float, float, list[np.ndarray]]:
    """A closed box on its base; returns depth (x), width (z), height, base height and parts."""
    depth = rng.uniform(0.35, 0.6)
    width = rng.uniform(0.4, 1.3)
    height = min(rng.uniform(1.2, 2.0) if tall else rng.uniform(0.45, 1.1), max_height)
    base_h, parts = _base(rng, depth, width)
    parts.append(box([0, base_h + (height - base_h) / 2, 0], (depth, height - base_h, width)))
    if rng.random() < 0.5:  # overhanging top
        over = rng.uniform(0.01, 0.04)
        parts.append(box([over / 2, height + 0.015, 0], (depth + over, 0.03, width + 2 * over)))
    return depth, width, height, base_h, parts


def _doors(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    depth, width, height, base_h, parts = _carcass(rng, tall=rng.random() < 0.4)
    n_doors = 1 if width < 0.6 else int(rng.choice([2, 2, 3]))
    round_handles = rng.random() < 0.5
    door_w = width / n_doors
    front = depth / 2
    for k in range(n_doors):
        z = -width / 2 + door_w * (k + 0.5)
        parts.append(box([front + 0.005, (base_h + height) / 2, z], (0.02, height - base_h - 0.02, door_w - 0.008)))
        edge = -1 if k < n_doors / 2 else 1
        hz = z - edge * (door_w / 2 - 0.05)
        parts.append(_handle(round_handles, np.array([front + 0.03, base_h + (height - base_h) * 0.55, hz]), True, 0.12))
    return "doors", parts


def _drawers(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    depth, width, height, base_h, parts = _carcass(rng, tall=False)
    rows = int(rng.integers(2, 7))
    columns = 2 if width > 0.9 and rng.random() < 0.5 else 1
    round_handles = rng.random() < 0.5
    front = depth / 2
    row_h = (height - base_h - 0.02) / rows
    col_w = width / columns
    for r in range(rows):
        y = base_h + 0.01 + row_h * (r + 0.5)
        for c in range(columns):
            z = -width / 2 + col_w * (c + 0.5)
            parts.append(box([front + 0.005, y, z], (0.02, row_h - 0.008, col_w - 0.008)))
            parts.append(_handle(round_handles, np.array([front + 0.03, y, z]), False, min(0.15, col_w * 0.3)))
    return "drawers", parts


def _shelves(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    depth = rng.uniform(0.25, 0.45)
    width = rng.uniform(0.5, 1.2)
    height = rng.uniform(0.6, 2.0)
    board = rng.uniform(0.015, 0.04)
    parts = []
    for sz in (-1, 1):
        parts.append(box([0, height / 2, sz * (width / 2 - board / 2)], (depth, height, board)))
    inner = width - 2 * board + 0.01
    n_shelves = max(1, int(round(height / rng.uniform(0.25, 0.45))))
    for y in np.linspace(board / 2, height - board / 2, n_shelves + 1):
        parts.append(box([0, y, 0], (depth, board, inner)))
    if rng.random() < 0.7:  # back panel
        parts.append(box([-depth / 2 + 0.005, height / 2, 0], (0.01, height, inner)))
    return "shelves", parts


def _hutch(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    depth, width, lower_h, base_h, parts = _carcass(rng, tall=False, max_height=0.95)
    front = depth / 2
    n_doors = 2 if width > 0.6 else 1
    door_w = width / n_doors
    for k in range(n_doors):
        z = -width / 2 + door_w * (k + 0.5)
        parts.append(box([front + 0.005, (base_h + lower_h) / 2, z], (0.02, lower_h - base_h - 0.02, door_w - 0.008)))
    upper_d = depth * rng.uniform(0.5, 0.8)
    upper_h = rng.uniform(0.5, 1.0)
    board = 0.025
    x = -depth / 2 + upper_d / 2
    for sz in (-1, 1):
        parts.append(box([x, lower_h + upper_h / 2, sz * (width / 2 - board / 2)], (upper_d, upper_h + 0.01, board)))
    for y in np.linspace(lower_h + upper_h * 0.4, lower_h + upper_h - board / 2, 2):
        parts.append(box([x, y, 0], (upper_d, board, width - 0.04)))
    parts.append(box([-depth / 2 + 0.005, lower_h + upper_h / 2, 0], (0.01, upper_h, width - 0.04)))
    return "hutch", parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one cabinet: (subtype, vertices of each convex part); see `base.draw_subtype`."""
    return draw_subtype(rng, (_doors, _drawers, _shelves, _hutch), [0.35, 0.3, 0.2, 0.15])
