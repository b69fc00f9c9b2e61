"""Benchmarks: PCN-layout datasets (canonical and rotated, with noise or point removal) and KITTI cars.

Metrics follow DESIGN.md and are named by formula: CD-L1 x 1000 (unsquared, the two
directions averaged), CD-L2 x 1000 (squared, summed), F-Score@1%. KITTI has no ground
truth: Fidelity (input -> output) and MMD (CD-L2 to the nearest reference car), x 1000.
Benchmark averages are the mean of the per-category means.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from escape_cli.errors import DatasetError

METRIC_DEFINITIONS = {
    "cd_l1_x1000": "1000 * (mean_x min_y ||x-y|| + mean_y min_x ||y-x||) / 2",
    "cd_l2_x1000": "1000 * (mean_x min_y ||x-y||^2 + mean_y min_x ||y-x||^2)",
    "fscore_1pct": "2PR/(P+R), P = share of output within 0.01 of truth, R = share of truth within 0.01 of output",
    "pred_to_gt_x1000": "1000 * mean_x min_y ||x-y||, x in the output, y in the truth (precision half of CD-L1)",
    "gt_to_pred_x1000": "1000 * mean_y min_x ||y-x|| (recall half of CD-L1)",
    "ratio_to_input": "CD-L1(output, truth) / CD-L1(input, truth); pairs: the mean of the per-pair ratios",
    "fidelity_x1000": "1000 * mean over input points of the distance to the nearest predicted output point (the observed points merged into the output would make it 0)",
    "mmd_cd_l2_x1000": "1000 * min over reference cars of CD-L2(output, reference)",
}

Completer = Callable[[np.ndarray], np.ndarray]  # (N, 3) partial -> (M, 3) completion


@dataclass(frozen=True)
class Perturbation:
    """Robustness settings of the paper's supplementary tables."""

    noise: float = 0.0  # Gaussian sigma added to every input point
    drop: float = 0.0  # share of input points removed at random

    def apply(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """points : (N, 3) -> (N', 3)"""
        out = points
        if self.drop > 0:
            keep = rng.random(len(out)) >= self.drop
            if keep.sum() < 16:
                keep[: 16] = True
            out = out[keep]
        if self.noise > 0:
            out = out + rng.normal(scale=self.noise, size=out.shape)
        return out


def pcn_metrics(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    from escape_cli.core.metrics import point_metrics

    m = point_metrics(pred, truth, threshold=0.01)
    return {"cd_l1_x1000": 1000 * m["cd_l1"], "cd_l2_x1000": 1000 * m["cd_l2"], "fscore_1pct": m["fscore"],
            "pred_to_gt_x1000": 1000 * m["pred_to_gt"], "gt_to_pred_x1000": 1000 * m["gt_to_pred"]}


@dataclass
class PCNEvaluation:
    """Per-sample records of one PCN evaluation; `summary()` gives the tables."""

    methods: list[str]
    rotate: bool
    records: list[dict] = field(default_factory=list)
    mean_of_ratios: bool = False  # the average ratio to the input copy: mean of rows' ratios (pairs), else ratio of averages

    def summary(self) -> dict:
        from escape_cli.data.pcn import CATEGORIES

        categories: dict[str, dict] = {}
        synsets = sorted({r["synset"] for r in self.records})
        for synset in synsets:
            rows = [r for r in self.records if r["synset"] == synset]
            name = rows[0].get("category") or CATEGORIES.get(synset, synset)
            categories[name] = {"synset": synset, "count": len(rows), **_aggregate(rows)}
        average = {}
        if categories:
            keys = next(iter(categories.values())).keys() - {"synset", "count"}
            average = {k: float(np.mean([c[k] for c in categories.values()])) for k in sorted(keys)}
            average["count"] = sum(c["count"] for c in categories.values())
            for stats in categories.values():
                _add_ratios(stats)
            _add_ratios(average)
            if self.mean_of_ratios:
                for key in [k for k in average if k.endswith("ratio_to_input")]:
                    average[key] = float(np.mean([c[key] for c in categories.values()]))
        return {"categories": categories, "average": average}


def _add_ratios(stats: dict) -> None:
    """escape/cd_l1 mean over input/cd_l1 mean, for each pose, where the input copy was scored."""
    for prefix in ("", "rotated/"):
        ours, baseline = stats.get(f"{prefix}escape/cd_l1_x1000_mean"), stats.get(f"{prefix}input/cd_l1_x1000_mean")
        if ours is not None and baseline:
            stats[f"{prefix}escape/ratio_to_input"] = ours / baseline


def _aggregate(rows: list[dict]) -> dict[str, float]:
    out: dict[str, float] = {}
    for key in rows[0]["metrics"]:
        values = np.array([r["metrics"][key] for r in rows])
        out[f"{key}_mean"] = float(values.mean())
        if key.endswith("cd_l1_x1000"):
            out[f"{key}_median"] = float(np.median(values))
    return out


def evaluate_pcn(
    root: Path,
    completers: dict[str, Completer],
    *,
    split: str = "test",
    categories=None,
    rotate: bool = False,
    seed: int = 0,
    perturbation: Perturbation = Perturbation(),
    limit: int | None = None,
    save_dir: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> PCNEvaluation:
    """Evaluate each completer on the first view of every object of a split.

    With `rotate`, each sample is also evaluated after the paper's rotation (random
    angles in [0, 180] degrees about x, y and z; the ground truth rotated the same way),
    and metrics are stored as ``rotated/<name>``. Random choices are seeded per sample
    from (`seed`, sample index), so any subset gives the same numbers.
    """
    from escape_cli.data.pcn import list_samples, read_sample

    refs = list_samples(root, split, categories=categories, views="first")
    if limit is not None:
        refs = _limit_per_category(refs, limit)
    if not refs:
        raise DatasetError(f"no samples in {root} ({split})")
    result = PCNEvaluation(methods=list(completers), rotate=rotate)
    for i, ref in enumerate(refs):
        sample = read_sample(ref, n_points=None)
        rng = np.random.default_rng((seed, i))
        partial = perturbation.apply(sample.partial.astype(np.float64), rng)
        saver = None if save_dir is None else (lambda tag, pts, ref=ref: _save(save_dir, ref.synset, f"{ref.model_id}_{ref.view:02d}_{tag}", pts))
        metrics = _score_sample(partial, sample.complete.astype(np.float64), completers, rotate, rng, saver)
        result.records.append(
            {"synset": sample.synset, "category": sample.category, "model_id": sample.model_id, "view": sample.view,
             "input_points": int(len(partial)), "metrics": metrics}
        )
        if progress:
            progress(i + 1, len(refs))
    return result


def _score_sample(partial, truth, completers, rotate: bool, rng, saver=None) -> dict[str, float]:
    """Metrics of every completer on one (partial, truth) pair, canonical and optionally rotated."""
    from escape_cli.core.rotations import paper_rotation

    poses = {"": np.eye(3)}
    if rotate:
        poses["rotated/"] = paper_rotation(rng)
    metrics: dict[str, float] = {}
    for prefix, rotation in poses.items():
        for name, completer in completers.items():
            output = completer(partial @ rotation.T)
            for key, value in pcn_metrics(output, truth @ rotation.T).items():
                metrics[f"{prefix}{name}/{key}"] = value
            if saver is not None:
                saver(f"{name}{'_rotated' if prefix else ''}", output)
    return metrics


def evaluate_pairs(
    root: Path,
    completers: dict[str, Completer],
    *,
    rotate: bool = False,
    seed: int = 0,
    perturbation: Perturbation = Perturbation(),
    save_dir: Path | None = None,
) -> PCNEvaluation:
    """Evaluate partial views of one object with known ground truth.

    `root` holds `complete.<ext>` (the truth) and any number of partial views (every
    other cloud file), in the same frame, like realdata's p2c_chair. They are scored as
    one category named after the folder.
    """
    from escape_cli.io import CLOUD_SUFFIXES, read_points

    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root} is not a folder")
    files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in CLOUD_SUFFIXES)
    truth_files = [p for p in files if p.stem == "complete"]
    if len(truth_files) != 1:
        raise DatasetError(f"{root} must hold exactly one complete.<ext> ground-truth cloud")
    views = [p for p in files if p.stem != "complete"]
    if not views:
        raise DatasetError(f"{root} holds no partial views beside {truth_files[0].name}")
    truth = read_points(truth_files[0])
    result = PCNEvaluation(methods=list(completers), rotate=rotate)
    for i, view in enumerate(views):
        rng = np.random.default_rng((seed, i))
        partial = perturbation.apply(read_points(view), rng)
        saver = None if save_dir is None else (lambda tag, pts, v=view: _save(save_dir, root.name, f"{v.stem}_{tag}", pts))
        metrics = _score_sample(partial, truth, completers, rotate, rng, saver)
        result.records.append(
            {"synset": root.name, "category": root.name, "model_id": view.stem, "view": i,
             "input_points": int(len(partial)), "metrics": metrics}
        )
    return result


def pair_folder_files(root: Path) -> list[tuple[str, Path, Path]]:
    """(name, partial, complete) for every `<name>_partial.<ext>` with a `<name>_complete.<ext>` beside it, sorted."""
    from escape_cli.io import CLOUD_SUFFIXES

    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root} is not a folder")
    files = {p.stem: p for p in root.iterdir() if p.is_file() and p.suffix.lower() in CLOUD_SUFFIXES}
    pairs = []
    for stem, partial in sorted(files.items()):
        if not stem.endswith("_partial"):
            continue
        name = stem[: -len("_partial")]
        complete = files.get(f"{name}_complete")
        if complete is None:
            raise DatasetError(f"{partial.name} has no {name}_complete.<ext> beside it in {root}")
        pairs.append((name, partial, complete))
    if not pairs:
        raise DatasetError(f"{root} holds no <name>_partial.<ext> / <name>_complete.<ext> pairs")
    return pairs


