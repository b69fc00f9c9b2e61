"""Procedural cars (ShapeNet 02958343): sedans, hatchbacks/SUVs, vans, pickup trucks, sports cars.

Units are metres before normalisation; y up, the nose at +x, width along z.
"""

from __future__ import annotations

import numpy as np

from escape_cli.data.primitives import box, frustum

SUBTYPES = ("sedan", "hatchback", "van", "pickup", "sports")


def _extrude(profile_xy: list[tuple[float, float]], half_width: float) -> np.ndarray:
    """A convex x-y profile extruded symmetrically along z; returns (2 * P, 3) vertices."""
    profile = np.asarray(profile_xy, dtype=np.float64)
    return np.concatenate([np.column_stack([profile, np.full(len(profile), s * half_width)]) for s in (-1, 1)])


def _greenhouse(x_rear_bottom: float, x_front_bottom: float, x_rear_top: float, x_front_top: float,
                y_bottom: float, y_top: float, half_width_bottom: float, half_width_top: float) -> np.ndarray:
    """The cabin: a trapezoid in side view that narrows towards the roof; returns (8, 3) vertices."""
    corners = []
    for x0, x1, y, hw in ((x_rear_bottom, x_front_bottom, y_bottom, half_width_bottom),
                          (x_rear_top, x_front_top, y_top, half_width_top)):
        corners += [[x, y, z] for x in (x0, x1) for z in (-hw, hw)]
    return np.array(corners)


def _wheels(rng: np.random.Generator, wheelbase: float, x_centre: float, half_width: float,
            radius: float) -> list[np.ndarray]:
    tyre = rng.uniform(0.18, 0.3)
    parts = []
    for x in (x_centre - wheelbase / 2, x_centre + wheelbase / 2):
        for sz in (-1, 1):
            z_out = sz * (half_width + rng.uniform(0.0, 0.03))  # tyres sit flush or stand out a little
            parts.append(frustum([x, radius, z_out - sz * tyre], [x, radius, z_out], radius, radius, 18))
    return parts


def _mirrors(cabin: np.ndarray, y: float, half_width: float) -> list[np.ndarray]:
    """Wing mirrors at height `y`, just behind the windscreen of `cabin` (a `_greenhouse`), sticking out sideways."""
    bottom, top = cabin[cabin[:, 1] == cabin[:, 1].min()], cabin[cabin[:, 1] == cabin[:, 1].max()]
    t = (y - bottom[0, 1]) / (top[0, 1] - bottom[0, 1])
    front_x = (1 - t) * bottom[:, 0].max() + t * top[:, 0].max()
    inner, outer = 0.75 * half_width, half_width + 0.12
    return [box([front_x - 0.07, y, s * (inner + outer) / 2], (0.08, 0.07, outer - inner)) for s in (-1, 1)]


def _body(rng: np.random.Generator, length: float, width: float, ground: float, belt: float,
          nose_drop: float, tail_drop: float) -> np.ndarray:
    """Lower body: a side profile with raked bumpers, extruded across the width."""
    hl = length / 2
    rake_f, rake_r = rng.uniform(0.1, 0.3), rng.uniform(0.05, 0.2)
    profile = [
        (-hl, ground + 0.15), (-hl + rake_r, ground), (hl - rake_f, ground), (hl, ground + 0.2),
        (hl, belt - nose_drop - 0.05), (hl - 0.1, belt - nose_drop), (-hl + 0.05, belt - tail_drop), (-hl, belt - tail_drop - 0.05),
    ]
    return _extrude(profile, width / 2)


