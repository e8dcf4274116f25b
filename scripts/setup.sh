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

# The third-party clients the tests run (clients/node: zeromq.js, @msgpack/msgpack, @mcap/core),
# exactly as locked; skipped, like their tests, where Node.js is not installed. npm ci runs only
# when the lockfile changed since the last install, so a second `make setup` does nothing.
if command -v npm >/dev/null; then
    lock_sum=$(sha256sum clients/node/package-lock.json | cut -d" " -f1)
    if [ "$(cat clients/node/node_modules/.dtx-lock-sha256 2>/dev/null)" != "$lock_sum" ]; then
        echo "[setup] installing pinned npm packages in clients/node"
        log=$(mktemp)
        if ! (cd clients/node && npm ci --no-audit --no-fund --ignore-scripts) >"$log" 2>&1; then
            cat "$log" >&2; rm -f "$log"; exit 1
        fi
        rm -f "$log"
        echo "$lock_sum" > clients/node/node_modules/.dtx-lock-sha256
    fi
else
    echo "[setup] node/npm not found: the third-party client tests (tests/test_third_party_clients.py) will be skipped"
fi
echo "[setup] ready: $(.venv/bin/python -c 'import torch, open3d; print("torch", torch.__version__, "open3d", open3d.__version__)')"
