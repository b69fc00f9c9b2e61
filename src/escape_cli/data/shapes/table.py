"""Procedural tables (ShapeNet 04379243): four legs, pedestal, panel/trestle ends, desk with drawers.

Units are metres before normalisation; y up, the long side faces +x.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import beam, box, frustum
from escape_cli.data.shapes.base import draw_subtype

SUBTYPES = ("legs", "pedestal", "panel_ends", "desk")


def _top(rng: np.random.Generator, height: float, round_top: bool) -> tuple[np.ndarray, float, float, float]:
    """The table top; returns its vertices, depth (x), width (z) and thickness."""
    thickness = rng.uniform(0.02, 0.06)
    if round_top:
        radius = rng.uniform(0.35, 0.7)
        aspect = 1.0 if rng.random() < 0.6 else rng.uniform(1.2, 1.8)
        top = frustum([0, height - thickness, 0], [0, height, 0], radius, radius, segments=40, aspect=aspect)
        return top, 2 * radius * aspect, 2 * radius, thickness  # `aspect` stretches the top along x
    depth = rng.uniform(0.5, 1.0)
    width = depth * rng.uniform(1.0, 2.5)
    return box([0, height - thickness / 2, 0], (depth, thickness, width)), depth, width, thickness


def _legs(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    height = rng.uniform(0.4, 0.8)
    round_top = rng.random() < 0.3
    top, depth, width, thick = _top(rng, height, round_top)
    parts = [top]
    leg = rng.uniform(0.03, 0.07)
    round_legs = rng.random() < 0.4
    splay = rng.uniform(0, 0.06) if rng.random() < 0.4 else 0.0
    leg_top = height - thick / 2
    if round_top:
        n_legs = int(rng.choice([3, 4]))
        inset = rng.uniform(0.55, 0.8)
        corners = [(0.5 * depth * inset * np.cos(a), 0.5 * width * inset * np.sin(a))
                   for a in 2 * np.pi * np.arange(n_legs) / n_legs + np.pi / 4]
    else:
        inset = rng.uniform(0.0, 0.1)
        corners = [(sx * (depth / 2 - leg - inset * depth), sz * (width / 2 - leg - inset * width))
                   for sx in (-1, 1) for sz in (-1, 1)]
    for x, z in corners:
        top_point = np.array([x, leg_top, z])
        direction = np.array([x, 0, z]) / max(np.hypot(x, z), 1e-9)
        bottom = np.array([x, 0, z]) + splay * direction
        parts.append(frustum(bottom, top_point, leg * 0.35, leg * 0.55, 12) if round_legs else beam(bottom, top_point, leg))
    if not round_top and rng.random() < 0.5:  # apron under the top
        apron_h = rng.uniform(0.05, 0.12)
        inner_d, inner_w = depth - 2 * (leg + inset * depth), width - 2 * (leg + inset * width)
        y = height - thick - apron_h / 2 + 0.005
        for sx in (-1, 1):
            parts.append(box([sx * inner_d / 2, y, 0], (0.02, apron_h, inner_w)))
        for sz in (-1, 1):
            parts.append(box([0, y, sz * inner_w / 2], (inner_d, apron_h, 0.02)))
    if not round_top and splay == 0 and rng.random() < 0.3:  # lower shelf
        shelf_y = rng.uniform(0.08, 0.25)
        inner_d, inner_w = depth - 2 * (inset * depth), width - 2 * (inset * width)
        parts.append(box([0, shelf_y, 0], (inner_d - leg, 0.025, inner_w - leg)))
        return "legs_rect_shelf", parts
    return ("legs_round" if round_top else "legs_rect"), parts


def _pedestal(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    height = rng.uniform(0.45, 0.8)
    round_top = rng.random() < 0.75
    top, depth, width, thick = _top(rng, height, round_top)
    column_r = rng.uniform(0.03, 0.08)
    parts = [top, frustum([0, 0.02, 0], [0, height - thick / 2, 0], column_r * rng.uniform(1.0, 1.8), column_r, 20)]
    if rng.random() < 0.5:
        base_r = min(depth, width) * rng.uniform(0.25, 0.45)
        parts.append(frustum([0, 0, 0], [0, rng.uniform(0.02, 0.06), 0], base_r, base_r * rng.uniform(0.6, 1.0), 32))
        return "pedestal_disc", parts
    feet = int(rng.choice([3, 4]))
    foot_len = min(depth, width) * rng.uniform(0.3, 0.45)
    for a in 2 * np.pi * np.arange(feet) / feet + np.pi / 4:
        end = np.array([foot_len * np.cos(a), 0.02, foot_len * np.sin(a)])
        parts.append(beam([0, 0.06, 0], end, 0.05, 0.04))
        parts.append(box(end + [0, 0.0, 0], (0.06, 0.04, 0.06)))
    return "pedestal_feet", parts


def _panel_ends(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    height = rng.uniform(0.4, 0.78)
    top, depth, width, thick = _top(rng, height, False)
    panel_t = rng.uniform(0.03, 0.08)
    inset = rng.uniform(0.0, 0.15) * width
    parts = [top]
    panel_depth = depth * rng.uniform(0.6, 1.0)
    trestle = rng.random() < 0.5
    for sz in (-1, 1):
        z = sz * (width / 2 - inset - panel_t / 2)
        if trestle:  # post on a foot
            parts.append(box([0, (height - thick) / 2 + 0.02, z], (0.08, height - thick, panel_t)))
            parts.append(box([0, 0.03, z], (panel_depth, 0.06, panel_t * 1.3)))
            parts.append(box([0, height - thick - 0.02, z], (panel_depth * 0.9, 0.05, panel_t)))
        else:
            parts.append(box([0, (height - thick) / 2 + 0.005, z], (panel_depth, height - thick + 0.01, panel_t)))
    if rng.random() < 0.6:
        span = width - 2 * inset - panel_t
        y = rng.uniform(0.1, height * 0.6) if trestle else height * rng.uniform(0.5, 0.85)
        parts.append(box([0 if trestle else -panel_depth * 0.3, y, 0], (0.04 if trestle else 0.02,
                                                                         0.08 if trestle else height * 0.3, span)))
    return ("panel_ends_trestle" if trestle else "panel_ends"), parts


def _desk(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    height = rng.uniform(0.68, 0.78)
    top, depth, width, thick = _top(rng, height, False)
    parts = [top]
    ped_w = rng.uniform(0.3, 0.45)
    drawers = int(rng.integers(2, 5))
    sides = (-1, 1) if rng.random() < 0.4 else (int(rng.choice([-1, 1])),)
    for sz in sides:
        z = sz * (width / 2 - ped_w / 2 - 0.01)
        body_h = height - thick + 0.005
        parts.append(box([0, body_h / 2, z], (depth * 0.95, body_h, ped_w)))
        front = depth * 0.475
        gap = 0.01
        drawer_h = (body_h - 0.04) / drawers
        for k in range(drawers):
            y = 0.03 + drawer_h * (k + 0.5)
            parts.append(box([front + 0.005, y, z], (0.02, drawer_h - gap, ped_w - 0.03)))
            parts.append(box([front + 0.02, y + drawer_h * 0.25, z], (0.03, 0.015, ped_w * 0.3)))
    if len(sides) == 1:  # the other end stands on a panel or two legs
        z = -sides[0] * (width / 2 - 0.03)
        if rng.random() < 0.5:
            parts.append(box([0, (height - thick) / 2 + 0.005, z], (depth * 0.95, height - thick + 0.01, 0.04)))
        else:
            for sx in (-1, 1):
                parts.append(beam([sx * (depth / 2 - 0.04), 0, z], [sx * (depth / 2 - 0.04), height - thick / 2, z], 0.04))
    if rng.random() < 0.6:  # modesty panel at the back
        parts.append(box([-depth / 2 + 0.05, height * 0.6, 0], (0.015, height * 0.5, width - 2 * ped_w * 0.5)))
    return "desk", parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one table: (subtype, vertices of each convex part); see `base.draw_subtype`."""
    return draw_subtype(rng, (_legs, _pedestal, _panel_ends, _desk), [0.45, 0.25, 0.15, 0.15])
