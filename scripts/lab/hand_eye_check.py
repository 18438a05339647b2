"""Hand-eye (``stages.hand_eye``) of every non-reference camera of a rig with ground truth: error per parameter.

Usage: .venv/bin/python scripts/lab/hand_eye_check.py RIG [CAMERA ...]
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.camera_registration import camera_sensors
from moisst_ns.stages.camera.photometric import CameraFrames
from hand_eye import HandEyeConfig, camera_motion, hand_eye  # scripts/lab/hand_eye.py
from moisst_ns.stages.trust.observability import PARAMETERS


def main() -> None:
    rig = load_rig(sys.argv[1])
    truth = load_calibration(rig.root / "ground_truth.json")
    traj = ReferenceTrajectory.of(rig)
    import os
    config = HandEyeConfig(method=os.environ.get("HE_METHOD", "RANSAC"))
    for name in sys.argv[2:] or camera_sensors(rig):
        begun = time.time()
        spec = rig.sensors[name]
        frames = CameraFrames.of(rig, name, [1])
        motion = camera_motion([np.asarray(i) for i in frames.levels[1].intensity], spec.intrinsics, config)
        result = hand_eye(traj, name, frames.stamps, motion, spec.T_ref_sensor, float(spec.time_offset), config)
        th = torch.as_tensor(result.theta)
        est = calibrated_extrinsic(torch.as_tensor(spec.T_ref_sensor, dtype=torch.float64), th[:3], th[3:6]).numpy()
        before = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], spec.T_ref_sensor, spec.time_offset)
        after = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], est, spec.time_offset + result.theta[6])
        units = [100, 100, 100, 57.29578, 57.29578, 57.29578, 1000]
        print(f"RESULT {name}: pairs {result.pairs}, weak {result.weak}, {time.time() - begun:.0f} s")
        for p, b, a, s, u in zip(PARAMETERS, before, after, result.sigma, units):
            print(f"  {p:12s} prior {b * u:9.3f}  after {a * u:9.3f}  sigma {s * u:9.3f}  covered {abs(a) <= 3 * s}")


if __name__ == "__main__":
    main()
