"""tests/test_rolling_shutter.py's ``stage`` (the forward-right camera from the paper perturbation, the LiDAR at the
truth) on its 96x72 rolling-shutter rig, camera-stage sampling seeds 0-3, with rig.json's 30 ms readout and with every
readout forced to 0; prints each run's errors (cm / deg / ms).

Usage (from the tree to measure; the rig is made once in RIG_DIR):
    PYTHONPATH=. .venv/bin/python scripts/lab/pyrdown_rolling_seeds.py RIG_DIR [--long]
``--long``: rig.json's readout only, seeds 0-2, each also with 20 finest iterations, a 0.002 px stop and 40
evaluations (does the finest level stop where it would stop anyway?).
(docs/lab/2026-12-07-sift-keypoint-bias.md: the same with docs/lab/2026-12-07-pyrdown-centres.patch applied.)
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path.cwd() / "tests"))
from moisst_ns.datasets.synth import SynthConfig, make_rig  # noqa: E402
from test_rolling_shutter import READOUT, stage  # noqa: E402

folder = Path(sys.argv[1])
if not (folder / "rig.json").exists():
    make_rig(SynthConfig(out=folder, seed=0, frames=12, width=96, height=72, rolling_shutter=READOUT))
LONG = {"fine_iterations": 20, "fine_stop_px": 0.002, "max_evaluations": 40}
runs = [(s, None, kw) for s in range(3) for kw in ({}, LONG)] if "--long" in sys.argv else [(s, r, {}) for s in range(4) for r in (None, 0.0)]
for seed, readout, settings in runs:
    _, e = stage(folder, readout=readout, seed=seed, **settings)
    print(f"seed {seed} readout {'rig' if readout is None else 0}{' long' if settings else ''}: {e['translation_cm']:.2f} cm "
          f"{e['rotation_deg']:.3f} deg {e['time_ms']:.2f} ms", flush=True)
