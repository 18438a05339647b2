"""Stock nerfacto (moisst_ns.bench.baseline: the preset's field, rays and steps, no pose optimiser) trained on a rig posed
with a calibration.json, for the training PSNR the scene target of issue 36 compares with (docs/lab/2026-11-23-metric-scene.md).

Usage: .venv/bin/python scripts/lab/stock_nerfacto_psnr.py RIG CALIBRATION OUT STEPS
then:  .venv/bin/python scripts/lab/train_psnr.py OUT   (the mean of the last five logged training PSNRs)
"""
import sys
from pathlib import Path

import torch

from moisst_ns.bench.baseline import nerfacto_trainer_config
from moisst_ns.stage_run import seed_everything

rig, calibration, out, steps = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4])
torch.set_num_threads(2)
config = nerfacto_trainer_config("moisst-lite", steps, "off")
config.pipeline.datamanager.data = rig
config.pipeline.datamanager.dataparser.data = rig
config.pipeline.datamanager.dataparser.prior_calibration = calibration
config.output_dir, config.experiment_name, config.timestamp, config.machine.seed = out, ".", "run", 42
config.method_name = "moisst-lite"  # train_psnr.py reads OUT/moisst-lite/run
seed_everything(42)
trainer = config.setup(local_rank=0, world_size=1)
trainer.setup()
trainer.train()
