"""Procedural chairs (ShapeNet 03001627): four-legged, swivel office, lounge armchair, cantilever sled.

Units are metres before normalisation; y up, the seat's front edge faces +x.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import beam, box, ellipsoid, frustum, rotation_matrix
from escape_cli.data.shapes.base import draw_subtype

SUBTYPES = ("four_leg", "swivel", "lounge", "sled")


def _back(rng: np.random.Generator, rear_x: float, seat_top: float, width: float, height: float,
          tilt: float, style: str) -> list[np.ndarray]:
    """A chair back standing on the seat's rear edge, leaning back by `tilt` radians."""
    rot = rotation_matrix("z", tilt)
    up = rot @ np.array([0.0, 1.0, 0.0])
    base = np.array([rear_x, seat_top - 0.02, 0.0])
    thickness = rng.uniform(0.02, 0.05)
    parts = []
    if style == "solid":
        top_width = width * rng.uniform(0.8, 1.05)
        bottom, top = base, base + up * height
        hw0, hw1 = width / 2, top_width / 2
        t = thickness / 2
        normal = rot @ np.array([1.0, 0, 0])
        corners = [bottom + s * t * normal + np.array([0, 0, z]) for s in (-1, 1) for z in (-hw0, hw0)]
        corners += [top + s * t * normal + np.array([0, 0, z]) for s in (-1, 1) for z in (-hw1, hw1)]
        parts.append(np.array(corners))
        return parts
    post = rng.uniform(0.025, 0.045)
    for z in (-width / 2 + post / 2, width / 2 - post / 2):
        parts.append(beam(base + [0, 0, z], base + up * height + [0, 0, z], post, thickness))
    rail_h = rng.uniform(0.05, 0.12)
    parts.append(box(base + up * (height - rail_h / 2), (thickness, rail_h, width), rot))
    if style == "vertical_slats":
        n = int(rng.integers(2, 6))
        slat_w = rng.uniform(0.02, 0.06)
        for z in np.linspace(-width / 2, width / 2, n + 2)[1:-1]:
            parts.append(beam(base + [0, 0, z], base + up * (height - rail_h / 2) + [0, 0, z], slat_w, thickness * 0.6))
    else:  # horizontal slats
        n = int(rng.integers(1, 4))
        slat_h = rng.uniform(0.04, 0.09)
        for frac in np.linspace(0.15, 0.7, n):
            parts.append(box(base + up * (frac * height), (thickness * 0.7, slat_h, width), rot))
    return parts


def _arms(rng: np.random.Generator, front_x: float, rear_x: float, seat_top: float, half_width: float,
          post_bottom: float) -> list[np.ndarray]:
    """Two armrests on front posts, their rear ends reaching the back."""
    height = seat_top + rng.uniform(0.17, 0.25)
    pad_w, pad_t = rng.uniform(0.04, 0.08), rng.uniform(0.025, 0.05)
    post = rng.uniform(0.025, 0.045)
    parts = []
    for side in (-1, 1):
        z = side * (half_width - pad_w / 2)
        parts.append(box([(front_x + rear_x) / 2, height, z], (front_x - rear_x + 0.02, pad_t, pad_w)))
        px = front_x - rng.uniform(0.03, 0.1)
        parts.append(beam([px, post_bottom, z], [px, height, z], post, post))
    return parts


