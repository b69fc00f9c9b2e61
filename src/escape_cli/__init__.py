"""escape: rotation-equivariant completion of partial point clouds (ESCAPE).

    from escape_cli import complete
    result = complete(points)   # (N, 3) partial scan -> result.points (16384, 3)
"""

from escape_cli.version import __version__

__all__ = ["complete", "Completion", "__version__"]


def __getattr__(name):  # lazy, so `escape --help` does not import numpy and friends
    if name in ("complete", "Completion"):
        from escape_cli import pipeline

        return getattr(pipeline, name)
    raise AttributeError(name)
