"""Where a camera's photometric cost pulls, by depth: each camera of a rig with ground truth at its true calibration,
its pairs with the reference camera against the reference camera's triangulated features (the map the camera stage
uses when a LiDAR is undetermined), binned by the point's depth; per bin and partner (the reference frame of the same
instant, or another), the image shift of the camera's projections that minimises the Huber cost. A bin that wants a
shift where the others want none holds points that are not where the map says (docs/lab/2026-11-29-movers.md).

Usage: .venv/bin/python scripts/pair_depth_shift.py RIG CAMERA [CAMERA ...] [--calibration calibration.json]
(``--calibration``: a run's output whose ``trajectory_T_reference`` carries the trajectory first.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_guards import points_per_frame
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.lidar_map import bilinear, pyramid_factors
from moisst_ns.stages.camera.photometric import CameraFrames, Registration, robust_cost

BINS = ((0.0, 6.0), (6.0, 10.0), (10.0, np.inf))
SHIFTS = np.arange(-3.0, 3.01, 0.25)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rig", type=Path)
    parser.add_argument("cameras", nargs="+")
    parser.add_argument("--calibration", type=Path, default=None)
    args = parser.parse_args()
    rig, truth = load_rig(args.rig), load_calibration(args.rig / "ground_truth.json")
    turn = load_calibration(args.calibration).trajectory_T_reference if args.calibration is not None else None
    if turn is not None:
        rig.carry_trajectory(np.asarray(turn))
    config = CameraRegistrationConfig()
    world = feature_map(rig, truth, FeatureMapConfig(voxel=config.map_voxel), log=lambda s: None)
    traj = ReferenceTrajectory.of(rig)
    for name in args.cameras:
        factors = pyramid_factors(int(rig.sensors[name].intrinsics["w"]), config.min_width)
        camera, reference = CameraFrames.of(rig, name, factors), CameraFrames.of(rig, rig.reference_sensor, factors)
        problem, finest = Registration(traj, world, camera, reference, truth, config), min(factors)
        stack = camera.levels[finest]
        pairs = problem.pairs(np.zeros(7), finest, points_per_frame(config, finest, True))
        depth = problem.model.camera_points(np.zeros(7), pairs.points, pairs.frame_a)[:, 2]
        uv, _ = problem.model.pixels(np.zeros(7), stack.model, pairs.points, pairs.frame_a, jacobian=False)
        nearest = np.abs(reference.stamps[None] - camera.stamps[:, None]).argmin(axis=1)
        at_once = ~pairs.own & (pairs.frame_b == nearest[pairs.frame_a])
        print(f"{name}: {len(uv)} pairs at the truth, {at_once.mean():.0%} with the reference frame of the same instant")
        for near, far in BINS:
            for partner, chosen in (("same instant", at_once), ("other instant", ~pairs.own & ~at_once)):
                rows = chosen & (depth >= near) & (depth < far)
                if rows.sum() < 50:
                    continue
                costs = []
                for du in SHIFTS:
                    value, _, ok = bilinear(stack, pairs.frame_a[rows], uv[rows] + [du, 0.0])
                    costs.append(robust_cost((value - pairs.value_b[rows])[ok], config.huber))
                best = int(np.argmin(costs))
                print(f"  depth {near:g}-{far:g} m, {partner}: {int(rows.sum())} pairs; cost lowest at a shift of {SHIFTS[best]:+.2f} px "
                      f"({costs[best]:.4f}; {costs[len(SHIFTS) // 2]:.4f} unshifted)")


if __name__ == "__main__":
    main()
