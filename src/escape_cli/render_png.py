"""Pictures of point clouds: orthographic, depth-shaded point splats written as PNG.

Dependency-free (numpy, zlib, struct). Several clouds are drawn side by side, one
column per cloud and one row per view (front, side, top, oblique), all at one common
scale so sizes compare. Points can be coloured by a per-point value.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.errors import PointCloudError

BACKGROUND = (255, 255, 255)
BASE_COLOUR = np.array([70, 110, 190], dtype=np.float64)
SEPARATOR = (215, 215, 215)
_COLOURMAP_STOPS = np.array(  # a viridis-like ramp: dark purple, blue, green, yellow
    [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=np.float64)


@dataclass(frozen=True)
class View:
    """An orthographic view: `right`, `up` and `toward_viewer` are orthonormal (3,) directions."""

    name: str
    right: tuple[float, float, float]
    up: tuple[float, float, float]
    toward_viewer: tuple[float, float, float]

    def matrix(self) -> np.ndarray:
        """Rows right, up, toward-viewer: (3, 3) float64."""
        return np.array([self.right, self.up, self.toward_viewer], dtype=np.float64)


def _oblique(azimuth_deg: float, elevation_deg: float) -> View:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    toward = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    right = np.cross([0.0, 1.0, 0.0], toward)
    right /= np.linalg.norm(right)
    up = np.cross(toward, right)
    return View("oblique", tuple(right), tuple(up), tuple(toward))


VIEWS: tuple[View, ...] = (
    View("front", (0, 0, -1), (0, 1, 0), (1, 0, 0)),
    View("side", (1, 0, 0), (0, 1, 0), (0, 0, 1)),
    View("top", (0, 0, -1), (-1, 0, 0), (0, 1, 0)),
    _oblique(35.0, 25.0),
)
"""Fixed views in the order `--views N` takes them (y up, front towards +x)."""


def colour_by_value(values: np.ndarray) -> np.ndarray:
    """Map values to RGB with a viridis-like ramp, min-max scaled (non-finite -> grey).

    Parameters
    ----------
    values : (N,) float

    Returns
    -------
    rgb : (N, 3) float64 in [0, 255]
    """
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    rgb = np.full((len(values), 3), 160.0)
    if finite.any():
        lo, hi = values[finite].min(), values[finite].max()
        t = (values[finite] - lo) / (hi - lo) if hi > lo else np.zeros(finite.sum())
        pos = t * (len(_COLOURMAP_STOPS) - 1)
        i = np.minimum(pos.astype(int), len(_COLOURMAP_STOPS) - 2)
        frac = (pos - i)[:, None]
        rgb[finite] = _COLOURMAP_STOPS[i] * (1 - frac) + _COLOURMAP_STOPS[i + 1] * frac
    return rgb


def _splat_offsets(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    dy, dx = np.meshgrid(r, r, indexing="ij")
    keep = dx**2 + dy**2 <= radius**2 + radius
    return np.column_stack([dy[keep], dx[keep]])


def draw_view(points: np.ndarray, colours: np.ndarray, view: View, centre: np.ndarray, half_extent: float,
              size: int, point_radius: int = 1) -> np.ndarray:
    """Rasterise one orthographic view of a cloud with a z-buffer.

    Parameters
    ----------
    points : (N, 3) float64
    colours : (N, 3) float64
        Base colour per point; shaded darker with distance from the viewer.
    view : View
    centre : (3,) float64
        World point at the image centre.
    half_extent : float
        World distance from the image centre to its edge.
    size : int
        Image side in pixels.
    point_radius : int
        Splat radius in pixels.

    Returns
    -------
    image : (size, size, 3) uint8
    """
    image = np.empty((size, size, 3), dtype=np.uint8)
    image[:] = BACKGROUND
    if len(points) == 0:
        return image
    coords = (points - centre) @ view.matrix().T  # (N, 3): right, up, toward viewer
    scale = (size / 2 - point_radius - 1) / half_extent
    col = np.round(size / 2 + coords[:, 0] * scale).astype(np.int64)
    row = np.round(size / 2 - coords[:, 1] * scale).astype(np.int64)
    depth = coords[:, 2]
    span = depth.max() - depth.min()
    nearness = (depth - depth.min()) / span if span > 0 else np.ones(len(depth))
    shaded = colours * (0.35 + 0.65 * nearness)[:, None]
    offsets = _splat_offsets(point_radius)  # (S, 2)
    rows = (row[:, None] + offsets[None, :, 0]).reshape(-1)
    cols = (col[:, None] + offsets[None, :, 1]).reshape(-1)
    owner = np.repeat(np.arange(len(points)), len(offsets))
    inside = (rows >= 0) & (rows < size) & (cols >= 0) & (cols < size)
    rows, cols, owner = rows[inside], cols[inside], owner[inside]
    pixel = rows * size + cols
    order = np.lexsort((-depth[owner], pixel))  # per pixel, the nearest point first
    pixel, owner = pixel[order], owner[order]
    first = np.concatenate([[True], pixel[1:] != pixel[:-1]])
    flat = image.reshape(-1, 3)
    flat[pixel[first]] = np.clip(shaded[owner[first]], 0, 255).astype(np.uint8)
    return image


def render_clouds(clouds: Sequence[np.ndarray], values: Sequence[np.ndarray | None] | None = None,
                  n_views: int = 3, size: int = 256, point_radius: int | None = None) -> np.ndarray:
    """Draw clouds side by side (one column each), in `n_views` fixed views (one row each).

    Parameters
    ----------
    clouds : sequence of (N_i, 3) float
    values : sequence of (N_i,) float or None, optional
        Per-point values to colour each cloud by.
    n_views : int
        How many of `VIEWS` to draw (1-4).
    size : int
        Side of each panel in pixels.
    point_radius : int, optional
        Splat radius; default grows with `size`.

    Returns
    -------
    image : (n_views * size + gaps, len(clouds) * size + gaps, 3) uint8
    """
    if not clouds:
        raise PointCloudError("nothing to render: no clouds given")
    if not 1 <= n_views <= len(VIEWS):
        raise PointCloudError(f"--views must be between 1 and {len(VIEWS)}, got {n_views}")
    if size < 16:
        raise PointCloudError(f"panel size must be at least 16 pixels, got {size}")
    values = list(values) if values is not None else [None] * len(clouds)
    arrays = []
    for i, cloud in enumerate(clouds):
        raw = np.asarray(cloud)
        if raw.ndim == 2 and raw.dtype.kind == "f":
            raw = raw[np.isfinite(raw).all(axis=1)]  # organised scans: NaN rows are not drawn
        arrays.append(as_points(raw, f"cloud {i}", min_points=0))
    non_empty = [c for c in arrays if len(c)]
    if not non_empty:
        raise PointCloudError("nothing to render: every cloud is empty")
    half_extent = max(float(np.linalg.norm(c.max(0) - c.min(0))) for c in non_empty) / 2 or 1.0
    radius = point_radius if point_radius is not None else max(1, size // 256)
    gap = 2
    height = n_views * size + (n_views - 1) * gap
    width = len(arrays) * size + (len(arrays) - 1) * gap
    canvas = np.empty((height, width, 3), dtype=np.uint8)
    canvas[:] = SEPARATOR
    for j, (cloud, value) in enumerate(zip(arrays, values)):
        if value is not None:
            value = np.asarray(value, dtype=np.float64).reshape(-1)
            if len(value) != len(cloud):
                raise PointCloudError(f"cloud {j} has {len(cloud)} points but {len(value)} colour values")
            colours = colour_by_value(value)
        else:
            colours = np.tile(BASE_COLOUR, (len(cloud), 1))
        centre = (cloud.min(0) + cloud.max(0)) / 2 if len(cloud) else np.zeros(3)
        for i, view in enumerate(VIEWS[:n_views]):
            panel = draw_view(cloud, colours, view, centre, half_extent, size, radius)
            canvas[i * (size + gap): i * (size + gap) + size, j * (size + gap): j * (size + gap) + size] = panel
    return canvas


def encode_png(image: np.ndarray) -> bytes:
    """Encode an RGB image as PNG bytes.

    Parameters
    ----------
    image : (H, W, 3) uint8
    """
    image = np.ascontiguousarray(image, dtype=np.uint8)
    if image.ndim != 3 or image.shape[2] != 3:
        raise PointCloudError(f"image must have shape (H, W, 3), got {image.shape}")
    height, width = image.shape[:2]
    raw = np.concatenate([np.zeros((height, 1), dtype=np.uint8), image.reshape(height, -1)], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) uint8 image to `path` as PNG."""
    Path(path).write_bytes(encode_png(image))
