"""The finest pyramid level's minimum on independent draws of map points, everything at the truth (docs/method.md,
"The finest level"): one solve from the true calibration per draw, for each points-per-frame count; prints each
estimate's corrections (mdeg x3, mm x3, ms) and their mean and spread. ``own`` / ``ref`` keep only the camera's own
pairs or only the reference-camera pairs. Needs a rig with a LiDAR and ground truth.

Usage: .venv/bin/python scripts/finest_level_spread.py RIG CAMERA 600,5000 [all|own|ref] [DRAWS] [FIELD=VALUE ...]
(``FIELD=VALUE``: ``CameraRegistrationConfig`` fields to change, e.g. ``map_voxel=0.02 huber=2``.)
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_guards import solve, subset
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.camera.lidar_map import lidar_map
from moisst_ns.stages.camera.photometric import Registration
from moisst_ns.stages.stage_floor import rig_at

UNITS = np.array([1e3 * 180 / np.pi] * 3 + [1e3] * 3 + [1e3])
"""Solver corrections (rad, m, s) to mdeg, mm, ms."""


def main() -> None:
    folder, name, counts = Path(sys.argv[1]), sys.argv[2], [int(x) for x in sys.argv[3].split(",")]
    positional = [a for a in sys.argv[1:] if "=" not in a]
    mode = positional[3] if len(positional) > 3 else "all"
    draws = int(positional[4]) if len(positional) > 4 else 4
    defaults, changes = CameraRegistrationConfig(), {}
    for key, value in (a.split("=", 1) for a in sys.argv[1:] if "=" in a):
        if not hasattr(defaults, key):
            sys.exit(f"finest_level_spread.py: {key}: not a CameraRegistrationConfig field")
        changes[key] = type(getattr(defaults, key))(value)
    torch.set_num_threads(1)
    rig, truth = load_rig(folder), load_calibration(folder / "ground_truth.json")
    at_truth = rig_at(rig, truth)
    config = CameraRegistrationConfig(**changes)
    world = lidar_map(at_truth, truth, config.map_voxel, config.min_range, log=lambda s: None)
    traj = ReferenceTrajectory.of(rig)
    camera, reference = CameraFrames.of(at_truth, name, [1]), CameraFrames.of(at_truth, rig.reference_sensor, [1])
    for count in counts:
        estimates = []
        for seed in range(draws):
            start = time.perf_counter()
            problem = Registration(traj, world, camera, reference, truth, dataclasses.replace(config, seed=seed))
            pairs = problem.pairs(np.zeros(7), 1, count)
            if mode != "all":
                pairs = subset(pairs, np.flatnonzero(pairs.own if mode == "own" else ~pairs.own))
            theta = solve(problem, np.zeros(7), np.ones(7, bool), pairs, 1, config)[0] * UNITS
            estimates.append(theta)
            print(f"{count}/frame draw {seed} ({len(pairs.points)} pairs, {time.perf_counter() - start:.0f} s):",
                  " ".join(f"{x:7.3f}" for x in theta), flush=True)
        estimates = np.array(estimates)
        print(f"{count}/frame mean:", " ".join(f"{x:7.3f}" for x in estimates.mean(0)),
              " sd:", " ".join(f"{x:6.3f}" for x in estimates.std(0, ddof=1)), flush=True)


if __name__ == "__main__":
    main()
