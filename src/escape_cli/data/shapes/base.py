"""The procedural shape type and the PCN normalisation shared by every category.

Normalisation (the ShapeNet/PCN convention): the axis-aligned bounding box of the
whole shape is centred at the origin and the shape is scaled so that the box
diagonal has length 1; every shape then fits inside [-0.5, 0.5]^3.
Canonical frame: y up, the object's front (a chair's seat edge, a car's nose, a
cabinet's doors) faces +x.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from escape_cli.data.primitives import ConvexPart
from escape_cli.errors import DegenerateGeometryError


@dataclass(frozen=True, eq=False)
class ProceduralShape:
    """A normalised union of convex parts.

    Attributes
    ----------
    synset : str
        ShapeNet synset id of the category.
    subtype : str
        Structural variant within the category (e.g. "swivel", "pickup").
    parts : tuple of ConvexPart
        The solids whose union is the shape.
    """

    synset: str
    subtype: str
    parts: tuple[ConvexPart, ...]

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """All parts' triangles in one (overlapping, non-manifold) triangle soup.

        Returns
        -------
        vertices : (V, 3) float64
        triangles : (F, 3) int64
        """
        vertices, triangles, offset = [], [], 0
        for part in self.parts:
            vertices.append(part.vertices)
            triangles.append(part.triangles + offset)
            offset += len(part.vertices)
        return np.concatenate(vertices), np.concatenate(triangles)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box `(lower, upper)`, each (3,) float64."""
        return (
            np.min([p.lower for p in self.parts], axis=0),
            np.max([p.upper for p in self.parts], axis=0),
        )


def normalise_to_unit_diagonal(point_sets: list[np.ndarray]) -> list[np.ndarray]:
    """Centre the joint bounding box at the origin and scale its diagonal to 1.

    Parameters
    ----------
    point_sets : list of (V_i, 3) float64
        Vertices of each part.

    Returns
    -------
    normalised : list of (V_i, 3) float64
    """
    stacked = np.concatenate(point_sets)
    lower, upper = stacked.min(axis=0), stacked.max(axis=0)
    diagonal = float(np.linalg.norm(upper - lower))
    if diagonal <= 0:
        raise DegenerateGeometryError("shape has zero extent")
    centre = (lower + upper) / 2
    return [(p - centre) / diagonal for p in point_sets]


def build_shape(synset: str, subtype: str, point_sets: list[np.ndarray]) -> ProceduralShape:
    """Normalise the parts' vertices and turn each into a `ConvexPart`."""
    parts = tuple(ConvexPart.from_points(p) for p in normalise_to_unit_diagonal(point_sets))
    return ProceduralShape(synset, subtype, parts)


ShapeBuilder = Callable[[np.random.Generator], tuple[str, list[np.ndarray]]]


def draw_subtype(rng: np.random.Generator, builders: Sequence[ShapeBuilder], weights: Sequence[float]):
    """Pick one sub-type builder with the given probabilities and run it.

    Returns
    -------
    subtype : str
    point_sets : list of (V_i, 3) float64
        Vertices of each convex part.
    """
    return builders[rng.choice(len(builders), p=weights)](rng)
