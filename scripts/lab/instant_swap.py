"""The LiDAR placed at the same instants (``lidar_instant.place_lidar``) with the stereo cameras taken from a run's
estimate component by component, the rest at the ground truth: which of the cameras' errors moves the LiDAR.

Usage: .venv/bin/python scripts/lab/instant_swap.py RIG CAMERAS.json LIDAR.json SPEC [SPEC ...]

With LIDAR.json's ``lidar_first.json`` beside it, ``place_lidars`` also runs on the full estimate (what the camera stage
takes, given that stage's undetermined parameters and sigma).

CAMERAS.json: a calibration whose image_01 / image_03 are taken (``camera_registration/calibration.json`` of a run);
its ``camera_registration.json`` beside it gives the cameras' sigma (the shifts' prior) when present. LIDAR.json: the
Velodyne's start (``lidar_first/calibration.json``). SPEC: which of the cameras' components come from CAMERAS.json,
any of ``x y z r d`` (r: rotation, d: time offset; ``none``: every component at the truth). KITTI raw rigs.
"""
import json
import sys
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.lidar.lidar_instant import place_lidar
from moisst_ns.stages.lidar.lidar_placement import place_lidars
from moisst_ns.stages.lidar.lidar_report import stage_sigma
from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig, load_scans
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER

CAMERAS = ("image_01", "image_03")
rig = load_rig(sys.argv[1])
truth = load_calibration(rig.root / "ground_truth.json")
est, lidar = load_calibration(sys.argv[2]), load_calibration(sys.argv[3])
record = Path(sys.argv[2]).parent / "camera_registration.json"
sigma = ({c: [v["sigma"][j] if v["sigma"][j] is not None else float("inf") for j in JACOBIAN_ORDER]
          for c, v in json.loads(record.read_text())["sensors"].items()} if record.is_file() else None)
traj = ReferenceTrajectory.of(rig)
scans = load_scans(rig, "velodyne", traj, LidarFirstConfig(), log=lambda line: None)
for spec in sys.argv[4:]:
    cal = Calibration(truth.reference_sensor, dict(truth.T_ref_sensor), dict(truth.time_offset))
    for c in CAMERAS:
        T, Te = np.array(truth.T_ref_sensor[c], dtype=np.float64), np.asarray(est.T_ref_sensor[c], dtype=np.float64)
        for i, axis in enumerate("xyz"):
            T[i, 3] = Te[i, 3] if axis in spec else T[i, 3]
        T[:3, :3] = Te[:3, :3] if "r" in spec else T[:3, :3]
        cal.T_ref_sensor[c], cal.time_offset[c] = T, est.time_offset[c] if "d" in spec else truth.time_offset[c]
    cal.T_ref_sensor["velodyne"], cal.time_offset["velodyne"] = lidar.T_ref_sensor["velodyne"], lidar.time_offset["velodyne"]
    placed = place_lidar(rig, cal, "velodyne", scans, list(CAMERAS), log=print, camera_sigma=sigma)
    error = parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, placed.estimate.matrix(), 0.0)
    print(f"{spec}: velodyne " + ", ".join(f"{p} {v * (100 if i < 3 else np.rad2deg(1.0)):+.2f}" for i, (p, v) in enumerate(zip(PARAMETERS[:6], error)))
          + f" (cm, deg); shifts {np.round(100 * np.asarray(placed.shifts), 2).tolist()} cm", flush=True)
first = Path(sys.argv[3]).parent / "lidar_first.json"
if first.is_file():
    entry = json.loads(first.read_text())["sensors"]["velodyne"]
    unknown = entry.get("motion_undetermined", entry["undetermined"])
    cal = Calibration(est.reference_sensor, dict(est.T_ref_sensor), dict(est.time_offset))
    cal.T_ref_sensor["velodyne"], cal.time_offset["velodyne"] = lidar.T_ref_sensor["velodyne"], lidar.time_offset["velodyne"]
    out = place_lidars(rig, cal, list(CAMERAS), {"velodyne": unknown}, {"velodyne": stage_sigma(entry)[0]}, log=print, camera_sigma=sigma)
    error = parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, np.asarray(cal.T_ref_sensor["velodyne"]), 0.0)
    print("place_lidars: velodyne " + ", ".join(f"{p} {v * (100 if i < 3 else np.rad2deg(1.0)):+.2f}" for i, (p, v) in enumerate(zip(PARAMETERS[:6], error)))
          + f" (cm, deg); taken {out['velodyne'].taken}; turn {np.round(np.rad2deg(out['velodyne'].turn), 3).tolist()} deg")
