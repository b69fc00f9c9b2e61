"""Deterministic farthest point sampling and the fixed-size network input.

Everything here is equivariant: the chosen indices do not change when the cloud is
rotated, translated or permuted (up to exact ties, which are broken by an equivariant
rule first and by index only when the geometry itself is symmetric).
"""

from __future__ import annotations

import numpy as np

from escape_cli.core.checks import as_points, as_rows
from escape_cli.core.params import as_count
from escape_cli.errors import DegenerateGeometryError, PointCloudError

try:  # built with the package where a C compiler was found (setup.py)
    from escape_cli.core import _kernels
except ImportError:  # pragma: no cover - a build without it uses the numpy path
    _kernels = None

# Values within this relative tolerance of the best are treated as tied.
TIE_RTOL = 1e-9


def power_of_two_unit(points) -> float:
    """2**-e for the exponent e of the largest |coordinate| (1 for an all-zero cloud), within 2**±1000.

    Multiplying by it is exact (a power of two), so results computed on the scaled
    points are those computed on the points, bit for bit, except that squares and
    sums of squares can neither underflow (a cloud 1e-300 across) nor overflow.
    """
    points = as_points(points, "points", min_points=0)
    largest = float(np.abs(points).max()) if len(points) else 0.0
    if largest == 0.0:
        return 1.0
    exponent = -int(np.frexp(largest)[1])
    return float(np.ldexp(1.0, min(max(exponent, -1000), 1000)))  # 2**1074 would overflow (subnormal clouds)


def farthest_from_centroid(points: np.ndarray) -> int:
    """Index of the point farthest from the centroid (ties: lowest index).

    Parameters
    ----------
    points : (N, 3) float64
    """
    points = as_points(points, "points", min_points=1)
    radius = np.linalg.norm(points - points.mean(axis=0), axis=1)  # (N,)
    return int(np.flatnonzero(radius >= radius.max() * (1.0 - TIE_RTOL))[0])


def farthest_point_sampling(points, count: int, start: int | None = None) -> np.ndarray:
    """Deterministic farthest point sampling.

    The first point is the one farthest from the centroid (or `start`); each next point
    is the one farthest from those chosen. Near-ties are broken by the larger distance
    to the centroid, then by index, so the result is rotation, translation and
    permutation invariant for any cloud without exact symmetries.

    The same indices in the same order as `farthest_point_sampling_naive` (the distances
    are computed with the same floating-point operations and compared with the same
    rule); it is faster because it touches only the points a new choice can change:
    in compiled code (`_kernels.c`) where the package was built with it, else in numpy,
    making many choices per round of array operations (`_fps_blocked`).

    Parameters
    ----------
    points : (N, 3) float64
    count : number of points to choose, at most the number of distinct points.
    start : index of the first point, or None for the point farthest from the centroid.

    Returns
    -------
    indices : (count,) int64, in the order chosen.
    """
    pts = as_points(points)
    n = len(pts)
    if count > n:
        raise PointCloudError(f"cannot choose {count} points from a cloud of {n}")
    pts = pts * power_of_two_unit(pts)  # the same choices, at any scale (no squared distance underflows)
    if _kernels is not None:
        return _fps_compiled(pts, count, start)
    if count <= _LOOP_COUNT or n <= _LOOP_POINTS:  # a few choices (anchors) or a tiny cloud: the plain loop
        return farthest_point_sampling_naive(pts, count, start)
    return _fps_blocked(pts, count, start)


def _fps_compiled(pts: np.ndarray, count: int, start: int | None) -> np.ndarray:
    """`farthest_point_sampling` by the compiled kernel, the points in Morton-ordered blocks of 16."""
    n = len(pts)
    radius = np.linalg.norm(pts - pts.mean(axis=0), axis=1)  # (N,) the tie-break, as the naive loop
    first = farthest_from_centroid(pts) if start is None else int(start)
    order = _slot_order(pts, _BLOCK)  # (S,)
    where = np.empty(n, dtype=np.int64)
    where[order[:n]] = np.arange(n)
    chosen = np.empty(count, dtype=np.int64)
    made = _kernels.fps(np.ascontiguousarray(pts[order]), order, radius, n, int(where[first]), chosen)
    if made < count:
        raise DegenerateGeometryError(f"the cloud has only {made} distinct points; {count} are needed")
    return chosen


