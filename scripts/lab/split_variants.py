"""The camera stage's split-half test at a run's estimate, the frames split in time (as ``camera_guards.split_half_spread``)
and in other ways: each half's estimate, as a correction from the run's, and half their difference
(docs/lab/2026-11-29-movers.md, "The split-half sigma and image_02").

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/split_variants.py RIG CALIBRATION.json CAMERA [CAMERA ...]
(CALIBRATION.json: a run's estimate; its ``trajectory_T_reference`` carries the trajectory first; the map is the
reference camera's features, as on a rig whose LiDAR the LiDAR stage left undetermined.)
"""

import sys
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_guards import points_per_frame, solve, subset
from moisst_ns.stages.trust.observability import SOLVER_NAMES
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.lidar_map import pyramid_factors
from moisst_ns.stages.camera.photometric import CameraFrames, Registration

UNITS = np.array([np.rad2deg(1.0)] * 3 + [100.0] * 3 + [1000.0])  # solver order: deg, cm, ms


def main() -> None:
    rig_dir, estimate_file, names = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:]
    rig, truth, est = load_rig(rig_dir), load_calibration(rig_dir / "ground_truth.json"), load_calibration(estimate_file)
    if est.trajectory_T_reference is not None:
        rig.carry_trajectory(np.asarray(est.trajectory_T_reference))
    config = CameraRegistrationConfig()
    world = feature_map(rig, est, FeatureMapConfig(voxel=config.map_voxel), log=lambda s: None)
    traj = ReferenceTrajectory.of(rig)
    for name in names:
        factors = pyramid_factors(int(rig.sensors[name].intrinsics["w"]), config.min_width)
        camera, reference = CameraFrames.of(rig, name, factors), CameraFrames.of(rig, rig.reference_sensor, factors)
        problem, finest = Registration(traj, world, camera, reference, est, config), min(factors)
        theta, active = np.zeros(7), np.ones(7, dtype=bool)
        error = np.asarray(parameter_difference(np.asarray(est.T_ref_sensor[name]), est.time_offset[name],
                                                np.asarray(truth.T_ref_sensor[name]), truth.time_offset[name]))
        to_truth = error[[PARAMETERS.index(p) for p in SOLVER_NAMES]]  # the correction that would reach the truth
        print(f"{name}: the correction to the truth ({', '.join(SOLVER_NAMES)}; deg, cm, ms):", np.round(to_truth * UNITS, 3))
        pairs = problem.pairs(theta, finest, points_per_frame(config, finest, True))
        half = len(camera.stamps) // 2
        depth = problem.model.camera_points(theta, pairs.points, pairs.frame_a)[:, 2]
        splits = {"time (the stage's)": pairs.frame_a < half, "depth under 10 m": depth < 10.0,
                  "random": np.random.default_rng(0).random(len(depth)) < 0.5}
        for label, rows in splits.items():
            a, b = (solve(problem, theta, active, subset(pairs, r), finest, config)[0] for r in (rows, ~rows))
            print(f"  {label}: {rows.sum()} / {(~rows).sum()} pairs; halves", np.round(a * UNITS, 3), np.round(b * UNITS, 3),
                  "; half their difference", np.round(np.abs(a - b) / 2 * UNITS, 3), "; the farther from the whole", np.round(np.fmax(np.abs(a), np.abs(b)) * UNITS, 3))


if __name__ == "__main__":
    main()
