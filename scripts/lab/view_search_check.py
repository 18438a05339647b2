"""The LiDAR stage's shared-view search (``lidar_view.search_held``) alone, from a given start, on given columns:
what it places and where that leaves the LiDAR against the ground truth (docs/lab/2026-11-25-kitti-shared-view.md).

Usage: .venv/bin/python scripts/lab/view_search_check.py RIG LIDAR START COLUMNS
  START: ``truth+c:v,c:v`` (the truth moved by increments v on Jacobian columns c: 0-2 rotation vector, rad; 3-5 lever
         arm, m; 6 time offset, s) or an .npz with rotation, translation, time_offset (a saved stage estimate)
  COLUMNS: comma-separated Jacobian columns to search (e.g. 0,4,5)
"""
import sys
import time
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, load_scans, scan_pairs
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic
from moisst_ns.stages.lidar.lidar_view import SharedView, search_held
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, TEST_STEPS

root, lidar, start, columns = sys.argv[1], sys.argv[2], sys.argv[3], [int(c) for c in sys.argv[4].split(",")]
rig, truth = load_rig(root), load_calibration(Path(root) / "ground_truth.json")
T = np.asarray(truth.T_ref_sensor[lidar])
gt = Extrinsic(T[:3, :3].copy(), T[:3, 3].copy(), float(truth.time_offset[lidar]))
if start.endswith(".npz"):
    d = np.load(start)
    ext = Extrinsic(d["rotation"], d["translation"], float(d["time_offset"]))
else:
    inc = np.zeros(7)
    for item in filter(None, start.removeprefix("truth").lstrip("+").split(",")):
        c, v = item.split(":")
        inc[int(c)] = float(v)
    ext = gt.updated(inc)
traj, config = ReferenceTrajectory.of(rig), LidarFirstConfig()
scans = load_scans(rig, lidar, traj, config, log=lambda _: None)
pairs, _ = scan_pairs(traj, scans, ext.time_offset, config)
shared = SharedView.of(rig, traj, scans).at(traj, ext, scans, pairs)
began = time.time()
found = search_held(traj, ext, scans, shared, pairs, columns, config.hold_split_half, np.array(TEST_STEPS)[np.argsort(JACOBIAN_ORDER)])
after = ext.updated(found.increment)
show = lambda e: (lambda d: f"cm {np.round(np.array(d[:3]) * 100, 1)} deg {np.round(np.rad2deg(d[3:6]), 2)}")(
    parameter_difference(e.matrix(), e.time_offset, gt.matrix(), gt.time_offset))
print(f"{len(shared.rows.point)} rows; placed {found.accepted} of {columns} (sigma {[round(float(found.sigma[c]), 4) for c in found.accepted]}); notes {found.notes}")
print(f"before {show(ext)} -> after {show(after)}; {found.evaluations} evaluations, {time.time() - began:.0f} s")
