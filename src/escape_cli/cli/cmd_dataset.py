"""`escape dataset`: make PCN-layout training sets (procedural shapes, or any collection of shapes) and inspect them."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

import escape_cli.interrupts as interrupts
from escape_cli.cli.options import JSON, OVERWRITE, print_summary

MAX_OBJECTS = 100_000
"""Objects per category and split: PCN's largest category has 5,750; more is a typo."""
MAX_COMPLETE_POINTS = 1 << 20

app = typer.Typer(help="Make and inspect training datasets (PCN layout).", no_args_is_help=True)

CATEGORIES_OPTION = typer.Option(
    None, "--categories", "-c",
    help="Categories by name or taxonomy id (repeat or comma-separate); default: all of the dataset's (PCN: the 8).",
)


@app.command("synth")
def synth(
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (must be empty unless --overwrite)."),
    train: int = typer.Option(0, "--train", min=0, max=MAX_OBJECTS, help="Training objects PER CATEGORY."),
    val: int = typer.Option(0, "--val", min=0, max=MAX_OBJECTS, help="Validation objects PER CATEGORY."),
    test: int = typer.Option(0, "--test", min=0, max=MAX_OBJECTS, help="Test objects PER CATEGORY."),
    seed: int = typer.Option(0, "--seed", min=0, help="Run seed; same seed, byte-identical point files."),
    views: int = typer.Option(8, "--views", min=1, max=100, help="Partial views per training object (PCN: 8)."),
    eval_views: int = typer.Option(1, "--eval-views", min=1, max=100, help="Partial views per val/test object (PCN: 1)."),
    workers: int = typer.Option(1, "--workers", "-w", min=1, max=256, help="Worker processes (results do not depend on it)."),
    categories: Optional[List[str]] = CATEGORIES_OPTION,
    complete_points: int = typer.Option(16384, "--complete-points", min=16, max=MAX_COMPLETE_POINTS, help="Points per complete cloud (PCN: 16384)."),
    generator: int = typer.Option(
        2, "--generator", min=1, max=2,
        help="Shape generator: 2 (rounded edges, hollow shades, rowing boats, shell chairs) or 1 (convex primitives only, the first models' data).",
    ),
    overwrite: bool = OVERWRITE,
    json_out: bool = JSON,
) -> None:
    """Generate procedural shapes of the PCN categories in the PCN folder layout (needs the synth extra: open3d).

    Each object: a complete cloud (points on its outer surface) and partial clouds (depth views).

    Writes OUT/{train,val,test}/{partial,complete}/..., OUT/PCN.json and OUT/escape_synth.json.
    """
    import json
    import logging

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from escape_cli.data.pcn import resolve_categories
    from escape_cli.data.synth import SynthConfig, check_config, prepare_output, synthesize
    from escape_cli.errors import DatasetError
    from escape_cli.extras import require
    from escape_cli.io.files import check_output_folder

    if train + val + test == 0:
        raise DatasetError("nothing to generate: give --train, --val and/or --test a positive count (objects per category)")
    config = SynthConfig(
        objects_per_category={"train": train, "val": val, "test": test},
        views={"train": views, "val": eval_views, "test": eval_views},
        categories=tuple(resolve_categories(categories)),
        seed=seed,
        complete_points=complete_points,
        generator=generator,
    )
    check_config(config)
    require("open3d", "escape dataset synth")  # the synth extra: depth views are ray-cast with open3d
    check_output_folder(out)  # a file, or a folder that cannot be made or written
    prepare_output(out, overwrite)  # refuse a non-empty folder before any progress bar shows
    total = len(config.jobs())
    quiet = not logging.getLogger("escape").isEnabledFor(logging.WARNING)
    progress = Progress(
        TextColumn("[bold]synth[/bold]"), BarColumn(), MofNCompleteColumn(), TextColumn("objects"),
        TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True), disable=quiet,
    )
    with progress, interrupts.on_interrupt(progress.stop):  # Ctrl-C: the terminal's cursor back, the bar's line ended
        task = progress.add_task("synth", total=total)
        metadata = synthesize(out, config, workers=workers, overwrite=True,
                              on_object=lambda _result: progress.advance(task))
    timing = metadata["timing"]
    print_summary(
        f"escape: wrote {metadata['totals']['objects']} objects, {metadata['totals']['partial_views']} partial views "
        f"to {out} in {timing['elapsed_s']:.1f} s ({timing['objects_per_s']:.2f} objects/s, "
        f"{timing['views_per_s']:.1f} views/s)"
    )
    if json_out:
        typer.echo(json.dumps(metadata))


