"""Lab: the LiDAR placed by the reference camera's own view of its map (issue 34/35).

The reference camera is registered photometrically against the LiDAR map as if its extrinsic were unknown (own-frame
pairs only: its known pose is not used); the apparent extrinsic ``X`` and offset ``d`` it finds mean the map sits at
``X^-1`` from where the LiDAR calibration puts it, so the LiDAR's implied calibration is ``X^-1 @ ref_T_L``, offset
``delta_L - d``. Repeated ``ROUNDS`` times (the map rebuilt each time). Prints the LiDARs' errors from ground_truth.json.

Usage: .venv/bin/python scripts/lab/reference_view.py RIG CALIBRATION_JSON [ROUNDS] [FIELD=VALUE ...]
(``FIELD=VALUE``: ``CameraRegistrationConfig`` changes.)
"""

from __future__ import annotations

import sys
import time

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_registration import register_camera
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.camera.lidar_map import lidar_map, pyramid_factors
from moisst_ns.stages.camera.photometric import Registration


def errors(calibration, truth, name: str) -> str:
    d = np.array(parameter_difference(calibration.T_ref_sensor[name], calibration.time_offset[name], truth.T_ref_sensor[name], truth.time_offset[name]))
    return (f"{np.linalg.norm(d[:3]) * 100:.2f} cm {np.rad2deg(np.linalg.norm(d[3:6])):.3f} deg {abs(d[6]) * 1000:.2f} ms; "
            f"cm {np.round(d[:3] * 100, 2)} deg {np.round(np.rad2deg(d[3:6]), 3)}")


def main() -> None:
    rig = load_rig(sys.argv[1])
    calibration = load_calibration(sys.argv[2])
    truth = load_calibration(rig.root / "ground_truth.json")
    rounds = int(sys.argv[3]) if len(sys.argv) > 3 and "=" not in sys.argv[3] else 2
    changes = {k: type(getattr(CameraRegistrationConfig, k))(eval(v)) for k, v in (a.split("=", 1) for a in sys.argv[3:] if "=" in a)}
    config = CameraRegistrationConfig(**changes)
    reference = rig.reference_sensor
    lidars = [n for n, s in rig.sensors.items() if s.type == "lidar" and n != reference]
    traj = ReferenceTrajectory.of(rig)
    camera = CameraFrames.of(rig, reference, pyramid_factors(int(rig.sensors[reference].intrinsics["w"]), config.min_width))
    start = time.time()
    for name in lidars:
        print(f"START {name}: {errors(calibration, truth, name)}", flush=True)
    for round_ in range(rounds):
        world = lidar_map(rig, calibration, config.map_voxel, config.min_range)
        result = register_camera(Registration(traj, world, camera, None, calibration, config), config, log=lambda s: print(s, flush=True))
        fit = result.history[-1]
        X, d = np.asarray(fit["T_ref_sensor"]), float(fit["time_offset"])
        print(f"ROUND {round_}: kept_prior {result.kept_prior} ({result.note}); correction {np.round(fit['correction'], 5).tolist()}; "
              f"sigma {np.round(result.sigma, 5).tolist()}; wall {time.time() - start:.0f} s", flush=True)
        for name in lidars:
            calibration.T_ref_sensor[name] = np.linalg.inv(X) @ np.asarray(calibration.T_ref_sensor[name])
            calibration.time_offset[name] = float(calibration.time_offset[name]) - d
            print(f"ROUND {round_} {name}: {errors(calibration, truth, name)}", flush=True)


if __name__ == "__main__":
    main()
