#!/usr/bin/env bash
# Check the install a user gets: build the wheel, install it WITHOUT extras into a fresh
# virtual environment, and complete an example there with the model inside the package.
# Fails on a missing package-data line, a runtime import of a training-only library, or
# a torch/open3d that crept into the runtime dependencies.
# Usage: bash scripts/check_runtime_install.sh   (PYTHON=python3.11 to choose the interpreter)
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
PYTHON=${PYTHON:-python3}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

say() { echo "check-install: $*"; }
fail() { echo "check-install: FAILED: $*" >&2; exit 1; }

# 1. the wheel, built from a copy of the sources (the checkout stays clean)
mkdir -p "$work/src"
cp pyproject.toml setup.py README.md LICENSE "$work/src/"
cp -r src "$work/src/src"
find "$work/src" -name __pycache__ -prune -exec rm -rf {} +
find "$work/src" -name "*.so" -delete  # the editable install's build of the kernels: the wheel builds its own
"$PYTHON" -m venv "$work/build-env"
"$work/build-env/bin/pip" install --quiet --upgrade pip
"$work/build-env/bin/pip" wheel --quiet --no-deps -w "$work/dist" "$work/src"
wheel=$(ls "$work"/dist/escape_cli-*.whl)
"$PYTHON" - "$wheel" src/escape_cli/models <<'EOF' || fail "the wheel lacks a packaged model or the compiled kernels"
import sys, zipfile
from pathlib import Path
names = set(zipfile.ZipFile(sys.argv[1]).namelist())
models = sorted(Path(sys.argv[2]).glob("escape-*.onnx"))  # every packaged model of the checkout, with its metadata
wanted = ["escape_cli/models/escape-small.onnx"] + [f"escape_cli/models/{p.name}" for p in models]
wanted += [n[: -len(".onnx")] + ".json" for n in wanted]
missing = sorted({n for n in wanted if n not in names})
if not any(n.startswith("escape_cli/core/_kernels") and n.endswith((".so", ".pyd")) for n in names):
    missing.append("escape_cli/core/_kernels (the compiled kernels: is a C compiler installed?)")
sys.exit(f"missing from the wheel: {missing}" if missing else 0)
EOF
say "wheel $(basename "$wheel"): $(du -h "$wheel" | cut -f1)"

# 2. a fresh virtual environment with the runtime only
"$PYTHON" -m venv "$work/runtime"
"$work/runtime/bin/pip" install --quiet --upgrade pip
start=$(date +%s)
"$work/runtime/bin/pip" install --quiet "$wheel"
say "pip install of the wheel (no extras): $(( $(date +%s) - start )) s; environment $(du -sh "$work/runtime" | cut -f1)"
bin="$work/runtime/bin"

# 3. no training or synthesis library came with it
for module in torch open3d h5py; do
    if "$bin/python" -c "import $module" 2>/dev/null; then
        fail "import $module works in the runtime install"
    fi
done
say "import torch / open3d / h5py fail, as they should"
"$bin/python" -c "from escape_cli.core import _kernels" || fail "the compiled kernels do not import"

# 4. it completes a scan with the model shipped in the package, run from outside the checkout
out="$work/out"
mkdir -p "$out"
(cd "$work" && env -u ESCAPE_MODEL "$bin/escape" complete "$repo/examples/chair.pcd" -o "$out/chair.ply" --residuals) \
    || fail "escape complete without --model"
(cd "$work" && env -u ESCAPE_MODEL "$bin/escape" complete "$repo/examples/car.ply" -o "$out/car.laz" --points 4096) \
    || fail "escape complete to LAZ"
(cd "$work" && env -u ESCAPE_MODEL "$bin/python" -m escape_cli --version) || fail "python -m escape_cli --version"
"$bin/python" - "$out" <<'EOF' || fail "the completed clouds"
import sys
from pathlib import Path
from escape_cli.io import read_point_fields, read_points
points, fields = read_point_fields(Path(sys.argv[1]) / "chair.ply")
assert points.shape[1] == 3 and len(points) > 10000 and fields["observed"].sum() > 0, points.shape
assert read_points(Path(sys.argv[1]) / "car.laz").shape == (4096, 3)
assert "torch" not in sys.modules
EOF
say "escape complete works with no --model (PLY and LAZ out)"
for model in src/escape_cli/models/escape-*.onnx; do  # each packaged model by its name, from the installed package
    name=$(basename "$model" .onnx); name=${name#escape-}
    (cd "$work" && env -u ESCAPE_MODEL "$bin/escape" -q complete "$repo/examples/chair.pcd" -o "$out/chair-$name.ply" --model "$name") \
        || fail "escape complete --model $name"
    help=$(cd "$work" && COLUMNS=250 "$bin/escape" complete --help)
    [[ "$help" == *"A packaged model ("*"$name"* ]] || fail "escape complete --help does not list $name"
done
say "escape complete --model NAME works for every packaged model: $(cd src/escape_cli/models && ls escape-*.onnx | tr '\n' ' ')"

# 5. the jobs of the extras say which extra to install, in one line
if message=$(cd "$work" && "$bin/escape" dataset synth --out "$out/synth" --train 1 2>&1); then
    fail "escape dataset synth ran without open3d"
fi
[ "$(printf '%s\n' "$message" | wc -l)" -eq 1 ] && [[ "$message" == *"escape-cli[synth]"* ]] \
    || fail "escape dataset synth without open3d said: $message"
if message=$(cd "$work" && "$bin/escape" train --data "$out" --out "$out/run" 2>&1); then
    fail "escape train ran without torch"
fi
[[ "$message" == *"escape-cli[train]"* ]] || fail "escape train without torch said: $message"
say "synth and train name their extras: $message"
say "ok"