def evaluate_pair_folder(
    root: Path,
    completers: dict[str, Completer],
    *,
    rotate: bool = False,
    seed: int = 0,
    perturbation: Perturbation = Perturbation(),
    save_dir: Path | None = None,
) -> PCNEvaluation:
    """Evaluate a folder of partial/complete pairs (the layout of realdata's `mvp_pairs`).

    Every `<name>_partial.<ext>` is completed and scored against `<name>_complete.<ext>`
    (the two in one frame); each pair is its own row, and the average ratio to the
    input copy is the mean of the per-pair ratios, which is free of the pairs' units.
    """
    from escape_cli.io import read_points

    result = PCNEvaluation(methods=list(completers), rotate=rotate, mean_of_ratios=True)
    for i, (name, partial_path, complete_path) in enumerate(pair_folder_files(root)):
        rng = np.random.default_rng((seed, i))
        partial = perturbation.apply(read_points(partial_path), rng)
        saver = None if save_dir is None else (lambda tag, pts, n=name: _save(save_dir, "pairs", f"{n}_{tag}", pts))
        metrics = _score_sample(partial, read_points(complete_path), completers, rotate, rng, saver)
        result.records.append(
            {"synset": name, "category": name, "model_id": name, "view": 0,
             "input_points": int(len(partial)), "metrics": metrics}
        )
    return result


