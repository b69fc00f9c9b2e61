"""Training samples: PCN pairs turned into FPS-ordered inputs with their anchors, cached.

Each partial goes through `escape_cli.core.normalize.network_input`, the same function
`complete` uses, so training sees exactly the rows a user's scan produces: in the
partial's own frame (`PartialFrame`), and its complete cloud is mapped by the same
similarity when a batch is drawn. Preparing a partial (farthest-point ordering and
anchor selection) costs ~50 ms, so it is done once per dataset split, in parallel, and
kept in an `.npz` cache. Distances are computed on the fly from the cached coordinates
(cheap), which keeps the cache small.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from escape_cli.core.settings import AnchorSettings

log = logging.getLogger("escape")


@dataclass
class PreparedSplit:
    """One dataset split, ready for training.

    Attributes
    ----------
    inputs : (S, N, 3) float32, FPS-ordered partial points (short partials repeated), in
        the network's frame.
    anchors : (S, K, 3) float32, in the network's frame.
    object_index : (S,) int64, row of `completes` for each sample.
    completes : (O, M, 3) float32, complete clouds.
    synsets, model_ids : (O,) str
    views : (S,) int64
    unique_counts : (S,) int64, distinct leading rows of each input.
    centers : (S, 3) float64, scales : (S,) float64: sample i's network frame is
        (x - centers[i]) / scales[i] of the dataset's coordinates.
    """

    inputs: np.ndarray
    anchors: np.ndarray
    object_index: np.ndarray
    completes: np.ndarray
    synsets: np.ndarray
    model_ids: np.ndarray
    views: np.ndarray
    unique_counts: np.ndarray
    centers: np.ndarray
    scales: np.ndarray

    def __len__(self) -> int:
        return len(self.inputs)

    def complete_in_frame(self, sample: int, rows=slice(None)) -> np.ndarray:
        """Sample `sample`'s complete cloud (its `rows`) in that sample's network frame -> (M', 3) float32."""
        cloud = self.completes[self.object_index[sample]][rows].astype(np.float64)
        return ((cloud - self.centers[sample]) / self.scales[sample]).astype(np.float32)


def concatenate_splits(splits: list[PreparedSplit]) -> PreparedSplit:
    """One split made of several (e.g. the train splits of two datasets), samples in order."""
    if len(splits) == 1:
        return splits[0]
    offsets = np.cumsum([0] + [len(s.completes) for s in splits[:-1]])
    return PreparedSplit(
        inputs=np.concatenate([s.inputs for s in splits]),
        anchors=np.concatenate([s.anchors for s in splits]),
        object_index=np.concatenate([s.object_index + offset for s, offset in zip(splits, offsets)]),
        completes=np.concatenate([s.completes for s in splits]),
        synsets=np.concatenate([s.synsets for s in splits]),
        model_ids=np.concatenate([s.model_ids for s in splits]),
        views=np.concatenate([s.views for s in splits]),
        unique_counts=np.concatenate([s.unique_counts for s in splits]),
        centers=np.concatenate([s.centers for s in splits]),
        scales=np.concatenate([s.scales for s in splits]),
    )


def _prepare_one(args) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, float]:
    from escape_cli.core.anchors import select_anchors
    from escape_cli.core.normalize import network_input
    from escape_cli.data.pcn import read_pcd

    partial_path, input_points, settings, frame = args
    partial = read_pcd(partial_path).astype(np.float64)
    net_in = network_input(partial, input_points, frame)
    anchors = select_anchors(net_in.observed, **settings.to_dict())
    norm = net_in.normalization
    return net_in.rows.astype(np.float32), anchors.points.astype(np.float32), net_in.unique, norm.center.copy(), norm.scale


