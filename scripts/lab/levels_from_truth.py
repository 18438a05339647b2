"""Where each pyramid level of the camera stage leads one camera on a rig with ground truth: every level descended alone
from the truth and from the feature start, and the feature start descended from the second-finest level alone
(docs/uncertainty.md, "The camera stage's part": realistic plaza seed 2 without a LiDAR).

Usage: .venv/bin/python scripts/lab/levels_from_truth.py RIG CAMERA   (the reference camera's feature map)
"""

from __future__ import annotations

import sys

import numpy as np
import roma
import torch

from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera import camera_registration as cr
from moisst_ns.stages.camera.camera_guards import bounds
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.feature_start import feature_start
from moisst_ns.stages.camera.lidar_map import pyramid_factors
from moisst_ns.stages.camera.photometric import CameraFrames, Registration


def main(folder: str, name: str) -> None:
    rig, truth = load_rig(folder), load_calibration(folder + "/ground_truth.json")
    calibration, config = Calibration.from_rig(rig), cr.CameraRegistrationConfig()
    world = feature_map(rig, calibration, FeatureMapConfig(voxel=config.map_voxel), lambda s: None)
    traj = ReferenceTrajectory.of(rig)
    factors = pyramid_factors(int(rig.sensors[name].intrinsics["w"]), config.min_width)
    reference = CameraFrames.of(rig, rig.reference_sensor, factors)
    problem = Registration(traj, world, CameraFrames.of(rig, name, factors), reference, calibration, config)
    prior, true_T = np.asarray(calibration.T_ref_sensor[name]), np.asarray(truth.T_ref_sensor[name])
    rotation = roma.rotmat_to_rotvec(torch.from_numpy(prior[:3, :3].T @ true_T[:3, :3])).numpy()
    at_truth = np.r_[rotation, true_T[:3, 3] - prior[:3, 3], truth.time_offset[name] - calibration.time_offset[name]]

    def error(theta: np.ndarray) -> str:
        pose, offset = cr._corrected(prior, calibration.time_offset[name], theta)
        return f"{100 * np.linalg.norm(pose[:3, 3] - true_T[:3, 3]):.2f} cm, {1000 * (offset - truth.time_offset[name]):+.2f} ms"

    initial = feature_start(traj, world, problem.camera, reference, np.asarray(calibration.T_ref_sensor[rig.reference_sensor]),
                            float(calibration.time_offset[rig.reference_sensor]), prior, calibration.time_offset[name],
                            rig.sensors[name].intrinsics, bounds(config), cr.START, lambda s: None)
    if initial.theta is None:
        raise SystemExit(f"{name}: no feature start ({initial.note})")
    print(f"feature start: {error(initial.theta)}")
    theta = initial.theta
    for factor in sorted(factors, reverse=True):
        theta, history, _, _ = cr._descend(problem, config, lambda s: None, theta, [factor])
        alone, alone_history, _, _ = cr._descend(problem, config, lambda s: None, at_truth, [factor])
        print(f"1/{factor}: coarse to fine from the feature start {error(theta)}, cost {history[-1]['cost']:.4f}; "
              f"this level alone from the truth {error(alone)}, cost {alone_history[-1]['cost']:.4f}")
    theta, history, _, _ = cr._descend(problem, config, lambda s: None, initial.theta, sorted(factors, reverse=True)[-2:])
    print(f"the feature start from 1/{sorted(factors)[1]} to 1/1: {error(theta)}, cost {history[-1]['cost']:.4f}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
