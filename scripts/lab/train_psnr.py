"""The mean of the last five logged training PSNRs (tensorboard events) of moisst-calibrate runs: OUT ... (each OUT/moisst-lite/run).

Usage: .venv/bin/python scripts/lab/train_psnr.py OUT [OUT ...]
"""
import sys, glob
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
for run in sys.argv[1:]:
    f = glob.glob(f"{run}/moisst-lite/run/events.out.tfevents.*")
    ea = EventAccumulator(f[0], size_guidance={"scalars": 0}); ea.Reload()
    tags = [t for t in ea.Tags()["scalars"] if "psnr" in t.lower()]
    out = {t: round(sum(e.value for e in ea.Scalars(t)[-5:]) / len(ea.Scalars(t)[-5:]), 2) for t in tags}
    print(run, out)
