#!/usr/bin/env bash
# A batch shell pipeline: complete every partial scan in a folder, two at a time,
# streaming each file through escape's stdin/stdout.
# Usage: bash examples/pipeline.sh [IN_DIR] [OUT_DIR]   (defaults: examples out/pipeline)
set -euo pipefail
cd "$(dirname "$0")/.."
ESCAPE=${ESCAPE:-$PWD/.venv/bin/escape}
IN=${1:-examples}
OUT=${2:-out/pipeline}
mkdir -p "$OUT"
export ESCAPE OUT

# find -> xargs -P 2: each scan goes in on stdin and comes out on stdout as binary PLY,
# its one-line JSON summary goes to OUT/NAME.log. A failing scan is reported and the
# others go on; xargs exits non-zero at the end if any failed.
find "$IN" -maxdepth 1 \( -name '*.ply' -o -name '*.pcd' \) -print0 | sort -z |
    xargs -0 -n 1 -P 2 sh -c '
        name=$(basename "${1%.*}")
        "$ESCAPE" complete - -o - < "$1" > "$OUT/$name.ply" 2> "$OUT/$name.log" \
            || { echo "failed: $1: $(cat "$OUT/$name.log")" >&2; rm -f "$OUT/$name.ply"; exit 1; }
        echo "$name -> $OUT/$name.ply"
    ' sh
