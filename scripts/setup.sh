#!/usr/bin/env bash
# Idempotent set-up on a fresh Debian machine with Python 3.11 and root:
# system libraries, a virtual environment in .venv, pinned Python packages.
set -euo pipefail
cd "$(dirname "$0")/.."

# libusb for Open3D, OpenNI2 for the Kinect driver, libGL/libgomp for Open3D and OpenCV.
SYSTEM_PACKAGES=(libusb-1.0-0 libopenni2-0 libgl1 libgomp1)
missing=()
for pkg in "${SYSTEM_PACKAGES[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "[setup] installing system packages: ${missing[*]}"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null || PYTHON=python3
if [ ! -x .venv/bin/python ]; then
    echo "[setup] creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi
# pip's output is only shown when it fails (the local package mirrors warn about every index entry).
pip_install() {
    local log; log=$(mktemp)
    if ! .venv/bin/python -m pip install --disable-pip-version-check "$@" >"$log" 2>&1; then
        grep -v "is ignored" "$log" >&2; rm -f "$log"; exit 1
    fi
    rm -f "$log"
}
echo "[setup] installing pinned Python packages"
pip_install -q --upgrade pip==26.3
pip_install -q -c constraints.txt -e ".[dev]"
.venv/bin/python -c "import dtx, torch, open3d, zmq, mcap" 
echo "[setup] ready: $(.venv/bin/python -c 'import torch, open3d; print("torch", torch.__version__, "open3d", open3d.__version__)')"
