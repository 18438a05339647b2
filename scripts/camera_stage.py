"""The pre-NeRF stages alone on rigs with ground truth: LiDAR first (when the rig has a LiDAR), then the cameras
against the map; prints every sensor's error and each camera's sigma, and writes the per-parameter errors and sigmas
(x, y, z, roll, pitch, yaw, time offset; m, rad, s) to JSON for coverage tables (docs/method.md, docs/uncertainty.md).

Usage: .venv/bin/python scripts/camera_stage.py RIG [RIG ...] [--json OUT.json] [--set points_per_frame=1500 ...] [--lidar-map]
(``--set estimate_readout=true`` prints each camera's fitted readout time and the one it uses.)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import roma
import torch

from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig, register_cameras
from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, calibrate_lidars, lidar_sensors
from moisst_ns.stages.lidar.lidar_report import stage_sigma, stage_summary
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, UNITS

def config_from(settings: list) -> CameraRegistrationConfig:
    """``CameraRegistrationConfig`` with ``name=value`` overrides (typed like the field's default)."""
    defaults = CameraRegistrationConfig()
    fields = {f.name for f in dataclasses.fields(defaults)}
    changes = {}
    for item in settings:
        name, _, value = item.partition("=")
        if name not in fields:
            raise SystemExit(f"--set {item}: no such CameraRegistrationConfig field")
        kind = type(getattr(defaults, name))
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return dataclasses.replace(defaults, **changes)


def run(folder: Path, config: CameraRegistrationConfig, lidar_map: bool = False) -> dict:
    """Both stages on one rig; the per-camera record."""
    rig, truth = load_rig(folder), load_calibration(folder / "ground_truth.json")
    start = time.perf_counter()
    lidar = calibrate_lidars(rig, LidarFirstConfig(), log=lambda s: None) if lidar_sensors(rig) else None
    calibration = lidar.calibration if lidar else Calibration.from_rig(rig)
    lidar_s = time.perf_counter() - start
    entries = stage_summary(lidar, LidarFirstConfig(), calibration, None)["sensors"] if lidar else {}
    result = register_cameras(rig, calibration, config, lidar_undetermined=None if lidar is None or lidar_map else {n: r.motion_undetermined() for n, r in lidar.lidars.items()},
                              lidar_sigma={n: stage_sigma(e)[0] for n, e in entries.items()})
    print(f"{folder}: map from the {result.map_source}{': ' + result.map_note if result.map_note else ''}")
    print(f"{folder}: LiDAR first {lidar_s:.1f} s, cameras {time.perf_counter() - start - lidar_s:.1f} s")
    errors = calibration_report_errors(result.calibration, truth)
    record = {}
    for name, e in errors.items():
        if name == truth.reference_sensor:
            continue
        line = f"  {name:<16} {e['translation_cm']:8.3f} cm {e['rotation_deg']:7.4f} deg {e['time_ms']:8.3f} ms"
        r = result.cameras.get(name)
        if r is not None:
            true_T, est_T = np.asarray(truth.T_ref_sensor[name]), np.asarray(r.estimate)
            rotation = roma.rotmat_to_rotvec(torch.from_numpy(est_T[:3, :3].T @ true_T[:3, :3])).numpy()
            error = np.r_[est_T[:3, 3] - true_T[:3, 3], rotation, r.time_offset - truth.time_offset[name]]
            record[name] = {"error": error.tolist(), "sigma": [r.sigma[j] if np.isfinite(r.sigma[j]) else None for j in JACOBIAN_ORDER], "kept": r.kept_prior,
                            "note": r.note, "wall_s": r.wall_s, "errors": e}
            line += f"  {'prior kept: ' + (r.note or 'held-back check') if r.kept_prior else 'accepted'}"
            if not r.kept_prior:  # the error in units of the stage's sigma, per parameter (x, y, z, roll, pitch, yaw, time offset)
                sigma = np.array(record[name]["sigma"], dtype=float)
                line += "; error / sigma " + ", ".join(f"{p} {abs(x) / s:.2f}" for p, x, s in zip(PARAMETERS, error, sigma))
            if r.readout_estimate is not None:  # --set estimate_readout=true
                line += (f"; readout {r.readout_time * 1000:.2f} ms used (fit {r.readout_estimate * 1000:.2f} ms, sigma {r.readout_sigma * 1000:.2f} ms"
                         + (f": {r.readout_note}" if r.readout_note else "") + ")")
                record[name].update(readout_time=r.readout_time, readout_estimate=r.readout_estimate, readout_sigma=r.readout_sigma)
        print(line)
    for name, placed in result.lidars.items():  # placed against the cameras at the same instants
        sigma = stage_sigma(dict(entries[name], shared_instant=placed.to_json()))[0]
        apart = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], result.calibration.T_ref_sensor[name], result.calibration.time_offset[name])
        print(f"  {name}: took {placed.taken} from the shared instants; error per axis "
              + ", ".join(f"{p} {v * u[0]:.3g} (sigma {s * u[0]:.3g})" for p, v, s, u in zip(PARAMETERS, apart, sigma, UNITS)))
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rigs", type=Path, nargs="+")
    parser.add_argument("--json", type=Path, default=None, help="write {rig: {camera: record}} here")
    parser.add_argument("--set", nargs="*", default=[], help="CameraRegistrationConfig overrides, name=value")
    parser.add_argument("--lidar-map", action="store_true", help="the LiDAR map even where the LiDAR stage left a parameter undetermined")
    args = parser.parse_args()
    config = config_from(args.set)
    records = {str(folder): run(folder, config, args.lidar_map) for folder in args.rigs}
    if args.json:
        args.json.write_text(json.dumps(records, indent=1) + "\n")


if __name__ == "__main__":
    main()
