"""Per-pair noise of the camera motions that ``hand_eye.camera_motion`` measures, at the ground-truth calibration.

Usage: .venv/bin/python scripts/lab/hand_eye_noise.py RIG CAMERA [CAMERA ...]
"""
import sys, numpy as np, torch, roma
sys.path.insert(0, __import__("os").path.dirname(__file__))
from hand_eye import HandEyeConfig, camera_motion, motion_residuals
from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.photometric import CameraFrames
rig = load_rig(sys.argv[1]); truth = load_calibration(rig.root / "ground_truth.json")
traj = ReferenceTrajectory.of(rig)
for name in sys.argv[2:]:
    spec = rig.sensors[name]
    frames = CameraFrames.of(rig, name, [1])
    for method in ["RANSAC"]:
        m = camera_motion([np.asarray(i) for i in frames.levels[1].intensity], spec.intrinsics, HandEyeConfig(method=method))
        P = np.asarray(spec.T_ref_sensor); T = np.asarray(truth.T_ref_sensor[name])
        th = np.r_[roma.rotmat_to_rotvec(torch.from_numpy(P[:3,:3].T @ T[:3,:3])).numpy(), T[:3,3]-P[:3,3], truth.time_offset[name]-spec.time_offset]
        r = motion_residuals(th, traj, frames.stamps, P, spec.time_offset, m).reshape(-1, 6)
        lag = m.pairs[:,1]-m.pairs[:,0]
        for L in (1,2,3):
            k = lag == L
            print(name, method, "lag", L, "rot err deg median", np.degrees(np.median(np.linalg.norm(r[k,:3],axis=1))), "dir err deg median", np.degrees(np.median(np.linalg.norm(r[k,3:],axis=1))), "mean rot vec deg", np.degrees(r[k,:3].mean(0)).round(3), "mean dir deg", np.degrees(r[k,3:].mean(0)).round(3))
