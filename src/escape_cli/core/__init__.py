"""The numeric core: pure functions on arrays (numpy and scipy only; no files, no printing).

Letter legend for shapes: B batch, N input points, M output points, K anchors.
"""
