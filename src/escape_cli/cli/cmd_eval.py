"""`escape eval`: the rotated PCN benchmark (and robustness variants) and KITTI cars."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import List, Optional

import typer

from escape_cli.cli.options import ANCHOR_SETS, JSON, MODEL, NORMALIZE_HELP, OVERWRITE, SNAP_RADIUS, number_check


def command(
    dataset: str = typer.Option(
        "pcn", "--dataset",
        help="pcn (a PCN-layout tree, e.g. from `escape dataset synth`), pair (one object: a folder with complete.<ext> and partial views), pairs (a folder of <name>_partial.<ext> / <name>_complete.<ext> pairs) or kitti.",
    ),
    root: Path = typer.Option(..., "--root", help="Dataset folder."),
    split: str = typer.Option("test", "--split", help="PCN split: train, val or test."),
    categories: Optional[List[str]] = typer.Option(None, "--categories", "-c", help="Category names or synsets (repeatable)."),
    rotate: bool = typer.Option(False, "--rotate", help="Also evaluate rotated inputs (paper protocol) and report the gap."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of rotations, noise and point removal."),
    noise: float = typer.Option(0.0, "--noise", callback=number_check(minimum=0.0), help="Gaussian noise sigma added to the inputs."),
    drop: float = typer.Option(0.0, "--drop", callback=number_check(minimum=0.0, maximum=0.95), help="Share of input points removed at random."),
    limit: Optional[int] = typer.Option(None, "--limit", min=1, help="At most N objects per category."),
    model: Optional[str] = MODEL,
    baseline: bool = typer.Option(True, "--baseline/--no-baseline", help="Also score the trivial answer: the input cloud itself."),
    keep_input: bool = typer.Option(True, "--keep-input/--no-keep-input", help="Merge observed points into the output."),
    snap_radius: Optional[float] = SNAP_RADIUS,
    anchor_sets: int = ANCHOR_SETS,
    normalize: str = typer.Option("auto", "--normalize", help=NORMALIZE_HELP),
    reference: Optional[Path] = typer.Option(None, "--reference", help="KITTI: folder of complete reference cars for MMD."),
    reference_up: Optional[str] = typer.Option(
        None, "--reference-up", metavar="x|y|z",
        help="KITTI: the up axis of the --reference cars (z for ModelNet40); each is then put in the KITTI cars' box frame (centred on its bounding box, length 1 along x, up y) and taken both ways round. Default: used as they are (already in that frame, as `escape dataset synth` cars are).",
    ),
    json_lines: bool = JSON,
    json_path: Optional[Path] = typer.Option(None, "--json-out", help="Write every number to this JSON file."),
    save: Optional[Path] = typer.Option(None, "--save", help="Write every completion (PLY) under this folder."),
    overwrite: bool = OVERWRITE,
) -> None:
    """Score completions: CD-L1 / CD-L2 x 1000 and F-Score@1% per category (PCN), or Fidelity and MMD (KITTI).

    The table goes to stdout; with --json the report goes there as one JSON line and the
    table to stderr.
    """
    import logging

    from rich.console import Console

    from escape_cli.cli.options import check_anchor_sets, check_output
    from escape_cli.evaluation import (
        METRIC_DEFINITIONS,
        Perturbation,
        evaluate_kitti,
        evaluate_pair_folder,
        evaluate_pairs,
        evaluate_pcn,
    )
    from escape_cli.inference import load_model, model_path as resolve_model
    from escape_cli.io.files import check_output_folder
    from escape_cli.pipeline import complete
    from escape_cli.core.snap import SNAP_RADIUS as DEFAULT_SNAP_RADIUS

    if dataset not in ("pcn", "pair", "pairs", "kitti"):
        raise typer.BadParameter("must be pcn, pair, pairs or kitti", param_hint="--dataset")
    if split not in ("train", "val", "test"):
        raise typer.BadParameter("must be train, val or test", param_hint="--split")
    if normalize not in ("auto", "none"):
        raise typer.BadParameter("must be auto or none", param_hint="--normalize")
    if reference_up is not None:
        from escape_cli.core.normalize import AXES

        if reference_up not in AXES:
            raise typer.BadParameter("must be x, y or z", param_hint="--reference-up")
        if reference is None:
            raise typer.BadParameter("needs --reference (the folder of complete cars)", param_hint="--reference-up")
    if reference is not None:
        _check_reference_folder(reference, dataset)
    model_path = resolve_model(model)
    inputs = [root, reference, model_path, model_path.with_suffix(".json")]
    check_output(json_path, overwrite, inputs=inputs)
    if save is not None:
        check_output_folder(save, inputs=[root, reference])
        if save.is_dir() and any(save.iterdir()) and not overwrite:
            from escape_cli.errors import OutputExistsError

            raise OutputExistsError(f"{save} is not empty (use --overwrite to write into it)")
    net = load_model(str(model_path))
    check_anchor_sets(anchor_sets, net.k)
    options = dict(normalize=normalize, keep_input=keep_input, snap_radius=snap_radius, anchor_sets=anchor_sets)

    def escape_completer(points):
        return complete(points, net, **options).points

    completers = {"escape": escape_completer}
    if baseline:
        completers["input"] = lambda points: points
    quiet = not logging.getLogger("escape").isEnabledFor(logging.WARNING)
    console = Console(stderr=True, quiet=quiet)
    table_stream = None if quiet and json_lines else (sys.stderr if json_lines else sys.stdout)
    settings = {
        "dataset": dataset, "root": str(root), "model": str(net.path), "rotate": rotate, "seed": seed,
        "keep_input": keep_input, "snap_radius": DEFAULT_SNAP_RADIUS if snap_radius is None else snap_radius, "normalize": normalize,
        "anchor_sets": anchor_sets,
    }
    if dataset == "pcn":
        settings.update(split=split, noise=noise, drop=drop, limit=limit)
        with console.status("evaluating") as status:
            result = evaluate_pcn(
                root, completers, split=split, categories=categories, rotate=rotate, seed=seed,
                perturbation=Perturbation(noise=noise, drop=drop), limit=limit, save_dir=save,
                progress=lambda i, n: status.update(f"evaluating {i}/{n}"),
            )
    elif dataset in ("pair", "pairs"):
        settings.update(noise=noise, drop=drop)
        evaluate = evaluate_pairs if dataset == "pair" else evaluate_pair_folder
        result = evaluate(
            root, completers, rotate=rotate, seed=seed, perturbation=Perturbation(noise=noise, drop=drop), save_dir=save
        )
    if dataset in ("pcn", "pair", "pairs"):
        summary = result.summary()
        _print_pcn_table(summary, list(completers), rotate, table_stream)
        report = {"settings": settings, "metrics": METRIC_DEFINITIONS, **summary, "samples": result.records}
    else:
        refs = _read_references(reference, reference_up) if reference else None
        settings.update(reference=None if reference is None else str(reference), reference_up=reference_up)
        if refs is None:
            logging.getLogger("escape").warning(
                "no --reference folder of complete cars: MMD is not scored, nor is the input copy "
                "(Fidelity is measured on the predicted points, and the copy predicts none)"
            )
        completers = _kitti_completers(net, completers, **options)
        report = evaluate_kitti(root, completers, reference=refs, rotate=rotate, seed=seed, save_dir=save)
        report = {"settings": settings, "metrics": METRIC_DEFINITIONS, **report}
        _print_kitti_table(report, table_stream)
    if json_path is not None:
        from escape_cli.io.files import write_output_bytes

        write_output_bytes(json_path, (json.dumps(report, indent=1) + "\n").encode(), overwrite=overwrite)
    if json_lines:
        print(json.dumps(report), flush=True)


def _check_reference_folder(folder: Path, dataset: str) -> None:
    """--reference (KITTI's complete cars) before any work: only for kitti, an existing folder."""
    from escape_cli.errors import DatasetError

    if dataset != "kitti":
        raise typer.BadParameter("only for --dataset kitti (a folder of complete reference cars)", param_hint="--reference")
    if not folder.exists():
        raise DatasetError(f"--reference {folder}: no such folder (the complete reference cars MMD compares with)")
    if not folder.is_dir():
        raise DatasetError(f"--reference {folder} is a file; give the folder of complete reference cars")


def _kitti_completers(net, completers: dict, **options) -> dict:
    """The KITTI completers: escape's returns the whole `Completion`, so that Fidelity can leave out
    the observed points; the input copy marks all its points observed (it predicts none)."""
    import numpy as np

    from escape_cli.pipeline import complete

    kitti = {"escape": lambda points: complete(points, net, **options)}
    if "input" in completers:
        kitti["input"] = lambda points: SimpleNamespace(points=points, is_observed=np.ones(len(points), dtype=bool))
    return kitti


def _read_references(folder: Path, up: Optional[str] = None) -> list:
    """The reference cars of FOLDER (and below), as they are or, with `up`, in the box frame (both ways round)."""
    from escape_cli.cli.inputs import expand_inputs
    from escape_cli.core.normalize import car_in_box_frame
    from escape_cli.io import read_points

    clouds = [read_points(p) for p in expand_inputs([str(folder)], recursive=True)]
    if up is None:
        return clouds
    return [turned for cloud in clouds for turned in car_in_box_frame(cloud, up)]


def _print_pcn_table(summary: dict, methods: list[str], rotate: bool, stream) -> None:
    if stream is None:
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title="CD-L1 x1000 (mean / median), CD-L2 x1000, F-Score@1%", show_lines=False)
    table.add_column("category")
    table.add_column("n", justify="right")
    poses = [""] + (["rotated/"] if rotate else [])
    for prefix in poses:
        for name in methods:
            tag = f"{name}{' rot' if prefix else ''}"
            table.add_column(f"{tag} CD-L1", justify="right")
            if name == "escape":
                table.add_column(f"{tag} med", justify="right")
                table.add_column(f"{tag} CD-L2", justify="right")
                table.add_column(f"{tag} F@1%", justify="right")
    ratio = "input" in methods
    if ratio:
        table.add_column("escape / input", justify="right")
    if rotate:
        table.add_column("rot gap", justify="right")

    def row(label: str, stats: dict) -> list[str]:
        cells = [label, str(stats.get("count", ""))]
        for prefix in poses:
            for name in methods:
                cells.append(f"{stats[f'{prefix}{name}/cd_l1_x1000_mean']:.2f}")
                if name == "escape":
                    cells.append(f"{stats[f'{prefix}{name}/cd_l1_x1000_median']:.2f}")
                    cells.append(f"{stats[f'{prefix}{name}/cd_l2_x1000_mean']:.2f}")
                    cells.append(f"{stats[f'{prefix}{name}/fscore_1pct_mean']:.3f}")
        if ratio:
            cells.append(f"x{stats['escape/ratio_to_input']:.2f}")
        if rotate:
            a, b = stats["escape/cd_l1_x1000_mean"], stats["rotated/escape/cd_l1_x1000_mean"]
            cells.append(f"{100 * (b - a) / a:+.2f}%")
        return cells

    for name, stats in summary["categories"].items():
        table.add_row(*row(name, stats))
    table.add_row(*row("[bold]average", summary["average"]))
    Console(file=stream, width=max(120, 14 * len(table.columns))).print(table)


def _print_kitti_table(report: dict, stream) -> None:
    if stream is None:
        return
    from rich.console import Console
    from rich.table import Table

    keys = list(report["cars"][0]["metrics"])
    table = Table(title="KITTI cars: Fidelity and MMD (CD-L2) x1000")
    table.add_column("car")
    table.add_column("points", justify="right")
    for key in keys:
        table.add_column(key.replace("_x1000", ""), justify="right")
    for rec in report["cars"]:
        table.add_row(rec["car"], str(rec["input_points"]), *[f"{rec['metrics'][k]:.3f}" for k in keys])
    table.add_row("[bold]mean", "", *[f"{report['average'][k + '_mean']:.3f}" for k in keys])
    Console(file=stream, width=max(120, 16 * len(table.columns))).print(table)
