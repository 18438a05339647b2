#!/usr/bin/env bash
# Install moisst-ns into .venv/ at the repo root (idempotent; skipped when nothing it depends on changed).
# Needs: python3.11 and Debian's apt (open3d needs libusb-1.0-0). Nothing is downloaded at run time afterwards.
#
# torch: MOISST_TORCH=cpu|cuda|auto (default auto: cuda when `nvidia-smi -L` lists a GPU, else cpu).
#   cpu : torch 2.13.0, CPU build (the machine's local wheel when pip's find-links has one, else PyTorch's CPU
#         index, else PyPI's build), with torchvision 0.28.0. PyPI's torchvision is a CUDA build; beside a CPU
#         torch its C operators cannot load and `import torchvision` would fail: a .pth line then declares the two
#         operators it needs to import (moisst_ns/torchvision_cpu.py).
#   cuda: torch 2.14.1 + torchvision 0.29.1 from PyPI (CUDA build with its nvidia libraries, ~5.5 GB).
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then  # not grep -q: with pipefail its early exit fails the pipe
    echo "[install] Debian package libusb-1.0-0 (needed by open3d)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q libusb-1.0-0 >/dev/null; }
fi

TORCH_KIND=${MOISST_TORCH:-auto}
if [ "$TORCH_KIND" = auto ]; then
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L 2>/dev/null | grep -q GPU; then TORCH_KIND=cuda; else TORCH_KIND=cpu; fi
fi
case "$TORCH_KIND" in
    cpu) TORCH=2.13.0; TORCHVISION=0.28.0 ;;
    cuda) TORCH=2.14.1; TORCHVISION=0.29.1 ;;
    *) echo "[install] MOISST_TORCH must be cpu, cuda or auto, not '$TORCH_KIND'" >&2; exit 2 ;;
esac

PY=${PYTHON:-python3.11}
STAMP=.venv/.moisst-installed
WANT=$( (cat pyproject.toml scripts/install.sh; echo "$TORCH_KIND") | sha256sum | cut -d' ' -f1)
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ]; then
    echo "[install] .venv up to date"
    exit 0
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
PIP=(.venv/bin/pip install -q --disable-pip-version-check)
quiet_pip() { "${PIP[@]}" "$@" 2>&1 | { grep -v "^WARNING: Location" || true; }; return "${PIPESTATUS[0]}"; }

if ! .venv/bin/python -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$TORCH')" 2>/dev/null; then
    echo "[install] torch $TORCH ($TORCH_KIND) / torchvision $TORCHVISION"
    if [ "$TORCH_KIND" = cpu ]; then
        # a local CPU wheel (find-links) first, then PyTorch's CPU index, then PyPI
        quiet_pip --no-index --no-deps "torch==$TORCH" >/dev/null 2>&1 \
            || quiet_pip --retries 0 --timeout 20 --index-url https://download.pytorch.org/whl/cpu "torch==$TORCH+cpu" "torchvision==$TORCHVISION+cpu" >/dev/null 2>&1 \
            || quiet_pip "torch==$TORCH"
    else
        quiet_pip "torch==$TORCH"
    fi
fi
.venv/bin/python -c "import torchvision" 2>/dev/null || quiet_pip --no-deps "torchvision==$TORCHVISION" || true

SITE=$(.venv/bin/python -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
.venv/bin/python -c "from importlib.metadata import version as v; print(f'torch=={v(\"torch\")}\ntorchvision=={v(\"torchvision\")}')" > .venv/moisst-constraints.txt
echo "[install] moisst-ns + nerfstudio 1.1.5"
quiet_pip -c .venv/moisst-constraints.txt -e ".[test]"

rm -f "$SITE/moisst_torchvision_cpu.pth"
if .venv/bin/python -c "import moisst_ns.torchvision_cpu as m, sys; sys.exit(not m.needed())"; then
    echo "import sys; exec('try:\n import moisst_ns.torchvision_cpu as m; m.install()\nexcept ImportError: pass')" > "$SITE/moisst_torchvision_cpu.pth"
    echo "[install] CPU torch beside PyPI's CUDA torchvision: $SITE/moisst_torchvision_cpu.pth (moisst_ns/torchvision_cpu.py)"
fi
.venv/bin/python -W ignore::FutureWarning -c "import torchvision, moisst_ns.method_configs, open3d" >/dev/null
echo "$WANT" > "$STAMP"
echo "[install] done: torch $(.venv/bin/python -c 'import torch; print(torch.__version__)'), $(du -sh .venv | cut -f1) in .venv"
