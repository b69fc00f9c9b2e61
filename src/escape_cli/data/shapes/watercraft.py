"""Procedural watercraft (ShapeNet 04530566): sailboats, motorboats, ships.

Units are hull lengths before normalisation; y up, the bow at +x, beam along z.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import beam, box, frustum, polygon_section
from escape_cli.data.shapes.base import draw_subtype

SUBTYPES = ("sailboat", "motorboat", "ship")


def _hull(rng: np.random.Generator, beam_width: float, depth: float, deadrise: float, transom: float,
          sheer: float) -> list[np.ndarray]:
    """A convex hull from stern (x=-0.5) to bow (x=+0.5): V sections, a raked stem, a rising sheer.

    Returns the aft body and the bow as two convex parts sharing the midship section.
    """
    hb = beam_width / 2

    def section(x: float, half_beam: float, keel_y: float, deck_y: float, chine: float) -> np.ndarray:
        outline = [(keel_y, -0.02 * hb), (keel_y, 0.02 * hb), (keel_y + deadrise * depth, chine * half_beam),
                   (keel_y + deadrise * depth, -chine * half_beam), (deck_y, half_beam), (deck_y, -half_beam)]
        return polygon_section(np.array(outline), x)

    stern = section(-0.5, hb * transom, depth * 0.15, depth, 0.9)
    mid = section(0.0, hb, 0.0, depth, 0.85)
    shoulder_x = rng.uniform(0.15, 0.25)
    shoulder = section(shoulder_x, hb * 0.9, depth * 0.02, depth + sheer * 0.3, 0.75)
    stem_top = np.array([[0.5, depth + sheer, -0.01], [0.5, depth + sheer, 0.01]])
    forefoot = np.array([[0.5 - rng.uniform(0.08, 0.2), depth * 0.1, -0.01], [0.5 - rng.uniform(0.08, 0.2), depth * 0.1, 0.01]])
    return [np.concatenate([stern, mid]), np.concatenate([mid, shoulder]), np.concatenate([shoulder, stem_top, forefoot])]


def _sailboat(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    beam_width, depth = rng.uniform(0.25, 0.35), rng.uniform(0.08, 0.12)
    parts = _hull(rng, beam_width, depth, rng.uniform(0.3, 0.5), rng.uniform(0.6, 0.85), rng.uniform(0.01, 0.04))
    keel_len = rng.uniform(0.15, 0.3)
    keel_depth = rng.uniform(0.12, 0.25)
    parts.append(np.array([[0.05, 0.02, s] for s in (-0.012, 0.012)] + [[0.05 - keel_len, 0.03, s] for s in (-0.012, 0.012)]
                          + [[0.0, -keel_depth, s] for s in (-0.01, 0.01)] + [[-keel_len * 0.7, -keel_depth, s] for s in (-0.01, 0.01)]))
    parts.append(box([-0.45, -0.02, 0], (0.06, 0.16, 0.012)))  # rudder
    if rng.random() < 0.7:  # cabin
        parts.append(box([-0.05, depth + 0.03, 0], (rng.uniform(0.25, 0.4), 0.08, beam_width * 0.55)))
    mast_x = rng.uniform(0.05, 0.2)
    mast_h = rng.uniform(0.9, 1.4)
    parts.append(frustum([mast_x, depth - 0.01, 0], [mast_x, depth + mast_h, 0], 0.01, 0.007, 10))
    boom_y = depth + rng.uniform(0.1, 0.18)
    boom_len = rng.uniform(0.35, 0.5)
    parts.append(beam([mast_x, boom_y, 0], [mast_x - boom_len, boom_y, 0], 0.012))
    sail_t = 0.004
    main_top = depth + mast_h * rng.uniform(0.9, 0.98)
    parts.append(np.array([[mast_x - 0.008, boom_y + 0.006, s] for s in (-sail_t, sail_t)]
                          + [[mast_x - boom_len, boom_y + 0.006, s] for s in (-sail_t, sail_t)]
                          + [[mast_x - 0.008, main_top, s] for s in (-sail_t, sail_t)]))
    two_sails = rng.random() < 0.7
    if two_sails:  # jib from the bow to the mast head
        jib_top = depth + mast_h * rng.uniform(0.7, 0.9)
        parts.append(np.array([[0.48, depth + 0.03, s] for s in (-sail_t, sail_t)]
                              + [[mast_x + 0.01, depth + 0.05, s] for s in (-sail_t, sail_t)]
                              + [[mast_x + 0.01, jib_top, s] for s in (-sail_t, sail_t)]))
    return ("sailboat_sloop" if two_sails else "sailboat_cat"), parts


def _motorboat(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    beam_width, depth = rng.uniform(0.3, 0.42), rng.uniform(0.1, 0.16)
    parts = _hull(rng, beam_width, depth, rng.uniform(0.2, 0.4), rng.uniform(0.85, 0.98), rng.uniform(0.02, 0.06))
    cabin = rng.random() < 0.55
    if cabin:  # a cabin with a raked windscreen
        cab_len, cab_h = rng.uniform(0.3, 0.5), rng.uniform(0.08, 0.16)
        x0 = rng.uniform(-0.2, 0.0)
        hw = beam_width * rng.uniform(0.3, 0.42)
        rake = rng.uniform(0.05, 0.15)
        parts.append(np.array([[x, depth - 0.01, z] for x in (x0 - cab_len / 2, x0 + cab_len / 2) for z in (-hw, hw)]
                              + [[x, depth + cab_h, z] for x in (x0 - cab_len / 2, x0 + cab_len / 2 - rake) for z in (-hw * 0.9, hw * 0.9)]))
        if rng.random() < 0.5:  # flybridge rail / roof
            parts.append(box([x0 - 0.03, depth + cab_h + 0.01, 0], (cab_len * 0.9, 0.02, hw * 2)))
    else:  # open boat: console with windscreen
        parts.append(box([-0.05, depth + 0.05, 0], (0.1, 0.12, beam_width * 0.3)))
        parts.append(box([0.0, depth + 0.13, 0], (0.02, 0.05, beam_width * 0.35)))
    motor_h = rng.uniform(0.12, 0.2)
    parts.append(box([-0.52, depth + 0.02, 0], (0.07, 0.08, 0.06)))
    parts.append(box([-0.52, depth - motor_h / 2, 0], (0.03, motor_h, 0.025)))
    return ("motorboat_cabin" if cabin else "motorboat_open"), parts


def _ship(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    beam_width, depth = rng.uniform(0.12, 0.2), rng.uniform(0.06, 0.1)
    parts = _hull(rng, beam_width, depth, rng.uniform(0.6, 0.8), rng.uniform(0.7, 0.9), rng.uniform(0.01, 0.03))
    bridge_x = rng.uniform(-0.35, 0.15)
    levels = int(rng.integers(2, 5))
    level_h = rng.uniform(0.025, 0.045)
    hb = beam_width / 2
    for k in range(levels):
        shrink = 1 - 0.15 * k
        parts.append(box([bridge_x - 0.01 * k, depth + level_h * (k + 0.5) - 0.005, 0],
                         (rng.uniform(0.08, 0.2) * shrink, level_h + 0.005, hb * 1.6 * shrink)))
    top = depth + levels * level_h
    parts.append(frustum([bridge_x, top - 0.01, 0], [bridge_x, top + rng.uniform(0.06, 0.12), 0], 0.005, 0.004, 8))
    n_funnels = int(rng.integers(0, 3))
    for k in range(n_funnels):
        fx = bridge_x - 0.12 - 0.07 * k
        if fx > -0.45:
            parts.append(frustum([fx, depth - 0.005, 0], [fx - 0.01, depth + rng.uniform(0.06, 0.1), 0], 0.02, 0.017, 14, aspect=0.8))
    cargo = rng.random() < 0.5
    if cargo:  # container stacks on deck
        for x in np.arange(bridge_x + 0.1, 0.35, rng.uniform(0.07, 0.1)):
            stack_h = rng.uniform(0.03, 0.06)
            parts.append(box([x, depth - 0.005 + stack_h / 2, 0], (0.06, stack_h, hb * 1.5)))
    else:  # turrets fore and aft
        for x in (0.3, bridge_x - 0.2):
            if -0.4 < x < 0.4:
                parts.append(frustum([x, depth - 0.005, 0], [x, depth + 0.025, 0], 0.03, 0.025, 14))
                parts.append(beam([x, depth + 0.015, 0], [x + (0.08 if x > bridge_x else -0.08), depth + 0.02, 0], 0.008))
    return ("ship_cargo" if cargo else "ship_naval"), parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one watercraft: (subtype, vertices of each convex part); see `base.draw_subtype`."""
    return draw_subtype(rng, (_sailboat, _motorboat, _ship), [0.35, 0.35, 0.3])
