"""The PCN dataset layout: reading samples for training/evaluation and writing new trees.

Layout (the real PCN dataset and `escape dataset synth` output alike)::

    ROOT/PCN.json                                    split file (optional when reading)
    ROOT/{train,val,test}/partial/<synset>/<model_id>/NN.pcd   depth views (00-07 train, 00 val/test)
    ROOT/{train,val,test}/complete/<synset>/<model_id>.pcd     16384 surface points

`PCN.json` is a list of ``{"taxonomy_id", "taxonomy_name", "train": [ids], "val": [...],
"test": [...]}``. Point files are PCD v0.7 with float32 x y z; this module reads ASCII,
binary and binary_compressed PCD and writes binary PCD.
"""

from __future__ import annotations

import json
import zlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from escape_cli.core.checks import as_points
from escape_cli.errors import DatasetError

log = logging.getLogger("escape")

CATEGORIES: dict[str, str] = {
    "02691156": "airplane",
    "02933112": "cabinet",
    "02958343": "car",
    "03001627": "chair",
    "03636649": "lamp",
    "04256520": "sofa",
    "04379243": "table",
    "04530566": "watercraft",
}
"""The 8 PCN categories: ShapeNet synset id -> name."""

SPLITS = ("train", "val", "test")
SPLIT_FILE = "PCN.json"


# --------------------------------------------------------------------------- categories


def resolve_categories(names_or_synsets: Sequence[str] | None, known: dict[str, str] | None = None) -> list[str]:
    """Turn category names or taxonomy ids into taxonomy ids.

    Parameters
    ----------
    names_or_synsets : sequence of str or None
        Names ("chair", case-insensitive) or ids ("03001627"); entries may also be
        comma-separated lists. None or empty means every known category.
    known : dict of str to str, optional
        The categories to choose from, ``{taxonomy id: name}``: a dataset's own
        (`dataset_categories`), the default when no name is given; PCN's 8 are
        recognised in any case. Default: PCN's 8.

    Returns
    -------
    ids : list of str
        Sorted, without duplicates.

    Raises
    ------
    DatasetError
        On an unknown name or id.
    """
    default = CATEGORIES if known is None else known
    if not names_or_synsets:
        return sorted(default)
    known = {**CATEGORIES, **default}
    by_name = {name.lower(): synset for synset, name in known.items()}
    synsets = set()
    for entry in names_or_synsets:
        for token in str(entry).split(","):
            token = token.strip()
            if not token:
                continue
            if token in known:
                synsets.add(token)
            elif token.lower() in by_name:
                synsets.add(by_name[token.lower()])
            else:
                shown = ", ".join(n if n == s else f"{n} ({s})" for s, n in sorted(known.items()))
                raise DatasetError(f"unknown category {token!r}; known: {shown}")
    if not synsets:
        raise DatasetError("no category given")
    return sorted(synsets)


def category_name(synset: str, known: dict[str, str] | None = None) -> str:
    """The name of a taxonomy id: the dataset's (`known`), PCN's, or the id itself."""
    if known and synset in known:
        return known[synset]
    return CATEGORIES.get(synset, synset)


def dataset_categories(root: str | Path) -> dict[str, str]:
    """Every category of a PCN-layout dataset, ``{taxonomy id: name}``.

    From its PCN.json (``taxonomy_name``, else the PCN name or the id) where it has one,
    else from the category folders of its splits. A root with neither gives PCN's 8.
    """
    root = Path(root)
    split_file = root / SPLIT_FILE
    if split_file.is_file():
        names = _split_file_names(split_file)
        if names:
            return names
    found = set()
    for split in SPLITS:
        folder = root / split / "partial"
        if folder.is_dir():
            found.update(p.name for p in folder.iterdir() if p.is_dir())
    return {synset: category_name(synset) for synset in sorted(found)} if found else dict(CATEGORIES)


def _split_file_names(path: Path) -> dict[str, str]:
    try:
        entries = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(entries, list):
        return {}
    names = {}
    for entry in entries:
        if isinstance(entry, dict) and "taxonomy_id" in entry:
            synset = str(entry["taxonomy_id"])
            names[synset] = str(entry.get("taxonomy_name") or category_name(synset))
    return names


# --------------------------------------------------------------------------- PCD files

def read_pcd(path: str | Path) -> np.ndarray:
    """Read the x, y, z fields of a PCD file (ascii, binary or binary_compressed).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    points : (N, 3) float32
        Rows with a non-finite coordinate are dropped.

    Raises
    ------
    InputFileError
        When the file is missing, not PCD, or truncated.
    """
    from escape_cli.io import read_points

    return read_points(path, "pcd").astype(np.float32)


