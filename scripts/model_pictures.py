"""The model card's picture: real partial scans beside their completions by one or more models.

Usage: `.venv/bin/python scripts/model_pictures.py -o models/escape-small.demo.png --model synth --model small`

One row pair per scan (a side and an oblique view, as `escape render` draws them), one
column for the scan and one per model, in the order given. The scans are the real
partials in ../shared/realdata (the PCN and PoinTr demo inputs and KITTI LiDAR cars):
shown, never trained or tuned on. Default options, as `escape complete` runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from escape_cli.inference import load_model
from escape_cli.io import read_points
from escape_cli.pipeline import complete
from escape_cli.render_png import SEPARATOR, render_clouds, write_png

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
SCANS = [
    "pcn_demo/airplane.pcd", "pcn_demo/car.pcd", "pcn_demo/chair.pcd", "pcn_demo/lamp.pcd",
    "pointr_demo/airplane.pcd", "pointr_demo/sofa.pcd", "pointr_demo/input.ply",
    "kitti_cars/cars/frame_8_car_0.pcd", "kitti_cars/cars/frame_8_car_1.pcd", "kitti_cars/cars/frame_8_car_3.pcd",
]
VIEW_ROWS = (1, 3)  # side and oblique of render_png.VIEWS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--out", required=True, help="PNG to write")
    parser.add_argument("--model", action="append", required=True, help="packaged model name or .onnx (repeatable)")
    parser.add_argument("--size", type=int, default=150, help="panel side in pixels")
    args = parser.parse_args()

    nets = [load_model(name) for name in args.model]
    rows = []
    for scan in SCANS:
        partial = read_points(REALDATA / scan)
        clouds = [partial] + [complete(partial, net).points for net in nets]
        image = render_clouds(clouds, n_views=4, size=args.size)
        step = args.size + 2
        rows += [image[i * step: i * step + args.size] for i in VIEW_ROWS]
        print(f"{scan}: {len(partial)} points")
    gap = np.empty((4, rows[0].shape[1], 3), dtype=np.uint8)
    gap[:] = SEPARATOR
    stacked = [part for row in rows for part in (row, gap)][:-1]
    write_png(args.out, np.concatenate(stacked))
    print(f"columns: scan, {', '.join(args.model)}; wrote {args.out}")


if __name__ == "__main__":
    main()
