"""Own-pair photometric cost of one camera around its true calibration, for several own-partner baselines.

Everything at the ground truth (LiDAR map from the true extrinsics); each of along-track z, the time offset and x is
scanned alone over +-6 cm / +-6 ms and a parabola fitted: where its minimum sits and how sharp it is says how well
two frames that far apart pin that correction (docs/method.md, "Farther own partners at the finest level").

Usage: .venv/bin/python scripts/own_pair_profile.py RIG CAMERA 1.5,3,5,8
"""

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.camera.lidar_map import lidar_map
from moisst_ns.stages.camera.photometric import Registration, robust_cost

SCANS = ((5, "z", "cm", 100.0, 0.06), (6, "time_offset", "ms", 1000.0, 0.006), (3, "x", "cm", 100.0, 0.06))
"""(solver index, name, unit, unit per SI unit, half range in SI units)."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rig", type=Path)
    parser.add_argument("camera")
    parser.add_argument("baselines", help="comma-separated own-partner baselines, metres")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rig, truth = load_rig(args.rig), load_calibration(args.rig / "ground_truth.json")
    base = CameraRegistrationConfig(fine_baseline=0.0)
    world = lidar_map(rig, truth, base.map_voxel, base.min_range, lambda s: None)
    traj = ReferenceTrajectory.of(rig)
    reference, camera = CameraFrames.of(rig, rig.reference_sensor, [1]), CameraFrames.of(rig, args.camera, [1])
    for baseline in (float(b) for b in args.baselines.split(",")):
        config = dataclasses.replace(base, own_baseline=baseline)
        problem = Registration(traj, world, camera, reference, truth, config)
        pairs = problem.pairs(np.zeros(7), 1, 1000)
        parts = []
        for index, name, unit, per_si, half in SCANS:
            steps = np.linspace(-half, half, 7)
            costs = []
            for value in steps:
                theta = np.zeros(7)
                theta[index] = value
                res, _, ok = problem.residuals(theta, pairs, 1, jacobian=False)
                costs.append(robust_cost(res[ok & pairs.own], config.huber))
            a, b, _ = np.polyfit(steps, costs, 2)
            parts.append(f"{name}: minimum {-b / (2 * a) * per_si:+.2f} {unit}, curvature {a:.3g}")
        print(f"own partners >= {baseline:g} m: {int(pairs.own.sum())} own pairs; " + "; ".join(parts), flush=True)


if __name__ == "__main__":
    main()
