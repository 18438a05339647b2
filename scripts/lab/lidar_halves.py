"""The LiDAR-first stage on a rig with ground truth, each split-half fit recorded: the error and sigma per parameter,
half the halves' difference (the stage's split-half part) and each half's distance from the whole drive's estimate
(docs/lab/2026-11-29-movers.md, "The split-half sigma, evening").

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/lidar_halves.py RIG
"""

import sys
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.lidar import lidar_first
from moisst_ns.stages.lidar.lidar_report import stage_sigma, stage_summary
from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig
from moisst_ns.stages.trust.observability import UNITS


def main() -> None:
    rig_dir = Path(sys.argv[1])
    rig, truth = load_rig(rig_dir), load_calibration(rig_dir / "ground_truth.json")
    seen, measure = [], lidar_first.split_half_spread

    def recorded(fit, pairs, baselines, num_scans):  # the stage's own half fits, kept as they are made
        halves = []

        def kept(p, b):
            halves.append(fit(p, b))
            return halves[-1]

        spread = measure(kept, pairs, baselines, num_scans)
        seen.append((fit.__defaults__[0], halves))
        return spread

    lidar_first.split_half_spread = recorded
    result = lidar_first.calibrate_lidars(rig, LidarFirstConfig(), log=lambda s: None)
    line = lambda values: " ".join(f"{p} {v * u:+.2f}" for p, v, (u, _) in zip(PARAMETERS, values, UNITS))
    for name, r in result.lidars.items():
        sigma, source = stage_sigma(stage_summary(result, LidarFirstConfig(), result.calibration, None)["sensors"][name])
        print(name, "error", line(parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], r.estimate.matrix(), r.estimate.time_offset)))
        print(name, "sigma", line(sigma), f"({source})")
        print(name, "half the difference", line(r.sigma_split or [np.nan] * 7))
        for whole, halves in seen:
            if len(halves) < 2 or any(h is None for h in halves):
                print("  a half was not fitted")
                continue
            apart = [np.asarray(parameter_difference(whole.matrix(), whole.time_offset, h.matrix(), h.time_offset)) for h in halves]
            print("  each half from the whole:", " ".join(f"{p} {a * u:+.2f}/{b * u:+.2f}" for p, a, b, (u, _) in zip(PARAMETERS, *apart, UNITS)))


if __name__ == "__main__":
    main()
