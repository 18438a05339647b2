"""The same-instant placement of a synthetic rig's LiDAR (``lidar_instant.place_lidar``) from a fixed start, for the
lab entry docs/lab/2026-12-07-trajectory-smoother-and-movers.md: the cameras at the truth, the LiDAR at the truth plus
the realistic street seed 2 LiDAR stage's errors (x -12.41, y 0.62, z -7.5 cm; 0.077, 0.105, -0.007 deg; time offset
+10.77 ms), its pairs' shifts free; once with that time offset error, once at the true time offset. Prints the
placement's line (rows, movers left out, sigma, placed) and its error per axis.

Usage: .venv/bin/python scripts/lab/instant_movers_check.py RIG   (RIG from moisst-synth with a LiDAR)
"""

import sys

import numpy as np
from scipy.spatial.transform import Rotation

from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar.lidar_instant import place_lidar
from moisst_ns.stages.lidar.lidar_placement import _scans

rig = load_rig(sys.argv[1])
truth = load_calibration(rig.root / "ground_truth.json")
start = Calibration(truth.reference_sensor, {k: np.array(v) for k, v in truth.T_ref_sensor.items()}, dict(truth.time_offset))
T = start.T_ref_sensor["lidar"].copy()
T[:3, 3] += [-0.1241, 0.0062, -0.075]
T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(np.deg2rad([0.077, 0.105, -0.007])).as_matrix()
start.T_ref_sensor["lidar"] = T
scans = _scans(rig, "lidar", {}, lambda line: None)
for label, offset in (("time offset +10.77 ms", 0.01077), ("time offset at the truth", 0.0)):
    start.time_offset["lidar"] = truth.time_offset["lidar"] + offset
    found = place_lidar(rig, start, "lidar", scans, ["cam_front_right"], log=print)
    error = np.asarray(parameter_difference(np.asarray(truth.T_ref_sensor["lidar"], dtype=float), 0.0, found.estimate.matrix(), 0.0), dtype=float)
    print(f"{label}: error x, y, z {np.round(error[:3] * 100, 2)} cm; roll, pitch, yaw {np.round(np.rad2deg(error[3:6]), 3)} deg")