def write_pcd(path: str | Path, points: np.ndarray) -> None:
    """Write points as a binary PCD v0.7 file with float32 x y z (PCN's own format), atomically.

    The file is whole or absent, also after Ctrl-C (`io.files.write_file_atomically`).

    Parameters
    ----------
    path : str or Path
    points : (N, 3) float
    """
    points = np.ascontiguousarray(as_points(points, "points"), dtype="<f4")
    n = len(points)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    from escape_cli.io.files import write_file_atomically

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_file_atomically(path, header.encode("ascii") + points.tobytes())


# --------------------------------------------------------------------------- layout paths


def partial_path(root: str | Path, split: str, synset: str, model_id: str, view: int) -> Path:
    """ROOT/split/partial/synset/model_id/NN.pcd."""
    return Path(root) / split / "partial" / synset / model_id / f"{view:02d}.pcd"


def complete_path(root: str | Path, split: str, synset: str, model_id: str) -> Path:
    """ROOT/split/complete/synset/model_id.pcd."""
    return Path(root) / split / "complete" / synset / f"{model_id}.pcd"


def write_model(root: str | Path, split: str, synset: str, model_id: str, complete: np.ndarray,
                partials: Sequence[np.ndarray]) -> None:
    """Write one model's complete cloud and its partial views in the PCN layout.

    Parameters
    ----------
    root : str or Path
    split : {"train", "val", "test"}
    synset : str
    model_id : str
    complete : (M, 3) float
    partials : sequence of (N_i, 3) float
        Written as 00.pcd, 01.pcd, ...
    """
    _check_split(split)
    write_pcd(complete_path(root, split, synset, model_id), complete)
    for view, partial in enumerate(partials):
        write_pcd(partial_path(root, split, synset, model_id, view), partial)


def write_split_file(root: str | Path, model_ids: dict[str, dict[str, list[str]]],
                     names: dict[str, str] | None = None) -> Path:
    """Write ROOT/PCN.json.

    Parameters
    ----------
    root : str or Path
    model_ids : dict
        ``{synset: {split: [model ids]}}``.
    names : dict, optional
        ``{synset: taxonomy name}``; default the PCN name, else the id.

    Returns
    -------
    path : Path
    """
    entries = []
    for synset in sorted(model_ids):
        entry = {"taxonomy_id": synset, "taxonomy_name": (names or {}).get(synset) or category_name(synset)}
        for split in SPLITS:
            entry[split] = list(model_ids[synset].get(split, []))
        entries.append(entry)
    path = Path(root) / SPLIT_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(entries, indent=4) + "\n")
    return path


def read_split_file(path: str | Path) -> dict[str, dict[str, list[str]]]:
    """Parse a PCN.json split file.

    Returns
    -------
    model_ids : dict
        ``{synset: {split: [model ids]}}`` (splits missing in the file are empty lists).

    Raises
    ------
    DatasetError
        When the file is not valid JSON or not shaped like PCN.json.
    """
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"cannot read split file {path}: {err}") from err
    if not isinstance(entries, list):
        raise DatasetError(f"{path}: expected a list of categories, got {type(entries).__name__}")
    model_ids: dict[str, dict[str, list[str]]] = {}
    for entry in entries:
        if not isinstance(entry, dict) or "taxonomy_id" not in entry:
            raise DatasetError(f"{path}: every entry needs a 'taxonomy_id'")
        ids = {}
        for split in SPLITS:
            value = entry.get(split, [])
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise DatasetError(f"{path}: '{split}' of {entry['taxonomy_id']} must be a list of ids")
            ids[split] = value
        model_ids[str(entry["taxonomy_id"])] = ids
    return model_ids


# --------------------------------------------------------------------------- reading samples


@dataclass(frozen=True)
class SampleRef:
    """Where one (partial view, complete shape) pair lives on disk."""

    root: Path
    split: str
    synset: str
    model_id: str
    view: int
    partial_path: Path
    complete_path: Path
    category: str = ""  # the category's name ("" : the PCN name or the id)


@dataclass(frozen=True)
class PCNSample:
    """One loaded pair.

    Attributes
    ----------
    partial : (N, 3) float32
    complete : (M, 3) float32
    synset, category, model_id : str
    view : int
    """

    partial: np.ndarray
    complete: np.ndarray
    synset: str
    category: str
    model_id: str
    view: int


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise DatasetError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")


def _view_files(model_dir: Path) -> list[tuple[int, Path]]:
    views = []
    for file in model_dir.glob("*.pcd"):
        if file.stem.isdigit():
            views.append((int(file.stem), file))
    return sorted(views)


