"""Generator 2: the shapes of generator 1 made closer to real objects, plus hollow sub-types.

Real ShapeNet objects have rounded edges (cushions, car bodies, table tops), thin open
walls (lamp shades, rowing boats) and curved moulded parts (shell chairs), which the
convex primitives of generator 1 lack. Generator 2 draws a generator-1 shape with the
object's own random stream (so the same structure and sizes) and then, with a second
stream of its own:

- rounds the edges of the small convex parts (`primitives.rounded`), with a radius that
  is a share of each part's smallest extent, drawn once per object;
- gives lamps open thin-walled shades (`lamp.generate(hollow=True)`);
- adds two hollow sub-types: rowing boats (an open hull with thwarts) and moulded shell
  chairs (one curved seat-and-back on legs or a pedestal), both built from
  `primitives.grid_shell`.

Units are metres before normalisation; y up, front towards +x.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import beam, box, frustum, grid_shell, rounded
from escape_cli.data.shapes.airplane import generate as airplane
from escape_cli.data.shapes.cabinet import generate as cabinet
from escape_cli.data.shapes.car import generate as car
from escape_cli.data.shapes.chair import generate as chair
from escape_cli.data.shapes.lamp import generate as lamp
from escape_cli.data.shapes.sofa import generate as sofa
from escape_cli.data.shapes.table import generate as table
from escape_cli.data.shapes.watercraft import generate as watercraft

# synset -> (probability that the object's parts are rounded, share of the smallest extent (low, high))
ROUNDING = {
    "02691156": (0.3, (0.1, 0.3)),  # airplane
    "02933112": (0.5, (0.05, 0.2)),  # cabinet
    "02958343": (0.85, (0.2, 0.45)),  # car
    "03001627": (0.5, (0.1, 0.35)),  # chair
    "03636649": (0.3, (0.1, 0.3)),  # lamp
    "04256520": (0.85, (0.2, 0.45)),  # sofa
    "04379243": (0.5, (0.1, 0.35)),  # table
    "04530566": (0.4, (0.1, 0.3)),  # watercraft
}
ROUNDED_MAX_VERTICES = 64  # parts with more vertices (ellipsoids, fine frusta) are smooth already
SHELL_WALL = 0.012  # metres: boat hulls and moulded seats

SUBTYPES_ADDED = {"04530566": ("rowboat",), "03001627": ("shell",)}
"""Sub-types that only generator 2 makes."""

_BASE = {
    "02691156": airplane,
    "02933112": cabinet,
    "02958343": car,
    "03001627": chair,
    "04256520": sofa,
    "04379243": table,
    "04530566": watercraft,
}


def generate(synset: str, rng: np.random.Generator, detail: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one generator-2 shape of a category: (subtype, vertices of each convex part).

    Parameters
    ----------
    synset : str
    rng : numpy.random.Generator
        The object's stream (sizes and structure).
    detail : numpy.random.Generator
        A second stream for what generator 2 adds.
    """
    if synset == "04530566" and detail.random() < 0.25:
        return _rowboat(rng)
    if synset == "03001627" and detail.random() < 0.2:
        return _shell_chair(rng)
    if synset == "03636649":
        hollow = detail.random() < 0.75
        subtype, parts = lamp(rng, hollow=hollow)
        subtype = f"{subtype}_open" if hollow and not subtype.endswith("_open") else subtype
    else:
        subtype, parts = _BASE[synset](rng)
    probability, (low, high) = ROUNDING[synset]
    if detail.random() < probability:
        share = detail.uniform(low, high)
        parts = [_round(part, share) for part in parts]
        subtype = f"{subtype}_rounded"
    return subtype, parts


def _round(vertices: np.ndarray, share: float) -> np.ndarray:
    if len(vertices) > ROUNDED_MAX_VERTICES:
        return vertices
    extent = np.ptp(vertices, axis=0)
    return rounded(vertices, share * float(extent.min()))


