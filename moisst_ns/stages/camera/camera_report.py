"""What the camera-registration stage leaves in a run folder: ``calibration.json``, ``camera_registration.json`` and
``camera_registration.md``. No nerfstudio import."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np
from scipy.spatial.transform import Rotation

from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import Calibration
from moisst_ns.rig.trust import finite_or_none
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_result import CameraStageResult
from moisst_ns.stages.lidar.lidar_report import truth_table, write_stage_files
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, PARAMETERS, TEST_STEPS, UNITS

REPORT_JSON = "camera_registration.json"
REPORT_MD = "camera_registration.md"


def stage_summary(result: CameraStageResult, config: CameraRegistrationConfig, start: Calibration,
                  truth: Optional[Calibration]) -> dict:
    """The JSON-ready record of a stage run (``camera_registration.json``).

    ``sigma`` (and its parts ``sigma_formal``, ``sigma_split_half``, ``sigma_resolution``, ``sigma_convergence``, and
    ``sigma_trajectory`` where rig.json states the trajectory's errors, ``sigma_map`` where the map is the reference
    camera's features) is in the trust order (``x, y, z, roll, pitch,
    yaw, time_offset``; m, rad, s); a parameter whose sigma exceeds its typical prior error (10 cm, 1 deg, 10 ms), or
    that its evidence cannot fix on this drive (``CameraResult.weak``), is listed in ``weak``; ``blind`` lists those its view does not tell a typical prior error apart on
    (``typical_error_significance`` under ``min_significance``): such a camera keeps its prior, and ``moisst-calibrate``
    holds it there. ``readout_time`` is the rolling-shutter readout the camera's projections used (rig.json's, or with
    ``estimate_readout`` the estimate when the drive determines it: ``readout_estimate``, ``readout_sigma``,
    ``readout_note``), seconds.
    """
    before = calibration_report_errors(start, truth) if truth else {}
    after = calibration_report_errors(result.calibration, truth) if truth else {}
    sensors = {}
    for name, r in result.cameras.items():
        sigma = [float(r.sigma[j]) for j in JACOBIAN_ORDER]
        parts = {f"sigma_{k}": [finite_or_none(v[j]) for j in JACOBIAN_ORDER] for k, v in (("formal", r.sigma_formal), ("split_half", r.sigma_split),
                                                                                   ("resolution", r.sigma_resolution), ("convergence", r.sigma_convergence),
                                                                                   ("trajectory", r.sigma_trajectory), ("map", r.sigma_map)) if v}
        entry = {"T_ref_sensor": np.asarray(r.estimate).tolist(), "time_offset": r.time_offset, "prior_T_ref_sensor": np.asarray(r.prior).tolist(),
                 "prior_time_offset": r.prior_offset, "sigma": [finite_or_none(s) for s in sigma],
                 "weak": [p for p, s, step in zip(PARAMETERS, sigma, TEST_STEPS) if not s <= step or p in r.weak],
                 "loss_estimate": finite_or_none(r.cost_estimate), "loss_prior": finite_or_none(r.cost_prior), "kept_prior": r.kept_prior,
                 "note": r.note, "cost_ratio_to_reference": r.cost_ratio, "start": r.start, "wall_s": r.wall_s, "history": r.history,
                 "typical_error_significance": [finite_or_none(r.significance[j]) for j in JACOBIAN_ORDER] if r.significance else None,
                 "blind": [p for p in PARAMETERS if p in r.blind],
                 "held_there": r.held_there, "map_source": result.map_source, "readout_time": r.readout_time, "prior_readout_time": r.readout_prior,
                 **({"readout_estimate": r.readout_estimate, "readout_sigma": finite_or_none(r.readout_sigma), "readout_note": r.readout_note}
                    if r.readout_estimate is not None else {}),
                 **parts}
        if truth:
            entry["errors_before"], entry["errors_after"] = before[name], after[name]
        sensors[name] = entry
    return {"stage": "camera-registration", "config": asdict(config), "map_points": result.map_points, "map_source": result.map_source,
            "map_note": result.map_note, "sensors": sensors, "lidars": {n: r.to_json() for n, r in result.lidars.items()}}


def write_stage_outputs(result: CameraStageResult, config: CameraRegistrationConfig, start: Calibration, truth: Optional[Calibration],
                        out: Path) -> dict:
    """Write ``calibration.json``, ``camera_registration.json`` and ``camera_registration.md`` into ``out``."""
    summary = stage_summary(result, config, start, truth)
    what = "LiDAR map points" if result.map_source == "lidar" else "triangulated features of the reference camera"
    turn = result.calibration.trajectory_T_reference
    turned = [] if turn is None else [
        f"The trajectory is turned {np.degrees(Rotation.from_matrix(turn[:3, :3]).as_rotvec()).round(3).tolist()} deg (rotation vector) from the "
        "reference camera (the LiDARs' motion against their shared instants): the cameras were registered on it carried to the reference camera "
        "(`trajectory_T_reference` in calibration.json).", ""]
    md = [f"# Camera registration against the {'LiDAR map' if result.map_source == 'lidar' else 'reference camera features'}", "",
          *([f"The map is the reference camera's features: {result.map_note}.", ""] if result.map_note else []),
          *turned,
          f"Photometric consistency of {result.map_points} {what} between each camera's frames and the reference "
          "camera's (module `moisst_ns.stages.camera.camera_registration`). Held-back cost: mean Huber cost of fresh pairs at the "
          "estimate vs at the prior; a camera whose estimate is not better keeps its prior.", ""]
    for name, s in summary["sensors"].items():
        if s["note"]:
            md += [f"## {name}", "", f"Prior kept: {s['note']}.", ""]
            continue
        md += [f"## {name}", "", f"Started from the {s['start']}; {s['wall_s']:.1f} s; held-back cost {s['loss_prior']:.4f} at the prior, {s['loss_estimate']:.4f} at the "
               f"estimate{' (prior kept)' if s['kept_prior'] else ''}.", "",
               "| | " + " | ".join(PARAMETERS) + " |", "|---|" + "---|" * len(PARAMETERS),
               "| sigma | " + " | ".join("inf" if v is None else f"{v * u:.3g} {unit}" for v, (u, unit) in zip(s["sigma"], UNITS)) + " |", ""]
        if "readout_estimate" in s:
            sigma = "inf" if s["readout_sigma"] is None else f"{s['readout_sigma'] * 1000:.2f} ms"
            md += [f"Rolling-shutter readout: estimated {s['readout_estimate'] * 1000:.2f} ms (sigma {sigma}) from rig.json's "
                   f"{s['prior_readout_time'] * 1000:g} ms; used {s['readout_time'] * 1000:.2f} ms{'; ' + s['readout_note'] if s['readout_note'] else ''}.", ""]
        md += truth_table(s, "start") if truth else []
        md += ["| level | iteration | pairs | cost |", "|---|---|---|---|"]
        md += [f"| 1/{h['level']} | {h['iteration']} | {h['pairs']} | {h['cost']:.4f} |" for h in s["history"]]
        md += [""]
    write_stage_files(out, result.calibration, summary, md, REPORT_JSON, REPORT_MD)
    return summary
