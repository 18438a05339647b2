#!/usr/bin/env bash
# Build .whl/site-py312.tar.xz: the Python 3.12 / x86-64 packages that `ns-train moisst` needs beyond what the GPU
# machine's image has (torch, torchvision, numpy 2, scipy, matplotlib, opencv, pillow, scikit-image, imageio,
# jaxtyping, rich, tqdm, pyyaml, psutil, requests, tensorboard, torchmetrics, ...), pruned and xz-compressed so that
# the travelling tree stays under ~60 MiB (the wheels as downloaded are ~140 MB, open3d-cpu alone 105 MB).
# scripts/device/gpu_measure.sh unpacks it to /tmp/site. moisst_ns itself is not in it: PYTHONPATH=repo root, and
# the method / dataparser are registered by NERFSTUDIO_METHOD_CONFIGS / NERFSTUDIO_DATAPARSER_CONFIGS.
#
# Kept = the third-party top-level packages imported (sys.modules, every process) by moisst-synth,
# `ns-train moisst-lite/moisst --help` and a short `ns-train moisst-lite` run, under Python 3.12 + torch 2.11 CPU.
# Pruned (never imported on those paths): plotly/dash (open3d's draw_plotly: its import is made optional below),
# pydantic, mediapy, trimesh, plyfile, nodeenv, pyliblzfse (no cp312 wheel), xatlas, pymeshlab, ray, rosbags;
# open3d's GUI resources, TF/torch ops, examples and ML code; gsplat's CUDA sources (splatfacto only);
# viser's web client (viewer only); tensorly's datasets.
#
# Usage: scripts/device/build_bundle.sh   (needs python3 with pip, network for the first download)
set -euo pipefail
cd "$(dirname "$0")/../.."

WHEELS=${WHEELS_DIR:-/tmp/moisst-wheels}
STAGE=${STAGE_DIR:-/tmp/moisst-site-stage}
OUT=.whl/site-py312.tar.xz
PINS=(
    nerfstudio==1.1.5 tyro==1.0.17 docstring_parser==0.18.0 typeguard==4.6.1 roma==1.8.0 nerfacc==0.5.2
    gsplat==1.4.0 viser==0.2.7 websockets==17.4 msgspec==0.22.0 splines==0.3.0 appdirs==1.4.4 pathos==0.3.5
    dill==0.4.1 multiprocess==0.70.19 ppft==1.7.8 pox==0.3.7 pyquaternion==0.9.9 rawpy==0.28.0 fpsample==0.3.3
    tensorly==0.10.0 pytorch-msssim==1.0.0 torch_fidelity==0.4.0 open3d-cpu==0.20.0
)
TAGS=(--only-binary=:all: --python-version 3.12 --implementation cp --abi cp312
      --platform manylinux_2_35_x86_64 --platform manylinux_2_34_x86_64 --platform manylinux_2_31_x86_64
      --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64
      --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64)

mkdir -p "$WHEELS" .whl
PIP_CONSTRAINT="" python3 -m pip download -q --no-deps "${TAGS[@]}" -d "$WHEELS" "${PINS[@]}" 2>&1 | { grep -v "WARNING: Location" || true; }

rm -rf "$STAGE" && mkdir -p "$STAGE"
PIP_CONSTRAINT="" python3 -m pip install -q --no-index --no-deps --no-compile "${TAGS[@]}" --target "$STAGE" \
    --find-links "$WHEELS" "${PINS[@]}" 2>&1 | { grep -v "WARNING: Location" || true; }

cd "$STAGE"
rm -rf bin share etc
rm -rf open3d/resources open3d/open3d_tf_ops.so open3d/open3d_torch_ops.so open3d/examples open3d/_ml3d \
       open3d/labextension open3d/nbextension open3d/agent_skills open3d/ml/tf open3d/ml/torch open3d/ml/contrib/*.pyi
rm -rf gsplat/cuda/csrc viser/client tensorly/datasets/data
find . -name tests -type d -prune -exec rm -rf {} +
find . -name '*.pyi' -delete
# open3d/visualization imports draw_plotly (dash + plotly, ~60 MB) unconditionally; we never draw with plotly
python3 - <<'EOF'
p = "open3d/visualization/__init__.py"
s = open(p).read()
old = ("from .draw_plotly import get_plotly_fig\nfrom .draw_plotly import draw_plotly\n"
       "from .draw_plotly import draw_plotly_server\n")
assert old in s, "open3d/visualization/__init__.py changed: update build_bundle.sh"
new = "try:  # moisst device bundle: dash/plotly left out\n" + "".join("    " + l + "\n" for l in old.splitlines()) \
      + "except ImportError:\n    pass\n"
open(p, "w").write(s.replace(old, new))
EOF
ls -d *.dist-info | sed 's/\.dist-info$//' > MOISST_BUNDLE.txt
cd - >/dev/null
tar -C "$STAGE" -cf - . | xz -9e -T2 > "$OUT.tmp" && mv "$OUT.tmp" "$OUT"
echo "$OUT: $(du -m "$OUT" | cut -f1) MiB ($(du -sm "$STAGE" | cut -f1) MiB unpacked), $(wc -l < "$STAGE/MOISST_BUNDLE.txt") packages"
