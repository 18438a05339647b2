"""The mean of the last five logged training PSNRs (tensorboard events) of runs: OUT ... (each OUT/<method>/run,
``moisst-calibrate``'s and ``stock_nerfacto.py``'s layout).

Usage: .venv/bin/python scripts/lab/train_psnr.py OUT [OUT ...]
"""
import sys, glob
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
for run in sys.argv[1:]:
    f = sorted(glob.glob(f"{run}/*/run/events.out.tfevents.*"))
    ea = EventAccumulator(f[-1], size_guidance={"scalars": 0}); ea.Reload()
    tags = [t for t in ea.Tags()["scalars"] if "psnr" in t.lower()]
    out = {t: round(sum(e.value for e in ea.Scalars(t)[-5:]) / len(ea.Scalars(t)[-5:]), 2) for t in tags}
    print(run, out)
