"""The feature start of every non-reference camera of a rig, its PnP scored by plain RANSAC and by MAGSAC++ (the
stage's since d181b28): the start's distance from the truth, its RMS and matches (docs/method.md, "Two starts").
With TURN (deg, a rotation vector: e.g. 0.57,-0.058,-0.005, the turn KITTI raw 0048's run finds) the trajectory is
carried by it and the map is the reference camera's features; without, the LiDAR at the truth makes the map (the
features where the rig has none).

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/feature_start_ransac.py RIG [TURN]
"""
import sys
from pathlib import Path
import numpy as np, cv2
from scipy.spatial.transform import Rotation
import moisst_ns.stages.camera.feature_start as fs
from moisst_ns.rig.format import load_calibration, load_rig, Calibration
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_guards import bounds
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.lidar_map import pyramid_factors, lidar_map
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.camera.camera_registration import _corrected, camera_sensors

rig_dir = Path(sys.argv[1])
rig, truth = load_rig(rig_dir), load_calibration(rig_dir / "ground_truth.json")
if len(sys.argv) > 2:  # carried by a turn (deg, rotation vector), the map then the features
    turn = np.eye(4); turn[:3, :3] = Rotation.from_rotvec(np.deg2rad([float(v) for v in sys.argv[2].split(",")])).as_matrix()
    rig.carry_trajectory(turn)
prior = Calibration.from_rig(rig)
start = Calibration(prior.reference_sensor, dict(prior.T_ref_sensor), dict(prior.time_offset))
has_lidar = len(sys.argv) <= 2 and any(s.type == "lidar" for s in rig.sensors.values())
for n, s in rig.sensors.items():
    if s.type == "lidar":
        start.T_ref_sensor[n], start.time_offset[n] = truth.T_ref_sensor[n], truth.time_offset[n]
config = CameraRegistrationConfig()
world = lidar_map(rig, start, config.map_voxel, config.min_range, log=lambda s: None) if has_lidar else feature_map(rig, start, FeatureMapConfig(voxel=config.map_voxel), log=lambda s: None)
traj = ReferenceTrajectory.of(rig)
orig = cv2.solvePnPRansac
for name in camera_sensors(rig):
    factors = pyramid_factors(int(rig.sensors[name].intrinsics["w"]), config.min_width)
    camera, reference = CameraFrames.of(rig, name, factors), CameraFrames.of(rig, rig.reference_sensor, factors)
    T, off = np.asarray(start.T_ref_sensor[name]), float(start.time_offset[name])
    for mode in ("ransac", "magsac"):
        cv2.solvePnPRansac = (lambda *a, **k: orig(*a, **dict(k, flags=cv2.SOLVEPNP_ITERATIVE))) if mode == "ransac" else orig
        r = fs.feature_start(traj, world, camera, reference, np.asarray(start.T_ref_sensor[rig.reference_sensor]), float(start.time_offset[rig.reference_sensor]),
                             T, off, rig.sensors[name].intrinsics, bounds(config), fs.FeatureStartConfig(), lambda s: None)
        if r.theta is None:
            print(f"{rig_dir.name} {name:16s} {mode}: no start ({r.note})"); continue
        pose, d = _corrected(T, off, r.theta)
        G = np.asarray(truth.T_ref_sensor[name])
        print(f"{rig_dir.name} {name:16s} {mode}: {np.linalg.norm(pose[:3,3]-G[:3,3])*100:6.2f} cm {np.rad2deg(np.linalg.norm(Rotation.from_matrix(pose[:3,:3].T@G[:3,:3]).as_rotvec())):.3f} deg {(d-truth.time_offset[name])*1000:+7.2f} ms, RMS {r.rms_px:.2f} px, {r.matches} matches")
