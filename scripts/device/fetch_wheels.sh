#!/usr/bin/env bash
# Download into .whl/ (git-ignored: `echo /.whl/ >> .git/info/exclude`) the Python 3.12 / x86-64 wheels that
# `ns-train moisst` needs beyond the GPU machine's image (torch, numpy 2, scipy, opencv, matplotlib, scikit-image,
# tensorboard, torchmetrics, ... are there): 21 wheels, 23 MB. The list is the third-party top-level modules an
# `ns-train moisst --pipeline.stages-from` run imports (sys.modules at exit, every process), less the image's.
# open3d is not among them: its wheel (105 MB) cannot travel (a call carries 64 MiB); scripts/device/open3d_standin
# stands in for the one call that run makes. scripts/device/gpu_measure.sh installs them into /tmp/site.
set -euo pipefail
cd "$(dirname "$0")/../.."
mkdir -p .whl
PY=${PYTHON:-.venv/bin/python}
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \
    nerfstudio==1.1.5 viser==0.2.7 tyro==1.0.17 docstring_parser==0.18.0 typeguard==4.6.1 roma==1.8.0 nerfacc==0.5.2 \
    gsplat==1.4.0 splines==0.3.0 appdirs==1.4.4 pathos==0.3.5 dill==0.4.1 multiprocess==0.70.19 ppft==1.7.8 \
    pyquaternion==0.9.9 rawpy==0.28.0 fpsample==0.3.3 tensorly==0.10.0 pytorch-msssim==1.0.0 websockets==17.4 msgspec==0.22.0
ls .whl | wc -l; du -sh .whl
