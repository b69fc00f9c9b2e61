#!/usr/bin/env bash
# Install the system libraries the package's extras need, where they are missing (Debian/Ubuntu).
# Usage: bash scripts/install_system_deps.sh [EXTRA...]     e.g. synth
#   (no extra)  the runtime (numpy, scipy, onnxruntime, laspy/lazrs) needs no system library
#   synth       open3d loads libGL, libEGL, libX11, libusb, libudev and libgomp
#   test        a C compiler, for the package's compiled kernels (setup.py; a user's install
#               without one falls back to numpy and scipy, the tests insist on them)
set -euo pipefail
needed=()
for extra in "$@"; do
    case "$extra" in
        synth) needed+=(libgl1 libegl1 libx11-6 libusb-1.0-0 libudev1 libgomp1) ;;
        test) command -v cc >/dev/null || needed+=(gcc) ;;
        train | h5 | ray) ;;  # pip wheels only
        *) echo "escape: unknown extra '$extra' (synth, train, h5, ray, test)" >&2; exit 2 ;;
    esac
done
missing=()
for pkg in "${needed[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -eq 0 ]; then
    exit 0
fi
if ! command -v apt-get >/dev/null; then
    echo "escape: please install the system libraries: ${missing[*]}" >&2
    exit 1
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
