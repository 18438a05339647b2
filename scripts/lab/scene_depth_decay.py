"""``scene_from_cached_stages.py`` with the depth terms' weight (LiDAR depth and the map's range) decayed over the second
half of the run to FINAL of its value (lab experiment, docs/lab/2026-11-23-metric-scene.md, 2026-11-27 evening): does
the metric scene keep its geometry and win back training PSNR?

Usage: DEPTH_FINAL=0.1 .venv/bin/python scripts/lab/scene_depth_decay.py STAGES_OUT DATASET --output-dir OUT [options]
"""
import os
import runpy
import sys
from pathlib import Path

from moisst_ns.model import MoisstModel

FINAL = float(os.environ.get("DEPTH_FINAL", "0.1"))
ramp = MoisstModel._depth_ramp


def decayed(self) -> float:
    steps = max(self.config.schedule_steps, 1)
    late = min(max((self._step - 0.5 * steps) / (0.5 * steps), 0.0), 1.0)
    return ramp(self) * (1.0 - (1.0 - FINAL) * late)


MoisstModel._depth_ramp = decayed
sys.argv[0] = str(Path(__file__).with_name("scene_from_cached_stages.py"))
runpy.run_path(sys.argv[0], run_name="__main__")
