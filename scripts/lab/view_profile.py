"""The shared view's two costs (the mean Huber edge distance and the median, ``lidar_view``) profiled along each
rotation and lever-arm column at a rig's true LiDAR calibration: is each least at the truth? (docs/lab/2026-12-01-edge-silhouettes.md)

Usage: .venv/bin/python scripts/lab/view_profile.py RIG   (a rig with ``ground_truth.json`` and one LiDAR named ``lidar``)
Prints one line per column: the costs at the truth moved by -4..4 steps (0.5 deg, 5 cm), rows drawn at the truth.
"""

from __future__ import annotations

import sys

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.photometric import huber_costs
from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, load_scans, scan_pairs
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic
from moisst_ns.stages.lidar.lidar_view import HUBER_PX, SharedView, view_residuals


def main() -> None:
    rig = load_rig(sys.argv[1])
    truth = load_calibration(rig.root / "ground_truth.json")
    config, T = LidarFirstConfig(), truth.T_ref_sensor["lidar"]
    ext = Extrinsic(T[:3, :3].copy(), T[:3, 3].copy(), float(truth.time_offset["lidar"]))
    traj = ReferenceTrajectory.of(rig)
    scans = load_scans(rig, "lidar", traj, config, lambda line: None)
    pairs, _ = scan_pairs(traj, scans, ext.time_offset, config)
    shared = SharedView.of(rig, traj, scans).at(traj, ext, scans, pairs)
    print("rows", len(shared.rows.point), "frames", len(np.unique(shared.rows.frame)))
    for c, name in enumerate(["rot x", "rot y", "rot z", "x", "y", "z"]):
        mean, median = [], []
        for offset in np.arange(-4, 5) * (np.deg2rad(0.5) if c < 3 else 0.05):
            increment = np.zeros(7)
            increment[c] = offset
            d = view_residuals(traj, ext, scans, shared.view, shared.rows, increment)
            mean.append(huber_costs(d, HUBER_PX).mean()), median.append(np.median(d))
        print(name, "mean", " ".join(f"{v:.3f}" for v in mean), "| median", " ".join(f"{v:.2f}" for v in median))


if __name__ == "__main__":
    main()
