"""The point-cloud file formats escape reads and writes, by name (imports nothing: `--help` lists them).

Each name is also the file extension that selects it; `escape_cli.io` dispatches on
these names, one module per format.
"""

TEXT_FORMATS = ("xyz", "txt", "pts", "csv")
FORMATS = ("ply", "pcd", *TEXT_FORMATS, "npy", "npz", "las", "laz", "h5")
"""Every format `read_points` and `write_points` know, in the order `--help` lists them."""
CLOUD_SUFFIXES = tuple(f".{fmt}" for fmt in FORMATS)
"""File name endings of point-cloud files (what a folder input is searched for)."""
FORMAT_LIST = ", ".join(FORMATS)
