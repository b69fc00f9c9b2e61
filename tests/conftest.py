"""Shared fixtures: seeded synthetic clouds, the third-party scans in ../shared/realdata and shapes in ../shared/shapes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
REALDATA = REPO.parent / "shared" / "realdata"
SHAPES = REPO.parent / "shared" / "shapes"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def realdata_dir() -> Path:
    """../shared/realdata, or skip the test with a message where it is absent."""
    if not REALDATA.is_dir():
        pytest.skip(f"third-party scans not found at {REALDATA}")
    return REALDATA


@pytest.fixture(scope="session")
def shapes_dir() -> Path:
    """../shared/shapes (ModelNet40 and the test meshes), or skip the test with a message where it is absent."""
    if not SHAPES.is_dir():
        pytest.skip(f"third-party shapes not found at {SHAPES}")
    return SHAPES


def realdata_clouds() -> list:
    """Every point-cloud file under ../shared/realdata, for parametrize.

    Where the folder is absent: one parameter that skips with a message saying so.
    """
    if not REALDATA.is_dir():
        return [pytest.param(None, marks=pytest.mark.skip(reason=f"third-party scans not found at {REALDATA}"))]
    return sorted(p for p in REALDATA.rglob("*") if p.suffix.lower() in (".pcd", ".ply") and p.is_file())


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory) -> Path:
    """An untrained tiny network exported to ONNX (256 input points, 1024 outputs)."""
    pytest.importorskip("torch")
    from escape_cli.nn.export import export_onnx
    from tests_support import write_tiny_checkpoint

    folder = tmp_path_factory.mktemp("tiny_model")
    write_tiny_checkpoint(folder / "tiny.pt")
    export_onnx(folder / "tiny.pt", folder / "tiny.onnx")
    return folder / "tiny.onnx"


@pytest.fixture(scope="session")
def tiny_absolute_model(tmp_path_factory) -> Path:
    """The tiny network as a model of the older kind, trained in absolute PCN units."""
    pytest.importorskip("torch")
    from escape_cli.nn.export import export_onnx
    from tests_support import write_tiny_checkpoint

    folder = tmp_path_factory.mktemp("tiny_absolute_model")
    write_tiny_checkpoint(folder / "tiny.pt", partial_frame=False)
    export_onnx(folder / "tiny.pt", folder / "tiny.onnx")
    return folder / "tiny.onnx"


def realdata_id(path) -> str:
    """Test id of a realdata cloud: its folder and name."""
    return "absent" if path is None else f"{path.parent.name}/{path.name}"
