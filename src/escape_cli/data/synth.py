"""Generate a PCN-layout dataset from procedural shapes (`escape dataset synth`).

For each (split, category, index) an object is drawn from its own seed
(`object_seed(seed, split, synset, index)`), so results do not depend on the number
of workers or on the order jobs run in. Per object: a normalised procedural shape,
`complete_points` area-uniform points on its outer surface (the complete cloud) and
`views` depth renders from random viewpoints back-projected to 3D (the partials).
Same seed, same bytes in every `.pcd` file and in `PCN.json`; `escape_synth.json`
adds run statistics and wall-clock timing.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from escape_cli.version import __version__
from escape_cli.data.depth_views import DepthCamera, DepthScanner
from escape_cli.data.pcn import CATEGORIES, SPLIT_FILE, SPLITS, complete_path, partial_path, write_model, write_split_file
from escape_cli.data.shapes import generate_shape
from escape_cli.data.surface import sample_outer_surface
from escape_cli.errors import DatasetError, OutputExistsError

GENERATORS = (1, 2)
"""Shape generators: 1, convex primitives (the data the first models were trained on);
2, the same shapes made closer to real objects plus hollow sub-types
(`escape_cli.data.shapes.realism`). A generator's files never change for a seed: a new
kind of data is a new generator number."""
DEFAULT_GENERATOR = 2

METADATA_FILE = "escape_synth.json"


@dataclass(frozen=True)
class SynthConfig:
    """What to generate.

    Attributes
    ----------
    objects_per_category : dict
        ``{split: objects per category}`` for "train", "val", "test".
    views : dict
        ``{split: partial views per object}`` (PCN: 8 train, 1 val/test).
    categories : tuple of str
        Synset ids.
    seed : int
    complete_points : int
        Points in every complete cloud (PCN: 16384).
    camera : DepthCamera
    generator : int
        One of `GENERATORS`.
    """

    objects_per_category: dict[str, int] = field(default_factory=lambda: {"train": 0, "val": 0, "test": 0})
    views: dict[str, int] = field(default_factory=lambda: {"train": 8, "val": 1, "test": 1})
    categories: tuple[str, ...] = tuple(sorted(CATEGORIES))
    seed: int = 0
    complete_points: int = 16384
    camera: DepthCamera = DepthCamera()
    generator: int = DEFAULT_GENERATOR

    def jobs(self) -> list[tuple[str, str, int]]:
        """Every (split, synset, index) to make, categories interleaved."""
        out = []
        for split in SPLITS:
            for index in range(self.objects_per_category.get(split, 0)):
                for synset in self.categories:
                    out.append((split, synset, index))
        return out


@dataclass(frozen=True)
class GeneratedObject:
    """One object's clouds.

    Attributes
    ----------
    subtype : str
    complete : (M, 3) float64
    partials : list of (N_i, 3) float64
    """

    subtype: str
    complete: np.ndarray
    partials: list[np.ndarray]


def object_seed(seed: int, split: str, synset: str, index: int) -> np.random.SeedSequence:
    """The seed of one object, from the run seed and the object's identity."""
    return np.random.SeedSequence([int(seed), SPLITS.index(split), int(synset), int(index)])


def detail_seed(seed: int, split: str, synset: str, index: int) -> np.random.SeedSequence:
    """The second stream of one object, for what generator 2 adds to generator 1's shape."""
    return np.random.SeedSequence([int(seed), SPLITS.index(split), int(synset), int(index), 2])


def model_id_for(seed: int, split: str, synset: str, index: int, generator: int = DEFAULT_GENERATOR) -> str:
    """A ShapeNet-looking 32-hex model id, deterministic in (generator, seed, split, synset, index)."""
    key = f"escape-synth/{generator}/{seed}/{split}/{synset}/{index}"
    return hashlib.md5(key.encode()).hexdigest()


def generate_object(synset: str, rng: np.random.Generator, n_views: int, complete_points: int = 16384,
                    camera: DepthCamera = DepthCamera(), detail: np.random.Generator | None = None) -> GeneratedObject:
    """Draw one shape and make its complete cloud and partial views.

    Parameters
    ----------
    synset : str
    rng : numpy.random.Generator
    n_views : int
    complete_points : int
    camera : DepthCamera
    detail : numpy.random.Generator or None
        Generator 2's second stream (None: generator 1).

    Returns
    -------
    obj : GeneratedObject
    """
    shape = generate_shape(synset, rng, detail)
    complete = sample_outer_surface(shape.parts, complete_points, rng)
    vertices, triangles = shape.mesh()
    partials = DepthScanner(vertices, triangles, camera).random_views(n_views, rng)
    return GeneratedObject(shape.subtype, complete, partials)


def _make_and_write(args: tuple[str, SynthConfig, tuple[str, str, int]]) -> dict:
    """Worker: generate one object and write its files; returns its statistics."""
    root, config, (split, synset, index) = args
    rng = np.random.default_rng(object_seed(config.seed, split, synset, index))
    detail = np.random.default_rng(detail_seed(config.seed, split, synset, index)) if config.generator >= 2 else None
    obj = generate_object(synset, rng, config.views[split], config.complete_points, config.camera, detail)
    model_id = model_id_for(config.seed, split, synset, index, config.generator)
    write_model(root, split, synset, model_id, obj.complete, obj.partials)
    return {"split": split, "synset": synset, "index": index, "model_id": model_id, "subtype": obj.subtype,
            "partial_points": [len(p) for p in obj.partials]}


def _folders_of(job: tuple[str, SynthConfig, tuple[str, str, int]]) -> list[Path]:
    """The folders one object's files go into (where a stopped worker may leave a temporary file)."""
    root, config, (split, synset, index) = job
    model_id = model_id_for(config.seed, split, synset, index, config.generator)
    return [partial_path(root, split, synset, model_id, 0).parent, complete_path(root, split, synset, model_id).parent]