def _car(rng: np.random.Generator, kind: str) -> tuple[str, list[np.ndarray]]:
    if kind == "sports":
        length, width, roof = rng.uniform(4.0, 4.7), rng.uniform(1.8, 2.0), rng.uniform(1.1, 1.3)
    elif kind == "van":
        length, width, roof = rng.uniform(4.5, 5.5), rng.uniform(1.8, 2.1), rng.uniform(1.9, 2.5)
    elif kind == "pickup":
        length, width, roof = rng.uniform(5.0, 6.0), rng.uniform(1.85, 2.1), rng.uniform(1.75, 2.0)
    elif kind == "hatchback":
        length, width, roof = rng.uniform(3.6, 4.8), rng.uniform(1.65, 1.95), rng.uniform(1.45, 1.8)
    else:
        length, width, roof = rng.uniform(4.3, 5.1), rng.uniform(1.7, 1.9), rng.uniform(1.35, 1.5)
    radius = rng.uniform(0.3, 0.36) if kind != "pickup" else rng.uniform(0.36, 0.45)
    ground = radius * rng.uniform(0.45, 0.7)
    belt_fraction = rng.uniform(0.5, 0.6) if kind != "sports" else rng.uniform(0.45, 0.55)
    belt = ground + (roof - ground) * belt_fraction
    hl, hw = length / 2, width / 2
    parts = []
    wheelbase = length * rng.uniform(0.56, 0.64)
    parts += _wheels(rng, wheelbase, rng.uniform(-0.05, 0.05) * length, hw, radius)
    top_hw = hw * rng.uniform(0.78, 0.9)
    if kind == "pickup":
        cab_rear = hl - length * rng.uniform(0.38, 0.45)
        parts.append(_body(rng, length, width, ground, belt, 0.0, 0.0))
        hood_x = hl - length * rng.uniform(0.15, 0.2)
        parts.append(_greenhouse(cab_rear, hood_x, cab_rear + 0.05, hood_x - 0.4, belt - 0.15, roof, hw * 0.97, top_hw))
        cabin = parts[-1]
        bed_wall = rng.uniform(0.3, 0.5)
        wall_t = 0.05
        bed_len = cab_rear - (-hl)
        for sz in (-1, 1):
            parts.append(box([-hl + bed_len / 2, belt + bed_wall / 2 - 0.01, sz * (hw - wall_t / 2)], (bed_len, bed_wall, wall_t)))
        parts.append(box([-hl + wall_t / 2, belt + bed_wall / 2 - 0.01, 0], (wall_t, bed_wall, width)))
        parts += _mirrors(cabin, belt + 0.08, hw)
        return "pickup", parts
    if kind == "van":
        parts.append(_body(rng, length, width, ground, belt, 0.0, 0.0))
        nose = length * rng.uniform(0.05, 0.15)
        parts.append(_greenhouse(-hl, hl - nose, -hl + 0.05, hl - nose - rng.uniform(0.4, 0.8), belt - 0.15, roof,
                                 hw * 0.99, hw * 0.95))
        cabin = parts[-1]
        parts += _mirrors(cabin, belt + 0.08, hw)
        return "van", parts
    nose_drop = rng.uniform(0.0, 0.15)
    parts.append(_body(rng, length, width, ground, belt, nose_drop, rng.uniform(0.0, 0.1)))
    glass_h = roof - belt
    if kind == "hatchback":
        cabin_rear_bottom = -hl + rng.uniform(0.05, 0.2)
        rear_rake = rng.uniform(0.05, 0.4)
        windscreen = hl - length * rng.uniform(0.2, 0.28)
    elif kind == "sports":
        cabin_rear_bottom = -hl + length * rng.uniform(0.12, 0.25)
        rear_rake = rng.uniform(0.5, 0.9)
        windscreen = hl - length * rng.uniform(0.36, 0.42)
    else:  # sedan: a separate boot
        cabin_rear_bottom = -hl + length * rng.uniform(0.14, 0.2)
        rear_rake = rng.uniform(0.3, 0.5)
        windscreen = hl - length * rng.uniform(0.28, 0.34)
    front_rake = glass_h * rng.uniform(1.3, 2.0)  # windscreen slope, metres back per metre up
    cabin_rear_top = cabin_rear_bottom + rear_rake
    roof_front = max(windscreen - front_rake, cabin_rear_top + 0.5)
    parts.append(_greenhouse(cabin_rear_bottom, windscreen, cabin_rear_top, roof_front,
                             belt - 0.2, roof, hw * 0.96, top_hw))  # its foot sinks into the body
    cabin = parts[-1]
    parts += _mirrors(cabin, belt + 0.06, hw)
    if kind == "sports" and rng.random() < 0.5:  # rear wing
        for sz in (-0.6, 0.6):
            parts.append(box([-hl + 0.2, belt + 0.03, sz * hw], (0.06, 0.32, 0.05)))
        parts.append(box([-hl + 0.2, belt + 0.19, 0], (0.25, 0.03, width * 0.9)))
    return kind, parts


def generate(rng: np.random.Generator) -> tuple[str, list[np.ndarray]]:
    """Draw one car.

    Returns
    -------
    subtype : str
    point_sets : list of (V_i, 3) float64
        Vertices of each convex part, in metres.
    """
    kind = str(rng.choice(SUBTYPES, p=[0.35, 0.2, 0.15, 0.15, 0.15]))
    return _car(rng, kind)
