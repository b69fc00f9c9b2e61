"""escape: rotation-equivariant completion of partial point clouds (ESCAPE)."""

__version__ = "0.1.0"
