"""A PCN-layout dataset from any collection of complete shapes (`escape dataset from-shapes`).

Sources are meshes (OBJ, OFF, STL, PLY with faces or tristrips) and point clouds (every
format `read_points` reads), laid out as ``<category>/{train,test}/<file>`` (ModelNet),
``<category>/<file>``, or a flat folder of one category. Every shape is centred on its
bounding box and scaled to a diagonal of 1 (the PCN frame; its orientation is kept).
A mesh gives `complete_points` area-uniform surface points and depth renders
(`DepthScanner`); a cloud is densified in its tangent planes and seen through splats
(`cloud_views.SplatScanner`), so that its views occlude like views of a surface.

Each shape draws from its own seed (`shape_seed(seed, category, model_id)`), so the
point files do not depend on `workers` or on the order jobs run in. Every point file
is written atomically (`pcn.write_pcd`), the complete cloud after the views: a shape
with a complete cloud has all its views. The workers are `data.workers.run_in_workers`'
(Ctrl-C and SIGTERM stop them and remove what they were writing).
"""

from __future__ import annotations

import hashlib
import json
import re
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from escape_cli.data.cloud_views import SplatScanner, SplatSettings, densify, tangent_frames, view_coverage
from escape_cli.data.depth_views import DepthCamera
from escape_cli.data.meshes import MESH_SUFFIXES, ply_has_faces, read_mesh
from escape_cli.data.pcn import CATEGORIES, SPLITS, complete_path, partial_path, write_pcd, write_split_file
from escape_cli.errors import DatasetError, DegenerateGeometryError, EscapeError, OutputFileError
from escape_cli.formats import CLOUD_SUFFIXES
from escape_cli.version import __version__

METADATA_FILE = "escape_shapes.json"
SHAPE_SUFFIXES = tuple(sorted(set(MESH_SUFFIXES) | set(CLOUD_SUFFIXES)))
"""File endings taken from a source folder (others are skipped and counted)."""
MIN_SOURCE_POINTS = 32
"""Fewer distinct points than this are not a shape."""
LAYOUT_SPLITS = ("train", "test")
"""Split folders of the ModelNet layout."""


@dataclass(frozen=True)
class ShapeSource:
    """One shape file and where it goes.

    Attributes
    ----------
    path : Path
    category : str
        Taxonomy id: the PCN synset for a PCN category name, else the name itself.
    model_id : str
        Unique within its category.
    split : str or None
        "train" or "test" from a ModelNet layout, None where the layout has none.
    """

    path: Path
    category: str
    model_id: str
    split: str | None = None


@dataclass(frozen=True)
class ShapesConfig:
    """What to make of the shapes.

    Attributes
    ----------
    views : dict
        ``{split: partial views per shape}``.
    seed : int
    complete_points : int
    val_fraction : float
        Share of each category's training shapes that become validation shapes.
    test_fraction : float
        Share of each category's shapes that become test shapes, where the layout has no test split.
    camera : DepthCamera
    splat : SplatSettings
    """

    views: dict[str, int] = field(default_factory=lambda: {"train": 8, "val": 1, "test": 1})
    seed: int = 0
    complete_points: int = 16384
    val_fraction: float = 0.05
    test_fraction: float = 0.0
    camera: DepthCamera = DepthCamera()
    splat: SplatSettings = SplatSettings()


# --------------------------------------------------------------------------- finding shapes


def category_id(name: str) -> str:
    """The taxonomy id of a category folder's name: PCN's synset for its 8 names, else the name."""
    by_name = {n: synset for synset, n in CATEGORIES.items()}
    return by_name.get(name.lower(), name)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "shape"


def _is_shape_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in SHAPE_SUFFIXES and not path.name.startswith(".")


def _shape_files(folder: Path) -> tuple[list[Path], int]:
    """Shape files directly in `folder` (sorted) and the count of other files."""
    files = sorted(p for p in folder.iterdir() if p.is_file())
    shapes = [p for p in files if _is_shape_file(p)]
    return shapes, len(files) - len(shapes)


