"""The one boundary check: every public core function refuses bad arrays with PointCloudError."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from escape_cli.core import (
    anchors,
    checks,
    curvature,
    encoding,
    metrics,
    normalize,
    reconstruction,
    rotations,
    sampling,
    neighbours,
    snap,
)
from escape_cli.core.checks import MAX_MAGNITUDE, as_points, as_rows
from escape_cli.core.params import as_choice, as_count, as_number
from escape_cli.errors import ParameterError, PointCloudError

RNG = np.random.default_rng(3)
CLOUD = RNG.normal(size=(200, 3)) * [0.4, 0.3, 0.2]
ANCHORS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1.2]], float)
DISTANCES = np.linalg.norm(CLOUD[:20, None] - ANCHORS[None], axis=2)  # (20, 8)
BOX = np.array([[0, 0, 0], [0, 0, 1], [2, 0, 1], [2, 0, 0], [0, 1, 0], [0, 1, 1], [2, 1, 1], [2, 1, 0]], float)

# function -> (valid arguments, positions of the array arguments)
CALLS = {
    checks.as_points: ((CLOUD,), [0]),
    checks.as_rows: ((DISTANCES, "distances", 8), [0]),
    checks.as_vector: ((np.ones(3), "vector"), [0]),
    checks.check_not_collinear: ((CLOUD,), [0]),
    sampling.farthest_from_centroid: ((CLOUD,), [0]),
    sampling.farthest_point_sampling: ((CLOUD, 16), [0]),
    sampling.farthest_point_sampling_naive: ((CLOUD, 16), [0]),
    sampling.count_distinct: ((CLOUD,), [0]),
    sampling.power_of_two_unit: ((CLOUD,), [0]),
    sampling.thin_by_radius: ((CLOUD, 50), [0]),
    sampling.first_unique_rows: ((DISTANCES, 8), [0]),
    sampling.prepare_input: ((CLOUD, 64), [0]),
    sampling.select_confident_rows: ((np.abs(CLOUD[:, 0]), 150), [0]),
    curvature.tie_stable_neighbours: ((CLOUD, 8), [0]),
    curvature.surface_variation: ((CLOUD, 8), [0]),
    anchors.select_anchors: ((CLOUD,), [0]),
    anchors.anchor_sets: ((CLOUD, 3), [0]),
    encoding.distance_matrix: ((CLOUD, ANCHORS), [0, 1]),
    reconstruction.check_anchors: ((ANCHORS,), [0]),
    reconstruction.linear_multilateration: ((DISTANCES, ANCHORS), [0, 1]),
    reconstruction.linear_multilateration_naive: ((DISTANCES, ANCHORS), [0, 1]),
    reconstruction.plane_normal: ((ANCHORS, CLOUD), [0, 1]),
    reconstruction.rms_residuals: ((CLOUD[:20], DISTANCES, ANCHORS), [0, 1, 2]),
    reconstruction.reconstruct: ((DISTANCES, ANCHORS), [0, 1]),
    snap.snap_to_scan: ((CLOUD[:20], CLOUD), [0, 1]),
    neighbours.NeighbourIndex: ((CLOUD,), [0]),
    neighbours.NeighbourIndex(CLOUD).query: ((CLOUD[:20], 4), [0]),
    normalize.cloud_radius: ((CLOUD,), [0]),
    normalize.cloud_radius_naive: ((CLOUD,), [0]),
    normalize.fit_normalization: ((CLOUD, 0.3), [0]),
    normalize.Normalization.identity().apply: ((CLOUD,), [0]),
    normalize.Normalization.identity().invert: ((CLOUD,), [0]),
    normalize.box_normalization(BOX).apply: ((CLOUD,), [0]),
    normalize.box_normalization(BOX).invert: ((CLOUD,), [0]),
    normalize.car_in_box_frame: ((CLOUD, "z"), [0]),
    rotations.rotation_about_axis: ((np.ones(3), 0.3), [0]),
    metrics.nearest_distances: ((CLOUD, CLOUD), [0, 1]),
    metrics.nearest_distances_naive: ((CLOUD, CLOUD), [0, 1]),
    metrics.chamfer_l1: ((CLOUD, CLOUD), [0, 1]),
    metrics.chamfer_l1_naive: ((CLOUD, CLOUD), [0, 1]),
    metrics.chamfer_l2: ((CLOUD, CLOUD), [0, 1]),
    metrics.chamfer_l2_naive: ((CLOUD, CLOUD), [0, 1]),
    metrics.fscore: ((CLOUD, CLOUD), [0, 1]),
    metrics.fscore_naive: ((CLOUD, CLOUD), [0, 1]),
    metrics.fidelity: ((CLOUD, CLOUD), [0, 1]),
    metrics.fidelity_naive: ((CLOUD, CLOUD), [0, 1]),
    metrics.point_metrics: ((CLOUD, CLOUD), [0, 1]),
    metrics.point_metrics_naive: ((CLOUD, CLOUD), [0, 1]),
}
if hasattr(normalize, "network_input"):
    CALLS[normalize.network_input] = ((CLOUD, 64), [0])
    CALLS[normalize.PartialFrame().fit] = ((CLOUD,), [0])

# Public core callables that take no point array (scalars, generators, records, predicates).
NO_ARRAYS = {
    "params": {"as_number", "as_count", "as_choice"},
    "settings": {"AnchorSettings"},
    "sampling": {"resample_rows"},
    "snap": {"check_snap_radius", "Snap"},
    "rotations": {"as_generator", "random_rotation", "paper_rotation", "is_rotation"},
    "anchors": {"Anchors", "AnchorSettings"},
    "reconstruction": {"Reconstruction"},
    "normalize": {"Normalization", "BoxNormalization", "box_normalization", "PartialFrame", "NetworkInput"},
    "threads": {"thread_map"},
}


def _wrong_shape(good):
    return np.zeros((5, 2)) if np.ndim(good) == 2 else np.zeros((2, 2))


def _with_nan(good):
    bad = np.array(good, dtype=float, copy=True)
    bad.flat[min(3, bad.size - 1)] = np.nan
    return bad


BAD = {
    "wrong shape": _wrong_shape,
    "NaN": _with_nan,
    "a string": lambda good: "not points",
    "complex": lambda good: np.asarray(good) * (1 + 1j),
    "huge": lambda good: np.asarray(good, dtype=float) * 1e300 + 1e300,
}


def _cases():
    for func, (args, positions) in CALLS.items():
        for position in positions:
            for label in BAD:
                name = getattr(func, "__qualname__", str(func))
                yield pytest.param(func, args, position, label, id=f"{name}-arg{position}-{label}")


@pytest.mark.parametrize("func, args, position, label", list(_cases()))
def test_bad_arrays_raise_point_cloud_error(func, args, position, label):
    bad_args = list(args)
    bad_args[position] = BAD[label](args[position])
    with pytest.raises(PointCloudError):
        func(*bad_args)


@pytest.mark.parametrize("func, args", [pytest.param(f, a, id=getattr(f, "__qualname__", "")) for f, (a, _) in CALLS.items()])
def test_valid_arguments_pass(func, args):
    func(*args)  # the table itself is right: good arguments do not raise


def test_every_public_core_function_is_covered():
    import escape_cli.core as core_package
    import pkgutil

    covered = {getattr(f, "__qualname__", "") for f in CALLS} | {
        getattr(getattr(f, "__self__", None), "__class__", type(None)).__name__ + "." + f.__name__
        for f in CALLS if hasattr(f, "__self__")
    }
    missing = []
    for info in pkgutil.iter_modules(core_package.__path__):
        module = __import__(f"escape_cli.core.{info.name}", fromlist=["_"])
        for name, obj in vars(module).items():
            if name.startswith("_") or not (inspect.isfunction(obj) or inspect.isclass(obj)):
                continue
            if getattr(obj, "__module__", "") != module.__name__:
                continue
            if name in NO_ARRAYS.get(info.name, set()) or name in covered:
                continue
            missing.append(f"{info.name}.{name}")
    assert not missing, f"public core functions not in the bad-array table: {missing}"


def test_one_wording():
    with pytest.raises(PointCloudError, match=r"^scan must have shape \(N, 3\), not shape \(4, 2\)$"):
        as_points(np.zeros((4, 2)), "scan")
    with pytest.raises(PointCloudError, match=r"^scan has 3 points; at least 16 are needed$"):
        as_points(np.zeros((3, 3)), "scan", min_points=16)
    with pytest.raises(PointCloudError, match=r"^scan is empty \(no points\)$"):
        as_points(np.zeros((0, 3)), "scan", min_points=1)
    with pytest.raises(PointCloudError, match=r"^NaN or infinite values in scan$"):
        as_points([[0, 0, np.inf]], "scan")
    with pytest.raises(PointCloudError, match="at most 1e\\+150"):
        as_points([[0, 0, MAX_MAGNITUDE * 10]], "scan")
    with pytest.raises(PointCloudError, match=r"distances must have shape \(M, K\)"):
        as_rows(np.zeros(4), "distances", None, letters="MK")


def test_coercion_keeps_values_and_accepts_array_likes():
    out = as_points([[1, 2, 3], [4, 5, 6]])
    assert out.dtype == np.float64 and out.flags.c_contiguous
    np.testing.assert_array_equal(out, [[1, 2, 3], [4, 5, 6]])
    f32 = np.ones((4, 3), np.float32)
    assert as_points(f32).dtype == np.float64
    with pytest.raises(PointCloudError, match="numbers"):
        as_points([[1, 2], [3, 4, 5]])  # ragged


def test_parameters_raise_parameter_error():
    for call in (lambda: as_number("abc", "radius"), lambda: as_number(float("nan"), "radius"),
                 lambda: as_number(-1, "radius", minimum=0), lambda: as_number(0, "radius", above=0),
                 lambda: as_count(0, "points", minimum=1), lambda: as_count(2.5, "points"), lambda: as_count(True, "points"),
                 lambda: as_choice("bogus", "method", ("ball", "fps"))):
        with pytest.raises(ParameterError):
            call()
    assert as_number(np.float32(0.5), "radius", minimum=0) == 0.5
    assert as_count(np.int64(3), "k") == 3
