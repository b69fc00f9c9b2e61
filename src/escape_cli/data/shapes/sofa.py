"""Procedural sofas (ShapeNet 04256520): straight, L-shaped sectional, armless/loveseat, rolled arms.

Units are metres before normalisation; y up, the seat faces +x, the length runs along z.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import beam, box, frustum, rotation_matrix

SUBTYPES = ("straight", "sectional", "armless")


def _legs(rng: np.random.Generator, x0: float, x1: float, z0: float, z1: float, height: float) -> list[np.ndarray]:
    round_legs = rng.random() < 0.5
    parts = []
    for x in (x0 + 0.05, x1 - 0.05):
        for z in (z0 + 0.05, z1 - 0.05):
            p0, p1 = np.array([x, 0, z]), np.array([x, height + 0.02, z])
            parts.append(frustum(p0, p1, 0.015, 0.025, 10) if round_legs else beam(p0, p1, 0.04))
    return parts


def _sofa(rng: np.random.Generator, kind: str) -> tuple[str, list[np.ndarray]]:
    length = rng.uniform(1.2, 1.6) if kind == "armless" else rng.uniform(1.6, 2.6)
    depth = rng.uniform(0.8, 1.0)
    leg_h = rng.uniform(0.04, 0.16) if rng.random() < 0.7 else 0.0
    seat_top = rng.uniform(0.4, 0.48)
    cushion_t = rng.uniform(0.1, 0.18)
    base_top = seat_top - cushion_t
    back_t = rng.uniform(0.15, 0.28)
    back_top = rng.uniform(0.7, 0.95)
    has_arms = kind != "armless" or rng.random() < 0.3
    arm_w = rng.uniform(0.1, 0.25) if has_arms else 0.0
    arm_top = seat_top + rng.uniform(0.12, 0.25) if kind != "armless" else seat_top + rng.uniform(0.05, 0.1)
    hx, hz = depth / 2, length / 2
    chaise_side = int(rng.choice([-1, 1]))
    chaise_len = rng.uniform(0.6, 0.9) if kind == "sectional" else 0.0
    parts = []
    if leg_h > 0:
        parts += _legs(rng, -hx, hx, -hz, hz, leg_h)
    parts.append(box([0, (leg_h + base_top) / 2, 0], (depth, base_top - leg_h, length)))
    tilt = rotation_matrix("z", rng.uniform(0.0, 0.2))
    back_h = back_top - leg_h
    parts.append(box(np.array([-hx + back_t / 2, leg_h, 0]) + tilt @ [0, back_h / 2, 0], (back_t, back_h, length), tilt))
    n_cushions = int(rng.integers(1, 4))
    seat_len = length - 2 * arm_w
    cushion_len = seat_len / n_cushions
    for k in range(n_cushions):
        z = -seat_len / 2 + cushion_len * (k + 0.5)
        parts.append(box([back_t / 2 + 0.01, seat_top - cushion_t / 2, z], (depth - back_t, cushion_t, cushion_len - 0.01)))
    if rng.random() < 0.5:  # back cushions
        cushion_h = (back_top - seat_top) * 0.75
        for k in range(n_cushions):  # leaning on the back, sitting on the seat cushions
            z = -seat_len / 2 + cushion_len * (k + 0.5)
            local = np.array([back_t / 2 + 0.05, seat_top - leg_h + cushion_h / 2 - 0.02, 0.0])
            c = np.array([-hx + back_t / 2, leg_h, z]) + tilt @ local
            parts.append(box(c, (0.14, cushion_h, cushion_len - 0.02), tilt))
    if kind == "sectional":
        z_far = chaise_side * (hz + chaise_len)
        z_near = chaise_side * (hz - 0.4)
        zc, zl = (z_far + z_near) / 2, abs(z_far - z_near)
        parts.append(box([hx + 0.3 - depth / 2 + 0.0, (leg_h + base_top) / 2, zc], (depth + 0.6, base_top - leg_h, zl)))
        parts.append(box([hx + 0.3 - depth / 2 + back_t / 2, seat_top - cushion_t / 2, zc], (depth + 0.6 - back_t, cushion_t, zl - 0.02)))
        if leg_h > 0:
            parts += _legs(rng, hx - 0.3, hx + 0.6, min(z_far, z_near), max(z_far, z_near), leg_h)
        parts.append(box(np.array([-hx + back_t / 2, leg_h, z_far - chaise_side * chaise_len / 2]) + tilt @ [0, back_h / 2, 0],
                         (back_t, back_h, chaise_len), tilt))
    if has_arms:
        rolled = rng.random() < 0.4
        for side in (-1, 1):
            z_end = side * (hz + (chaise_len if kind == "sectional" and side == chaise_side else 0.0))
            z = z_end - side * arm_w / 2
            arm_depth = depth + (0.6 if kind == "sectional" and side == chaise_side else 0.0)
            x = -hx + arm_depth / 2
            top = arm_top - (arm_w * 0.4 if rolled else 0.0)
            parts.append(box([x, (leg_h + top) / 2, z], (arm_depth, top - leg_h, arm_w)))
            if rolled:
                parts.append(frustum([-hx, top, z], [-hx + arm_depth + 0.03, top, z], arm_w * 0.55, arm_w * 0.55, 16))
    return (kind if kind != "straight" or has_arms else "straight"), parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one sofa.

    Returns
    -------
    subtype : str
    point_sets : list of (V_i, 3) float64
        Vertices of each convex part, in metres.
    """
    kind = str(rng.choice(SUBTYPES, p=[0.55, 0.25, 0.2]))
    return _sofa(rng, kind)
