"""The package as pip installs it: the model inside the wheel, a runtime without torch or open3d, one extra per job.

The full check (the wheel installed without extras into a fresh virtual environment,
completing an example) is `make check-install` (scripts/check_runtime_install.sh), run
by CI after the tests.
"""

from __future__ import annotations

import fnmatch
import re
import shutil
import subprocess
import sys
import zipfile

import pytest

from conftest import REPO

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

PACKAGE = REPO / "src" / "escape_cli"
MODEL_FILES = ("models/escape-small.onnx", "models/escape-small.json")


def packaged_model_files() -> list[str]:
    """Every packaged model of the checkout (`escape-<name>.onnx`) and its metadata, relative to the package."""
    models = sorted((PACKAGE / "models").glob("escape-*.onnx"))
    return [f"models/{p.name}" for p in models] + [f"models/{p.with_suffix('.json').name}" for p in models]
TRAINING_ONLY = {"torch", "onnx", "open3d", "h5py"}


@pytest.fixture(scope="module")
def pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def requirement_name(spec: str) -> str:
    return re.split(r"[\[<>=!~; ]", spec, maxsplit=1)[0].lower()


def test_package_data_covers_the_shipped_model(pyproject):
    patterns = pyproject["tool"]["setuptools"]["package-data"]["escape_cli"]
    shipped = sorted(p.relative_to(PACKAGE).as_posix() for p in (PACKAGE / "models").iterdir() if p.is_file())
    assert set(MODEL_FILES) <= set(packaged_model_files()) <= set(shipped)  # every model has its metadata
    # every packaged model ships, and so would one added later (`escape-synth.onnx` beside `escape-small.onnx`)
    later = ["models/escape-synth.onnx", "models/escape-synth.json"]
    uncovered = [name for name in shipped + later if not any(fnmatch.fnmatch(name, pattern) for pattern in patterns)]
    assert not uncovered, f"package data misses {uncovered}"
    for name in packaged_model_files():
        assert (PACKAGE / name).stat().st_size < 50e6, name  # installable from a plain index


def test_the_runtime_has_no_training_or_synthesis_library(pyproject):
    runtime = {requirement_name(spec) for spec in pyproject["project"]["dependencies"]}
    assert {"numpy", "scipy", "onnxruntime", "typer", "rich"} <= runtime
    assert not runtime & TRAINING_ONLY
    extras = pyproject["project"]["optional-dependencies"]
    assert {requirement_name(s) for s in extras["synth"]} == {"open3d"}
    assert {requirement_name(s) for s in extras["train"]} == {"torch", "onnx"}
    assert "torch==2.13.0" in extras["train"]
    assert {requirement_name(s) for s in extras["h5"]} == {"h5py"}
    assert {"pytest", "hypothesis"} <= {requirement_name(s) for s in extras["test"]}


def test_extras_match_the_install_and_error_messages(pyproject):
    from escape_cli.extras import EXTRA_OF

    extras = pyproject["project"]["optional-dependencies"]
    for module, extra in EXTRA_OF.items():
        assert module in {requirement_name(s) for s in extras[extra]}, (module, extra)
    makefile = (REPO / "Makefile").read_text()
    listed = re.search(r"^EXTRAS \?= (\S+)$", makefile, re.M).group(1).split(",")
    assert set(extras) <= set(listed)  # `make install` takes every extra


def _can_build_without_isolation() -> bool:
    try:
        import setuptools
    except ImportError:
        return False
    return int(setuptools.__version__.split(".")[0]) >= 77


@pytest.mark.slow
@pytest.mark.skipif(not _can_build_without_isolation(), reason="needs setuptools>=77 in this environment")
def test_the_wheel_contains_the_model(tmp_path):
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md", "LICENSE"):
        shutil.copy(REPO / name, source / name)
    shutil.copytree(REPO / "src", source / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "*.so"))
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "dist"),
         str(source)], capture_output=True, text=True, timeout=600,
    )
    assert built.returncode == 0, built.stderr
    (wheel,) = (tmp_path / "dist").glob("escape_cli-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in packaged_model_files():
        assert f"escape_cli/{name}" in names
    assert "escape_cli/py.typed" in names
    assert any(n.startswith("escape_cli/core/_kernels") and n.endswith((".so", ".pyd")) for n in names)  # compiled here
    assert wheel.stat().st_size < 100e6  # two packaged models of < 50 MB each; PyPI's default file limit is 100 MB
    metadata = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    unconditional = {requirement_name(line.split(":", 1)[1].strip()) for line in metadata.splitlines()
                     if line.startswith("Requires-Dist:") and "extra ==" not in line}
    assert not unconditional & TRAINING_ONLY