def find_shapes(sources: Sequence[str | Path], category: str | None = None) -> tuple[list[ShapeSource], int]:
    """Every shape file of the sources, with its category and layout split.

    Parameters
    ----------
    sources : sequence of str or Path
        Folders and files. A folder with subfolders holds one category per subfolder
        (``<category>/{train,test}/<file>`` or ``<category>/<file>``; files beside
        them, such as a README or a list, are skipped); a folder without is flat.
    category : str, optional
        The category of files given directly and of a flat folder's files (default:
        the name of the folder they are in).

    Returns
    -------
    shapes : list of ShapeSource
        Model ids made unique within each category.
    skipped : int
        Files in the folders that are not shape files.

    Raises
    ------
    DatasetError
        A source that does not exist, or no shape file at all.
    """
    found: list[tuple[Path, str, str | None]] = []
    skipped = 0
    for source in map(Path, sources):
        if source.is_file():
            found.append((source, category or source.resolve().parent.name, None))
            continue
        if not source.is_dir():
            raise DatasetError(f"{source}: no such file or folder")
        folders = sorted(p for p in source.iterdir() if p.is_dir() and not p.name.startswith("."))
        files, other = _shape_files(source)
        if not folders:  # a flat folder of one category
            skipped += other
            found += [(f, category or source.resolve().name, None) for f in files]
            continue
        skipped += other + len(files)  # beside category folders, loose files (README, lists) are not shapes
        for sub in folders:
            split_folders = [sub / s for s in LAYOUT_SPLITS if (sub / s).is_dir()]
            if split_folders:  # ModelNet: <category>/{train,test}/<file>
                for folder in split_folders:
                    files, other = _shape_files(folder)
                    skipped += other
                    found += [(f, sub.name, folder.name) for f in files]
            else:  # <category>/<file>
                files, other = _shape_files(sub)
                skipped += other
                found += [(f, sub.name, None) for f in files]
    if not found:
        shown = ", ".join(str(s) for s in sources) or "(none)"
        raise DatasetError(f"no shape files ({', '.join(s[1:] for s in SHAPE_SUFFIXES)}) in {shown}")
    return _unique_ids(found), skipped


def _unique_ids(found: list[tuple[Path, str, str | None]]) -> list[ShapeSource]:
    """Model ids from file stems; a stem met twice in a category gets its extension, then a number."""
    shapes, taken = [], set()
    for path, name, split in found:
        cat = category_id(_safe(name))
        base = _safe(path.stem)
        model_id = base
        if (cat, model_id) in taken:
            model_id = f"{base}_{_safe(path.suffix.lower())}"
        number = 2
        while (cat, model_id) in taken:
            model_id, number = f"{base}_{number}", number + 1
        taken.add((cat, model_id))
        shapes.append(ShapeSource(path, cat, model_id, split))
    return shapes


def _rank(shape: ShapeSource) -> str:
    return hashlib.md5(f"{shape.category}/{shape.model_id}".encode()).hexdigest()


def assign_splits(shapes: Sequence[ShapeSource], val_fraction: float, test_fraction: float) -> list[str]:
    """The split of every shape: the layout's, with val (and test, where the layout has none) carved out.

    Per category, the shapes are ranked by a hash of their id, so the choice depends on
    neither the seed nor the order the shapes were found in; round(fraction x count)
    of them are taken.
    """
    splits = ["test" if s.split == "test" else "train" for s in shapes]
    categories = sorted({s.category for s in shapes})
    for cat in categories:
        free = [i for i, s in enumerate(shapes) if s.category == cat and s.split is None]
        if free and test_fraction > 0:
            ranked = sorted(free, key=lambda i: _rank(shapes[i]))
            for i in ranked[: int(round(test_fraction * len(free)))]:
                splits[i] = "test"
        train = [i for i, s in enumerate(shapes) if s.category == cat and splits[i] == "train"]
        ranked = sorted(train, key=lambda i: _rank(shapes[i]), reverse=True)  # another order than test's
        for i in ranked[: int(round(val_fraction * len(train)))]:
            splits[i] = "val"
    return splits


# --------------------------------------------------------------------------- one shape


def shape_seed(seed: int, category: str, model_id: str) -> np.random.SeedSequence:
    """The seed of one shape, from the run seed and the shape's identity."""
    return np.random.SeedSequence([int(seed), zlib.crc32(f"{category}/{model_id}".encode())])