def prepare_split(
    root: Path,
    split: str,
    input_points: int,
    settings: AnchorSettings,
    cache_dir: Path,
    frame=None,
    categories=None,
    views: str = "all",
    max_views: int | None = None,
    workers: int = 2,
    limit: int | None = None,
) -> PreparedSplit:
    """Read a PCN-layout split and prepare every partial, using a cache in `cache_dir`.

    `max_views` keeps the first V views of each object; `limit` the first samples.
    `frame` is the `PartialFrame` of the network (None: absolute dataset units).
    """
    from escape_cli.data.pcn import list_samples, read_pcd

    refs = list_samples(root, split, categories=categories, views=views)
    if max_views is not None:
        refs = [r for r in refs if r.view < max_views]
    if limit is not None:
        refs = refs[:limit]
    key = hashlib.sha1(
        json.dumps(
            [str(Path(root).resolve()), split, input_points, settings.__dict__,
             None if frame is None else frame.to_dict(), [str(r.partial_path) for r in refs]]
        ).encode()
    ).hexdigest()[:12]
    cache = Path(cache_dir) / f"prepared-{split}-{key}.npz"
    if cache.exists():
        data = np.load(cache, allow_pickle=False)
        log.info("using cached %s split from %s", split, cache)
        return PreparedSplit(**{name: data[name] for name in data.files})

    objects: dict[tuple[str, str], int] = {}
    for ref in refs:
        objects.setdefault((ref.synset, ref.model_id), len(objects))
    complete_paths = {(r.synset, r.model_id): r.complete_path for r in refs}
    jobs = [(r.partial_path, input_points, settings, frame) for r in refs]
    results = _run_parallel(_prepare_one, jobs, workers, f"preparing {Path(root).name} {split}")
    completes = np.stack([read_pcd(complete_paths[key]) for key in objects]).astype(np.float32)
    split_data = PreparedSplit(
        inputs=np.stack([r[0] for r in results]),
        anchors=np.stack([r[1] for r in results]),
        object_index=np.array([objects[(r.synset, r.model_id)] for r in refs], dtype=np.int64),
        completes=completes,
        synsets=np.array([k[0] for k in objects]),
        model_ids=np.array([k[1] for k in objects]),
        views=np.array([r.view for r in refs], dtype=np.int64),
        unique_counts=np.array([r[2] for r in results], dtype=np.int64),
        centers=np.stack([r[3] for r in results]).astype(np.float64),
        scales=np.array([r[4] for r in results], dtype=np.float64),
    )
    _write_cache(cache, split_data)
    return split_data


def _write_cache(cache: Path, split_data: PreparedSplit) -> None:
    """Write CACHE whole or not at all (`io.files.write_atomically`).

    Runs sharing a cache folder may write the same file at once; each writes a temporary
    file of its own (named by its process), and a reader sees one whole file or none.
    """
    from escape_cli.io.files import write_atomically

    cache.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(cache, lambda handle: np.savez(handle, **split_data.__dict__))


def log_line(text: str, stream=None) -> None:
    """`text` as one time-stamped, flushed line on `stream` (default stderr): progress in a log file."""
    import sys
    import time

    print(f"{time.strftime('%H:%M:%S')} {text}", file=stream or sys.stderr, flush=True)


def _run_parallel(func, jobs, workers: int, label: str) -> list:
    """[func(job) for job in jobs] on `workers` processes, with a bar on a terminal (a line before and after in a log)."""
    import logging
    import time

    from rich.console import Console
    from rich.progress import Progress

    results = []
    console = Console(stderr=True)
    quiet = not logging.getLogger("escape").isEnabledFor(logging.WARNING)
    lines = not quiet and not console.is_terminal  # a log file: no bar, which would leave blank lines there
    if lines:
        start = time.perf_counter()
        log_line(f"{label}: {len(jobs)} samples")
    with Progress(transient=True, console=console, disable=quiet or lines) as progress:
        task = progress.add_task(label, total=len(jobs))
        if workers <= 1:
            for job in jobs:
                results.append(func(job))
                progress.advance(task)
        else:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(workers) as pool:
                for res in pool.imap(func, jobs, chunksize=16):
                    results.append(res)
                    progress.advance(task)
                # each worker ends on its own; leaving the block at once would terminate() them, which
                # can hang forever when a worker waits on the task queue's lock as the pool kills them
                pool.close()
                pool.join()
    if lines:
        log_line(f"{label}: done in {time.perf_counter() - start:.0f} s")
    return results
