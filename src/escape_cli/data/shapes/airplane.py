"""Procedural airplanes (ShapeNet 02691156): airliners, propeller planes, fighter jets.

Units are fuselage lengths before normalisation; y up, the nose at +x, wings along z.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import airfoil_section, box, ellipsoid, frustum, rotation_matrix
from escape_cli.data.shapes.base import draw_subtype

SUBTYPES = ("airliner", "propeller", "fighter")


def _wing_pair(root_le: np.ndarray, root_chord: float, half_span: float, sweep_deg: float, taper: float,
               thickness: float, dihedral_deg: float = 0.0) -> list[np.ndarray]:
    """Two mirrored tapered, swept wing panels from a root leading edge at z = root_le[2]."""
    parts = []
    tip_chord = root_chord * taper
    sweep = half_span * np.tan(np.radians(sweep_deg))
    rise = half_span * np.tan(np.radians(dihedral_deg))
    for side in (-1, 1):
        root = np.array([root_le[0], root_le[1], side * root_le[2]])
        tip = root + np.array([-sweep, rise, side * half_span])
        parts.append(np.concatenate([airfoil_section(root, root_chord, thickness),
                                     airfoil_section(tip, tip_chord, thickness * max(taper, 0.4))]))
    return parts


def _fin(base_le: np.ndarray, root_chord: float, height: float, sweep_deg: float, taper: float,
         thickness: float) -> np.ndarray:
    """A vertical fin: airfoil sections in horizontal planes (thickness along z)."""
    swap = rotation_matrix("x", np.pi / 2)  # maps the section's y thickness onto z
    root = (airfoil_section([0, 0, 0], root_chord, thickness) @ swap.T) + base_le
    tip_le = base_le + np.array([-height * np.tan(np.radians(sweep_deg)), height, 0])
    tip = (airfoil_section([0, 0, 0], root_chord * taper, thickness * 0.6) @ swap.T) + tip_le
    return np.concatenate([root, tip])


def _fuselage(rng: np.random.Generator, length: float, radius: float, nose_len: float, tail_len: float,
              tail_rise: float, pointed: bool) -> list[np.ndarray]:
    """Nose cone, cylindrical body and upswept tail cone, nose at +length/2."""
    hl = length / 2
    body_front, body_rear = hl - nose_len, -hl + tail_len
    parts = [
        frustum([body_rear, 0, 0], [body_front, 0, 0], radius, radius, 20),
        frustum([body_rear, 0, 0], [-hl, tail_rise, 0], radius, radius * rng.uniform(0.15, 0.35), 20),
    ]
    if pointed:
        parts.append(frustum([body_front, 0, 0], [hl, -radius * 0.2, 0], radius, 0.0, 20))
    else:
        parts.append(ellipsoid([body_front, -radius * 0.1, 0], (nose_len, radius * 0.95, radius * 0.98), rings=10))
        parts.append(frustum([body_front, 0, 0], [body_front + 1e-3, 0, 0], radius, radius, 20))
    return parts


def _airliner(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    length, radius = 1.0, rng.uniform(0.04, 0.06)
    parts = _fuselage(rng, length, radius, rng.uniform(0.08, 0.14), rng.uniform(0.2, 0.28), radius * 0.5, False)
    half_span = rng.uniform(0.4, 0.55)
    root_chord = rng.uniform(0.16, 0.24)
    sweep = rng.uniform(20, 38)
    wing_x = rng.uniform(0.05, 0.15)
    wing_y = -radius * rng.uniform(0.3, 0.6) if rng.random() < 0.8 else radius * 0.6
    parts += _wing_pair(np.array([wing_x, wing_y, 0.0]), root_chord, half_span, sweep, rng.uniform(0.25, 0.4),
                        radius * 0.35, rng.uniform(2, 7))
    n_engines = int(rng.choice([2, 4], p=[0.75, 0.25]))
    spans = [0.35] if n_engines == 2 else [0.3, 0.6]
    engine_r = radius * rng.uniform(0.45, 0.65)
    for frac in spans:
        for side in (-1, 1):
            z = side * frac * half_span
            x_le = wing_x - frac * half_span * np.tan(np.radians(sweep))
            y = wing_y + frac * half_span * np.tan(np.radians(4)) - engine_r * 1.4
            parts.append(frustum([x_le - 0.12, y, z], [x_le + 0.06, y, z], engine_r * 0.8, engine_r, 16))
            parts.append(box([x_le - 0.03, y + engine_r, z], (0.1, engine_r * 1.2, 0.008)))
    t_tail = rng.random() < 0.25
    fin_h = rng.uniform(0.12, 0.18)
    fin_chord = rng.uniform(0.12, 0.18)
    parts.append(_fin(np.array([-0.5 + fin_chord + 0.02, radius * 0.5, 0]), fin_chord, fin_h + radius * 0.5, rng.uniform(30, 45),
                      0.5, 0.02))
    stab_y = radius * 0.5 + fin_h if t_tail else radius * 0.4
    stab_x = -0.5 + fin_chord * (0.6 if t_tail else 0.9) + (-(fin_h + 0.02) * np.tan(np.radians(35)) if t_tail else 0)
    parts += _wing_pair(np.array([stab_x + 0.03, stab_y, 0.0]), fin_chord * 0.8, rng.uniform(0.12, 0.18), sweep, 0.45, 0.012)
    return ("airliner_t_tail" if t_tail else "airliner"), parts


def _propeller(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    length, radius = 1.0, rng.uniform(0.06, 0.09)
    parts = _fuselage(rng, length, radius, rng.uniform(0.08, 0.12), rng.uniform(0.35, 0.45), radius * 0.3, False)
    half_span = rng.uniform(0.55, 0.75)
    root_chord = rng.uniform(0.14, 0.2)
    high_wing = rng.random() < 0.5
    wing_x = rng.uniform(0.12, 0.25)
    wing_y = radius * 0.85 if high_wing else -radius * 0.6
    parts += _wing_pair(np.array([wing_x, wing_y, 0.0]), root_chord, half_span, rng.uniform(-3, 6), rng.uniform(0.55, 1.0),
                        radius * 0.3, rng.uniform(0, 4))
    twin = rng.random() < 0.35
    blades = int(rng.choice([2, 3, 4]))
    prop_r = rng.uniform(0.1, 0.16)

    def propeller(hub: np.ndarray, spinner_r: float) -> list[np.ndarray]:
        out = [frustum(hub - [0.03, 0, 0], hub + [0.05, 0, 0], spinner_r, 0.0, 14)]
        for k in range(blades):
            rot = rotation_matrix("x", 2 * np.pi * k / blades + 0.3)
            out.append(box(hub + rot @ [0, prop_r / 2, 0], (0.01, prop_r, 0.025), rot))
        return out

    if twin:
        for side in (-1, 1):
            z = side * half_span * 0.35
            nac_r = radius * 0.5
            parts.append(frustum([wing_x - root_chord, wing_y, z], [wing_x + 0.08, wing_y, z], nac_r * 0.6, nac_r, 14))
            parts += propeller(np.array([wing_x + 0.1, wing_y, z]), nac_r * 0.9)
    else:
        parts += propeller(np.array([0.5 + 0.02, -radius * 0.1, 0.0]), radius * 0.45)
    fin_chord = rng.uniform(0.1, 0.16)
    parts.append(_fin(np.array([-0.5 + fin_chord + 0.02, radius * 0.2, 0]), fin_chord, rng.uniform(0.12, 0.18),
                      rng.uniform(15, 40), 0.6, 0.015))
    parts += _wing_pair(np.array([-0.5 + fin_chord + 0.02, radius * 0.25, 0.0]), fin_chord, rng.uniform(0.15, 0.22), 5, 0.7, 0.012)
    if rng.random() < 0.5:  # fixed landing gear
        for side in (-1, 1):
            foot = np.array([wing_x - 0.02, -radius - 0.08, side * radius * 1.5])
            parts.append(frustum(foot + [0, 0.02, 0], np.array([wing_x - 0.02, -radius * 0.6, side * radius * 0.5]), 0.006, 0.006, 8))
            parts.append(frustum(foot - [0, 0, 0.012], foot + [0, 0, 0.012], 0.03, 0.03, 14))
    return ("propeller_twin" if twin else "propeller"), parts


def _fighter(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    length, radius = 1.0, rng.uniform(0.045, 0.065)
    parts = _fuselage(rng, length, radius, rng.uniform(0.2, 0.3), rng.uniform(0.1, 0.15), 0.0, True)
    parts.append(ellipsoid([0.22, radius * 0.7, 0], (0.12, radius * 0.6, radius * 0.55), rings=8))  # canopy
    half_span = rng.uniform(0.25, 0.4)
    root_chord = rng.uniform(0.35, 0.5)
    sweep = rng.uniform(40, 62)
    parts += _wing_pair(np.array([root_chord - 0.3, -radius * 0.1, 0.0]), root_chord, half_span, sweep,
                        rng.uniform(0.08, 0.25), radius * 0.3, rng.uniform(-3, 2))
    for side in (-1, 1):  # intakes along the sides
        parts.append(box([0.0, -radius * 0.2, side * radius * 1.1], (0.35, radius * 1.2, radius * 0.8)))
    twin = rng.random() < 0.5
    fin_chord = rng.uniform(0.14, 0.22)
    fin_h = rng.uniform(0.1, 0.16)
    if twin:
        for side in (-1, 1):
            fin = _fin(np.array([-0.5 + fin_chord + 0.05, radius * 0.5, side * radius * 0.9]), fin_chord, fin_h, 40, 0.4, 0.012)
            pivot = np.array([0, radius * 0.5, side * radius * 0.9])
            parts.append((fin - pivot) @ rotation_matrix("x", -side * 0.3).T + pivot)
    else:
        parts.append(_fin(np.array([-0.5 + fin_chord + 0.05, radius * 0.5, 0]), fin_chord, fin_h, 45, 0.35, 0.012))
    if rng.random() < 0.7:  # tailplanes
        parts += _wing_pair(np.array([-0.5 + fin_chord * 0.8, 0.0, 0.0]), fin_chord * 0.8, half_span * 0.45, sweep, 0.3, 0.01)
    return ("fighter_twin_fin" if twin else "fighter"), parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one airplane: (subtype, vertices of each convex part); see `base.draw_subtype`."""
    return draw_subtype(rng, (_airliner, _propeller, _fighter), [0.45, 0.3, 0.25])
