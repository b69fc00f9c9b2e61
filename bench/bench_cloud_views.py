"""How views of sparse clouds compare with depth renders of the meshes they were sampled from.

For each test mesh (../shared/shapes/test-meshes): 8 depth renders of the mesh against
its 16384 area-uniform points (the reference), and 8 views of a 1024-point cloud sampled
from it (ModelNet's density) against the cloud densified to 16384 points, for several
splat sizes; a splat of ~0 is a plain point z-buffer. Prints the share of the complete
cloud that a view covers (within 2% of the diagonal of a view point), its ratio to the
mesh renders', and how far the densified points lie from the true surface.

    .venv/bin/python bench/bench_cloud_views.py [--meshes spot,cow] [--scales 0.01,0.7,1.0,1.25,1.5]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from escape_cli.core.metrics import chamfer_l1
from escape_cli.data.cloud_views import SplatScanner, SplatSettings, densify, tangent_frames, view_coverage
from escape_cli.data.depth_views import DepthScanner
from escape_cli.data.from_shapes import unit_frame
from escape_cli.data.meshes import read_mesh
from escape_cli.data.surface import sample_triangles

MESHES = Path(__file__).resolve().parents[2] / "shared" / "shapes" / "test-meshes"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="spot,cow,teapot,fandisk,rocker-arm,suzanne")
    parser.add_argument("--scales", default="0.01,0.7,1.0,1.25,1.5")
    parser.add_argument("--views", type=int, default=8)
    args = parser.parse_args()
    import open3d as o3d

    scales = [float(s) for s in args.scales.split(",")]
    rows = {s: [] for s in scales}
    print(f"{'mesh':12s} {'renders':>8s} " + " ".join(f"{'splat ' + str(s):>11s}" for s in scales) + "   fuzz mean/p99  CD dense/source")
    for name in args.meshes.split(","):
        path = next(p for p in MESHES.glob(f"{name}.*"))
        mesh = read_mesh(path)
        centre, diagonal = unit_frame(mesh.vertices[np.unique(mesh.triangles)])
        vertices = (mesh.vertices - centre) / diagonal
        rng = np.random.default_rng(1)
        complete, _ = sample_triangles(vertices, mesh.triangles, 16384, rng)
        renders = DepthScanner(vertices, mesh.triangles).random_views(args.views, rng)
        reference = np.mean([view_coverage(complete, v) for v in renders])
        source = sample_triangles(vertices, mesh.triangles, 1024, np.random.default_rng(7))[0]
        frames = tangent_frames(source)
        cells = []
        for scale in scales:
            settings = replace(SplatSettings(), splat_scale=scale)
            rng = np.random.default_rng(1)
            dense, parent = densify(source, frames, 16384, rng, settings)
            start = time.perf_counter()
            views = SplatScanner(source, frames, dense, parent, settings=settings).random_views(args.views, rng)
            elapsed = (time.perf_counter() - start) / args.views
            coverage = np.mean([view_coverage(dense, v) for v in views])
            rows[scale].append(coverage / reference)
            cells.append(f"{coverage:.3f} x{coverage / reference:.2f}")
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        fuzz = scene.compute_distance(o3d.core.Tensor(dense[1024:].astype(np.float32))).numpy()
        truth = sample_triangles(vertices, mesh.triangles, 16384, np.random.default_rng(99))[0]
        print(f"{name:12s} {reference:8.3f} " + " ".join(f"{c:>11s}" for c in cells)
              + f"   {fuzz.mean():.4f}/{np.percentile(fuzz, 99):.4f}  {1000 * chamfer_l1(dense, truth):.2f}/{1000 * chamfer_l1(source, truth):.2f}"
              + f"  ({1000 * elapsed:.0f} ms a view)")
    print("mean ratio to renders: " + "  ".join(f"splat {s}: x{np.mean(r):.2f}" for s, r in rows.items()))


if __name__ == "__main__":
    main()
