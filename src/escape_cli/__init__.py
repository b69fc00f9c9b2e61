"""escape: rotation-equivariant completion of partial point clouds (ESCAPE).

    from escape_cli import complete, complete_many
    result = complete(points)   # (N, 3) partial scan -> result.points (16384, 3)
    results = complete_many(clouds)   # one result per scan, the network run on batches of scans
"""

from escape_cli.version import __version__

__all__ = ["complete", "complete_many", "Completion", "__version__"]


def __getattr__(name):  # lazy, so `escape --help` does not import numpy and friends
    if name in ("complete", "complete_many", "Completion"):
        from escape_cli import pipeline

        return getattr(pipeline, name)
    raise AttributeError(name)
