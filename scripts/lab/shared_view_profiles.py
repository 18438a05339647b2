"""One-parameter profiles of the shared view's edge cost at the true LiDAR calibration: the mean Huber (2 px) edge
distance and the median edge distance of the depth-edge rows seen at the truth, with one parameter moved at a time
(along-track / vertical lever arm of the reference frame, the time offset, the roll). Which statistic has its
minimum at the truth? (docs/lab/2026-11-25-kitti-shared-view.md, 2026-11-26 entry.)

Usage: .venv/bin/python scripts/lab/shared_view_profiles.py RIG LIDAR
"""

from __future__ import annotations

import sys

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.stages.lidar_first import LidarFirstConfig, consistency_residuals, find_correspondences, load_scans, scan_pairs
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory
from moisst_ns.stages.lidar_view import SharedView, view_residuals
from moisst_ns.stages.photometric import huber_costs

PROFILES = ((5, (-1.0, -0.5, -0.2, 0.0, 0.2, 0.5, 1.0, 1.5), "reference z (m)"), (6, (-0.1, -0.05, 0.0, 0.05, 0.1), "time offset (s)"),
            (4, (-0.2, -0.1, 0.0, 0.1, 0.2), "reference y (m)"), (0, tuple(np.deg2rad([-2.0, -1.0, 0.0, 1.0, 2.0])), "roll (rad)"))
"""(Jacobian column, increments, name): on KITTI's and moisst-synth's reference camera, z is forward, y down."""


def main() -> None:
    rig, lidar = load_rig(sys.argv[1]), sys.argv[2]
    truth = load_calibration(rig.root / "ground_truth.json")
    T = np.asarray(truth.T_ref_sensor[lidar], dtype=np.float64)
    gt = Extrinsic(T[:3, :3].copy(), T[:3, 3].copy(), float(truth.time_offset[lidar]))
    traj, config = Trajectory.from_rig(rig), LidarFirstConfig()
    scans = load_scans(rig, lidar, traj, config, lambda line: None)
    pairs, _ = scan_pairs(traj, scans, gt.time_offset, config)
    plane = consistency_residuals(traj, gt, scans, find_correspondences(traj, gt, scans, pairs, config.radius_end, config), np.zeros(7))[0]
    shared = SharedView.of(rig, traj, scans).at(traj, gt, scans, pairs, plane)
    print(f"{len(shared.rows.point)} depth-edge rows seen at the truth; per increment: mean Huber cost / median distance (px)")
    for column, values, name in PROFILES:
        cells = []
        for value in values:
            increment = np.zeros(7)
            increment[column] = value
            d = view_residuals(traj, gt, scans, shared.view, shared.rows, increment)[0]
            cells.append(f"{value:+.3f}: {np.mean(huber_costs(d, 2.0)):.2f} / {np.median(d):.2f}")
        print(f"{name}: " + " | ".join(cells))


if __name__ == "__main__":
    main()
