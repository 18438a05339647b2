#!/usr/bin/env bash
# Install moisst-ns into .venv/ at the repo root (idempotent; skipped when nothing it depends on changed).
# Needs: python3.11 and Debian's apt (open3d needs libusb-1.0-0). Nothing is downloaded at run time afterwards.
#
# MOISST_EXTRAS=fleet also installs pyproject.toml's `fleet` extra (Ray, for moisst-fleet; `make test` sets it).
#
# torch: MOISST_TORCH=cpu|cuda|auto (default auto: cuda when `nvidia-smi -L` lists a GPU, else cpu).
#   cpu : torch 2.13.0, CPU build (the machine's local wheel when pip's find-links has one, else PyTorch's CPU
#         index, else PyPI's build), with torchvision 0.28.0. PyPI's torchvision is a CUDA build; beside a CPU
#         torch its C operators cannot load and `import torchvision` would fail: a .pth line then declares the two
#         operators it needs to import (moisst_ns/torchvision_cpu.py).
#   cuda: torch 2.14.1 + torchvision 0.29.1 from PyPI (CUDA build with its nvidia libraries, ~5.5 GB).
#
# Slim venv (issue 18): nerfstudio 1.1.5 (and viser) go in with --no-deps, beside the part of its dependencies that the code
# paths we use import (scripts/nerfstudio-deps.txt: kept, and dropped with why); the rest of pyproject.toml's
# dependencies are read from it. open3d: the CPU-only build `open3d-cpu` on x86_64 Linux (same `open3d` module,
# ~320 MB instead of ~900 MB: we only use its CPU geometry), `open3d` elsewhere. `pip check` then reports only
# those known omissions (nerfstudio's dropped packages, and `open3d` by that name), which this script filters.
# An existing .venv keeps what it had; `rm -r .venv` for a slim one.
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
EXTRAS=${MOISST_EXTRAS:-}
stamp() { (cat pyproject.toml scripts/install.sh scripts/nerfstudio-deps.txt; echo "$TORCH_KIND $1") | sha256sum | cut -d' ' -f1; }
WANT=$(stamp "$EXTRAS")
# a venv with the fleet extra serves a plain install too (make demo after make test)
if [ -f "$STAMP" ] && { [ "$(cat "$STAMP")" = "$WANT" ] || { [ -z "$EXTRAS" ] && [ "$(cat "$STAMP")" = "$(stamp fleet)" ]; }; }; then
    echo "[install] .venv up to date"
    exit 0
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
# --no-compile: no .pyc for the ~300 MB of modules never imported (Python writes those it imports, at first use)
PIP=(.venv/bin/pip install -q --disable-pip-version-check --no-compile)
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
# open3d: CPU-only wheels exist for x86_64 Linux only (PyPI's open3d-cpu); both write the module `open3d`, so
# never both in one venv (a venv from before this change has the big one: swap it)
if [ "$(uname -s)-$(uname -m)" = Linux-x86_64 ]; then
    OPEN3D="open3d-cpu>=0.18"
    .venv/bin/pip show -q open3d >/dev/null 2>&1 && .venv/bin/pip uninstall -q -y open3d
else
    OPEN3D="open3d>=0.17"
fi
# pyproject.toml's dependencies, test extra and MOISST_EXTRAS, less nerfstudio and open3d (installed as above and below)
MOISST_EXTRAS="$EXTRAS" .venv/bin/python - > .venv/moisst-requirements.txt <<'EOF'
import os, re, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
extras = ["test"] + [e for e in os.environ["MOISST_EXTRAS"].split(",") if e]
for dep in project["dependencies"] + [d for e in extras for d in project["optional-dependencies"][e]]:
    if re.match(r"(nerfstudio|open3d)\b", dep) is None:
        print(dep)
EOF
echo "[install] moisst-ns + nerfstudio 1.1.5 (--no-deps: scripts/nerfstudio-deps.txt), $OPEN3D"
quiet_pip -c .venv/moisst-constraints.txt -r .venv/moisst-requirements.txt -r scripts/nerfstudio-deps.txt "$OPEN3D"
quiet_pip --no-deps "nerfstudio==1.1.5" "viser==0.2.7" -e .
DROPPED=$(sed -n 's/^#-dropped \([^ ]*\).*/\1/p' scripts/nerfstudio-deps.txt | paste -sd'|')
.venv/bin/pip check 2>/dev/null | grep -Ev "^(nerfstudio 1\.1\.5|viser 0\.2\.7|moisst-ns [^ ]*) requires ($DROPPED|open3d), which is not installed\.$|^No broken requirements" \
    | sed 's/^/[install] pip check: /' || true

rm -f "$SITE/moisst_torchvision_cpu.pth"
if .venv/bin/python -c "import moisst_ns.torchvision_cpu as m, sys; sys.exit(not m.needed())"; then
    echo "import sys; exec('try:\n import moisst_ns.torchvision_cpu as m; m.install()\nexcept ImportError: pass')" > "$SITE/moisst_torchvision_cpu.pth"
    echo "[install] CPU torch beside PyPI's CUDA torchvision: $SITE/moisst_torchvision_cpu.pth (moisst_ns/torchvision_cpu.py)"
fi
.venv/bin/python -W ignore -c "import torchvision, open3d, moisst_ns.method_configs, nerfstudio.scripts.train, nerfstudio.scripts.exporter, nerfstudio.scripts.viewer.run_viewer" >/dev/null
echo "$WANT" > "$STAMP"
echo "[install] done: torch $(.venv/bin/python -c 'from importlib.metadata import version; print(version("torch"))'), $(du -sh .venv | cut -f1) in .venv"
