"""Point-cloud pictures (escape_cli.render_png) and `escape render`."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from cli_runner import run_escape
from typer.testing import CliRunner

from escape_cli.cli.main import app
from escape_cli.errors import PointCloudError
from escape_cli.io import write_array, write_points
from escape_cli.render_png import BACKGROUND, VIEWS, colour_by_value, encode_png, render_clouds


def decode_png(data: bytes) -> np.ndarray:
    """Minimal decoder for the 8-bit RGB, filter-0 PNGs `encode_png` writes; returns (H, W, 3) uint8."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    position, chunks = 8, {}
    while position < len(data):
        (length,) = struct.unpack(">I", data[position:position + 4])
        tag = data[position + 4:position + 8]
        body = data[position + 8:position + 8 + length]
        assert struct.unpack(">I", data[position + 8 + length:position + 12 + length])[0] == zlib.crc32(tag + body)
        chunks[tag] = chunks.get(tag, b"") + body
        position += 12 + length
    width, height, depth, colour_type = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (depth, colour_type) == (8, 2)
    rows = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), dtype=np.uint8).reshape(height, 1 + 3 * width)
    assert np.all(rows[:, 0] == 0)
    return rows[:, 1:].reshape(height, width, 3)


def _sphere(n: int = 2000, seed: int = 0) -> np.ndarray:
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return 0.4 * p / np.linalg.norm(p, axis=1, keepdims=True)


