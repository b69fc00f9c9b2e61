"""End-to-end completion: normalise, anchors, encode, network, reconstruct, snap, merge.

    from escape_cli import complete, complete_many
    result = complete(points)          # points : (N, 3) in any frame and units
    result.points                      # (M, 3) completed cloud in the input's frame
    results = complete_many(clouds)    # one Completion per cloud, the network run in batches
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.core.params import as_choice, as_count
from escape_cli.core.sampling import count_distinct, first_unique_rows, resample_rows, select_confident_rows
from escape_cli.errors import EscapeError, ParameterError, PointCloudError

log = logging.getLogger("escape")

MIN_INPUT_POINTS = 16
NORMALIZE_MODES = ("auto", "none")
# With several anchor sets, this share of the pooled predicted points (the largest
# residuals) is left out before the even draw (chosen on validation: models/README.md).
ENSEMBLE_DROP = 0.1


@dataclass(frozen=True)
class Completion:
    """The result of `complete`.

    Attributes
    ----------
    points : (M, 3) float64, the completed cloud in the input's frame and units.
    residuals : (M,) float64, per-point reconstruction residual in input units (0 for
        observed points); a confidence measure.
    is_observed : (M,) bool, True for points copied from the input.
    is_snapped : (M,) bool, True for predicted points pulled onto the scan's surface.
    anchors : (K, 3) float64, the anchors in the input's frame (the first set's).
    anchor_indices : (K,) int64, rows of the network input (the FPS-ordered subsample).
    near_planar : bool, the anchors (of any set) were nearly coplanar (less reliable depth).
    normalization : the transform applied before the network (`invert` maps back).
    available : int, the distinct points the output was drawn from (predicted, plus the
        observed ones with `keep_input`); the output has min(output_points, available).
    """

    points: np.ndarray
    residuals: np.ndarray
    is_observed: np.ndarray
    is_snapped: np.ndarray
    anchors: np.ndarray
    anchor_indices: np.ndarray
    near_planar: bool
    normalization: object
    available: int

    def summary(self) -> dict:
        predicted = ~self.is_observed
        return {
            "points": int(len(self.points)),
            "available_points": int(self.available),
            "observed": int(self.is_observed.sum()),
            "snapped": int(self.is_snapped.sum()),
            "near_planar_anchors": bool(self.near_planar),
            "residual_mean": float(self.residuals[predicted].mean()) if predicted.any() else 0.0,
            "residual_p95": float(np.quantile(self.residuals[predicted], 0.95)) if predicted.any() else 0.0,
            "scale": float(self.normalization.scale),
        }


def complete(
    points,
    model=None,
    *,
    normalize: str = "auto",
    output_points: int = 16384,
    keep_input: bool = True,
    snap_radius: float | None = None,
    solver: str = "batched",
    threads: int = 0,
    anchor_sets: int = 1,
) -> Completion:
    """Complete a partial cloud.

    Parameters
    ----------
    points : (N, 3) float, the partial scan, N >= 16 distinct points, any pose.
    model : path to an .onnx model, a packaged model's name (``"small"``, ``"synth"``), a loaded
        `CompletionModel`, or None for the default.
    normalize : "auto" scales the scan so its radius matches the training partials
        (rotation invariant, exactly inverted afterwards); "none" feeds it as is (for
        data already in PCN units).
    output_points : M, the size of the returned cloud.
    keep_input : merge the observed points into the output.
    snap_radius : pull predicted points within about this distance of the scan onto its
        local surface (`escape_cli.core.snap`), in the network's units; None for the default
        (`SNAP_RADIUS`), 0 to turn it off.
    solver : "batched" (fast, guarded LM) or "scipy" (per-point reference LM).
    threads : cores this completion may use (onnxruntime's threads, and threads for the
        solver and the snap's neighbour query); 0 for all of them.
    anchor_sets : S, complete from S anchor sets (`escape_cli.core.anchors.anchor_sets`)
        and pool the results: the network runs S times, the solver on an even seeded
        share of each set's rows (as many as the output needs), the ENSEMBLE_DROP share
        of the pool with the largest residuals is left out, and an even seeded draw of the
        rest fills the output. Covers more of the unseen parts than one set
        (models/README.md, "Anchor-set ensembles"); 1 to K.

    Returns
    -------
    Completion
    """
    options = _Options.check(normalize, output_points, keep_input, snap_radius, solver, threads, anchor_sets)
    pts = _checked_cloud(points)
    net = _load(model, threads, options)
    scan = _prepare(pts, net, options)
    return _finish(scan, net.predict(scan.features), options)


def complete_many(
    clouds,
    model=None,
    *,
    batch_size: int = 16,
    return_exceptions: bool = False,
    normalize: str = "auto",
    output_points: int = 16384,
    keep_input: bool = True,
    snap_radius: float | None = None,
    solver: str = "batched",
    threads: int = 0,
    anchor_sets: int = 1,
) -> list:
    """Complete many partial clouds, running the network on `batch_size` scans at a time.

    Each result equals ``complete(cloud, model, **options)`` of that cloud (the network
    treats the scans of a batch independently); only the network's forward pass is
    shared. Measured on 2 busy cores (``bench/bench_complete.py``) that is no faster:
    the forward pass took 64 ms per scan one at a time, 74 in batches of 4 and 80 in
    batches of 16, and 64 scans went at 5.5 scans/s either way (7.4 with the compiled
    kernels); what it gives there is one model load and per-scan errors that do not
    stop the others.

    Parameters
    ----------
    clouds : iterable of (N_i, 3) float arrays.
    model : as in `complete`; loaded once.
    batch_size : scans per forward pass (B; each scan is S rows of it with `anchor_sets`).
    return_exceptions : put the `EscapeError` a cloud raises in its place in the result
        and go on with the others, instead of raising it.
    normalize, output_points, keep_input, snap_radius, solver, threads, anchor_sets : as in `complete`.

    Returns
    -------
    list of Completion (or EscapeError, with `return_exceptions`), one per cloud, in order.
    """
    options = _Options.check(normalize, output_points, keep_input, snap_radius, solver, threads, anchor_sets)
    batch_size = as_count(batch_size, "batch_size", minimum=1)
    net = _load(model, threads, options)
    results: list = []
    waiting: list = []  # (position in results, _Scan) before the network

    def run_batch() -> None:
        if not waiting:
            return
        try:
            rows = net.predict(np.concatenate([scan.features for _, scan in waiting]))  # (B * S, M', K)
            predicted = np.split(rows, len(waiting))  # B of (S, M', K)
        except EscapeError as err:
            if not return_exceptions:
                raise
            predicted = [err] * len(waiting)
        for (slot, scan), pred in zip(waiting, predicted):
            results[slot] = pred if isinstance(pred, EscapeError) else _guarded(
                lambda: _finish(scan, pred, options), return_exceptions)
        waiting.clear()

    for cloud in clouds:
        results.append(None)
        scan = _guarded(lambda: _prepare(_checked_cloud(cloud), net, options), return_exceptions)
        if isinstance(scan, EscapeError):
            results[-1] = scan
            continue
        waiting.append((len(results) - 1, scan))
        if len(waiting) == batch_size:
            run_batch()
    run_batch()
    return results


def _guarded(func, catch: bool):
    """func(), or the EscapeError it raised when `catch`."""
    if not catch:
        return func()
    try:
        return func()
    except EscapeError as err:
        return err


@dataclass(frozen=True)
class _Options:
    """The checked options of `complete` that shape each result."""

    normalize: str
    output_points: int
    keep_input: bool
    snap_radius: float
    solver: str
    workers: int  # threads of the solver and the snap
    anchor_sets: int

    @classmethod
    def check(cls, normalize, output_points, keep_input, snap_radius, solver, threads, anchor_sets=1) -> "_Options":
        from escape_cli.core.reconstruction import METHODS
        from escape_cli.core.snap import SNAP_RADIUS, check_snap_radius

        return cls(
            normalize=as_choice(normalize, "normalize", NORMALIZE_MODES),
            output_points=as_count(output_points, "output_points", minimum=1),
            keep_input=bool(keep_input),
            snap_radius=SNAP_RADIUS if snap_radius is None else check_snap_radius(snap_radius),
            solver=as_choice(solver, "the reconstruction method", METHODS),
            workers=as_count(threads, "threads", minimum=0) or (os.cpu_count() or 1),
            anchor_sets=as_count(anchor_sets, "anchor_sets", minimum=1),
        )


def _load(model, threads: int, options: _Options):
    """The loaded model, checked against the options that depend on it."""
    from escape_cli.inference import CompletionModel, load_model

    net = model if isinstance(model, CompletionModel) else load_model(None if model is None else str(model), threads)
    if options.anchor_sets > net.k:
        raise ParameterError(f"anchor_sets must be at most {net.k}, the anchors of {net.path.name}; got {options.anchor_sets}")
    return net


@dataclass(frozen=True, eq=False)
class _Scan:
    """A scan made ready for the network: its input, anchors and features."""

    net_in: object  # NetworkInput
    anchor_sets: list  # S Anchors, the first `select_anchors`'s
    features: np.ndarray  # (S, N', K) float32
    tree: object  # NeighbourIndex of the observed points, reused by the snap


def _checked_cloud(points) -> np.ndarray:
    """(N, 3) float64 with at least MIN_INPUT_POINTS distinct points, else PointCloudError."""
    pts = as_points(points, "input cloud", min_points=1)
    if len(pts) > 64 * MIN_INPUT_POINTS and count_distinct(pts[:: len(pts) // (64 * MIN_INPUT_POINTS)]) >= MIN_INPUT_POINTS:
        return pts  # enough distinct points among a few: no need to count them all (millions take seconds)
    distinct = count_distinct(pts)
    if distinct < MIN_INPUT_POINTS:
        raise PointCloudError(f"the input has {distinct} distinct points; at least {MIN_INPUT_POINTS} are needed to complete it")
    return pts


def _prepare(pts: np.ndarray, net, options: _Options) -> _Scan:
    """Everything before the network: the network's frame, anchors, distances (pts checked)."""
    from escape_cli.core.anchors import anchor_sets
    from escape_cli.core.encoding import distance_matrix
    from escape_cli.core.neighbours import NeighbourIndex

    net_in = _network_input(pts, net, options.normalize)
    observed = net_in.observed  # (U, 3) in the network's frame
    tree = NeighbourIndex(observed)
    sets = anchor_sets(observed, options.anchor_sets, **net.anchors.to_dict(), tree=tree)  # S of (K, 3)
    features = np.stack([distance_matrix(net_in.rows, a.points) for a in sets]).astype(np.float32)  # (S, N', K)
    return _Scan(net_in, sets, features, tree)


def _finish(scan: _Scan, predicted: np.ndarray, options: _Options) -> Completion:
    """Everything after the network: solve, snap, pool the sets, merge the observed points, back to the input's frame.

    predicted : (S, M', K) the network's distances for each anchor set of the scan.
    """
    net_in = scan.net_in
    observed_points = net_in.observed  # (U, 3)
    merged = len(observed_points) if options.keep_input else 0  # observed points joining the output
    wanted = max(options.output_points - merged, 0)  # predicted points the output needs
    share = _per_set_share(wanted, len(predicted))
    solved = [_solve(scan, anchors, pred, options, share, j) for j, (anchors, pred) in enumerate(zip(scan.anchor_sets, predicted))]
    out = np.concatenate([one.points for one in solved])  # (P, 3) pooled predicted points, P <= S * M'
    residuals = np.concatenate([one.residuals for one in solved])  # (P,)
    snapped = np.concatenate([one.snapped for one in solved])  # (P,)
    available = sum(one.rows for one in solved) + merged
    if len(solved) > 1:
        rows = pooled_rows(residuals, min(wanted, len(out)))
        out, residuals, snapped = out[rows], residuals[rows], snapped[rows]
    observed = np.zeros(len(out), dtype=bool)
    if options.keep_input:
        unique = len(observed_points)
        out = np.concatenate([out, observed_points])
        residuals = np.concatenate([residuals, np.zeros(unique)])
        observed = np.concatenate([observed, np.ones(unique, dtype=bool)])
        snapped = np.concatenate([snapped, np.zeros(unique, dtype=bool)])
    if options.output_points > available:
        log.warning("the completion has %d distinct points, fewer than the %d asked for; all are returned",
                    available, options.output_points)
    rows = select_confident_rows(residuals, min(options.output_points, len(out)))  # a subset: never a repeated point
    norm = net_in.normalization
    first = scan.anchor_sets[0]
    return Completion(
        points=norm.invert(out[rows]),
        residuals=residuals[rows] * norm.scale,
        is_observed=observed[rows],
        is_snapped=snapped[rows],
        anchors=norm.invert(first.points),
        anchor_indices=first.indices,
        near_planar=any(one.near_planar for one in solved),
        normalization=norm,
        available=available,
    )


@dataclass(frozen=True)
class _Solved:
    """The predicted points of one anchor set, in the network's frame."""

    points: np.ndarray  # (R, 3) after the snap, R <= M' (the rows solved)
    residuals: np.ndarray  # (R,) the solver's
    snapped: np.ndarray  # (R,) bool
    near_planar: bool
    rows: int  # M', the set's distinct predicted rows (solved or not)


def _per_set_share(wanted: int, sets: int) -> int | None:
    """Predicted rows to solve from each of `sets` anchor sets (None: all of them).

    The pooled draw keeps `wanted` points after leaving out the ENSEMBLE_DROP share, so
    an even draw of wanted / (S (1 - drop)) rows of each set is solved, not all S * M':
    the same pool in distribution, at about the solver's cost of one set.
    """
    if sets == 1:
        return None
    return max(1, int(np.ceil(wanted / (sets * (1.0 - ENSEMBLE_DROP)))))


def _solve(scan: _Scan, anchors, predicted: np.ndarray, options: _Options, share: int | None = None,
           set_index: int = 0) -> _Solved:
    """Points from one set's predicted distances (M', K): reconstruct, then snap onto the scan.

    share : solve an even seeded draw of this many rows (None: all); drawn from the row
        count and `set_index` alone, so the choice commutes with any similarity.
    """
    from escape_cli.core.reconstruction import reconstruct
    from escape_cli.core.snap import snap_to_scan

    observed_points = scan.net_in.observed  # (U, 3)
    predicted = np.asarray(predicted, dtype=np.float64)  # (M', K)
    if scan.net_in.unique < len(scan.net_in.rows):  # repeated input rows seed identical queries: drop their copies
        predicted = predicted[first_unique_rows(predicted, predicted.shape[1])]
    rows = len(predicted)
    if share is not None and share < rows:
        predicted = predicted[resample_rows(rows, share, seed=(1, set_index))]
    rec = reconstruct(predicted, anchors.points, method=options.solver, reference_points=observed_points,
                      workers=options.workers)
    snap = snap_to_scan(rec.points, observed_points, options.snap_radius, tree=scan.tree, workers=options.workers)
    return _Solved(snap.points, rec.residuals, snap.moved, bool(rec.near_planar), rows)


def pooled_rows(residuals, size: int, seed: int = 0) -> np.ndarray:
    """Rows of `size` pooled predicted points: the least sure share left out, an even draw of the rest.

    The ENSEMBLE_DROP share of the points with the largest residuals (no more than the
    surplus) is left out, then `size` of the others are drawn uniformly with a fixed
    seed. Depends only on the residuals' order and the rows' order, so it commutes with
    any similarity of the points.

    Parameters
    ----------
    residuals : (P,) float64, >= 0.
    size : rows to keep, 0 <= size <= P.

    Returns
    -------
    rows : (size,) int64, ascending, distinct.
    """
    count = len(residuals)
    if size >= count:
        return np.arange(count)
    drop = min(int(ENSEMBLE_DROP * count), count - size)
    kept = np.sort(np.argsort(residuals, kind="stable")[: count - drop])  # (P - drop,)
    rng = np.random.default_rng(seed)
    return np.sort(kept[rng.choice(len(kept), size, replace=False)])


def _network_input(pts: np.ndarray, net, normalize: str):
    """The network input of a scan (N, 3) in the model's frame (see `escape_cli.core.normalize`)."""
    from escape_cli.core.normalize import NetworkInput, Normalization, fit_normalization, network_input

    frame = net.frame
    if frame is not None:
        if normalize == "none":
            raise ParameterError(
                f"{net.path.name} works in each scan's own frame; --normalize none is only for models trained in absolute units"
            )
        return network_input(pts, net.input_points, frame)
    # a model trained in absolute PCN units: the older radius heuristic, or the units as given
    norm = fit_normalization(pts, net.target_radius) if normalize == "auto" and net.target_radius else Normalization.identity()
    plain = network_input(norm.apply(pts), net.input_points, None)
    return NetworkInput(plain.rows, plain.unique, norm)