def list_samples(root: str | Path, split: str = "test", categories: Sequence[str] | None = None,
                 views: str = "all") -> list[SampleRef]:
    """List the (partial view, complete shape) pairs of one split.

    Parameters
    ----------
    root : str or Path
        Dataset root (holding train/, val/, test/ and optionally PCN.json).
    split : {"train", "val", "test"}
    categories : sequence of str, optional
        Names or synsets (see `resolve_categories`); default all.
    views : {"all", "first"}
        Every partial view of a model, or only its lowest-numbered one.

    Returns
    -------
    refs : list of SampleRef
        Sorted by synset, model id, view. With PCN.json, the split's ids that exist on
        disk; without it, every model folder found.

    Raises
    ------
    DatasetError
        When the root or split folder is missing or no sample is found.
    """
    _check_split(split)
    if views not in ("all", "first"):
        raise DatasetError(f"views must be 'all' or 'first', got {views!r}")
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset root {root} is not a folder")
    known = dataset_categories(root)
    synsets = resolve_categories(categories, known)
    known = {**CATEGORIES, **known}
    partial_root, complete_root = root / split / "partial", root / split / "complete"
    if not partial_root.is_dir() or not complete_root.is_dir():
        raise DatasetError(f"{root} has no {split}/partial and {split}/complete folders (PCN layout expected)")
    split_file = root / SPLIT_FILE
    listed = read_split_file(split_file) if split_file.is_file() else None
    refs: list[SampleRef] = []
    missing = 0
    for synset in synsets:
        if listed is not None:
            model_ids = sorted(listed.get(synset, {}).get(split, []))
        else:
            folder = partial_root / synset
            model_ids = sorted(p.name for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []
        for model_id in model_ids:
            complete = complete_path(root, split, synset, model_id)
            view_files = _view_files(partial_root / synset / model_id)
            if not view_files or not complete.is_file():
                missing += 1
                continue
            if views == "first":
                view_files = view_files[:1]
            for view, file in view_files:
                refs.append(SampleRef(root, split, synset, model_id, view, file, complete, known[synset]))
    if missing:
        log.info("%d models of %s/%s have no partial views or no complete cloud on disk; skipped", missing, root, split)
    if not refs:
        names = ", ".join(known[s] for s in synsets)
        source = f"listed in {split_file.name}" if listed is not None else "found"
        raise DatasetError(f"no {split} samples {source} under {root} for {names}")
    return refs


def _sample_seed(seed: int, ref: SampleRef) -> list[int]:
    key = f"{ref.split}/{ref.synset}/{ref.model_id}/{ref.view}".encode()
    return [int(seed), zlib.crc32(key)]


def resample_points(points: np.ndarray, n_points: int, rng: np.random.Generator) -> np.ndarray:
    """PCN-style fixed-size input: a random subset, or every point plus random repeats.

    Parameters
    ----------
    points : (N, 3) float
        N >= 1.
    n_points : int
    rng : numpy.random.Generator

    Returns
    -------
    resampled : (n_points, 3), same dtype as `points`
    """
    from escape_cli.core.sampling import resample_rows

    as_points(points, "the cloud to resample", min_points=1)
    return points[resample_rows(len(points), n_points, rng)]


def read_sample(ref: SampleRef, n_points: int | None = 2048, seed: int = 0) -> PCNSample:
    """Load one pair.

    Parameters
    ----------
    ref : SampleRef
    n_points : int or None
        Resample the partial to this many points (`resample_points`, seeded from `seed`
        and the sample's identity, so it is deterministic); None keeps it raw.
    seed : int

    Returns
    -------
    sample : PCNSample
    """
    partial = read_pcd(ref.partial_path)
    complete = read_pcd(ref.complete_path)
    if len(partial) == 0:
        raise DatasetError(f"{ref.partial_path} holds no finite points")
    if len(complete) == 0:
        raise DatasetError(f"{ref.complete_path} holds no finite points")
    if n_points is not None:
        partial = resample_points(partial, n_points, np.random.default_rng(_sample_seed(seed, ref)))
    return PCNSample(partial, complete, ref.synset, ref.category or category_name(ref.synset), ref.model_id, ref.view)


class PCNDataset:
    """Indexable view of one split of a PCN-layout tree.

    Parameters
    ----------
    root : str or Path
    split : {"train", "val", "test"}
    categories : sequence of str, optional
    n_points : int or None
        Partial size after resampling (None: raw).
    seed : int
        Seed of the resampling.
    views : {"all", "first"}
    """

    def __init__(self, root: str | Path, split: str = "train", categories: Sequence[str] | None = None,
                 n_points: int | None = 2048, seed: int = 0, views: str = "all"):
        self.root = Path(root)
        self.split = split
        self.n_points = n_points
        self.seed = seed
        self.refs = list_samples(root, split, categories, views)

    def __len__(self) -> int:
        return len(self.refs)

    def __getitem__(self, index: int) -> PCNSample:
        return read_sample(self.refs[index], self.n_points, self.seed)
