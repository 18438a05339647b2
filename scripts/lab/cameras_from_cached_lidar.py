"""The camera stage alone, the LiDAR stage read from a ``moisst-calibrate`` OUT (its lidar_first/), or none on a rig
without a LiDAR; prints each camera's error (docs/lab/2026-11-27-reference-motion.md).

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/cameras_from_cached_lidar.py RIG [OUT] [--set name=value ...]
(``CALIBRATION_OUT=FILE`` in the environment writes the estimate there.)
(``OWN_ONLY_UNPAIRED=1`` in the environment with docs/lab/2026-11-27-own-pairs.patch applied: the own-pairs rule).
"""

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from camera_stage import config_from  # noqa: E402

import numpy as np  # noqa: E402

from moisst_ns.rig.calibration import calibration_report_errors  # noqa: E402
from moisst_ns.rig.format import Calibration, load_calibration, load_rig  # noqa: E402
from moisst_ns.rig.trust import PARAMETERS, parameter_difference  # noqa: E402
from moisst_ns.stages.camera.camera_registration import register_cameras  # noqa: E402
from moisst_ns.stages.lidar.lidar_report import stage_sigma  # noqa: E402
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, UNITS  # noqa: E402


def main() -> None:
    args = sys.argv[1:]
    rig_dir, cache = Path(args.pop(0)), None
    if args and not args[0].startswith("--"):
        cache = Path(args.pop(0))
    config = config_from(args[1:] if args and args[0] == "--set" else [])
    rig, truth = load_rig(rig_dir), load_calibration(rig_dir / "ground_truth.json")
    if cache:
        calibration = load_calibration(cache / "lidar_first" / "calibration.json")
        lidars = json.loads((cache / "lidar_first" / "lidar_first.json").read_text())["sensors"]
        undetermined = {n: e.get("motion_undetermined", e.get("undetermined", [])) for n, e in lidars.items()}
        sigma = {n: stage_sigma(e)[0] for n, e in lidars.items()}  # the LiDARs placed at the shared instants, as stage_run does
    else:
        calibration, undetermined, sigma = Calibration.from_rig(rig), None, None
    start = time.time()
    result = register_cameras(rig, calibration, config, lidar_undetermined=undetermined, log=print, lidar_sigma=sigma)
    print(rig_dir, "map", result.map_source, f"{time.time() - start:.0f} s")
    if os.environ.get("CALIBRATION_OUT"):  # the cameras' and LiDARs' estimate, for per-component comparisons
        result.calibration.write(Path(os.environ["CALIBRATION_OUT"]))
    errors = calibration_report_errors(result.calibration, truth)
    for name, r in result.cameras.items():
        e = errors[name]
        print(f"  {name:<16} {e['translation_cm']:7.3f} cm {e['rotation_deg']:7.4f} deg {e['time_ms']:7.3f} ms",
              "prior kept: " + r.note if r.kept_prior else "accepted")
        error = parameter_difference(np.asarray(truth.T_ref_sensor[name]), truth.time_offset[name],
                                     np.asarray(result.calibration.T_ref_sensor[name]), result.calibration.time_offset[name])
        print("    error (sigma, split-half part):", ", ".join(f"{p} {v * u:+.2f} ({r.sigma[j] * u:.2f}, {r.sigma_split[j] * u:.2f})"
                                                          for p, v, j, (u, _) in zip(PARAMETERS, error, JACOBIAN_ORDER, UNITS)))
    for name in result.lidars:
        e = errors[name]
        print(f"  {name:<16} {e['translation_cm']:7.3f} cm {e['rotation_deg']:7.4f} deg {e['time_ms']:7.3f} ms (placed at the shared instants)")


if __name__ == "__main__":
    main()