def farthest_point_sampling_naive(points, count: int, start: int | None = None) -> np.ndarray:
    """Reference for `farthest_point_sampling`: one pass over every point per choice.

    Parameters and result as `farthest_point_sampling`.
    """
    pts = as_points(points)
    n = len(pts)
    if count > n:
        raise PointCloudError(f"cannot choose {count} points from a cloud of {n}")
    radius = np.linalg.norm(pts - pts.mean(axis=0), axis=1)  # (N,)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = farthest_from_centroid(pts) if start is None else start
    min_dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)  # (N,)
    for i in range(1, count):
        best = min_dist.max()
        if best <= 0.0:
            raise DegenerateGeometryError(f"the cloud has only {i} distinct points; {count} are needed")
        tied = np.flatnonzero(min_dist >= best * (1.0 - TIE_RTOL))
        nxt = tied[0] if len(tied) == 1 else tied[np.argmax(radius[tied])]
        chosen[i] = nxt
        np.minimum(min_dist, np.linalg.norm(pts - pts[nxt], axis=1), out=min_dist)
    return chosen


# ------------------------------------------------------------------ blocked FPS
#
# `_fps_blocked` keeps, like the naive loop, every point's distance to the chosen set,
# but stored squared, in spatial blocks, and it makes its choices in rounds:
#
# 1. Candidates: the T points with the largest distances (argpartition); every other
#    point is at most tau (the largest distance outside), and distances only shrink.
# 2. Within the candidates, plain FPS (their pairwise distances in one T x T matrix)
#    for as long as the best candidate beats tau by more than the tie tolerance: then
#    no other point can be the farthest or tie with it, so each choice is the naive
#    loop's. Near-ties are checked for all choices of a round at once afterwards
#    (`_choose_among`), and the tie rule applied where one occurred.
# 3. Update: the round's choices against the blocks they can reach (a block whose
#    bounding sphere is farther from a choice than the block's largest distance cannot
#    change), blocks grouped in super-blocks so that a round tests few groups.
#
# Distances are the naive loop's floating-point operations, ((dx^2 + dy^2) + dz^2) and
# then sqrt, and a minimum is exact in any order, so every compared value is the same
# float as in the naive loop. Blocks are runs of the Morton (Z-order) curve: they only
# decide which work is skipped, never a result, so they need not be equivariant.

_LOOP_COUNT = 32  # at most this many choices: the plain loop (no set-up)
_LOOP_POINTS = 256  # clouds this small: the plain loop
_BLOCK = 16  # points per block
_GROUP = 16  # blocks per super-block
_FLAT_BLOCKS = 512  # up to this many blocks no super-blocks are used
_CANDIDATES = 128  # candidates per round (T)
_CHUNK = 32  # picks made before their ties are checked together
_RESTARTS = 4  # ties found in one round before every pick is checked as it is made
_DENSE_ROWS = 512  # candidate sets up to this size get the full T x T matrix; larger ones rows on demand


def _morton_order(pts: np.ndarray) -> np.ndarray:
    """(N,) a permutation that puts the points along a Z-order curve of a 1024^3 grid."""
    lo = pts.min(axis=0)
    extent = float((pts.max(axis=0) - lo).max())
    scale = 1023.0 / extent if extent > 0 else 0.0
    cells = np.minimum((pts - lo) * scale, 1023.0).astype(np.uint64)  # (N, 3)
    code = np.zeros(len(pts), dtype=np.uint64)
    for axis in range(3):  # spread the 10 bits of each axis three apart, then interleave
        v = cells[:, axis]
        v = (v | (v << np.uint64(16))) & np.uint64(0x030000FF)
        v = (v | (v << np.uint64(8))) & np.uint64(0x0300F00F)
        v = (v | (v << np.uint64(4))) & np.uint64(0x030C30C3)
        v = (v | (v << np.uint64(2))) & np.uint64(0x09249249)
        code |= v << np.uint64(axis)
    return np.argsort(code, kind="stable")


