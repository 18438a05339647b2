"""The own-motion fit (``stages/camera/own_motion.py``) of one camera alone, the map from the LiDAR at its true
calibration (``--map features``: the reference camera's triangulated features instead; ``--map none``: no map, the
camera's own tracks on the trajectory, ``stages/camera/own_tracks.py``, and the parameters the drive names weak for it):
error and error / sigma per parameter.
docs/lab/2026-12-02-own-motion.md, docs/lab/2026-12-02-own-tracks.md.

Usage: .venv/bin/python scripts/lab/own_motion_check.py RIG CAMERA [--map lidar|features|none]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.lidar_map import lidar_map
from moisst_ns.stages.camera.own_motion import OWN, MapSurface, fit_own_motion, own_matches
from moisst_ns.stages.camera.own_tracks import TRACKS, fit_own_tracks, weak_by_motion
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, UNITS


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("rig")
    parser.add_argument("camera")
    parser.add_argument("--map", choices=("lidar", "features", "none"), default="lidar")
    args = parser.parse_args()
    rig, truth = load_rig(args.rig), load_calibration(f"{args.rig}/ground_truth.json")
    start = Calibration.from_rig(rig)
    for name, spec in rig.sensors.items():
        if spec.type == "lidar":
            start.T_ref_sensor[name], start.time_offset[name] = truth.T_ref_sensor[name], truth.time_offset[name]
    begun = time.perf_counter()
    prior, offset = np.asarray(start.T_ref_sensor[args.camera]), float(start.time_offset[args.camera])
    traj, matches = ReferenceTrajectory.of(rig), own_matches(rig, args.camera, OWN)
    if args.map == "none":
        fit = fit_own_tracks(traj, matches, float(rig.sensors[args.camera].intrinsics["fl_x"]), prior, offset, TRACKS, print, args.camera,
                             halved=own_matches(rig, args.camera, OWN, downscale=2))
    else:
        world = lidar_map(rig, start, 0.05, 2.0, print) if args.map == "lidar" else feature_map(rig, start, FeatureMapConfig(patch_points=0), print)
        fit = fit_own_motion(traj, matches, MapSurface.of(world, OWN.normal_radius), prior, offset, OWN, print, args.camera)
    if fit is None:
        print(f"RESULT {args.rig} {args.camera}: not placed")
        return
    X = calibrated_extrinsic(torch.from_numpy(prior), torch.from_numpy(fit.theta[:3]), torch.from_numpy(fit.theta[3:6])).numpy()
    error = np.asarray(parameter_difference(truth.T_ref_sensor[args.camera], truth.time_offset[args.camera], X, offset + fit.theta[6]))
    sigma = fit.sigma[list(JACOBIAN_ORDER)]
    print(f"RESULT {args.rig} {args.camera}: {np.linalg.norm(error[:3]) * 100:.2f} cm {np.rad2deg(np.linalg.norm(error[3:6])):.3f} deg "
          f"{abs(error[6]) * 1000:.2f} ms; {time.perf_counter() - begun:.0f} s")
    if args.map == "none":  # the parameters the drive's own motion leaves weak (named so by the stage)
        weak = weak_by_motion(traj, matches, prior, offset, lambda _: None, args.camera)
        rest = [i for i, p in enumerate(PARAMETERS[:3]) if p not in weak]
        print(f"  weak: {', '.join(weak) or 'none'}; the lever arm without them {np.linalg.norm(error[rest]) * 100:.2f} cm")
    print("  error / sigma: " + ", ".join(f"{p} {e * u:.3g} {n} / {s * u:.3g}" for p, e, s, (u, n) in zip(PARAMETERS, error, sigma, UNITS)))


if __name__ == "__main__":
    main()
