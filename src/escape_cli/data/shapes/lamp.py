"""Procedural lamps (ShapeNet 03636649): floor lamps (straight or arc), desk lamps, table lamps, pendants.

Units are metres before normalisation; y up, an arm or arc leans towards +x.
"""

from __future__ import annotations

import numpy as np

from functools import partial

from escape_cli.data.primitives import box, ellipsoid, frustum, grid_shell, half_ellipsoid, revolved_grid
from escape_cli.data.shapes.base import draw_subtype

SUBTYPES = ("floor", "desk", "table", "pendant")
SHADE_WALL = 0.006  # metres: the wall of a hollow shade


def _shade(rng: np.random.Generator, top_centre: np.ndarray, kind: str, hollow: bool = False
           ) -> tuple[list[np.ndarray], float]:
    """A lamp shade hanging from `top_centre`: solid, or with `hollow` an open thin-walled shell.

    Returns its parts and height. The random draws do not depend on `hollow`.
    """
    height = rng.uniform(0.15, 0.35)
    if kind in ("drum", "cone"):
        r_bottom = rng.uniform(0.12, 0.25)
        r_top = r_bottom if kind == "drum" else r_bottom * rng.uniform(0.4, 0.8)
        if hollow:
            grid = revolved_grid([r_bottom, r_top], [-height, 0.0], 28, top_centre)
            return grid_shell(grid, SHADE_WALL), height
        return [frustum(top_centre - [0, height, 0], top_centre, r_bottom, r_top, 28)], height
    r = rng.uniform(0.12, 0.25)  # bowl / dome
    if hollow:  # a dome open below: rim at the bottom, a small opening on top for the cord
        t = np.linspace(0.0, 0.42 * np.pi, 6)
        grid = revolved_grid(r * np.cos(t) + 0.01, height * 0.7 * (np.sin(t) - 1.0), 28, top_centre)
        return grid_shell(grid, SHADE_WALL), height * 0.7
    return [half_ellipsoid(top_centre, (r, height * 0.7, r), downward=True)], height * 0.7


def _floor(rng: np.random.Generator, hollow: bool = False) -> tuple[str, list[np.ndarray]]:
    base_r = rng.uniform(0.12, 0.2)
    base_h = rng.uniform(0.02, 0.05)
    pole_h = rng.uniform(1.2, 1.7)
    pole_r = rng.uniform(0.01, 0.02)
    parts = [frustum([0, 0, 0], [0, base_h, 0], base_r, base_r * rng.uniform(0.7, 1.0), 28)]
    if rng.random() < 0.35:  # arc lamp: bent pole and a hanging bowl
        points = [np.array([0, base_h - 0.01, 0])]
        reach = rng.uniform(0.5, 0.9)
        for t in np.linspace(0, 1, 7)[1:]:
            angle = t * np.pi * 0.6
            points.append(np.array([reach * (1 - np.cos(angle)) / (1 - np.cos(np.pi * 0.6)), base_h + pole_h * np.sin(angle) / np.sin(np.pi * 0.6) * 0.5 + pole_h * 0.5 * t, 0]))
        for p0, p1 in zip(points[:-1], points[1:]):
            parts.append(frustum(p0, p1 + (p1 - p0) * 0.05, pole_r, pole_r, 10))
        tip = points[-1]
        parts.append(frustum(tip, tip - [0, 0.1, 0], pole_r * 0.6, pole_r * 0.6, 8))
        shade, _ = _shade(rng, tip - [0, 0.09, 0], "bowl", hollow)
        parts += shade
        return "floor_arc", parts
    parts.append(frustum([0, base_h - 0.01, 0], [0, pole_h, 0], pole_r, pole_r, 12))
    kind = str(rng.choice(["drum", "cone"]))
    shade, _ = _shade(rng, np.array([0, pole_h + rng.uniform(0.05, 0.15), 0]), kind, hollow)
    parts += shade
    return f"floor_{kind}", parts


