"""Stock nerfacto (``moisst_ns.bench.baseline``: the preset's field, sampling and camera rays, no pose optimiser)
trained on a rig at its rig.json poses, for the training-PSNR comparison of issue 36 (docs/lab/2026-11-23-metric-scene.md,
"2026-11-27 (evening)"). Give it the rig written with ``--perturb none`` (rig.json = the truth): the same images.

Usage: .venv/bin/python scripts/lab/stock_nerfacto.py RIG OUT STEPS; then scripts/lab/train_psnr.py OUT
"""
import sys
from pathlib import Path

import torch

from moisst_ns.bench.baseline import run_nerfacto

torch.set_num_threads(2)
result = run_nerfacto(Path(sys.argv[1]), Path(sys.argv[2]), "moisst-lite", int(sys.argv[3]), "off")
print(f"{result.seconds_per_step:.3f} s/step")