def _slot_order(pts: np.ndarray, multiple: int) -> np.ndarray:
    """(S,) int64 slot -> point: the Morton order, padded to a multiple of `multiple` by repeating its last point."""
    curve = _morton_order(pts)  # (N,)
    slots = -(-len(pts) // multiple) * multiple
    return np.concatenate([curve, np.full(slots - len(pts), curve[-1])]).astype(np.int64)


def _spheres(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres of rows of points: centres (R, 3) and radii (R,)."""
    centre = np.stack([x.mean(axis=1), y.mean(axis=1), z.mean(axis=1)], axis=1)  # (R, 3)
    reach = np.sqrt((x - centre[:, :1]) ** 2 + (y - centre[:, 1:2]) ** 2 + (z - centre[:, 2:]) ** 2)  # (R, L)
    return centre, reach.max(axis=1)


def _gaps(centre: np.ndarray, radius: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(R, Q) lower bounds of the distance from each query q to any point of each sphere."""
    d = np.sqrt((centre[:, :1] - q[:, 0]) ** 2 + (centre[:, 1:2] - q[:, 1]) ** 2 + (centre[:, 2:] - q[:, 2]) ** 2)
    return d - radius[:, None]


def _fps_blocked(pts: np.ndarray, count: int, start: int | None) -> np.ndarray:
    """`farthest_point_sampling` by rounds over spatial blocks (see the comment above)."""
    n = len(pts)
    radius = np.linalg.norm(pts - pts.mean(axis=0), axis=1)  # (N,) the tie-break, as the naive loop
    first = farthest_from_centroid(pts) if start is None else int(start)

    span = _BLOCK * _GROUP
    order = _slot_order(pts, span)  # (S,)
    slots = len(order)
    blocks = slots // _BLOCK
    coords = pts[order]  # (S, 3); pads repeat the curve's last point, with distance -1: never chosen
    xs, ys, zs = (np.ascontiguousarray(coords[:, c]) for c in range(3))  # (S,) each
    x, y, z = xs.reshape(blocks, _BLOCK), ys.reshape(blocks, _BLOCK), zs.reshape(blocks, _BLOCK)
    b_centre, b_radius = _spheres(x, y, z)  # (B, 3), (B,)
    groups = blocks // _GROUP
    g_centre, g_radius = _spheres(xs.reshape(groups, span), ys.reshape(groups, span), zs.reshape(groups, span))

    p0 = pts[first]
    dist2 = ((x - p0[0]) ** 2 + (y - p0[1]) ** 2) + (z - p0[2]) ** 2  # (B, L) squared distance to the chosen set
    flat = dist2.reshape(-1)  # (S,) a view
    flat[n:] = -1.0  # pads: never candidates (a minimum keeps them at -1)
    b_max = dist2.max(axis=1)  # (B,)
    slack = 1e-9 * (float(np.abs(pts).max()) + float(g_radius.max()) + 1e-300)  # rounding margin of the bounds

    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = first
    done = 1
    size = min(_CANDIDATES, n)
    while done < count:
        cand, tau2 = _candidates(flat, n, size)
        best = float(np.sqrt(flat[cand].max()))
        if best <= 0.0:
            raise DegenerateGeometryError(f"the cloud has only {done} distinct points; {count} are needed")
        tau = float(np.sqrt(tau2)) if tau2 >= 0 else -1.0
        if tau >= best * (1.0 - TIE_RTOL):  # points outside tie with the best: take them in too
            cand, tau = _with_ties(flat, cand, best)
        picks = _choose_among(cand, xs, ys, zs, np.sqrt(flat[cand]), tau, count - done, order, radius)
        sel = cand[picks]  # (b,) slots chosen this round, in order
        chosen[done:done + len(sel)] = order[sel]
        done += len(sel)
        if done < count:
            _update(dist2, b_max, x, y, z, b_centre, b_radius, g_centre, g_radius, coords[sel], slack)
    return chosen


def _candidates(flat: np.ndarray, n: int, size: int) -> tuple[np.ndarray, float]:
    """The `size` slots with the largest squared distances, and the largest one outside them (-1: none)."""
    if size >= n:
        return np.flatnonzero(flat >= 0.0), -1.0
    part = np.argpartition(flat, len(flat) - size - 1)
    return part[len(flat) - size:], float(flat[part[len(flat) - size - 1]])


def _with_ties(flat: np.ndarray, cand: np.ndarray, best: float) -> tuple[np.ndarray, float]:
    """Candidates grown by every slot tied with the best, and the new bound outside them."""
    inside = np.zeros(len(flat), dtype=bool)
    inside[cand] = True
    inside |= np.sqrt(np.maximum(flat, 0.0)) >= best * (1.0 - TIE_RTOL)
    inside &= flat >= 0.0
    outside = flat[~inside]
    tau2 = float(outside.max()) if outside.size else -1.0
    return np.flatnonzero(inside), (float(np.sqrt(tau2)) if tau2 >= 0 else -1.0)


def _choose_among(cand, xs, ys, zs, dist, tau: float, room: int, order, radius) -> list[int]:
    """Plain FPS inside the candidate set while no point outside can win or tie.

    Parameters
    ----------
    cand : (T,) slots of the candidates.
    xs, ys, zs : (S,) coordinates by slot.
    dist : (T,) the candidates' distances to the chosen set (exact; modified).
    tau : every other point's distance is at most this.
    room : choices still to make.
    order : (S,) slot -> point index; radius : (N,) the tie-break.

    Returns
    -------
    picks : positions in `cand`, in the order chosen.
    """
    cx, cy, cz = xs[cand], ys[cand], zs[cand]
    if len(cand) <= _DENSE_ROWS:
        table = np.sqrt(((cx[:, None] - cx) ** 2 + (cy[:, None] - cy) ** 2) + (cz[:, None] - cz) ** 2)  # (T, T)

        def rows(js):
            return table[js]
    else:
        def rows(js):  # (len(js), T) on demand
            js = np.asarray(js)
            return np.sqrt(((cx - cx[js, None]) ** 2 + (cy - cy[js, None]) ** 2) + (cz - cz[js, None]) ** 2)

    def tie_break(tied):  # the naive rule: larger distance to the centroid, then lower index
        who = order[cand[tied]]
        rank = np.argsort(who)
        return int(tied[rank][np.argmax(radius[who[rank]])])

    keep = 1.0 - TIE_RTOL
    picks: list[int] = []
    restarts = 0
    while len(picks) < room:
        first = len(picks)
        checked = dist.copy()  # the distances before the first pick of this run
        careful = restarts > _RESTARTS  # many ties (grid-like clouds): check every pick as it is made
        stop = room if careful else min(room, first + _CHUNK)
        while len(picks) < stop:
            j = int(dist.argmax())
            best = float(dist[j])
            if tau >= best * keep or best <= 0.0:
                break
            if careful:
                tied = np.flatnonzero(dist >= best * keep)
                if len(tied) > 1:
                    j = tie_break(tied)
            picks.append(j)
            np.minimum(dist, rows(j), out=dist)
        new = picks[first:]
        if careful or not new:
            break
        if len(new) < _CHUNK:  # the round ends after this run (or the count is reached)
            stop = -1
        # the distances before each pick of the run: was a pick within the tie tolerance of another point?
        before = np.minimum.accumulate(np.vstack([checked[None], rows(new[:-1])]), axis=0)  # (b, T)
        mine = before[np.arange(len(new)), new]  # (b,)
        ties = np.count_nonzero(before >= (mine * keep)[:, None], axis=1) > 1  # (b,)
        if not ties.any():
            if stop < 0:
                break
            continue
        i = int(np.argmax(ties))  # the first tie: keep the picks before it and apply the rule there
        del picks[first + i:]
        j = tie_break(np.flatnonzero(before[i] >= mine[i] * keep))
        picks.append(j)
        np.minimum(before[i], rows(j), out=dist)
        restarts += 1
    return picks


def _update(dist2, b_max, x, y, z, b_centre, b_radius, g_centre, g_radius, q, slack: float) -> None:
    """Lower the squared distances of every block the new choices q (Q, 3) can reach."""
    if len(b_radius) <= _FLAT_BLOCKS:  # few blocks: test them all against every choice
        reach = np.sqrt(np.maximum(b_max, 0.0))  # (B,)
        bi, qi = np.nonzero(_gaps(b_centre, b_radius, q) < reach[:, None] + slack)  # sorted by block
        bq = q[qi]
    else:  # groups first, then the blocks of the groups a choice reaches
        g_max = np.sqrt(np.maximum(b_max.reshape(len(g_radius), -1).max(axis=1), 0.0))  # (G,)
        gi, qi = np.nonzero(_gaps(g_centre, g_radius, q) < g_max[:, None] + slack)  # (P,) group-choice pairs
        bi = (gi[:, None] * _GROUP + np.arange(_GROUP)).reshape(-1)  # (P * GROUP,) their blocks
        bq = q[np.repeat(qi, _GROUP)]  # (P', 3)
        gap = np.sqrt((b_centre[bi, 0] - bq[:, 0]) ** 2 + (b_centre[bi, 1] - bq[:, 1]) ** 2
                      + (b_centre[bi, 2] - bq[:, 2]) ** 2) - b_radius[bi]
        keep = gap < np.sqrt(np.maximum(b_max[bi], 0.0)) + slack
        rank = np.argsort(bi[keep], kind="stable")
        bi, bq = bi[keep][rank], bq[keep][rank]
    if bi.size == 0:
        return
    d2 = ((x[bi] - bq[:, :1]) ** 2 + (y[bi] - bq[:, 1:2]) ** 2) + (z[bi] - bq[:, 2:]) ** 2  # (P, L)
    starts = np.flatnonzero(np.r_[True, bi[1:] != bi[:-1]])
    hit = bi[starts]
    lower = np.minimum(dist2[hit], np.minimum.reduceat(d2, starts, axis=0))  # (H, L)
    dist2[hit] = lower
    b_max[hit] = lower.max(axis=1)


def count_distinct(points: np.ndarray) -> int:
    """Number of distinct points: rows that differ in any coordinate (-0.0 equals 0.0).

    Exact, so at any scale: a cloud 1e-15 across has as many distinct points as the
    same cloud in metres (a rounding to fixed decimals would merge them all).
    """
    points = as_points(points, "points", min_points=0)
    return len(_first_of_each_row(points))


def first_unique_rows(values, columns: int) -> np.ndarray:
    """Rows of the first occurrence of each distinct row, ascending.

    The same as ``np.sort(np.unique(values, axis=0, return_index=True)[1])`` (-0.0 equals
    0.0), about 4x faster: rows are sorted as blocks of bytes (a stable sort, so the first
    of equal rows leads its run), and np.unique, which imports numpy.ma (~15 ms of a
    cold start), is not called.

    Parameters
    ----------
    values : (N, C) float, finite.
    columns : C, checked.

    Returns
    -------
    rows : (U,) int64
    """
    values = as_rows(values, "values", columns, 0, letters="NC")
    return _first_of_each_row(values)


def _first_of_each_row(values: np.ndarray) -> np.ndarray:
    """(U,) int64, ascending: the first row of each run of equal rows of finite (N, C) float64 `values`."""
    if len(values) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(_row_keys(values), kind="stable")  # (N,) equal rows adjacent, first occurrence first
    rows = values[order]
    leads = np.empty(len(rows), dtype=bool)
    leads[0] = True
    np.any(rows[1:] != rows[:-1], axis=1, out=leads[1:])  # -0.0 == 0.0, as their keys
    return np.sort(order[leads]).astype(np.int64)


def _row_keys(values: np.ndarray) -> np.ndarray:
    """(N,) one opaque key per row of a finite float64 (N, C) array: equal keys for equal rows."""
    rows = np.ascontiguousarray(values, dtype=np.float64) + 0.0  # -0.0 + 0.0 = +0.0: one pattern of bits for 0
    return rows.view(np.dtype((np.void, rows.itemsize * rows.shape[1]))).reshape(len(rows))


THIN_ABOVE = 131072
"""`prepare_input` first thins clouds of more points than this to about `THIN_TO`
(`thin_by_radius`); up to it the network input is the FPS of every point."""

THIN_TO = 65536


def thin_by_radius(points, target: int) -> np.ndarray:
    """About `target` rows of a cloud, chosen equivariantly in time ~N log N and memory ~N.

    The points are ordered by their distance to the centroid (a rotation-, translation-,
    permutation- and scale-invariant key) and every s-th is kept, s = ceil(N / target).
    Keys within TIE_RTOL of the largest key of each other form one group (rotating the
    cloud moves keys by rounding only, so it may reorder a group but never split one); a
    group is kept whole when any of its positions in the order is a multiple of s, so
    which rows are kept does not depend on the pose or on the order of the rows.
    Consecutive points in this order lie anywhere on the shell of their radius, so the
    kept rows thin the cloud evenly, like a random subset of 1 in s.

    Parameters
    ----------
    points : (N, 3) float
    target : rows wanted (at least 1); clouds of at most `target` points are kept whole, others
        thinned to N / ceil(N / target) rows (between target / 2 and target) plus whole groups.

    Returns
    -------
    rows : (R,) int64, ascending.
    """
    pts = as_points(points)
    target = as_count(target, "target", minimum=1)
    n = len(pts)
    if n <= target:
        return np.arange(n)
    centre = pts.mean(axis=0)
    key2 = np.zeros(n)
    for c in range(3):  # (N,) squared distance to the centroid, without an (N, 3) temporary
        d = pts[:, c] - centre[c]
        key2 += d * d
    order = np.argsort(key2, kind="stable")  # (N,)
    key = np.sqrt(key2[order])  # (N,) ascending
    del key2
    group = np.zeros(n, dtype=np.int64)  # group number of each position
    np.cumsum(np.diff(key) > TIE_RTOL * key[-1], out=group[1:])
    stride = -(-n // target)
    kept_groups = np.zeros(int(group[-1]) + 1, dtype=bool)
    kept_groups[group[::stride]] = True
    return np.sort(order[kept_groups[group]])


def prepare_input(points, size: int = 2048) -> tuple[np.ndarray, int]:
    """Make the fixed-size, farthest-point-ordered network input from a cloud of any size.

    Larger clouds are subsampled by farthest point sampling; smaller ones are put in
    farthest-point order and repeated cyclically (PCN repeats points too). Either way
    the first `q` rows are the `q`-point FPS subset for every `q`, which the network
    uses as its centres, and the result is equivariant. Clouds of more than THIN_ABOVE
    points are first thinned to about THIN_TO by `thin_by_radius` (also equivariant), so
    that a scan of millions of points takes seconds: the FPS of the thinned cloud
    covers the scan as the FPS of every point does (measured in docs/ARCHITECTURE.md).

    Parameters
    ----------
    points : (N, 3) float64, N >= 1 distinct points.
    size : number of output rows.

    Returns
    -------
    prepared : (size, 3) float64
    unique_count : number of leading rows that are distinct points (min(N, size)).
    """
    pts = as_points(points)
    if len(pts) > THIN_ABOVE:
        pts = pts[thin_by_radius(pts, THIN_TO)]
    if len(_first_of_each_row(pts)) < len(pts):  # duplicates carry no information and break FPS
        pts = np.unique(pts, axis=0)
    count = min(len(pts), size)
    order = farthest_point_sampling(pts, count)
    chosen = pts[order]  # (count, 3)
    if count < size:
        chosen = chosen[np.arange(size) % count]
    return chosen, count


def resample_rows(count: int, size: int, seed: int | tuple = 0) -> np.ndarray:
    """Deterministic rows to turn `count` points into `size`: a seeded subset, or all plus repeats.

    Depends only on the counts, so it commutes with any rotation of the points. The
    resampling rule of the network input and of PCN-style fixed-size samples (a
    completion keeps its points by `select_confident_rows`).

    Returns
    -------
    rows : (size,) int64
    """
    count = as_count(count, "count", minimum=1)
    size = as_count(size, "size", minimum=1)
    if size == count:
        return np.arange(count)
    rng = np.random.default_rng(seed)
    if size < count:
        return np.sort(rng.choice(count, size, replace=False))
    extra = rng.choice(count, size - count, replace=size - count > count)
    return np.concatenate([np.arange(count), extra])


DROP_POWER = 2.0  # chance of being left out grows as residual ** DROP_POWER (chosen on the validation split)


def select_confident_rows(residuals, size: int, seed: int = 0) -> np.ndarray:
    """Rows keeping `size` of the points, leaving out the surplus at random, the unsure ones first.

    Each left-out point is drawn without replacement with probability proportional to
    residual ** DROP_POWER (weighted sampling by exponential keys), so points the solver
    could not fit well are the likeliest to go, while low-residual points of the same
    region remain; points of residual 0 (the observed ones) go only when nothing else is
    left, and then uniformly. Depends only on the residuals (rotation invariant; their
    scale cancels) and a seeded draw, so it commutes with any similarity of the points.
    On 80 validation shapes it took a completion's CD-L1 x1000 from 13.48 (a uniform
    draw) to 13.06 (models/README.md).

    Parameters
    ----------
    residuals : (M,) float64, >= 0 and finite.
    size : rows to keep, 1 <= size <= M.

    Returns
    -------
    rows : (size,) int64, ascending, distinct.
    """
    column = np.expand_dims(residuals, 1) if np.ndim(residuals) == 1 else residuals
    r = as_rows(column, "residuals", columns=1, min_rows=1, letters="M1")[:, 0]  # (M,)
    if r.min() < 0:
        raise PointCloudError("residuals must not be negative")
    count = len(r)
    size = as_count(size, "size", minimum=1)
    if size > count:
        raise PointCloudError(f"cannot keep {size} of {count} points")
    if size == count:
        return np.arange(count)
    rng = np.random.default_rng(seed)
    uniform = rng.random(count)  # (M,) in [0, 1)
    peak = r.max()
    weight = (r / peak) ** DROP_POWER if peak > 0 else np.zeros(count)  # (M,) in [0, 1]
    positive = weight > 0
    sure, unsure = np.flatnonzero(~positive), np.flatnonzero(positive)
    surplus = count - size
    left_out = np.zeros(count, dtype=bool)
    if surplus <= len(unsure):  # leave out the largest keys u ** (1 / w), in logs
        key = np.log1p(-uniform[unsure]) / weight[unsure]
        left_out[unsure[np.argpartition(-key, surplus - 1)[:surplus]]] = True
    else:  # every unsure point, then zero-residual points uniformly
        left_out[unsure] = True
        rest = surplus - len(unsure)
        left_out[sure[np.argpartition(-uniform[sure], rest - 1)[:rest]]] = True
    return np.flatnonzero(~left_out)
