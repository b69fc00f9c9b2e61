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
FIELDLESS_FORMATS = ("npy",)
"""Formats that store the coordinates alone (no per-point fields such as ``residual``)."""
FIELD_FORMATS = tuple(fmt for fmt in FORMATS if fmt not in FIELDLESS_FORMATS)
"""Formats that keep per-point fields, in the order of `FORMATS`."""


def residuals_refusal(fmt: str) -> str:
    """The message for --residuals with an output in `fmt`, one of `FIELDLESS_FORMATS`."""
    return f"--residuals needs an output that keeps fields ({', '.join(FIELD_FORMATS)}); {fmt} holds the coordinates only"