def _limit_per_category(refs, limit: int):
    taken: dict[str, int] = {}
    out = []
    for ref in refs:
        if taken.get(ref.synset, 0) < limit:
            out.append(ref)
            taken[ref.synset] = taken.get(ref.synset, 0) + 1
    return out


def _save(folder: Path, group: str, name: str, points: np.ndarray) -> None:
    from escape_cli.io import write_points

    path = Path(folder) / group / f"{name}.ply"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_points(path, points, overwrite=True)


# -- KITTI -------------------------------------------------------------------------------


def read_box(path: Path) -> np.ndarray:
    """8 box corners from a text file (8 rows of x y z) -> (8, 3)."""
    try:
        corners = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as err:
        raise DatasetError(f"cannot read box {path}: {err}") from None
    if corners.shape != (8, 3):
        raise DatasetError(f"box {path} must hold 8 rows of x y z, got shape {corners.shape}")
    return corners


def kitti_pairs(root: Path) -> list[tuple[Path, Path]]:
    """(car cloud, box) pairs of a KITTI folder laid out as `cars/NAME.pcd` + `bboxes/NAME.txt`."""
    root = Path(root)
    cars = sorted((root / "cars").glob("*.pcd")) if (root / "cars").is_dir() else []
    if not cars:
        raise DatasetError(f"{root} has no cars/*.pcd (expected cars/NAME.pcd and bboxes/NAME.txt)")
    pairs = []
    for car in cars:
        box = root / "bboxes" / f"{car.stem}.txt"
        if not box.is_file():
            raise DatasetError(f"{car.name} has no box file {box}")
        pairs.append((car, box))
    return pairs