def unit_frame(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre of the bounding box and its diagonal: (3,) float64 and float."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo))


def is_mesh_file(path: Path) -> bool:
    """Whether a shape file is read as a mesh (OBJ, OFF, STL, or a PLY with faces)."""
    suffix = path.suffix.lower()
    return suffix in MESH_SUFFIXES and (suffix != ".ply" or ply_has_faces(path))


def make_shape(path: Path, n_views: int, rng: np.random.Generator, config: ShapesConfig) -> dict:
    """The complete cloud and partial views of one shape file, in the unit frame.

    Returns
    -------
    made : dict
        ``complete`` (M, 3) float64, ``partials`` list of (V_i, 3) float64, ``kind``
        ("mesh" or "cloud"), ``note`` (how it was read), ``source_points``.

    Raises
    ------
    EscapeError
        Unreadable, empty, NaN-only or degenerate shapes.
    """
    try:
        if is_mesh_file(path):
            return _mesh_shape(path, n_views, rng, config)
        return _cloud_shape(path, n_views, rng, config)
    except EscapeError as err:
        if str(err).startswith(str(path)):
            raise
        raise type(err)(f"{path}: {err}") from None


def _mesh_shape(path: Path, n_views: int, rng: np.random.Generator, config: ShapesConfig) -> dict:
    from escape_cli.data.depth_views import DepthScanner
    from escape_cli.data.surface import sample_triangles

    mesh = read_mesh(path)
    vertices, triangles = mesh.vertices, mesh.triangles
    finite = np.isfinite(vertices).all(axis=1)
    triangles = triangles[finite[triangles].all(axis=1)]
    if len(triangles) == 0:
        raise DegenerateGeometryError(f"{path}: no face with finite vertices")
    used = np.unique(triangles)
    centre, diagonal = unit_frame(vertices[used])
    if not diagonal > 0:
        raise DegenerateGeometryError(f"{path}: every vertex is the same point")
    vertices = np.where(finite[:, None], (vertices - centre) / diagonal, 0.0)
    complete, _ = sample_triangles(vertices, triangles, config.complete_points, rng)
    partials = DepthScanner(vertices, triangles, config.camera).random_views(n_views, rng)
    return {"complete": complete, "partials": partials, "kind": "mesh", "note": mesh.note, "source_points": len(used)}


def _cloud_shape(path: Path, n_views: int, rng: np.random.Generator, config: ShapesConfig) -> dict:
    from escape_cli.core.checks import check_not_collinear
    from escape_cli.io import read_points

    points = np.unique(np.asarray(read_points(path), dtype=np.float64), axis=0)  # NaN/Inf rows are dropped on read
    if len(points) < MIN_SOURCE_POINTS:
        raise DegenerateGeometryError(f"{path}: {len(points)} distinct finite points; a shape needs {MIN_SOURCE_POINTS}")
    check_not_collinear(points, f"{path}: the points")
    centre, diagonal = unit_frame(points)
    points = (points - centre) / diagonal
    points = points[rng.permutation(len(points))]  # unique() sorted them: no order may leak into the views
    if len(points) >= config.complete_points:
        complete = points[np.sort(rng.choice(len(points), config.complete_points, replace=False))]
        source, parent = complete, np.arange(len(complete))
        note = "subsampled"
    else:
        source = points
        note = f"densified from {len(points)} points"
    frames = tangent_frames(source)
    if len(points) < config.complete_points:
        complete, parent = densify(source, frames, config.complete_points, rng, config.splat)
    scanner = SplatScanner(source, frames, complete, parent, config.camera, config.splat)
    partials = scanner.random_views(n_views, rng)
    return {"complete": complete, "partials": partials, "kind": "cloud", "note": note, "source_points": len(points)}


def _make_and_write(args: tuple[str, ShapesConfig, ShapeSource, str]) -> dict:
    """Worker: one shape's files; its statistics, or its error."""
    root, config, shape, split = args
    identity = {"path": str(shape.path), "category": shape.category, "model_id": shape.model_id, "split": split}
    try:
        rng = np.random.default_rng(shape_seed(config.seed, shape.category, shape.model_id))
        made = make_shape(shape.path, config.views[split], rng, config)
        for view, partial in enumerate(made["partials"]):
            write_pcd(partial_path(root, split, shape.category, shape.model_id, view), partial)
        write_pcd(complete_path(root, split, shape.category, shape.model_id), made["complete"])
    except EscapeError as err:
        return {**identity, "error": str(err)}
    except (ValueError, OSError, MemoryError, np.linalg.LinAlgError) as err:
        return {**identity, "error": f"{shape.path}: {type(err).__name__}: {err}"}
    coverage = [view_coverage(made["complete"], p) for p in made["partials"]]
    return {**identity, "kind": made["kind"], "note": made["note"], "source_points": made["source_points"],
            "partial_points": [len(p) for p in made["partials"]], "coverage": [round(c, 4) for c in coverage]}


def _folders_of(job: tuple[str, ShapesConfig, ShapeSource, str]) -> list[Path]:
    """The folders one shape's files go into (where a stopped worker may leave a temporary file)."""
    root, _config, shape, split = job
    return [partial_path(root, split, shape.category, shape.model_id, 0).parent,
            complete_path(root, split, shape.category, shape.model_id).parent]


def _worker_died(job: tuple[str, ShapesConfig, ShapeSource, str], how: str) -> dict:
    _root, _config, shape, split = job
    return {"path": str(shape.path), "category": shape.category, "model_id": shape.model_id, "split": split,
            "error": f"{shape.path}: the worker process making it died ({how})"}


def _run_jobs(jobs: list, workers: int) -> Iterator[dict]:
    from escape_cli.data.workers import run_in_workers

    yield from run_in_workers(_make_and_write, jobs, workers, folders_of=_folders_of, on_death=_worker_died)


# --------------------------------------------------------------------------- the dataset


def build_from_shapes(root: str | Path, sources: Sequence[str | Path], config: ShapesConfig, *,
                      category: str | None = None, workers: int = 1, overwrite: bool = False,
                      on_shape: Callable[[dict], None] | None = None, on_start: Callable[[int, int], None] | None = None) -> dict:
    """Make a whole PCN-layout dataset from shape files.

    Parameters
    ----------
    root : str or Path
        Output folder (created; must be empty unless `overwrite`).
    sources : sequence of str or Path
    config : ShapesConfig
    category : str, optional
        Category of flat folders and single files (see `find_shapes`).
    workers : int
        Processes; the point files do not depend on it.
    overwrite : bool
    on_shape : callable, optional
        Called with each finished shape's statistics (an ``"error"`` key when it failed).
    on_start : callable, optional
        Called with (shapes, skipped files) once they are found.

    Returns
    -------
    metadata : dict
        What was written to ROOT/escape_shapes.json; ``failures`` lists the bad shapes.
    """
    from escape_cli.data.synth import prepare_output

    check_shapes_config(config)
    if workers < 1:
        raise DatasetError(f"workers must be at least 1, got {workers}")
    check_sources_outside(root, sources)
    shapes, skipped = find_shapes(sources, category)
    splits = assign_splits(shapes, config.val_fraction, config.test_fraction)
    if any(is_mesh_file(s.path) for s in shapes):
        from escape_cli.extras import require

        require("open3d", "escape dataset from-shapes with meshes (depth renders)")
    root = prepare_output(root, overwrite, extra_files=(METADATA_FILE,))
    if on_start is not None:
        on_start(len(shapes), skipped)
    start = time.perf_counter()
    results = []
    for result in _run_jobs([(str(root), config, s, split) for s, split in zip(shapes, splits)], workers):
        results.append(result)
        if on_shape is not None:
            on_shape(result)
    elapsed = time.perf_counter() - start
    results.sort(key=lambda r: (r["category"], r["model_id"]))
    good = [r for r in results if "error" not in r]
    ids: dict[str, dict[str, list[str]]] = {}
    for r in good:
        ids.setdefault(r["category"], {s: [] for s in SPLITS})[r["split"]].append(r["model_id"])
    names = {s.category: _category_name(s) for s in shapes}
    write_split_file(root, ids, names)
    metadata = _metadata(sources, config, results, skipped, names, elapsed, workers)
    (root / METADATA_FILE).write_text(json.dumps(metadata, indent=2) + "\n")
    return metadata


def _category_name(shape: ShapeSource) -> str:
    return CATEGORIES.get(shape.category, shape.category)


def check_sources_outside(root: str | Path, sources: Sequence[str | Path]) -> None:
    """OutputFileError when a source lies in the output folder's split folders, which --overwrite removes first
    (an earlier dataset's clouds made into a new one in its place)."""
    out = Path(root).resolve()
    splits = [out / split for split in SPLITS]
    for source in sources:
        resolved = Path(source).resolve()
        if resolved == out or any(resolved == s or s in resolved.parents for s in splits):
            raise OutputFileError(f"the source {source} is inside the output folder {root}, whose dataset "
                                  f"--overwrite removes first; give an output folder outside the sources")


def check_shapes_config(config: ShapesConfig) -> None:
    """Raise DatasetError on impossible options."""
    if any(config.views.get(s, 0) < 1 for s in SPLITS):
        raise DatasetError("every split needs at least 1 view per shape")
    for name in ("val_fraction", "test_fraction"):
        value = getattr(config, name)
        if not 0.0 <= value < 1.0:
            raise DatasetError(f"--{name.replace('_', '-')} must be in [0, 1), got {value}")
    if config.complete_points < MIN_SOURCE_POINTS:
        raise DatasetError(f"--complete-points must be at least {MIN_SOURCE_POINTS}")


def _stats(values: Sequence[float], digits: int = 1) -> dict | None:
    if not len(values):
        return None
    a = np.asarray(values, dtype=np.float64)
    return {"min": round(float(a.min()), digits), "median": round(float(np.median(a)), digits),
            "mean": round(float(a.mean()), digits), "max": round(float(a.max()), digits)}


def _metadata(sources, config: ShapesConfig, results: list[dict], skipped: int, names: dict, elapsed: float,
              workers: int) -> dict:
    """The content of escape_shapes.json; everything but "timing" is deterministic in the inputs and options."""
    good = [r for r in results if "error" not in r]
    per_category = {}
    for cat in sorted(names):
        mine = [r for r in good if r["category"] == cat]
        per_category[cat] = {
            "name": names[cat],
            "shapes": {split: sum(r["split"] == split for r in mine) for split in SPLITS},
            "kinds": {kind: sum(r["kind"] == kind for r in mine) for kind in ("mesh", "cloud") if any(r["kind"] == kind for r in mine)},
            "partial_points": _stats([c for r in mine for c in r["partial_points"]]),
            "view_coverage": _stats([c for r in mine for c in r["coverage"]], 3),
        }
    notes: dict[str, list[str]] = {}
    for r in good:
        if r["note"] not in ("triangles", "subsampled") and not r["note"].startswith("densified"):
            notes.setdefault(r["note"], []).append(r["path"])
    n_views = sum(len(r["partial_points"]) for r in good)
    return {
        "generator": "escape dataset from-shapes",
        "escape_version": __version__,
        "sources": [str(s) for s in sources],
        "seed": config.seed,
        "views_per_shape": dict(config.views),
        "complete_points": config.complete_points,
        "val_fraction": config.val_fraction,
        "test_fraction": config.test_fraction,
        "camera": asdict(config.camera),
        "splat": asdict(config.splat),
        "frame": "bounding box centred at the origin, diagonal 1; the source's orientation",
        "partials": "meshes: pinhole depth renders; clouds: tangent-plane splats in a z-buffer, one point per pixel",
        "totals": {"shapes": len(results), "written": len(good), "failed": len(results) - len(good),
                   "skipped_files": skipped, "partial_views": n_views,
                   "view_coverage": _stats([c for r in good for c in r["coverage"]], 3)},
        "categories": per_category,
        "notes": notes,
        "failures": [{"path": r["path"], "error": r["error"]} for r in results if "error" in r],
        "timing": {
            "workers": workers,
            "elapsed_s": round(elapsed, 2),
            "shapes_per_s": round(len(results) / elapsed, 3) if elapsed > 0 else None,
        },
    }
