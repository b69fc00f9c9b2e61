"""Recover points from their distances to K anchors: linear start + guarded Levenberg-Marquardt.

Per output point minimise  sum_j ( ||p - a_j|| - d_j )^2  (paper section 3.3).

Pipeline of `reconstruct`:

1. Work about the anchors' centre c (everything below is in centred coordinates
   q = p - c, so a translation of the anchors cancels exactly).
2. Closed-form start (`linear_multilateration`): subtracting the mean sphere equation
   leaves the linear system  -2 a'_j . q = d_j^2 - mean(d^2) - ||a'_j||^2 + mean||a'||^2,
   solved with a truncated SVD of the centred anchors (directions whose singular value
   is below `rel_cutoff` = 0.02 of the largest are dropped, which is what keeps noisy
   distances on nearly coplanar anchors from throwing the point far out of the plane).
3. Levenberg-Marquardt on all points at once (`method="batched"`): per point a 3x3
   damped system (H + lambda I) dq = -J^T r, where H is the exact Hessian when it is
   positive definite (Newton: quadratic convergence, also near an anchor or a flat
   anchor set where Gauss-Newton crawls) and J^T J otherwise; each point has its own
   adaptive lambda, a step bounded by the anchors' RMS radius, and keeps a step only
   when it lowers that point's cost (or, once the cost is flat to rounding, its
   gradient). Isotropic damping (lambda I, not diag(J^T J)) keeps every step
   rotation-equivariant. The cost never rises, so a point can never end farther
   from the anchors than its start allows: no explosion.
4. Near-planar anchors (smallest singular value < `PLANAR_RATIO` = 0.1 of the largest):
   distances cannot tell the two sides of the anchor plane apart well, so LM is also
   run from the in-plane start pushed by +h and -h along the plane normal
   (h^2 = mean_j d_j^2 - mean_j ||q_in - a'_j||^2, exact for centred anchors; at least
   0.01 of the anchors' RMS radius so neither start sits on the plane), and per
   point the lower final residual wins. When the two fits are equally good within
   `TIE_CHI2` noise variances (noise estimated once per call from the median
   residual) the side chosen by an equivariant rule wins: the candidate with the
   larger offset along the *oriented* normal n (see `plane_normal`).

`method="scipy"` is the reference: ``scipy.optimize.least_squares(method="lm")`` per
point from the same starts, with the same selection rule. `method="batched-naive"` is
the first numpy version of the batched iteration ((M, K, 3) arrays, every point in one
batch), kept as the reference of the fast one: same points to ~1e-13 (tested to 1e-6).

Equivariance: every quantity is built from rotation-equivariant operations
(centring, SVD-based pseudo-inverse, isotropic LM, a normal whose sign is fixed by
geometry), so ``reconstruct(D, A @ R.T + t).points == reconstruct(D, A).points @ R.T + t``
to rounding (measured <= 1e-12 at 500 points, also near-planar; reference points,
when given, must be moved with the anchors).

Shapes: M output points, K anchors, N reference (partial) points.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from itertools import combinations

import numpy as np

from escape_cli.core.checks import as_points, as_rows, check_not_collinear
from escape_cli.core.params import as_choice, as_count, as_number
from escape_cli.core.threads import thread_map
from escape_cli.errors import DegenerateGeometryError, ParameterError, PointCloudError

__all__ = [
    "Reconstruction",
    "check_anchors",
    "linear_multilateration",
    "linear_multilateration_naive",
    "plane_normal",
    "reconstruct",
    "rms_residuals",
    "METHODS",
    "REFERENCE_METHODS",
    "RCOND",
    "PLANAR_RATIO",
    "TIE_CHI2",
]

METHODS = ("batched", "scipy")
REFERENCE_METHODS = ("batched-naive",)
"""Accepted by `reconstruct` besides METHODS: "batched-naive" is the first numpy LM, the
reference the fast batched solver is tested and benchmarked against."""

RCOND = 0.02
"""Linear start: singular directions of the centred anchors below this share of the
largest singular value are dropped: with noisy distances on nearly coplanar anchors the
out-of-plane coordinate otherwise explodes."""

PLANAR_RATIO = 0.1
"""Anchors are *near-planar* when s_min / s_max of the centred anchors is below this,
and then the two-sided starts are used. Measured (box of PCN size, 8 anchors, noise
0.01, points on both sides of the anchors' plane): at s_min/s_max = 0.1 one start
leaves 0.1-0.3% of the points mirrored, two starts 0.01-0.02%; from 0.2 up both leave
< 0.2% off by more than 0.1 (and those by < 0.15: noise along the weak direction,
not mirrors), so the second start is not worth its cost there."""

COLLINEAR_RATIO = 1e-3
"""`check_anchors` rejects anchors whose second singular value is below this share of
the largest: with (nearly) collinear anchors a point's angle about the line is lost."""

TIE_CHI2 = 4.0
"""Near-planar selection: the two sides' fits count as equally good when their sums of
squared residuals differ by at most TIE_CHI2 x sigma^2, sigma^2 being the distance noise
variance estimated once per call as median_i min(SSE_a, SSE_b) / (K - 3). Since
dSSE / sigma^2 = -2 log(likelihood ratio), 4 means: the lower-residual side wins only
if it is ~e^2 = 7.4x more likely; otherwise the equivariant side rule decides
(`plane_normal`). Measured share of mirrored points (error > 0.3) on a PCN-sized box,
3000 points, 6 anchor sets per row; "front face": anchors on the front face and the
partial = front face + a side sliver (the rule's side is right); "mid-plane": anchors
on the box's mid-plane, points on both sides (the rule is wrong for half):

=============================  ==============  ====================  ================
anchors s_min/s_max, noise     residual alone  RMS within 20% = tie  TIE_CHI2 = 4
=============================  ==============  ====================  ================
front face 1e-3, 0.005         0.29            0.0003                0
front face 0.01, 0.005         0.16            0.053                 0.017
front face 0.01, 0.02          0.27            0.0067                0.0002
front face 0.03, 0.02          0.18            0.050                 0.013
mid-plane  0.01, 0.005         0.17            0.22                  0.24
mid-plane  0.03, 0.005         0.025           0.035                 0.035
mid-plane  0.03, 0.02          0.19            0.24                  0.26
=============================  ==============  ====================  ================

(a per-point relative rule fails on points whose residual is small by luck.)"""

_H_FLOOR = 0.01  # x anchor RMS radius: smallest out-of-plane offset of the two-sided starts
_TIE_ATOL = 1e-9  # x anchor RMS radius: exact-data ties (both residuals ~0)
_DISTINCT_RTOL = 1e-9  # anchors closer than this x their extent count as one
_STEP_BOUND = 1.0  # x anchor RMS radius: the longest LM step
_LAMBDA0 = 1e-3  # initial damping (J rows are unit vectors, so J^T J has trace K)
_LAMBDA_MIN, _LAMBDA_MAX = 1e-12, 1e12
_LAMBDA_DOWN, _LAMBDA_UP = 0.1, 4.0
_XTOL = 1e-13  # x anchor RMS radius: a point whose proposed step is shorter is done
_SIDE_RTOL = 1e-6  # a side-rule statistic smaller than this (relative) is 'no opinion'
_LM_BATCH = 4096  # points per batch of the fast LM (measured best of 1024-32768 on 16384 and 32768 points)
_LM_TAIL = 16  # a batch stops when fewer than 1/_LM_TAIL of its points are left; those finish together


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """The result of `reconstruct`.

    Attributes
    ----------
    points : (M, 3) float64
        Recovered coordinates, in the anchors' frame.
    residuals : (M,) float64
        RMS over anchors of ||p - a_j|| - d_j at the solution (a free confidence measure,
        in distance units).
    near_planar : bool
        The anchors were nearly coplanar and two-sided starts were used.
    anchor_singular_values : (3,) float64
        Singular values of the centred anchors, descending.
    iterations : int
        LM iterations run (batched: the loop count; scipy: the most Jacobian
        evaluations any point needed).
    """

    points: np.ndarray
    residuals: np.ndarray
    near_planar: bool
    anchor_singular_values: np.ndarray
    iterations: int


# --------------------------------------------------------------------------- checks


def _as_anchors(anchors) -> np.ndarray:
    return as_points(anchors, "anchors", min_points=0)


def check_anchors(anchors) -> None:
    """Raise DegenerateGeometryError unless the anchors can locate points in 3D.

    Rejected: fewer than 4 anchors, fewer than 4 distinct anchors (closer than 1e-9 of
    their extent count as one), and (nearly) collinear anchors (the package's one rule,
    `escape_cli.core.checks.check_not_collinear`). Coplanar anchors are accepted:
    `reconstruct` handles them (near_planar). Bad arrays (shape, NaN) raise
    PointCloudError.

    Parameters
    ----------
    anchors : (K, 3) float
    """
    anc = _as_anchors(anchors)
    k = anc.shape[0]
    if k < 4:
        raise DegenerateGeometryError(f"need at least 4 anchors to locate points in 3D, got {k}")
    centred = anc - anc.mean(axis=0)  # (K, 3)
    extent = float(np.sqrt((centred * centred).sum(axis=1)).max())
    gaps = np.sqrt(((anc[:, None, :] - anc[None, :, :]) ** 2).sum(axis=2))  # (K, K)
    same = gaps <= _DISTINCT_RTOL * extent
    distinct = sum(1 for i in range(k) if not np.any(same[i, :i]))
    if distinct < 4:
        raise DegenerateGeometryError(
            f"need at least 4 distinct anchors, got {distinct} distinct among {k}"
        )
    check_not_collinear(anc, "the anchors")


def _as_distances(distances, k: int) -> np.ndarray:
    dist = as_rows(distances, "distances", None, 0, letters="MK")
    if dist.shape[1] != k:
        raise PointCloudError(f"distances must have shape (M, K={k}) to match the anchors, got {dist.shape}")
    return np.maximum(dist, 0.0)  # (M, K): a network may predict slightly negative values


def _as_reference(points) -> np.ndarray | None:
    return None if points is None else as_points(points, "reference_points", min_points=1)


# ------------------------------------------------------------------- anchor frame


@dataclass(frozen=True, eq=False)
class _Frame:
    """Everything the solvers need from the anchors, in centred coordinates."""

    center: np.ndarray  # (3,)
    centred: np.ndarray  # (K, 3)
    u: np.ndarray  # (K, 3) left singular vectors
    s: np.ndarray  # (3,) singular values, descending
    vt: np.ndarray  # (3, 3) right singular vectors as rows
    radius: float  # RMS distance of the anchors from their centre
    near_planar: bool


def _frame(anchors: np.ndarray) -> _Frame:
    center = anchors.mean(axis=0)  # (3,)
    centred = anchors - center  # (K, 3)
    u, s, vt = np.linalg.svd(centred, full_matrices=False)  # (K, 3), (3,), (3, 3)
    radius = float(np.sqrt((centred * centred).sum() / len(centred)))
    return _Frame(center, centred, u, s, vt, radius, bool(s[2] < PLANAR_RATIO * s[0]))


def _linear_rhs(distances: np.ndarray, centred: np.ndarray) -> np.ndarray:
    """b (M, K) of the linear system  a'_j . q = b_j  (mean sphere equation subtracted)."""
    d2 = distances * distances  # (M, K)
    a2 = (centred * centred).sum(axis=1)  # (K,)
    return -0.5 * (d2 - d2.mean(axis=1, keepdims=True) - (a2 - a2.mean()))  # (M, K)


def linear_multilateration(distances, anchors, rel_cutoff: float = RCOND) -> np.ndarray:
    """Closed-form least-squares positions from distances, with a truncated SVD.

    With c the anchors' mean and a'_j = a_j - c, q = p - c, subtracting the mean of the
    K sphere equations ||q - a'_j||^2 = d_j^2 gives the linear system

        a'_j . q = -( d_j^2 - mean_k d_k^2 - ||a'_j||^2 + mean_k ||a'_k||^2 ) / 2,

    solved for every point at once with the pseudo-inverse of the centred anchors in
    which singular values below ``rel_cutoff * s_max`` are dropped (the position along
    a dropped direction is set to the anchors' centre).

    Parameters
    ----------
    distances : (M, K) float
    anchors : (K, 3) float
    rel_cutoff : float
        Relative singular-value cutoff, in [0, 1).

    Returns
    -------
    points : (M, 3) float64
    """
    anc = _as_anchors(anchors)
    check_anchors(anc)
    dist = _as_distances(distances, anc.shape[0])
    frame = _frame(anc)
    return _linear_centred(dist, frame, rel_cutoff) + frame.center


def _linear_centred(distances: np.ndarray, frame: _Frame, rel_cutoff: float) -> np.ndarray:
    rel_cutoff = as_number(rel_cutoff, "rel_cutoff", minimum=0.0)
    if rel_cutoff >= 1.0:
        raise ParameterError(f"rel_cutoff must be below 1, got {rel_cutoff!r}")
    keep = frame.s >= rel_cutoff * frame.s[0]  # (3,)
    pinv = (frame.vt[keep].T / frame.s[keep]) @ frame.u[:, keep].T  # (3, K)
    return _linear_rhs(distances, frame.centred) @ pinv.T  # (M, 3)


def linear_multilateration_naive(distances, anchors, rel_cutoff: float = RCOND) -> np.ndarray:
    """Reference for `linear_multilateration`: one ``np.linalg.lstsq`` per point."""
    anc = _as_anchors(anchors)
    dist = _as_distances(distances, anc.shape[0])
    center = anc.mean(axis=0)
    centred = anc - center
    out = np.empty((len(dist), 3))
    for i, row in enumerate(dist):
        b = [-0.5 * (row[j] ** 2 - np.mean(row**2) - centred[j] @ centred[j]
                     + np.mean((centred**2).sum(axis=1))) for j in range(len(anc))]
        out[i] = np.linalg.lstsq(centred, np.array(b), rcond=rel_cutoff)[0] + center
    return out


def plane_normal(anchors, reference_points=None) -> np.ndarray:
    """The unit normal of the anchors' best-fit plane, with an equivariant sign.

    The direction is the weakest right singular vector of the centred anchors; its sign
    from the SVD is arbitrary, so it is fixed by the first of these rules that has an
    opinion (|statistic| above 1e-6 of its natural scale):

    1. reference points (the partial cloud) given: n points to the side where they have
       more mass, i.e. mean_i (x_i - c) . n > 0;
    2. the anchors' own third moment of their offsets from the plane: mean_j z_j^3 > 0
       (an anchor standing off a flat face points toward where the object continues);
    3. the anchor order: among the triples (i < j < k) the first whose
       |((a_j - a_i) x (a_k - a_i)) . n| is at least half the largest gets a positive
       value (a handedness; rotations keep it, reflections flip it).

    Rule 1 is a heuristic: for a flat face seen with slivers of its sides (a cabinet
    front, a table top) the partial's mass lies on the side the object continues to;
    for a visible surface that bulges toward the viewer it would be the viewer's side.

    Each rule turns with the anchors (and the reference points), so
    ``plane_normal(A @ R.T + t, X @ R.T + t) == R @ plane_normal(A, X)``.

    Parameters
    ----------
    anchors : (K, 3) float
    reference_points : (N, 3) float or None

    Returns
    -------
    normal : (3,) float64
    """
    anc = _as_anchors(anchors)
    check_anchors(anc)
    return _oriented_normal(_frame(anc), _as_reference(reference_points))


def _oriented_normal(frame: _Frame, reference: np.ndarray | None) -> np.ndarray:
    n = frame.vt[2].copy()  # (3,) sign arbitrary
    if reference is not None:
        offset = float(((reference - frame.center) @ n).mean())
        scale = float(np.sqrt(((reference - frame.center) ** 2).sum(axis=1).mean()))
        if abs(offset) > _SIDE_RTOL * max(scale, frame.radius):
            return n if offset > 0 else -n
    z = frame.centred @ n  # (K,)
    m3 = float(np.mean(z**3))
    if np.mean(z * z) > (_SIDE_RTOL * frame.radius) ** 2 and abs(m3) > _SIDE_RTOL * np.mean(np.abs(z) ** 3):
        return n if m3 > 0 else -n
    a = frame.centred
    triples = list(combinations(range(len(a)), 3))
    vol = np.array([np.cross(a[j] - a[i], a[k] - a[i]) @ n for i, j, k in triples])  # (T,)
    first = int(np.flatnonzero(np.abs(vol) >= 0.5 * np.abs(vol).max())[0])
    return n if vol[first] > 0 else -n


# ---------------------------------------------------------------------- residuals


def rms_residuals(points, distances, anchors) -> np.ndarray:
    """RMS over anchors of ||p_i - a_j|| - d_ij.

    Parameters
    ----------
    points : (M, 3) float
    distances : (M, K) float
    anchors : (K, 3) float

    Returns
    -------
    residuals : (M,) float64
    """
    anc = _as_anchors(anchors)
    pts = as_points(points, "points", min_points=0)
    dist = _as_distances(distances, anc.shape[0])
    if pts.shape != (len(dist), 3):
        raise PointCloudError(f"points must have shape ({len(dist)}, 3), got {pts.shape}")
    r = np.sqrt(((pts[:, None, :] - anc[None, :, :]) ** 2).sum(axis=2)) - dist  # (M, K)
    return np.sqrt((r * r).mean(axis=1))


def _eval(q: np.ndarray, d: np.ndarray, a: np.ndarray):
    """diff (P, K, 3), dist (P, K), residual (P, K), cost (P,) for centred points q."""
    diff = q[:, None, :] - a[None, :, :]  # (P, K, 3)
    dist = np.sqrt(np.einsum("pki,pki->pk", diff, diff))  # (P, K)
    r = dist - d  # (P, K)
    return diff, dist, r, 0.5 * np.einsum("pk,pk->p", r, r)


# ------------------------------------------------------------------- batched LM


def _cholesky_solve3(h: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve h x = b for a batch of symmetric 3x3 systems by an explicit Cholesky.

    Parameters
    ----------
    h : (P, 3, 3) float64, symmetric
    b : (P, 3) float64

    Returns
    -------
    x : (P, 3) float64
        Garbage where ``ok`` is False.
    ok : (P,) bool
        h was numerically positive definite (all pivots > 0).
    """
    a00, a01, a02 = h[:, 0, 0], h[:, 0, 1], h[:, 0, 2]
    a11, a12, a22 = h[:, 1, 1], h[:, 1, 2], h[:, 2, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        p0 = a00
        l00 = np.sqrt(p0)
        l10, l20 = a01 / l00, a02 / l00
        p1 = a11 - l10 * l10
        l11 = np.sqrt(p1)
        l21 = (a12 - l20 * l10) / l11
        p2 = a22 - l20 * l20 - l21 * l21
        l22 = np.sqrt(p2)
        y0 = b[:, 0] / l00  # forward: L y = b
        y1 = (b[:, 1] - l10 * y0) / l11
        y2 = (b[:, 2] - l20 * y0 - l21 * y1) / l22
        x2 = y2 / l22  # backward: L^T x = y
        x1 = (y1 - l21 * x2) / l11
        x0 = (y0 - l10 * x1 - l20 * x2) / l00
    x = np.stack([x0, x1, x2], axis=1)  # (P, 3)
    ok = (p0 > 0) & (p1 > 0) & (p2 > 0) & np.all(np.isfinite(x), axis=1)
    return x, ok


def _lm_batched_naive(q0: np.ndarray, d: np.ndarray, frame: _Frame, max_iter: int, newton: bool = True):
    """Reference for `_lm_batched` (the first numpy version): the same iteration on (P, K, 3) arrays.

    Levenberg-Marquardt on all points at once; returns q (P, 3), cost (P,), iterations.

    Per point and iteration: the step solves (H + lambda I) dq = -g with H the exact
    Hessian of 0.5 sum_j r_j^2,

        H = sum_j w_j u_j u_j^T + (sum_j (1 - w_j)) I,   u_j = (q - a_j) / rho_j,  w_j = d_j / rho_j,

    where that matrix is positive definite (fast, quadratic convergence near the
    solution, also close to an anchor or for points near a flat anchor set, where
    Gauss-Newton crawls), else the Gauss-Newton matrix J^T J = sum_j u_j u_j^T. The
    step is cut to the anchors' RMS radius and kept only if the point's cost drops;
    lambda shrinks 10x after a kept step and grows 4x after a rejected one.
    """
    a = frame.centred  # (K, 3)
    q = q0.copy()  # (P, 3)
    diff, dist, r, cost = _eval(q, d, a)
    lam = np.full(len(q), _LAMBDA0)  # (P,)
    active = np.ones(len(q), dtype=bool)
    max_step = _STEP_BOUND * frame.radius
    tiny = 1e-300 + 1e-12 * frame.radius  # a point closer than this to an anchor: J row ~ 0
    eye = np.eye(3)
    iterations = 0
    for _ in range(max_iter):
        idx = np.flatnonzero(active)  # (p,)
        if idx.size == 0:
            break
        iterations += 1
        inv = 1.0 / np.maximum(dist[idx], tiny)  # (p, K)
        jac = diff[idx] * inv[:, :, None]  # (p, K, 3): rows u_j
        jac_t = jac.transpose(0, 2, 1)  # (p, 3, K)
        grad = (jac_t @ r[idx][:, :, None])[:, :, 0]  # (p, 3)
        damp = lam[idx, None, None] * eye  # (p, 3, 3)
        step = np.zeros_like(grad)  # (p, 3)
        solved = np.zeros(len(idx), dtype=bool)
        if newton:
            w = d[idx] * inv  # (p, K)
            hess = (jac_t * w[:, None, :]) @ jac + ((1.0 - w).sum(axis=1))[:, None, None] * eye  # (p, 3, 3)
            step, solved = _cholesky_solve3(hess + damp, -grad)
        if not solved.all():
            rest = ~solved
            gn = jac_t[rest] @ jac[rest] + damp[rest]  # (p', 3, 3)
            gn_step, gn_ok = _cholesky_solve3(gn, -grad[rest])
            gn_step[~gn_ok] = 0.0  # only with lambda ~ 0 on a degenerate point: no move
            step[rest] = gn_step
        norm = np.sqrt((step * step).sum(axis=1))  # (p,)
        step *= np.minimum(1.0, max_step / np.maximum(norm, 1e-300))[:, None]
        trial = q[idx] + step  # (p, 3)
        t_diff, t_dist, t_r, t_cost = _eval(trial, d[idx], a)
        # Keep a step that lowers the cost; where the change is within the cost's own
        # rounding error (eps * sum_j |r_j| (rho_j + d_j)) keep it if it lowers the
        # gradient instead, so points settle to ~1e-15 and not to sqrt(eps) ~ 1e-8.
        t_grad = ((t_diff / np.maximum(t_dist, tiny)[:, :, None]) * t_r[:, :, None]).sum(axis=1)  # (p, 3)
        noise = 16.0 * np.finfo(float).eps * (np.abs(r[idx]) * (dist[idx] + d[idx])).sum(axis=1)  # (p,)
        flat = t_cost <= cost[idx] + noise
        lower_grad = (t_grad * t_grad).sum(axis=1) < (grad * grad).sum(axis=1)
        ok = np.isfinite(t_cost) & ((t_cost < cost[idx]) | (flat & lower_grad))  # (p,)
        acc = idx[ok]
        q[acc], diff[acc], dist[acc] = trial[ok], t_diff[ok], t_dist[ok]
        r[acc], cost[acc] = t_r[ok], t_cost[ok]
        lam[idx] = np.where(ok, np.maximum(lam[idx] * _LAMBDA_DOWN, _LAMBDA_MIN),
                            np.minimum(lam[idx] * _LAMBDA_UP, _LAMBDA_MAX))
        done = (norm <= _XTOL * frame.radius) | (lam[idx] >= _LAMBDA_MAX)
        active[idx[done]] = False
    return q, cost, iterations


def _cholesky_solve3_entries(h00, h01, h02, h11, h12, h22, b0, b1, b2):
    """`_cholesky_solve3` on the six entries of symmetric 3x3 matrices, each (P,); returns x (3, P), ok (P,)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(h00)
        l10, l20 = h01 / l00, h02 / l00
        p1 = h11 - l10 * l10
        l11 = np.sqrt(p1)
        l21 = (h12 - l20 * l10) / l11
        p2 = h22 - l20 * l20 - l21 * l21
        l22 = np.sqrt(p2)
        y0 = b0 / l00  # forward: L y = b
        y1 = (b1 - l10 * y0) / l11
        y2 = (b2 - l20 * y0 - l21 * y1) / l22
        x2 = y2 / l22  # backward: L^T x = y
        x1 = (y1 - l21 * x2) / l11
        x0 = (y0 - l10 * x1 - l20 * x2) / l00
    x = np.stack([x0, x1, x2])  # (3, P)
    ok = (h00 > 0) & (p1 > 0) & (p2 > 0) & np.isfinite(x0) & np.isfinite(x1) & np.isfinite(x2)
    return x, ok


def _state(q: np.ndarray, d: np.ndarray, a: np.ndarray, tiny: float):
    """At points q (3, P): rho (K, P), r = rho - d (K, P), inv = 1 / rho (K, P), cost (P,), gradient (3, P).

    Anchor-major (K, P) arrays: every sum over the anchors adds K rows of length P.
    """
    dx = q[0] - a[:, :1]  # (K, P)
    dy = q[1] - a[:, 1:2]
    dz = q[2] - a[:, 2:]
    rho = np.sqrt(dx * dx + dy * dy + dz * dz)  # (K, P)
    r = rho - d  # (K, P)
    cost = 0.5 * np.einsum("kp,kp->p", r, r)  # (P,)
    inv = 1.0 / np.maximum(rho, tiny)  # (K, P)
    s = r * inv  # (K, P)
    grad = np.stack([np.einsum("kp,kp->p", s, dx), np.einsum("kp,kp->p", s, dy),
                     np.einsum("kp,kp->p", s, dz)])  # (3, P) J^T r, J rows u_j = (q - a_j) / rho_j
    return rho, r, inv, cost, grad


def _weighted_outer(c: np.ndarray, q: np.ndarray, moments: np.ndarray) -> tuple:
    """The six entries (P,) of sum_j c_j (q - a_j)(q - a_j)^T, from c (K, P), q (3, P) and the anchors' moments (9, K).

    sum_j c_j (q - a_j)(q - a_j)^T = C q q^T - q m^T - m q^T + S with C = sum_j c_j,
    m = sum_j c_j a_j and S = sum_j c_j a_j a_j^T: one (9, K) x (K, P) product.
    """
    total = c.sum(axis=0)  # (P,)
    ms = moments @ c  # (9, P)
    x, y, z = q
    mx, my, mz = ms[0], ms[1], ms[2]
    return (total * x * x - 2.0 * x * mx + ms[3], total * x * y - x * my - y * mx + ms[4],
            total * x * z - x * mz - z * mx + ms[5], total * y * y - 2.0 * y * my + ms[6],
            total * y * z - y * mz - z * my + ms[7], total * z * z - 2.0 * z * mz + ms[8])


def _lm_batched(q0: np.ndarray, d: np.ndarray, frame: _Frame, max_iter: int, newton: bool = True, workers: int = 1):
    """Levenberg-Marquardt on all points at once; returns q (P, 3), cost (P,), iterations.

    Per point and iteration: the step solves (H + lambda I) dq = -g with H the exact
    Hessian of 0.5 sum_j r_j^2,

        H = sum_j w_j u_j u_j^T + (sum_j (1 - w_j)) I,   u_j = (q - a_j) / rho_j,  w_j = d_j / rho_j,

    where that matrix is positive definite (fast, quadratic convergence near the
    solution, also close to an anchor or for points near a flat anchor set, where
    Gauss-Newton crawls), else the Gauss-Newton matrix J^T J = sum_j u_j u_j^T. The
    step is cut to the anchors' RMS radius and kept only if the point's cost drops;
    lambda shrinks 10x after a kept step and grows 4x after a rejected one.

    The iteration of `_lm_batched_naive`, arranged for speed (`_LM`): anchor-major
    (K, P) arrays (a sum over anchors adds K contiguous rows); the residuals, costs and
    gradients of a kept trial step reused at the next iteration instead of recomputed;
    the 3x3 systems as six (P,) entries; sum_j c_j u_j u_j^T expanded about the common
    anchors into one (9, K) x (K, P) product with the anchors' moments; points that are
    done leave the batch at once. Points are independent, so they are solved in batches
    of `_LM_BATCH` whose arrays stay in the processor's cache (measured 2-3x faster than
    one batch of 16384-32768 points), each until few of its points are left; those few
    of every batch then finish together, so the long tail of slow points costs one
    short batch per iteration instead of one per batch. With `workers` > 1 the batches
    run in that many threads (numpy releases the interpreter lock inside each array
    operation); each point's arithmetic, and so the result, is the same.
    """
    lm = _LM(frame, len(q0), max_iter, newton)

    def bulk(lo: int):
        hi = min(lo + _LM_BATCH, len(q0))
        batch = _Batch(np.arange(lo, hi), q0[lo:hi].T.copy(), np.ascontiguousarray(d[lo:hi].T),
                       np.full(hi - lo, _LAMBDA0), np.full(hi - lo, max_iter))
        return lm.run(batch, until=(hi - lo) // _LM_TAIL)

    tails = thread_map(bulk, range(0, len(q0), _LM_BATCH), workers)
    if tails:
        lm.run(_Batch(*(np.concatenate(parts, axis=-1) for parts in zip(*tails))), until=0)
    return lm.q.T.copy(), lm.cost, int(lm.used.max(initial=0))


@dataclass(eq=False)
class _Batch:
    """Points still iterating: rows (P,) of the output, q (3, P), d (K, P), lambda (P,), iterations left (P,)."""

    rows: np.ndarray
    q: np.ndarray
    d: np.ndarray
    lam: np.ndarray
    left: np.ndarray

    def __iter__(self):
        return iter((self.rows, self.q, self.d, self.lam, self.left))


class _LM:
    """The batched Levenberg-Marquardt iteration and the outputs it writes (see `_lm_batched`)."""

    def __init__(self, frame: _Frame, m: int, max_iter: int, newton: bool):
        a = frame.centred  # (K, 3)
        self.a = a
        self.moments = np.stack([a[:, 0], a[:, 1], a[:, 2], a[:, 0] * a[:, 0], a[:, 0] * a[:, 1],
                                 a[:, 0] * a[:, 2], a[:, 1] * a[:, 1], a[:, 1] * a[:, 2], a[:, 2] * a[:, 2]])  # (9, K)
        self.max_step = _STEP_BOUND * frame.radius
        self.xtol = _XTOL * frame.radius
        self.tiny = 1e-300 + 1e-12 * frame.radius  # a point closer than this to an anchor: J row ~ 0
        self.max_iter = max_iter
        self.newton = newton
        self.q = np.zeros((3, m))  # outputs, written as points finish
        self.cost = np.zeros(m)
        self.used = np.zeros(m, dtype=np.int64)  # iterations each point ran

    def run(self, batch: _Batch, until: int) -> tuple:
        """Iterate until at most `until` points are left; returns them as (rows, q, d, lam, left)."""
        rows, q, dist, lam, left = batch
        a, k, tiny = self.a, len(self.a), self.tiny
        noise_scale = 16.0 * np.finfo(float).eps
        rho, r, inv, cost, grad = _state(q, dist, a, tiny)
        while len(rows) > until:
            if self.newton:
                w = dist * inv  # (K, P)
                shift = (k + lam) - w.sum(axis=0)  # (P,): sum_j (1 - w_j) plus the damping, on the diagonal
                h = _weighted_outer(w * inv * inv, q, self.moments)
                step, solved = _cholesky_solve3_entries(h[0] + shift, h[1], h[2], h[3] + shift, h[4], h[5] + shift,
                                                        -grad[0], -grad[1], -grad[2])
            else:
                step, solved = np.zeros_like(grad), np.zeros(len(rows), dtype=bool)  # (3, P), (P,)
            if not solved.all():
                rest = np.flatnonzero(~solved)
                inv_r, lam_r = inv[:, rest], lam[rest]
                h = _weighted_outer(inv_r * inv_r, q[:, rest], self.moments)  # J^T J
                gn_step, gn_ok = _cholesky_solve3_entries(h[0] + lam_r, h[1], h[2], h[3] + lam_r, h[4], h[5] + lam_r,
                                                          -grad[0, rest], -grad[1, rest], -grad[2, rest])
                gn_step[:, ~gn_ok] = 0.0  # only with lambda ~ 0 on a degenerate point: no move
                step[:, rest] = gn_step
            norm = np.sqrt(np.einsum("ip,ip->p", step, step))  # (P,)
            step *= np.minimum(1.0, self.max_step / np.maximum(norm, 1e-300))
            trial = q + step  # (3, P)
            t_rho, t_r, t_inv, t_cost, t_grad = _state(trial, dist, a, tiny)
            # Keep a step that lowers the cost; where the change is within the cost's own
            # rounding error (eps * sum_j |r_j| (rho_j + d_j)) keep it if it lowers the
            # gradient instead, so points settle to ~1e-15 and not to sqrt(eps) ~ 1e-8.
            noise = noise_scale * np.einsum("kp,kp->p", np.abs(r), rho + dist)  # (P,)
            flat = t_cost <= cost + noise
            lower_grad = np.einsum("ip,ip->p", t_grad, t_grad) < np.einsum("ip,ip->p", grad, grad)
            ok = np.isfinite(t_cost) & ((t_cost < cost) | (flat & lower_grad))  # (P,)
            if ok.all():
                q, grad, rho, r, inv, cost = trial, t_grad, t_rho, t_r, t_inv, t_cost
            else:
                for mine, theirs in ((q, trial), (grad, t_grad), (rho, t_rho), (r, t_r), (inv, t_inv)):
                    np.copyto(mine, theirs, where=ok)
                cost = np.where(ok, t_cost, cost)
            lam = np.where(ok, np.maximum(lam * _LAMBDA_DOWN, _LAMBDA_MIN), np.minimum(lam * _LAMBDA_UP, _LAMBDA_MAX))
            left = left - 1
            done = (norm <= self.xtol) | (lam >= _LAMBDA_MAX) | (left == 0)  # (P,)
            if done.any():
                gone = rows[done]
                self.q[:, gone], self.cost[gone] = q[:, done], cost[done]
                self.used[gone] = self.max_iter - left[done]
                live = np.flatnonzero(~done)
                rows, lam, cost, left = rows[live], lam[live], cost[live], left[live]
                q, grad, dist, rho, r, inv = (x[:, live] for x in (q, grad, dist, rho, r, inv))
        return rows, q, dist, lam, left


# --------------------------------------------------------------------- scipy LM


def _lm_scipy(q0: np.ndarray, d: np.ndarray, frame: _Frame, max_iter: int):
    """Reference: scipy least_squares(method="lm") point by point, same output as _lm_batched."""
    from scipy.optimize import least_squares

    a = frame.centred

    def fun(x, row):
        return np.sqrt(((x - a) ** 2).sum(axis=1)) - row  # (K,)

    def jac(x, row):
        diff = x - a  # (K, 3)
        return diff / np.maximum(np.sqrt((diff * diff).sum(axis=1)), 1e-300)[:, None]

    q = np.empty_like(q0)
    iterations = 0
    for i in range(len(q0)):
        res = least_squares(fun, q0[i], jac=jac, method="lm", args=(d[i],), x_scale=1.0,
                            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=max(100, 10 * max_iter))
        q[i] = res.x
        iterations = max(iterations, int(res.njev if res.njev is not None else res.nfev))
    cost = _eval(q, d, a)[3]  # (P,)
    return q, cost, iterations


# ------------------------------------------------------------------ reconstruct


def _two_sided_starts(q_lin: np.ndarray, d: np.ndarray, frame: _Frame, n: np.ndarray):
    """In-plane part of the linear start pushed by +h and -h along the normal n."""
    q_in = q_lin - (q_lin @ n)[:, None] * n  # (M, 3)
    a = frame.centred
    sq = ((q_in[:, None, :] - a[None, :, :]) ** 2).sum(axis=2)  # (M, K)
    h = np.sqrt(np.maximum((d * d).mean(axis=1) - sq.mean(axis=1), 0.0))  # (M,)
    h = np.maximum(h, _H_FLOOR * frame.radius)  # never both starts on the plane (a saddle)
    return q_in + h[:, None] * n, q_in - h[:, None] * n


def _select(q_a, cost_a, q_b, cost_b, k: int, frame: _Frame, n: np.ndarray):
    """Per point the lower residual, unless within TIE_CHI2 noise variances: then the
    candidate farther along the oriented normal n."""
    sse_a, sse_b = 2.0 * cost_a, 2.0 * cost_b  # (M,) sums of squared residuals
    sigma2 = float(np.median(np.minimum(sse_a, sse_b))) / max(k - 3, 1) if len(sse_a) else 0.0
    atol = k * (_TIE_ATOL * frame.radius) ** 2
    tie = np.abs(sse_a - sse_b) <= TIE_CHI2 * sigma2 + atol  # (M,)
    pick_a = np.where(tie, q_a @ n >= q_b @ n, sse_a <= sse_b)  # (M,)
    return np.where(pick_a[:, None], q_a, q_b), np.where(pick_a, cost_a, cost_b)


def reconstruct(
    distances,
    anchors,
    method: str = "batched",
    *,
    max_iter: int = 20,
    reference_points=None,
    workers: int = 1,
) -> Reconstruction:
    """Recover points from their distances to the anchors.

    See the module docstring for the algorithm. Distances are clipped at 0 (a network
    may predict slightly negative values); the residuals are measured against the
    clipped values.

    Parameters
    ----------
    distances : (M, K) float
        Predicted or measured distances from each point to each anchor. M may be 0.
    anchors : (K, 3) float
        K >= 4 anchors, not collinear (see `check_anchors`).
    method : {"batched", "scipy", "batched-naive"}
        "batched": vectorised numpy LM (fast path). "scipy": per-point
        ``scipy.optimize.least_squares(method="lm")`` (reference; slow).
        "batched-naive": the same iteration as "batched" on (M, K, 3) arrays (reference).
    max_iter : int
        LM iterations (batched) or the scale of scipy's evaluation budget.
    reference_points : (N, 3) float or None
        The partial cloud the anchors were taken from; only used to choose the side of
        a near-planar anchor set when distances cannot (see `plane_normal`).
    workers : int
        Threads for the batched solver (the same result with any number).

    Returns
    -------
    Reconstruction

    Notes
    -----
    Points are solved independently except for one number: in the near-planar case the
    noise variance behind the side choice (`TIE_CHI2`) is the median over the call's
    points, so a borderline point may choose differently when solved in another batch.
    """
    as_choice(method, "the reconstruction method", METHODS + REFERENCE_METHODS)
    max_iter = as_count(max_iter, "max_iter", minimum=1)
    anc = _as_anchors(anchors)
    check_anchors(anc)
    dist = _as_distances(distances, anc.shape[0])  # (M, K)
    reference = _as_reference(reference_points)
    frame = _frame(anc)
    workers = as_count(workers, "workers", minimum=1)
    solve = {"batched": partial(_lm_batched, workers=workers), "scipy": _lm_scipy,
             "batched-naive": _lm_batched_naive}[method]
    k = anc.shape[0]
    m = dist.shape[0]

    q_lin = _linear_centred(dist, frame, RCOND)  # (M, 3)
    if not frame.near_planar:
        q, cost, iterations = solve(q_lin, dist, frame, int(max_iter))
    else:
        n = _oriented_normal(frame, reference)  # (3,)
        start_a, start_b = _two_sided_starts(q_lin, dist, frame, n)  # (M, 3) each
        q2, cost2, iterations = solve(np.concatenate([start_a, start_b]), np.concatenate([dist, dist]),
                                      frame, int(max_iter))  # (2M, 3), (2M,)
        q, cost = _select(q2[:m], cost2[:m], q2[m:], cost2[m:], k, frame, n)
    return Reconstruction(
        points=q + frame.center,
        residuals=np.sqrt(2.0 * cost / k),
        near_planar=frame.near_planar,
        anchor_singular_values=frame.s.copy(),
        iterations=int(iterations),
    )
