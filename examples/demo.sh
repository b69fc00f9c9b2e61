#!/usr/bin/env bash
# Complete every bundled example with the shipped model and draw inputs next to outputs.
# Usage: bash examples/demo.sh [OUT_DIR]   (default out/demo)
set -euo pipefail
cd "$(dirname "$0")/.."
ESCAPE=${ESCAPE:-.venv/bin/escape}
OUT=${1:-out/demo}
mkdir -p "$OUT"

"$ESCAPE" complete examples/*.ply examples/*.pcd -o "$OUT/" --residuals --overwrite

columns=()
for input in examples/*.ply examples/*.pcd; do
    name=$(basename "${input%.*}")
    columns+=("$input" "$OUT/$name.ply")
done
"$ESCAPE" render "${columns[@]}" -o "$OUT/completions.png" --views 2 --size 160 --overwrite
echo "completed clouds and $OUT/completions.png (each input left of its completion)"
