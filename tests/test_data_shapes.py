"""Procedural shapes, convex parts and outer-surface sampling (escape_cli.data.shapes, primitives, surface)."""

from __future__ import annotations

import numpy as np
import pytest

from escape_cli.data.pcn import CATEGORIES
from escape_cli.data.primitives import ConvexPart, box, ellipsoid, frustum
from escape_cli.data.shapes import GENERATORS, SUBTYPES, generate_shape
from escape_cli.data.surface import buried_mask, sample_outer_surface
from escape_cli.errors import DegenerateGeometryError

SYNSETS = sorted(CATEGORIES)


def test_generators_cover_the_8_pcn_categories():
    assert sorted(GENERATORS) == SYNSETS
    assert all(len(SUBTYPES[s]) >= 3 for s in SYNSETS)


@pytest.mark.parametrize("synset", SYNSETS)
def test_shapes_are_normalised_pcn_style(synset):
    for seed in range(3):
        shape = generate_shape(synset, np.random.default_rng(seed))
        lower, upper = shape.bounds()
        np.testing.assert_allclose((lower + upper) / 2, 0, atol=1e-12)
        assert np.linalg.norm(upper - lower) == pytest.approx(1.0, abs=1e-12)
        assert np.all(upper <= 0.5 + 1e-12) and np.all(lower >= -0.5 - 1e-12)


@pytest.mark.parametrize("synset", SYNSETS)
def test_each_category_draws_at_least_three_structural_subtypes(synset):
    seen = set()
    for seed in range(40):
        subtype, _ = GENERATORS[synset](np.random.default_rng(seed))
        seen.add(next(base for base in SUBTYPES[synset] if subtype.startswith(base)))
    assert len(seen) >= 3, f"{CATEGORIES[synset]}: only {sorted(seen)}"


def test_shapes_vary_continuously_within_a_subtype():
    extents = {tuple(np.round(generate_shape("03001627", np.random.default_rng(s)).bounds()[1], 6)) for s in range(10)}
    assert len(extents) == 10


def test_same_seed_same_shape():
    a = generate_shape("02691156", np.random.default_rng(7))
    b = generate_shape("02691156", np.random.default_rng(7))
    assert a.subtype == b.subtype
    for pa, pb in zip(a.parts, b.parts, strict=True):
        np.testing.assert_array_equal(pa.vertices, pb.vertices)


def test_convex_part_inside_test_is_strict():
    part = ConvexPart.from_points(box([0, 0, 0], (2, 2, 2)))
    inside = part.contains_strictly(np.array([[0, 0, 0], [0.99, 0, 0], [1.0, 0, 0], [1.5, 0, 0], [1, 1, 1]]))
    np.testing.assert_array_equal(inside, [True, True, False, False, False])
    assert part.surface_area() == pytest.approx(24.0)


@pytest.mark.parametrize("vertices", [box([0, 0, 0], (1, 2, 3)), frustum([0, 0, 0], [0, 1, 0], 0.5, 0.2),
                                      ellipsoid([1, 2, 3], (0.5, 0.2, 0.3))])
def test_convex_part_triangles_face_outwards(vertices):
    part = ConvexPart.from_points(vertices)
    tri = part.vertices[part.triangles]  # (F, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = tri.mean(axis=1) - part.vertices.mean(axis=0)
    assert np.all(np.einsum("fi,fi->f", normals, outward) > 0)


def test_flat_part_is_rejected():
    with pytest.raises(DegenerateGeometryError):
        ConvexPart.from_points(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))


def test_outer_surface_of_two_overlapping_cubes_is_area_uniform():
    # Cubes [0,2]^3 and [1,3]^3: the union's outer area is 2 * (24 - 3) = 42, the hidden parts of
    # each cube (3 unit squares inside the other) must get no points.
    parts = [ConvexPart.from_points(box([1, 1, 1], (2, 2, 2))), ConvexPart.from_points(box([2, 2, 2], (2, 2, 2)))]
    points = sample_outer_surface(parts, 20000, np.random.default_rng(0))
    assert points.shape == (20000, 3)
    assert not buried_mask(parts, points, np.full(len(points), -1)).any()
    # the face x = 0 of the first cube is 4 units of the 42 visible: 4/42 of the points
    on_face = np.isclose(points[:, 0], 0.0)
    assert on_face.mean() == pytest.approx(4 / 42, abs=0.01)
    # no point in the shared interior region (strictly inside both cubes)
    assert not np.any(np.all((points > 1 + 1e-9) & (points < 2 - 1e-9), axis=1))


@pytest.mark.parametrize("synset", SYNSETS)
def test_complete_points_are_on_the_outer_surface(synset):
    shape = generate_shape(synset, np.random.default_rng(3))
    points = sample_outer_surface(shape.parts, 4096, np.random.default_rng(4))
    assert points.shape == (4096, 3)
    for part in shape.parts:  # no point strictly inside any part, its own included
        assert not part.contains_strictly(points).any()
    # and every point lies on some part's surface
    depth = np.stack([(points @ p.planes[:, :3].T + p.planes[:, 3]).max(axis=1) for p in shape.parts])  # (P, N)
    assert np.abs(depth).min(axis=0).max() < 1e-9


def test_surface_sampling_is_seeded():
    shape = generate_shape("04379243", np.random.default_rng(0))
    a = sample_outer_surface(shape.parts, 1000, np.random.default_rng(1))
    b = sample_outer_surface(shape.parts, 1000, np.random.default_rng(1))
    c = sample_outer_surface(shape.parts, 1000, np.random.default_rng(2))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