def _desk(rng: np.random.Generator, hollow: bool = False) -> tuple[str, list[np.ndarray]]:
    if rng.random() < 0.5:
        base = box([0, 0.015, 0], (rng.uniform(0.12, 0.2), 0.03, rng.uniform(0.12, 0.2)))
    else:
        r = rng.uniform(0.07, 0.11)
        base = frustum([0, 0, 0], [0, 0.03, 0], r, r * 0.85, 24)
    arm_r = rng.uniform(0.008, 0.014)
    lower_len, upper_len = rng.uniform(0.25, 0.45), rng.uniform(0.25, 0.45)
    a1 = np.radians(rng.uniform(60, 85))  # lower arm elevation
    a2 = np.radians(rng.uniform(-30, 20))  # upper arm elevation
    shoulder = np.array([0, 0.03, 0])
    elbow = shoulder + lower_len * np.array([np.cos(a1), np.sin(a1), 0])
    wrist = elbow + upper_len * np.array([np.cos(a2), np.sin(a2), 0])
    parts = [base, ellipsoid(shoulder + [0, 0.01, 0], (0.025, 0.025, 0.025), rings=6, segments=10),
             frustum(shoulder, elbow, arm_r, arm_r, 10), ellipsoid(elbow, (0.022, 0.022, 0.022), rings=6, segments=10),
             frustum(elbow, wrist, arm_r, arm_r, 10)]
    shade_len = rng.uniform(0.1, 0.2)
    tilt = np.radians(rng.uniform(50, 90))  # shade axis angle below horizontal
    direction = np.array([np.cos(tilt), -np.sin(tilt), 0])
    r_neck, r_mouth = rng.uniform(0.02, 0.04), rng.uniform(0.06, 0.11)
    if hollow:  # a cone open at the mouth, closed at the neck
        t = np.linspace(0.0, 1.0, 3)[:, None]
        axis_points = wrist - direction * 0.02 + t * direction * (shade_len + 0.02)
        rot = _frame_from_axis(direction)
        angles = np.linspace(0.0, 2 * np.pi, 25)
        ring = np.stack([np.zeros_like(angles), np.cos(angles), np.sin(angles)], axis=1) @ rot.T  # (S, 3)
        radii = (r_neck + t * (r_mouth - r_neck))[:, :, None]
        grid = axis_points[:, None, :] + radii * ring[None]
        parts += grid_shell(grid, SHADE_WALL)
        parts.append(ellipsoid(wrist, (r_neck, r_neck, r_neck), rings=6, segments=10))
        return "desk_arm_open", parts
    parts.append(frustum(wrist - direction * 0.02, wrist + direction * shade_len, r_neck, r_mouth, 24))
    return "desk_arm", parts


def _table(rng: np.random.Generator, hollow: bool = False) -> tuple[str, list[np.ndarray]]:
    body_h = rng.uniform(0.2, 0.4)
    body_r = rng.uniform(0.06, 0.13)
    parts = []
    vase = rng.random() < 0.5
    if vase:
        parts.append(ellipsoid([0, body_h / 2, 0], (body_r, body_h / 2, body_r), rings=12, segments=20))
        parts.append(frustum([0, 0, 0], [0, body_h * 0.15, 0], body_r * 0.6, body_r * 0.7, 20))
    else:
        parts.append(frustum([0, 0, 0], [0, 0.03, 0], body_r * 1.2, body_r * 1.2, 24))
        parts.append(frustum([0, 0.02, 0], [0, body_h, 0], body_r * 0.25, body_r * 0.15, 14))
    neck_h = rng.uniform(0.08, 0.18)
    parts.append(frustum([0, body_h - 0.02, 0], [0, body_h + neck_h + 0.05, 0], 0.012, 0.012, 10))
    kind = str(rng.choice(["drum", "cone"]))
    shade, shade_h = _shade(rng, np.array([0, body_h + neck_h + 0.05, 0]), kind, hollow)
    parts += [part + [0, shade_h * 0.6, 0] for part in shade]  # the neck reaches well into the shade
    return f"table_{'vase' if vase else 'stem'}_{kind}", parts


def _pendant(rng: np.random.Generator, hollow: bool = False) -> tuple[str, list[np.ndarray]]:
    cord = rng.uniform(0.25, 0.7)
    canopy_r = rng.uniform(0.05, 0.09)
    parts = [frustum([0, cord, 0], [0, cord + 0.03, 0], canopy_r * 0.8, canopy_r, 20),
             frustum([0, 0.0, 0], [0, cord + 0.01, 0], 0.005, 0.005, 8)]
    kind = str(rng.choice(["drum", "cone", "bowl"]))
    shade, shade_h = _shade(rng, np.array([0, 0.02, 0]), kind, hollow)
    parts += shade
    if rng.random() < 0.5:  # a bulb showing below the shade
        parts.append(ellipsoid([0, 0.02 - shade_h - 0.03, 0], (0.035, 0.05, 0.035), rings=8, segments=12))
    return f"pendant_{kind}", parts


def _frame_from_axis(axis: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose first column is the unit `axis`."""
    x = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def generate(rng: np.random.Generator, hollow: bool = False) -> tuple[str, list[np.ndarray]]:
    """Draw one lamp: (subtype, vertices of each convex part); see `base.draw_subtype`.

    `hollow` gives the shades thin open walls (generator 2); the draws are the same.
    """
    builders = [partial(builder, hollow=hollow) for builder in (_floor, _desk, _table, _pendant)]
    return draw_subtype(rng, builders, [0.3, 0.25, 0.3, 0.15])
