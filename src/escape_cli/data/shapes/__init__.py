"""Procedural shapes of the 8 PCN categories, one module per category.

Each category module exposes `SUBTYPES` and `generate(rng) -> (subtype, point_sets)`,
where every point set is the vertex cloud of one convex part. `generate_shape` turns
that into a normalised `ProceduralShape` (see `base` for the frame and scale).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from escape_cli.data.shapes import airplane, cabinet, car, chair, lamp, realism, sofa, table, watercraft
from escape_cli.data.shapes.base import ProceduralShape, build_shape, normalise_to_unit_diagonal
from escape_cli.errors import DatasetError

GENERATORS: dict[str, Callable[[np.random.Generator], tuple[str, list[np.ndarray]]]] = {
    "02691156": airplane.generate,
    "02933112": cabinet.generate,
    "02958343": car.generate,
    "03001627": chair.generate,
    "03636649": lamp.generate,
    "04256520": sofa.generate,
    "04379243": table.generate,
    "04530566": watercraft.generate,
}
"""Synset id -> the function drawing one shape of that category."""

SUBTYPES: dict[str, tuple[str, ...]] = {
    "02691156": airplane.SUBTYPES,
    "02933112": cabinet.SUBTYPES,
    "02958343": car.SUBTYPES,
    "03001627": chair.SUBTYPES,
    "03636649": lamp.SUBTYPES,
    "04256520": sofa.SUBTYPES,
    "04379243": table.SUBTYPES,
    "04530566": watercraft.SUBTYPES,
}


def generate_shape(synset: str, rng: np.random.Generator, detail: np.random.Generator | None = None) -> ProceduralShape:
    """Draw one normalised shape of a category.

    Parameters
    ----------
    synset : str
        One of the 8 PCN synset ids.
    rng : numpy.random.Generator
    detail : numpy.random.Generator or None
        None: generator 1 (convex primitives only). A second stream: generator 2
        (`realism`: rounded edges, hollow shades, rowing boats, shell chairs).

    Returns
    -------
    shape : ProceduralShape
        Bounding box centred at the origin, diagonal 1, y up, front towards +x.
    """
    if synset not in GENERATORS:
        raise DatasetError(f"no procedural generator for synset {synset!r}")
    if detail is None:
        subtype, point_sets = GENERATORS[synset](rng)
    else:
        subtype, point_sets = realism.generate(synset, rng, detail)
    return build_shape(synset, subtype, point_sets)


__all__ = ["GENERATORS", "SUBTYPES", "ProceduralShape", "generate_shape", "normalise_to_unit_diagonal"]
