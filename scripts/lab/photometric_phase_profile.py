"""Lab (2026-12-07, issue 35): the camera stage's photometric cost of one camera along its time offset, every other
parameter at the truth, at the finest level on pairs drawn once at the truth; split into the pairs with a reference
camera partner and those with one of the camera's own frames. Tests whether a trajectory's white noise pulls the offset
towards the phases halfway between its samples (``delta_phase_profile.py`` shows it for the own tracks).

The map is the reference camera's triangulated features (``camera_map.feature_map``), as the stage uses on a rig
without a LiDAR. ``--resample PHASE CM DEG`` as in ``delta_phase_profile.py``.

Usage: .venv/bin/python scripts/lab/photometric_phase_profile.py RIG CAMERA [--resample PHASE CM DEG]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import roma
import torch

sys.path.insert(0, str(Path(__file__).parent))
from delta_phase_profile import from_arguments, phase  # noqa: E402

from moisst_ns.rig.format import Calibration  # noqa: E402
from moisst_ns.rig.geometry import ReferenceTrajectory  # noqa: E402
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig  # noqa: E402
from moisst_ns.stages.camera.camera_guards import points_per_frame  # noqa: E402
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map  # noqa: E402
from moisst_ns.stages.camera.lidar_map import pyramid_factors  # noqa: E402
from moisst_ns.stages.camera.photometric import CameraFrames, Registration, huber_costs  # noqa: E402


def main() -> None:
    name, rig, truth = from_arguments()
    config = CameraRegistrationConfig()
    calibration = Calibration.from_rig(rig)
    world = feature_map(rig, calibration, FeatureMapConfig(voxel=config.map_voxel), lambda s: None)
    factors = pyramid_factors(int(rig.sensors[name].intrinsics["w"]), config.min_width)
    problem = Registration(ReferenceTrajectory.of(rig), world, CameraFrames.of(rig, name, factors),
                           CameraFrames.of(rig, rig.reference_sensor, factors), calibration, config)
    prior, true_T = np.asarray(calibration.T_ref_sensor[name]), np.asarray(truth.T_ref_sensor[name])
    rotation = roma.rotmat_to_rotvec(torch.from_numpy(prior[:3, :3].T @ true_T[:3, :3])).numpy()
    at_truth = np.r_[rotation, true_T[:3, 3] - prior[:3, 3], truth.time_offset[name] - calibration.time_offset[name]]
    factor = min(factors)
    pairs = problem.pairs(at_truth, factor, points_per_frame(config, factor, True))
    print(f"{len(pairs.own)} pairs ({int(pairs.own.sum())} own); the camera's frames at phase {phase(rig, name, truth.time_offset[name]):.2f} of the trajectory's "
          f"{1000 * np.median(np.diff(rig.trajectory_stamps)):.0f} ms samples")
    for step in np.arange(-0.06, 0.0601, 0.005):
        theta = at_truth.copy()
        theta[6] += step
        res, _, ok = problem.residuals(theta, pairs, factor, False)
        cost = huber_costs(res, config.huber)
        parts = [float(np.mean(cost[ok & sel])) for sel in (~pairs.own, pairs.own)]
        print(f"offset {1000 * step:+5.1f} ms from the truth: all {float(np.mean(cost[ok])):.6f}, reference pairs {parts[0]:.6f}, own pairs {parts[1]:.6f}")


if __name__ == "__main__":
    main()