@app.command("from-shapes")
def from_shapes(
    sources: List[Path] = typer.Argument(
        ..., help="Folders (<category>/{train,test}/<file> as ModelNet, <category>/<file>, or flat) and shape files.",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (must be empty unless --overwrite)."),
    category: Optional[str] = typer.Option(
        None, "--category", help="Category of a flat folder's files and of files given directly (default: their folder's name).",
    ),
    val_fraction: float = typer.Option(0.05, "--val-fraction", min=0.0, max=0.99, help="Share of each category's training shapes held out for validation (chosen by a hash of their ids)."),
    test_fraction: float = typer.Option(0.0, "--test-fraction", min=0.0, max=0.99, help="Share of each category's shapes held out for testing, where the layout has no test split."),
    seed: int = typer.Option(0, "--seed", min=0, help="Run seed; same seed, byte-identical point files."),
    views: int = typer.Option(8, "--views", min=1, max=100, help="Partial views per training shape (PCN: 8)."),
    eval_views: int = typer.Option(1, "--eval-views", min=1, max=100, help="Partial views per val/test shape (PCN: 1)."),
    workers: int = typer.Option(1, "--workers", "-w", min=1, max=256, help="Worker processes (results do not depend on it)."),
    complete_points: int = typer.Option(16384, "--complete-points", min=32, max=MAX_COMPLETE_POINTS, help="Points per complete cloud (PCN: 16384)."),
    overwrite: bool = OVERWRITE,
    json_out: bool = JSON,
) -> None:
    """Make a PCN-layout dataset from complete shapes: meshes (OBJ, OFF, STL, PLY with faces) and point clouds.

    A mesh gives area-uniform surface points and depth renders (needs open3d); a cloud is
    densified in its tangent planes and seen through surface splats, so that its views
    occlude like views of a surface. A bad shape is one line on stderr; the others are
    written, and the exit code is 1 at the end.

    Writes OUT/{train,val,test}/{partial,complete}/..., OUT/PCN.json and OUT/escape_shapes.json.
    """
    import json
    import logging
    import sys

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from escape_cli.errors import one_line
    from escape_cli.data.from_shapes import (
        METADATA_FILE,
        ShapesConfig,
        build_from_shapes,
        check_shapes_config,
        check_sources_outside,
        find_shapes,
    )
    from escape_cli.data.synth import prepare_output
    from escape_cli.errors import DatasetError
    from escape_cli.io.files import check_output_folder

    log = logging.getLogger("escape")
    config = ShapesConfig(
        views={"train": views, "val": eval_views, "test": eval_views}, seed=seed, complete_points=complete_points,
        val_fraction=val_fraction, test_fraction=test_fraction,
    )
    check_shapes_config(config)
    missing = [s for s in sources if not s.exists()]
    if missing:
        raise DatasetError(f"{missing[0]}: no such file or folder")
    check_output_folder(out, inputs=[s for s in sources if s.is_dir()])
    check_sources_outside(out, sources)  # before --overwrite empties the output folder
    find_shapes(sources, category)  # no shape at all: one line before any progress bar
    prepare_output(out, overwrite, extra_files=(METADATA_FILE,))  # a non-empty folder is refused before the work
    quiet = not log.isEnabledFor(logging.WARNING)
    console = Console(stderr=True)
    progress = Progress(
        TextColumn("[bold]shapes[/bold]"), BarColumn(), MofNCompleteColumn(), TextColumn("shapes"),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, disable=quiet,
    )
    task = progress.add_task("shapes", total=None)

    def started(count: int, skipped: int) -> None:
        progress.update(task, total=count)
        if skipped:
            log.info("skipped %d files that are not shape files", skipped)

    def finished(result: dict) -> None:
        if "error" in result:
            print(f"escape: error: {one_line(result['error'])}", file=sys.stderr, flush=True)
        progress.advance(task)

    with progress, interrupts.on_interrupt(progress.stop):  # Ctrl-C: the terminal's cursor back, the bar's line ended
        metadata = build_from_shapes(out, sources, config, category=category, workers=workers, overwrite=True,
                                     on_shape=finished, on_start=started)
    totals, timing = metadata["totals"], metadata["timing"]
    print_summary(
        f"escape: wrote {totals['written']} shapes, {totals['partial_views']} partial views to {out} in "
        f"{timing['elapsed_s']:.1f} s ({timing['shapes_per_s']:.2f} shapes/s)"
    )
    if json_out:
        typer.echo(json.dumps(metadata))
    if totals["failed"]:
        raise DatasetError(f"{totals['failed']} of {totals['shapes']} shapes could not be used (named above); the others were written")


@app.command("info")
def info(
    root: Path = typer.Argument(..., help="Dataset root in the PCN layout."),
    categories: Optional[List[str]] = CATEGORIES_OPTION,
    json_out: bool = JSON,
) -> None:
    """Count the models and partial views per split and category of a PCN-layout dataset."""
    import json

    from escape_cli.data.pcn import SPLITS, category_name, dataset_categories, list_samples, resolve_categories
    from escape_cli.errors import DatasetError

    if not Path(root).is_dir():
        raise DatasetError(f"dataset root {root} is not a folder")
    known = dataset_categories(root)
    synsets = resolve_categories(categories, known)
    names = {synset: category_name(synset, known) for synset in synsets}
    counts: dict[str, dict[str, dict[str, int]]] = {}
    for split in SPLITS:
        try:
            refs = list_samples(root, split, synsets)
        except DatasetError:
            if not Path(root).is_dir():
                raise
            continue
        per_category = counts.setdefault(split, {})
        for synset in synsets:
            mine = [r for r in refs if r.synset == synset]
            per_category[names[synset]] = {"models": len({r.model_id for r in mine}), "views": len(mine)}
    if not counts:
        raise DatasetError(f"{root}: no split with samples (PCN layout expected)")
    if json_out:
        typer.echo(json.dumps(counts))
        return
    for split, per_category in counts.items():
        for name, c in per_category.items():
            typer.echo(f"{split}\t{name}\t{c['models']} models\t{c['views']} views")
