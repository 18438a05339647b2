#!/usr/bin/env bash
# Install moisst-ns into .venv/ at the repo root (idempotent; skipped when pyproject.toml is unchanged).
# Needs: python3.11 and Debian's apt (open3d needs libusb-1.0-0). Nothing is downloaded at run time afterwards.
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    echo "[install] Debian package libusb-1.0-0 (needed by open3d)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q libusb-1.0-0 >/dev/null; }
fi

PY=${PYTHON:-python3.11}
STAMP=.venv/.moisst-installed
WANT=$(cat pyproject.toml scripts/install.sh | sha256sum | cut -d' ' -f1)
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ]; then
    echo "[install] .venv up to date"
    exit 0
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
echo "[install] torch 2.14.1 / torchvision 0.29.1"
.venv/bin/pip install -q --disable-pip-version-check torch==2.14.1 torchvision==0.29.1 2>&1 | grep -v "^WARNING: Location" || true
echo "[install] moisst-ns + nerfstudio 1.1.5 (a few minutes the first time)"
.venv/bin/pip install -q --disable-pip-version-check -e ".[test]" 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import moisst_ns.method_configs, open3d" >/dev/null
echo "$WANT" > "$STAMP"
echo "[install] done"
