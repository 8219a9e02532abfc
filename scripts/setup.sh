#!/usr/bin/env bash
# Set up recon in a virtual environment on a fresh Debian machine (run as root, or with sudo).
#   bash scripts/setup.sh [VENV_DIR]
# - installs the system library libusb-1.0 that open3d needs, if it is missing;
# - creates the venv; installs torch only if the venv has none: the CPU wheel
#   (torch==2.13.0) unless RECON_TORCH_SPEC names another (e.g. a CUDA build);
# - installs recon in editable mode with its dev extras.
set -euo pipefail
venv="${1:-.venv}"
python="${PYTHON:-python3}"

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    echo "setup: installing libusb-1.0-0 (needed by open3d)"
    sudo=""
    [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

[ -x "$venv/bin/python" ] || "$python" -m venv "$venv"
pip="$venv/bin/python -m pip"
$pip install -q --upgrade pip >/dev/null

if ! "$venv/bin/python" -c "import torch" 2>/dev/null; then
    spec="${RECON_TORCH_SPEC:-torch==2.13.0}"
    echo "setup: installing $spec"
    $pip install -q "$spec"
fi

extras="${RECON_EXTRAS:-dev}"
echo "setup: installing recon[$extras]"
$pip install -q -e ".[$extras]"
"$venv/bin/python" -c "import open3d, torch, rerun; print('setup: ok (torch', torch.__version__ + ', open3d', open3d.__version__ + ')')"