def _rowboat(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """An open rowing boat or canoe: a thin U-section hull, thwarts across it, a transom unless a canoe."""
    length = rng.uniform(2.5, 5.0)
    beam_width = length * rng.uniform(0.22, 0.35)
    depth = beam_width * rng.uniform(0.3, 0.45)
    canoe = rng.random() < 0.4  # pointed at both ends
    sheer = depth * rng.uniform(0.1, 0.35)  # the gunwale rises towards the ends

    def half_breadth(x: float) -> float:  # the bow is fine, the stern of a rowing boat fuller
        power = 1.6 if (canoe or x > 0) else 3.0
        return 0.5 * beam_width * max(1.0 - abs(2 * x) ** power, 0.04)

    xs = np.linspace(-0.5, 0.5, 14)[(0 if canoe else 1):]  # a rowing boat's stern stops at the transom
    theta = np.linspace(-np.pi / 2, np.pi / 2, 11)
    grid = []
    for x in xs:
        t = abs(2 * x)
        keel, top = depth * 0.1 * t**2, depth + sheer * t**2
        grid.append([[x * length, keel + (top - keel) * (1 - np.cos(a)), half_breadth(x) * np.sin(a)] for a in theta])
    parts = grid_shell(np.asarray(grid), SHELL_WALL)  # (U - 1) (V - 1) slabs
    n_thwarts = int(rng.integers(1, 4))
    for k in range(n_thwarts):
        x = -0.3 + 0.6 * (k + 0.5) / n_thwarts
        parts.append(box([x * length, depth * 0.7, 0.0], (0.2, 0.03, 2 * half_breadth(x) * 0.95)))
    if canoe:
        return "rowboat_canoe", parts
    parts.append(box([xs[0] * length - 0.01, depth * 0.55, 0.0], (0.03, depth * 0.9, 2 * half_breadth(xs[0]) * 0.9)))
    return "rowboat", parts


def _shell_chair(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """A moulded shell chair: one curved seat and back whose sides curl up, on four legs or a pedestal."""
    width, depth = rng.uniform(0.42, 0.55), rng.uniform(0.4, 0.5)
    seat_h = rng.uniform(0.4, 0.47)
    back_h = rng.uniform(0.3, 0.45)
    lean = rng.uniform(0.05, 0.2) * back_h
    curl = rng.uniform(0.04, 0.09)  # how far the sides rise towards the sitter
    corner = rng.uniform(0.05, 0.09)  # radius of the bend between seat and back
    # centre line in side view (front lip to top of the back) and the direction towards the sitter
    line, towards = [], []
    for x in np.linspace(depth / 2, -depth / 2 + corner, 5):
        line.append([x, seat_h, 0.0])
        towards.append([0.0, 1.0, 0.0])
    centre = np.array([-depth / 2 + corner, seat_h + corner, 0.0])
    for a in np.linspace(0.0, np.pi / 2, 4)[1:]:
        line.append(centre + corner * np.array([-np.sin(a), -np.cos(a), 0.0]))
        towards.append([np.sin(a), np.cos(a), 0.0])
    for t in np.linspace(0.0, 1.0, 5)[1:]:
        line.append([-depth / 2 - lean * t, seat_h + corner + (back_h - corner) * t, 0.0])
        towards.append([1.0, 0.0, 0.0])
    line, towards = np.asarray(line), np.asarray(towards)  # (U, 3) each
    across = np.linspace(-1.0, 1.0, 9)
    grid = (line[:, None, :] + 0.5 * width * across[None, :, None] * np.array([0.0, 0.0, 1.0])
            + curl * (across**2)[None, :, None] * towards[:, None, :])  # (U, V, 3)
    parts = grid_shell(grid, SHELL_WALL)
    if rng.random() < 0.6:  # four thin splayed legs
        splay = rng.uniform(0.03, 0.08)
        for sx in (-1, 1):
            for sz in (-1, 1):
                top = np.array([sx * depth * 0.3, seat_h - 0.01, sz * width * 0.3])
                bottom = np.array([sx * (depth * 0.3 + splay), 0.0, sz * (width * 0.3 + splay)])
                parts.append(frustum(bottom, top, 0.009, 0.012, 8) if rng.random() < 0.5 else beam(bottom, top, 0.018))
        return "shell_legs", parts
    parts.append(frustum([0, 0.0, 0], [0, 0.02, 0], rng.uniform(0.2, 0.27), rng.uniform(0.18, 0.24), 24))
    parts.append(frustum([0, 0.01, 0], [0, seat_h - 0.005, 0], 0.025, 0.03, 12))
    return "shell_pedestal", parts
