"""The trajectory part of the LiDAR stage's sigma (``trajectory_noise.trajectory_spread``, as ``lidar_first`` imports it) with each draw's fit converged (the
stage's rule), or cut after 2 or 1 outer iterations: how much cheaper, and how much smaller (docs/uncertainty.md, "The
trajectory's own errors"). The stage runs once with the part off; the spread is then computed three ways from its
estimate.

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/trajectory_draw_iterations.py RIG   (a rig whose rig.json states
``trajectory_accuracy``, e.g. ``moisst-synth R --realistic``)
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np

import moisst_ns.stages.lidar.lidar_first as lidar_first
from moisst_ns.rig.format import load_rig


def main() -> None:
    rig = load_rig(sys.argv[1])
    spread, fit, caught = lidar_first.trajectory_spread, lidar_first._fit, {}

    def catch(refit, rig_, estimates, draws):  # the stage's own refit closure and estimate, no draws yet
        caught.update(refit=refit, estimates=estimates)
        return {name: np.zeros(7) for name in estimates}

    lidar_first.trajectory_spread = catch
    lidar_first.calibrate_lidar(rig, "lidar", lidar_first.LidarFirstConfig(), log=lambda line: None)
    lidar_first.trajectory_spread = spread
    for outer in (None, 2, 1):
        lidar_first._fit = fit if outer is None else (lambda *a, n=outer: fit(*a[:7], replace(a[7], max_outer=n), *a[8:]))
        begun = time.time()
        s = spread(caught["refit"], rig, caught["estimates"], lidar_first.LidarFirstConfig().trajectory_draws)["lidar"]
        print(f"outer iterations {'converged' if outer is None else outer}: {time.time() - begun:.0f} s, cm {np.round(100 * s[:3], 2)}, "
              f"deg {np.round(np.rad2deg(s[3:6]), 3)}, ms {1000 * s[6]:.2f}", flush=True)
    lidar_first._fit = fit


if __name__ == "__main__":
    main()
