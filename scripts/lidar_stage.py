"""The LiDAR-first stage alone on a rig with ground truth, with ``LidarFirstConfig`` changes (docs/lidar-first.md, "The
shared view"): prints each LiDAR's error per axis (cm, deg, ms), its weak parameters, formal sigmas, the split-half
sigmas (the shared view's for what it placed; m, rad, s), the trajectory's part (rig.json ``trajectory_accuracy``), the
error in units of the stage's sigma (``lidar_report.stage_sigma``) and wall time.

Usage: .venv/bin/python scripts/lidar_stage.py RIG [FIELD=VALUE ...]
(e.g. ``view_search=False split_half=False points_per_scan=1000``; ``save=PATH`` writes the calibration there.)
"""

from __future__ import annotations

import sys
import time

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, calibrate_lidars
from moisst_ns.stages.lidar.lidar_report import stage_sigma, stage_summary


def main() -> None:
    rig = load_rig(sys.argv[1])
    truth = load_calibration(rig.root / "ground_truth.json")
    changes, save = {}, None
    for arg in sys.argv[2:]:
        key, value = arg.split("=", 1)
        if key == "save":
            save = value
            continue
        changes[key] = type(getattr(LidarFirstConfig, key))(eval(value))
    start = time.time()
    config = LidarFirstConfig(**changes)
    result = calibrate_lidars(rig, config, log=lambda line: print(line, flush=True))
    summary = stage_summary(result, config, result.calibration, None)
    if save:
        result.calibration.write(save)
    for name, lidar in result.lidars.items():
        d = np.array(parameter_difference(result.calibration.T_ref_sensor[name], result.calibration.time_offset[name],
                                          truth.T_ref_sensor[name], truth.time_offset[name]))
        print(f"RESULT {sys.argv[1]} {changes} {name}: error {np.linalg.norm(d[:3]) * 100:.2f} cm "
              f"{np.rad2deg(np.linalg.norm(d[3:6])):.3f} deg {abs(d[6]) * 1000:.2f} ms; undetermined {lidar.undetermined()}; per axis cm {np.round(d[:3] * 100, 2)} "
              f"deg {np.round(np.rad2deg(d[3:6]), 3)}; weak {lidar.observability.weak}; "
              f"sigma {[f'{x.sigma:.3g}' for x in lidar.observability.dofs]}; split-half / placed sigma "
              f"{None if lidar.sigma_split is None else [f'{x:.3g}' for x in lidar.sigma_split]}; trajectory sigma "
              f"{None if lidar.sigma_trajectory is None else [f'{x:.3g}' for x in lidar.sigma_trajectory]}; wall {time.time() - start:.0f} s")
        entry = summary["sensors"][name]
        for what, sigma_of in (("", entry), (" without the trajectory's part", {k: v for k, v in entry.items() if k != "sigma_trajectory"})):
            sigma, source = stage_sigma(sigma_of)
            print(f"SIGMA {name}{what} ({source}): error / sigma " + ", ".join(f"{p} {abs(e) / s:.2f}" for p, e, s in zip(PARAMETERS, d, sigma)))


if __name__ == "__main__":
    main()