def test_png_round_trip():
    image = np.random.default_rng(0).integers(0, 256, size=(7, 5, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_png(encode_png(image)), image)


def test_render_layout_one_column_per_cloud_one_row_per_view():
    image = render_clouds([_sphere(), _sphere(seed=1)], n_views=3, size=64)
    assert image.shape == (3 * 64 + 2 * 2, 2 * 64 + 2, 3)
    panel = image[:64, :64]
    assert (panel != BACKGROUND).any(axis=2).mean() > 0.2  # the sphere fills a good part of its panel


def test_front_view_looks_along_minus_x():
    # front view: screen right is -z and up is +y, so +z lands left of the centre and +y above it
    for point, (row_sign, col_sign) in (([0, 0, 0.5], (0, -1)), ([0, 0.5, 0], (-1, 0))):
        cloud = np.array([point, np.negative(point)], dtype=float)  # bounding box centred at the origin
        panel = render_clouds([cloud], values=[np.array([1.0, 0.0])], n_views=1, size=65, point_radius=0)
        yellow = (panel[:, :, 0] > 200) & (panel[:, :, 2] < 100)  # the point valued 1
        marked = np.argwhere(yellow) - 32  # (1, 2) row, col from the centre
        assert len(marked) == 1
        assert (np.sign(marked[0, 0]), np.sign(marked[0, 1])) == (row_sign, col_sign)
    assert VIEWS[0].name == "front"


def test_nearer_points_hide_farther_ones_and_are_brighter():
    # front view looks along -x: x = +0.5 is nearest the viewer, x = -0.5 farthest
    cloud = np.array([[0.5, 0, 0], [-0.5, 0, 0], [0, 0.4, 0], [0, -0.4, 0]])
    panel = render_clouds([cloud], n_views=1, size=33, point_radius=0)
    np.testing.assert_array_equal(panel[16, 16], [70, 110, 190])  # the near point, at full brightness
    two_depths = np.array([[0.5, 0, 0.3], [-0.5, 0, -0.3]])  # near one on the left, far one on the right
    panel = render_clouds([two_depths], n_views=1, size=33, point_radius=0)
    drawn = np.argwhere((panel != BACKGROUND).any(axis=2))
    left, right = sorted(map(tuple, drawn), key=lambda rc: rc[1])
    assert panel[left].astype(int).sum() > panel[right].astype(int).sum()


def test_colour_by_value_spans_the_ramp():
    rgb = colour_by_value(np.array([0.0, 0.5, 1.0, np.nan]))
    assert rgb.shape == (4, 3)
    assert rgb[0, 2] > rgb[0, 1] and rgb[2, 0] > 200 and rgb[2, 1] > 200  # purple-ish to yellow
    np.testing.assert_array_equal(rgb[3], [160, 160, 160])


@pytest.mark.parametrize("clouds, kwargs, message", [
    ([], {}, "no clouds"),
    ([np.zeros((5, 2))], {}, "shape"),
    ([np.zeros((5, 3))], {"n_views": 9}, "views"),
    ([np.full((3, 3), np.nan)], {}, "empty"),
    ([np.zeros((5, 3))], {"values": [np.zeros(4)]}, "colour values"),
])
def test_render_rejects_bad_input(clouds, kwargs, message):
    with pytest.raises(PointCloudError, match=message):
        render_clouds(clouds, **kwargs)


# --------------------------------------------------------------------------- the CLI


@pytest.fixture
def clouds(tmp_path) -> tuple[Path, Path]:
    a, b = tmp_path / "a.ply", tmp_path / "b.pcd"
    write_points(a, _sphere(), fields={"height": _sphere()[:, 1]})
    write_points(b, _sphere(500, 1) * [1, 0.5, 1])
    return a, b


def test_cli_render_draws_clouds_side_by_side(tmp_path, clouds):
    out = tmp_path / "pic.png"
    result = CliRunner().invoke(app, ["render", str(clouds[0]), str(clouds[1]), "-o", str(out), "--views", "4", "--size", "96"])
    assert result.exit_code == 0, result.output
    image = decode_png(out.read_bytes())
    assert image.shape == (4 * 96 + 3 * 2, 2 * 96 + 2, 3)


def test_cli_render_colours_by_a_field_or_a_values_file(tmp_path, clouds):
    values = tmp_path / "v.npy"
    write_array(values, np.linspace(0, 1, 2000))
    runner = CliRunner()
    by_field = runner.invoke(app, ["render", str(clouds[0]), "-o", str(tmp_path / "f.png"), "--color-by", "height"])
    by_file = runner.invoke(app, ["render", str(clouds[0]), "-o", str(tmp_path / "n.png"), "--color-by", str(values)])
    assert by_field.exit_code == 0 and by_file.exit_code == 0
    plain = runner.invoke(app, ["render", str(clouds[0]), "-o", str(tmp_path / "p.png")])
    assert plain.exit_code == 0
    coloured, uniform = decode_png((tmp_path / "f.png").read_bytes()), decode_png((tmp_path / "p.png").read_bytes())
    hues = lambda img: len({tuple(c) for c in img.reshape(-1, 3)[::7]})
    assert hues(coloured) > hues(uniform)


def test_cli_render_reads_pcn_files(tmp_path):
    from escape_cli.data.pcn import write_pcd

    write_pcd(tmp_path / "00.pcd", _sphere(300))
    result = run_escape("render", str(tmp_path / "00.pcd"), "-o", str(tmp_path / "x.png"), "--views", "1", "--size", "32")
    assert result.exit_code == 0, result.stderr
    assert decode_png((tmp_path / "x.png").read_bytes()).shape == (32, 32, 3)


@pytest.mark.parametrize("make_args, message", [
    (lambda d, c: [str(d / "missing.ply"), "-o", str(d / "o.png")], "missing.ply"),
    (lambda d, c: [str(c[0]), "-o", str(d / "o.jpg")], "unknown image format '.jpg' for"),
    (lambda d, c: [str(c[0]), "-o", str(c[0].with_suffix(".png")), "--color-by", "nope"], "no field 'nope'"),
    (lambda d, c: [str(c[1]), "-o", str(d / "o.png"), "--color-by", str(d / "v.npy")], "2000 values for 500 points"),
    (lambda d, c: [str(c[0]), "-o", str(d / "exists.png")], "exists"),
])
def test_cli_render_bad_input_is_one_line(tmp_path, clouds, make_args, message):
    write_array(tmp_path / "v.npy", np.zeros(2000))
    (tmp_path / "exists.png").write_bytes(b"x")
    result = run_escape("render", *make_args(tmp_path, clouds))
    assert result.exit_code != 0
    assert len(result.stderr_lines) == 1 and result.stderr_lines[0].startswith("escape: error:"), result.stderr
    assert message in result.stderr
    assert not (tmp_path / "o.png").exists()
