"""Partial clouds the PCN way: pinhole depth renders of a mesh, back-projected to 3D.

Rays are cast on the CPU with open3d's `RaycastingScene`; every pixel that hits the
mesh gives the 3D hit point in the object's own frame (not re-centred), so the
partial lies exactly on the visible part of the surface and self-occlusion is real.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from escape_cli.errors import DegenerateGeometryError


@dataclass(frozen=True)
class DepthCamera:
    """Pinhole camera and view sampling for partial scans.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    fov_deg : float
        Horizontal field of view.
    distance_range : (float, float)
        Camera distance from the origin (the object's bounding-box centre), drawn uniformly.
    min_points : int
        Views with fewer hits are redrawn.
    max_attempts : int
        Redraws per view before giving up.
    """

    width: int = 160
    height: int = 120
    fov_deg: float = 60.0
    distance_range: tuple[float, float] = (1.3, 1.9)
    min_points: int = 256
    max_attempts: int = 50


def random_view_direction(rng: np.random.Generator) -> np.ndarray:
    """A direction drawn uniformly on the unit sphere; returns (3,) float64."""
    while True:
        v = rng.normal(size=3)
        norm = np.linalg.norm(v)
        if norm > 1e-6:
            return v / norm


def draw_viewpoint(rng: np.random.Generator, camera: DepthCamera) -> tuple[np.ndarray, np.ndarray]:
    """A random camera position looking at the origin, and its approximate up; two (3,) float64.

    The draws (direction, then distance) are the ones every dataset generator has made
    since generator 1, so its files stay byte for byte the same.
    """
    direction = random_view_direction(rng)
    distance = rng.uniform(*camera.distance_range)
    up = np.array([0.0, 1.0, 0.0]) if abs(direction[1]) < 0.95 else np.array([1.0, 0.0, 0.0])
    return direction * distance, up


def views_from_random_viewpoints(scan, camera: DepthCamera, n_views: int, rng: np.random.Generator) -> list[np.ndarray]:
    """`n_views` results of ``scan(eye, up)`` from viewpoints drawn by `draw_viewpoint`, each redrawn until it shows enough points.

    A view with fewer than `camera.min_points` points is drawn again, up to
    `camera.max_attempts` times; then DegenerateGeometryError.
    """
    views = []
    for _ in range(n_views):
        for _attempt in range(camera.max_attempts):
            eye, up = draw_viewpoint(rng, camera)
            points = scan(eye, up)
            if len(points) >= camera.min_points:
                views.append(points)
                break
        else:
            raise DegenerateGeometryError(
                f"no view with at least {camera.min_points} points after {camera.max_attempts} attempts")
    return views


class DepthScanner:
    """Casts pinhole depth views of one triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float64
    triangles : (F, 3) int64
    camera : DepthCamera
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, camera: DepthCamera = DepthCamera()):
        from escape_cli.extras import require

        o3d = require("open3d", "rendering depth views (escape dataset synth)")
        self.camera = camera
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
        )

    def scan(self, eye: np.ndarray, up: np.ndarray) -> np.ndarray:
        """Back-projected hits of one view looking from `eye` at the origin.

        Parameters
        ----------
        eye : (3,) float64
        up : (3,) float64
            Approximate camera up (must not be parallel to `eye`).

        Returns
        -------
        points : (H, 3) float64
            One point per pixel that hits the mesh, in the object's frame.
        """
        cam = self.camera
        rays = self._scene.create_rays_pinhole(
            fov_deg=cam.fov_deg, center=[0.0, 0.0, 0.0], eye=[float(e) for e in eye],
            up=[float(u) for u in up], width_px=cam.width, height_px=cam.height,
        )
        t_hit = self._scene.cast_rays(rays)["t_hit"].numpy().reshape(-1)  # (H*W,)
        rays_np = rays.numpy().reshape(-1, 6).astype(np.float64)
        hit = np.isfinite(t_hit)
        return rays_np[hit, :3] + t_hit[hit, None].astype(np.float64) * rays_np[hit, 3:]

    def random_views(self, n_views: int, rng: np.random.Generator) -> list[np.ndarray]:
        """`n_views` partial clouds from random viewpoints on a sphere around the object.

        Parameters
        ----------
        n_views : int
        rng : numpy.random.Generator

        Returns
        -------
        views : list of (H_i, 3) float64
            Each has at least `camera.min_points` points.

        Raises
        ------
        DegenerateGeometryError
            When a view keeps showing fewer than `camera.min_points` points.
        """
        return views_from_random_viewpoints(self.scan, self.camera, n_views, rng)
