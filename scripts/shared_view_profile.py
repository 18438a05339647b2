"""The shared-view cost (``stages/lidar_view.py``: LiDAR depth edges against the reference camera's image edges) along
each parameter of one LiDAR, at the ground truth and at the prior (docs/lidar-first.md, "The shared view"): mean Huber
cost (2 px) of the edge distances with one parameter stepped, the rows drawn at the point profiled.

Usage: .venv/bin/python scripts/shared_view_profile.py RIG
"""

from __future__ import annotations

import sys

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.stages.lidar_first import LidarFirstConfig, consistency_residuals, find_correspondences, load_scans, scan_pairs
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory
from moisst_ns.stages.lidar_view import SharedView, view_residuals
from moisst_ns.stages.photometric import huber_costs

STEPS = {"x (m)": (3, [-0.5, -0.2, -0.05, 0, 0.05, 0.2, 0.5]), "y (m)": (4, [-0.5, -0.2, -0.05, 0, 0.05, 0.2, 0.5]),
         "z (m)": (5, [-1, -0.3, -0.1, 0, 0.1, 0.3, 1]), "roll (deg)": (0, [-5, -2, -0.5, 0, 0.5, 2, 5]),
         "delta (s)": (6, [-0.05, -0.02, 0, 0.02, 0.05])}


def main() -> None:
    rig = load_rig(sys.argv[1])
    truth = load_calibration(rig.root / "ground_truth.json")
    name = next(n for n, s in rig.sensors.items() if s.type == "lidar")
    traj, config = Trajectory.from_rig(rig), LidarFirstConfig()
    scans = load_scans(rig, name, traj, config, lambda line: None)
    shared = SharedView.of(rig, traj, scans)
    prior_T = rig.sensors[name].T_ref_sensor
    for where, T, delta in (("truth", np.asarray(truth.T_ref_sensor[name]), float(truth.time_offset[name])),
                            ("prior", prior_T, rig.sensors[name].time_offset)):
        ext = Extrinsic(T[:3, :3], T[:3, 3], delta)
        pairs, _ = scan_pairs(traj, scans, delta, config)
        plane = consistency_residuals(traj, ext, scans, find_correspondences(traj, ext, scans, pairs, config.radius_end, config), np.zeros(7))[0]
        at = shared.at(traj, ext, scans, pairs, plane)
        print(f"{where}: {len(at.rows.point)} depth-edge rows")
        for label, (column, steps) in STEPS.items():
            costs = []
            for step in steps:
                increment = np.zeros(7)
                increment[column] = np.deg2rad(step) if "deg" in label else step
                costs.append(float(np.mean(huber_costs(view_residuals(traj, ext, scans, at.view, at.rows, increment)[0], 2.0))))
            print(f"  {label:11s}" + " ".join(f"{s:+g}:{c:.2f}" for s, c in zip(steps, costs)))


if __name__ == "__main__":
    main()