def _four_leg(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    width, depth = rng.uniform(0.4, 0.6), rng.uniform(0.38, 0.55)
    seat_top, seat_t = rng.uniform(0.4, 0.5), rng.uniform(0.025, 0.07)
    leg = rng.uniform(0.025, 0.05)
    splay = rng.uniform(0.0, 0.05)
    round_legs = rng.random() < 0.4
    parts = [box([0, seat_top - seat_t / 2, 0], (depth, seat_t, width))]
    leg_top = seat_top - seat_t / 2
    for sx in (-1, 1):
        for sz in (-1, 1):
            top = np.array([sx * (depth / 2 - leg), leg_top, sz * (width / 2 - leg)])
            bottom = top * [1, 0, 1] + np.array([sx * splay, 0, sz * splay])
            if round_legs:
                parts.append(frustum(bottom, top, leg * 0.4, leg * 0.6, segments=12))
            else:
                parts.append(beam(bottom, top, leg))
    if rng.random() < 0.4:  # stretchers between the legs
        y = rng.uniform(0.08, 0.2)
        for sz in (-1, 1):
            z = sz * (width / 2 - leg + splay * 0.7)
            parts.append(beam([-depth / 2 - splay * 0.5, y, z], [depth / 2 + splay * 0.5, y, z], leg * 0.5))
    style = str(rng.choice(["solid", "vertical_slats", "horizontal_slats"], p=[0.5, 0.25, 0.25]))
    parts += _back(rng, -depth / 2 + 0.02, seat_top, width, rng.uniform(0.35, 0.55), rng.uniform(0.0, 0.25), style)
    if rng.random() < 0.35:
        parts += _arms(rng, depth / 2, -depth / 2, seat_top, width / 2, seat_top - seat_t)
        return f"four_leg_arms_{style}", parts
    return f"four_leg_{style}", parts


def _swivel(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    width, depth = rng.uniform(0.45, 0.6), rng.uniform(0.42, 0.55)
    seat_top, seat_t = rng.uniform(0.45, 0.55), rng.uniform(0.06, 0.12)
    spokes = int(rng.integers(4, 6))
    spoke_len = rng.uniform(0.25, 0.35)
    hub_y = rng.uniform(0.06, 0.1)
    parts = []
    for k in range(spokes):
        angle = 2 * np.pi * k / spokes + np.pi / 2
        end = np.array([spoke_len * np.cos(angle), hub_y - 0.02, spoke_len * np.sin(angle)])
        parts.append(beam([0, hub_y, 0], end, 0.04, 0.035))
        parts.append(ellipsoid(end - [0, 0.035, 0], (0.03, 0.03, 0.02), rings=6, segments=10))
    parts.append(frustum([0, hub_y - 0.03, 0], [0, seat_top - seat_t + 0.01, 0], 0.035, 0.025, segments=16))
    parts.append(box([0, seat_top - seat_t / 2, 0], (depth, seat_t, width)))
    back_h = rng.uniform(0.4, 0.75)
    tilt = rng.uniform(0.05, 0.25)
    rot = rotation_matrix("z", tilt)
    back_base = np.array([-depth / 2 - 0.03, seat_top + 0.04, 0.0])
    back_t = rng.uniform(0.04, 0.09)
    back_w = width * rng.uniform(0.85, 1.05)
    parts.append(box(back_base + rot @ [0, back_h / 2, 0], (back_t, back_h, back_w), rot))
    if rng.random() < 0.5:  # headrest
        parts.append(box(back_base + rot @ [0, back_h + 0.05, 0], (back_t * 0.8, 0.12, back_w * 0.5), rot))
    parts.append(beam([0, seat_top - seat_t, 0], [-depth / 2 - 0.06, seat_top - seat_t, 0], 0.06, 0.025))
    parts.append(beam([-depth / 2 - 0.04, seat_top - seat_t - 0.01, 0], back_base + rot @ [0, 0.1, 0], 0.05, 0.02))
    if rng.random() < 0.6:
        parts += _arms(rng, depth / 2 - 0.05, -depth / 2, seat_top, width / 2 + 0.01, seat_top - seat_t / 2)
        return "swivel_arms", parts
    return "swivel", parts


def _lounge(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    width, depth = rng.uniform(0.65, 0.95), rng.uniform(0.7, 0.9)
    leg_h = rng.uniform(0.0, 0.15)
    seat_top = rng.uniform(0.38, 0.46)
    cushion_t = rng.uniform(0.08, 0.14)
    base_top = seat_top - cushion_t
    parts = []
    if leg_h > 0.03:
        for sx in (-1, 1):
            for sz in (-1, 1):
                p = np.array([sx * (depth / 2 - 0.06), 0, sz * (width / 2 - 0.06)])
                parts.append(frustum(p, p + [0, leg_h + 0.02, 0], 0.015, 0.025, segments=10))
    parts.append(box_between_y(leg_h, base_top, depth, width))
    back_t = rng.uniform(0.12, 0.22)
    back_h = rng.uniform(0.4, 0.6)
    rot = rotation_matrix("z", rng.uniform(0.05, 0.2))
    parts.append(box(np.array([-depth / 2 + back_t / 2, base_top, 0]) + rot @ [0, back_h / 2, 0],
                     (back_t, back_h + 0.1, width), rot))
    has_arms = rng.random() < 0.8
    arm_w = rng.uniform(0.08, 0.18) if has_arms else 0.0
    parts.append(box([back_t / 2, seat_top - cushion_t / 2, 0],
                     (depth - back_t, cushion_t, width - 2 * arm_w - 0.01)))
    if has_arms:
        arm_top = seat_top + rng.uniform(0.12, 0.25)
        for side in (-1, 1):
            z = side * (width / 2 - arm_w / 2)
            parts.append(box([0, (leg_h + arm_top) / 2, z], (depth, arm_top - leg_h, arm_w)))
            if rng.random() < 0.5:  # rolled arm
                parts.append(frustum([-depth / 2, arm_top, z], [depth / 2, arm_top, z], arm_w * 0.6, arm_w * 0.6, 14))
        return "lounge_arms", parts
    return "lounge", parts


def box_between_y(y0: float, y1: float, depth: float, width: float) -> np.ndarray:
    """A centred box spanning heights `y0`..`y1` with the given depth (x) and width (z)."""
    return box([0, (y0 + y1) / 2, 0], (depth, y1 - y0, width))


def _sled(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    width, depth = rng.uniform(0.42, 0.55), rng.uniform(0.4, 0.5)
    seat_top, seat_t = rng.uniform(0.42, 0.48), rng.uniform(0.02, 0.06)
    tube = rng.uniform(0.012, 0.02)
    parts = [box([0, seat_top - seat_t / 2, 0], (depth, seat_t, width))]
    for side in (-1, 1):
        z = side * (width / 2 + tube * 0.5)
        front, rear = depth / 2 - 0.02, -depth / 2 + 0.02
        floor_front = depth / 2 + rng.uniform(-0.02, 0.06)
        floor_rear = -depth / 2 - rng.uniform(-0.02, 0.05)
        parts.append(frustum([floor_rear, tube, z], [floor_front, tube, z], tube, tube, 10))
        parts.append(frustum([floor_front, tube, z], [front, seat_top - seat_t / 2, z], tube, tube, 10))
        parts.append(frustum([floor_rear, tube, z], [rear, seat_top - seat_t / 2, z], tube, tube, 10))
        parts.append(frustum([front + tube, seat_top - seat_t / 2, z], [rear, seat_top - seat_t / 2, z], tube, tube, 10))
    style = str(rng.choice(["solid", "vertical_slats", "horizontal_slats"], p=[0.6, 0.2, 0.2]))
    parts += _back(rng, -depth / 2 + 0.02, seat_top, width, rng.uniform(0.35, 0.5), rng.uniform(0.05, 0.25), style)
    return f"sled_{style}", parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one chair: (subtype, vertices of each convex part); see `base.draw_subtype`."""
    return draw_subtype(rng, (_four_leg, _swivel, _lounge, _sled), [0.5, 0.2, 0.15, 0.15])
