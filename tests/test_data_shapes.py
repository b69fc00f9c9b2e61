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


def _generator_2(synset: str, seed: int):
    return generate_shape(synset, np.random.default_rng(seed), np.random.default_rng(10_000 + seed))


@pytest.mark.parametrize("synset", SYNSETS)
def test_generator_2_shapes_are_normalised_with_outer_surface_points(synset):
    for seed in range(4):
        shape = _generator_2(synset, seed)
        lower, upper = shape.bounds()
        np.testing.assert_allclose((lower + upper) / 2, 0.0, atol=1e-9)
        assert np.linalg.norm(upper - lower) == pytest.approx(1.0)
        points = sample_outer_surface(shape.parts, 2048, np.random.default_rng(seed))
        for part in shape.parts:
            assert not part.contains_strictly(points).any()


def test_generator_2_adds_hollow_and_rounded_subtypes():
    boats = {_generator_2("04530566", s).subtype for s in range(40)}
    chairs = {_generator_2("03001627", s).subtype for s in range(40)}
    lamps = {_generator_2("03636649", s).subtype for s in range(20)}
    cars = [_generator_2("02958343", s).subtype for s in range(20)]
    assert {"rowboat", "rowboat_canoe"} & boats and {"shell_legs", "shell_pedestal"} & chairs
    assert any(s.endswith("_open") for s in lamps)
    assert sum(s.endswith("_rounded") for s in cars) >= 10


def test_rounding_keeps_the_box_and_rounds_the_corners():
    from escape_cli.data.primitives import rounded

    corners = box([0, 0, 0], (1.0, 0.5, 0.2))
    part = ConvexPart.from_points(rounded(corners, 0.05))
    np.testing.assert_allclose(part.lower, [-0.5, -0.25, -0.1])
    np.testing.assert_allclose(part.upper, [0.5, 0.25, 0.1])
    assert not part.contains_strictly(np.array([[0.499, 0.249, 0.099]]))[0]  # the corner is cut away
    assert part.contains_strictly(np.array([[0.45, 0.2, 0.05]]))[0]


def test_open_shell_has_no_buried_shared_faces():
    """A thin drum shell: sampled points lie on its inner or outer wall, never between its slabs."""
    from escape_cli.data.primitives import grid_shell, revolved_grid

    slabs = [ConvexPart.from_points(s) for s in grid_shell(revolved_grid([0.2, 0.2], [0.0, 0.3], 24), 0.01)]
    points = sample_outer_surface(slabs, 4000, np.random.default_rng(0))
    radius = np.linalg.norm(points[:, [0, 2]], axis=1)
    on_wall = (np.abs(radius - 0.2) < 0.004) | (np.abs(radius - 0.19) < 0.004)  # outer / inner (polygonal) wall
    on_rim = (points[:, 1] < 1e-6) | (points[:, 1] > 0.3 - 1e-6)
    assert (on_wall | on_rim).mean() > 0.97
    assert ((radius > 0.197) | (radius < 0.192)).mean() > 0.97  # next to nothing inside the wall