def evaluate_kitti(
    root: Path,
    completers: dict[str, Completer],
    *,
    reference: list[np.ndarray] | None = None,
    rotate: bool = False,
    seed: int = 0,
    save_dir: Path | None = None,
) -> dict:
    """Fidelity and MMD on real LiDAR car crops, normalised by their boxes (PCN/PoinTr way).

    A completer returns the (M, 3) completion, or a `pipeline.Completion` (anything
    with `points` and `is_observed`): Fidelity is then measured on its predicted
    points alone, since the observed points merged into the output would make it 0,
    and it is not scored for a completer that predicts no point (the input copy). MMD
    (on the whole output) needs `reference`. With `rotate`, each car is also turned
    about the box's up axis by a random angle (a vehicle's realistic motion), as in the
    paper's KITTI table. Log lines of a car's completion name the car.
    """
    from escape_cli.io import read_points
    from escape_cli.core.metrics import chamfer_l2, fidelity
    from escape_cli.core.normalize import box_normalization
    from escape_cli.core.rotations import rotation_about_axis

    records = []
    for i, (car_path, box_path) in enumerate(kitti_pairs(root)):
        box = box_normalization(read_box(box_path))
        car = box.apply(read_points(car_path))  # (N, 3) in the car's frame, length 1
        rng = np.random.default_rng((seed, i))
        poses = {"": np.eye(3)}
        if rotate:
            poses["rotated/"] = rotation_about_axis([0.0, 1.0, 0.0], rng.uniform(0, 2 * np.pi))
        metrics: dict[str, float] = {}
        for prefix, rotation in poses.items():
            for name, completer in completers.items():
                rotated_input = car @ rotation.T
                with _logged_about(car_path.stem):
                    output, predicted = _output_and_predicted(completer(rotated_input))
                output, predicted = output @ rotation, predicted @ rotation  # back to the box frame for MMD
                if len(predicted):
                    metrics[f"{prefix}{name}/fidelity_x1000"] = 1000 * fidelity(car, predicted)
                if reference:
                    metrics[f"{prefix}{name}/mmd_cd_l2_x1000"] = 1000 * min(chamfer_l2(output, ref) for ref in reference)
                if save_dir is not None:
                    path = Path(save_dir) / f"{car_path.stem}_{name}{'_rotated' if prefix else ''}.ply"
                    path.parent.mkdir(parents=True, exist_ok=True)
                    from escape_cli.io import write_points

                    write_points(path, box.invert(output), overwrite=True)
        records.append({"car": car_path.stem, "input_points": int(len(car)), "metrics": metrics})
    keys = records[0]["metrics"].keys()
    average = {f"{k}_mean": float(np.mean([r["metrics"][k] for r in records])) for k in keys}
    return {"cars": records, "average": average}


def _output_and_predicted(output) -> tuple[np.ndarray, np.ndarray]:
    """A completer's whole (M, 3) output and its (P, 3) predicted points (all of a bare array)."""
    if hasattr(output, "is_observed"):
        points = np.asarray(output.points, dtype=np.float64)
        return points, points[~np.asarray(output.is_observed, dtype=bool)]
    points = np.asarray(output, dtype=np.float64)
    return points, points


class _logged_about:
    """``with _logged_about(name):`` the escape log lines emitted within start with ``name: ``."""

    def __init__(self, name: str):
        self.name = name

    def filter(self, record) -> bool:
        record.msg = f"{self.name}: {record.msg}"
        return True

    def __enter__(self):
        import logging

        logging.getLogger("escape").addFilter(self)
        return self

    def __exit__(self, *exc) -> None:
        import logging

        logging.getLogger("escape").removeFilter(self)