def _run_jobs(root: Path, config: SynthConfig, workers: int) -> Iterator[dict]:
    from escape_cli.data.workers import run_in_workers

    jobs = [(str(root), config, job) for job in config.jobs()]
    yield from run_in_workers(_make_and_write, jobs, workers, folders_of=_folders_of)


def prepare_output(root: str | Path, overwrite: bool, extra_files: Sequence[str] = ()) -> Path:
    """Check the output folder; with `overwrite`, remove what an earlier run wrote there.

    `extra_files` are more metadata files a generator writes at the root.

    Raises
    ------
    OutputExistsError
        When `root` exists and is not empty and `overwrite` is False.
    """
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise OutputExistsError(f"{root} exists and is not a folder")
    if root.is_dir() and any(root.iterdir()):
        if not overwrite:
            raise OutputExistsError(f"{root} exists and is not empty (use --overwrite to replace the dataset in it)")
        for split in SPLITS:
            shutil.rmtree(root / split, ignore_errors=True)
        for name in (SPLIT_FILE, METADATA_FILE, *extra_files):
            (root / name).unlink(missing_ok=True)
    root.mkdir(parents=True, exist_ok=True)
    return root


def check_config(config: SynthConfig) -> None:
    """Raise DatasetError when `config` asks for nothing or for impossible counts."""
    for split, n in config.objects_per_category.items():
        if split not in SPLITS or n < 0:
            raise DatasetError(f"bad object count {split}={n}")
    if sum(config.objects_per_category.values()) == 0:
        raise DatasetError("nothing to generate: every split has 0 objects")
    if any(config.views.get(s, 0) < 1 for s in SPLITS):
        raise DatasetError("every split needs at least 1 view per object")
    if config.generator not in GENERATORS:
        raise DatasetError(f"unknown generator {config.generator}; choose from {', '.join(map(str, GENERATORS))}")
    unknown = [s for s in config.categories if s not in CATEGORIES]
    if unknown or not config.categories:
        raise DatasetError(f"unknown or no categories: {unknown}")


def _point_count_stats(counts: Sequence[int]) -> dict:
    a = np.asarray(counts)
    return {"views": int(len(a)), "min": int(a.min()), "median": float(np.median(a)), "mean": round(float(a.mean()), 1),
            "max": int(a.max())}


def synthesize(root: str | Path, config: SynthConfig, workers: int = 1, overwrite: bool = False,
               on_object: Callable[[dict], None] | None = None) -> dict:
    """Generate a whole PCN-layout dataset.

    Parameters
    ----------
    root : str or Path
        Output folder (created; must be empty unless `overwrite`).
    config : SynthConfig
    workers : int
        Processes; results do not depend on it.
    overwrite : bool
    on_object : callable, optional
        Called with each finished object's statistics (for progress bars).

    Returns
    -------
    metadata : dict
        What was written to ROOT/escape_synth.json.
    """
    if workers < 1:
        raise DatasetError(f"workers must be at least 1, got {workers}")
    check_config(config)
    root = prepare_output(root, overwrite)
    start = time.perf_counter()
    results = []
    for result in _run_jobs(root, config, workers):
        results.append(result)
        if on_object is not None:
            on_object(result)
    elapsed = time.perf_counter() - start
    results.sort(key=lambda r: (SPLITS.index(r["split"]), r["synset"], r["index"]))
    ids: dict[str, dict[str, list[str]]] = {s: {split: [] for split in SPLITS} for s in config.categories}
    for r in results:
        ids[r["synset"]][r["split"]].append(r["model_id"])
    write_split_file(root, ids)
    metadata = build_metadata(config, results, elapsed, workers)
    (root / METADATA_FILE).write_text(json.dumps(metadata, indent=2) + "\n")
    return metadata


def build_metadata(config: SynthConfig, results: list[dict], elapsed_s: float, workers: int) -> dict:
    """The content of escape_synth.json; everything but "timing" is deterministic in the config."""
    per_category = {}
    for synset in config.categories:
        mine = [r for r in results if r["synset"] == synset]
        counts = [c for r in mine for c in r["partial_points"]]
        subtypes: dict[str, int] = {}
        for r in mine:
            subtypes[r["subtype"]] = subtypes.get(r["subtype"], 0) + 1
        per_category[synset] = {
            "name": CATEGORIES[synset],
            "objects": {split: sum(r["split"] == split for r in mine) for split in SPLITS},
            "partial_points": _point_count_stats(counts) if counts else None,
            "subtypes": dict(sorted(subtypes.items())),
        }
    n_views = sum(len(r["partial_points"]) for r in results)
    return {
        "generator": "escape dataset synth",
        "generator_version": str(config.generator),
        "escape_version": __version__,
        "seed": config.seed,
        "objects_per_category": dict(config.objects_per_category),
        "views_per_object": dict(config.views),
        "complete_points": config.complete_points,
        "camera": asdict(config.camera),
        "frame": "y up, front towards +x; bounding box centred at the origin, diagonal 1 (ShapeNet/PCN)",
        "partials": "pinhole depth renders from random directions on a sphere, back-projected in the object frame",
        "totals": {"objects": len(results), "partial_views": n_views},
        "categories": per_category,
        "timing": {
            "workers": workers,
            "elapsed_s": round(elapsed_s, 2),
            "objects_per_s": round(len(results) / elapsed_s, 3) if elapsed_s > 0 else None,
            "views_per_s": round(n_views / elapsed_s, 3) if elapsed_s > 0 else None,
        },
    }
