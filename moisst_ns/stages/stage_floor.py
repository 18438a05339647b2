"""The floor of the pre-NeRF stages: where LiDAR-first and the camera registration settle when started at the truth.

``moisst-calibrate`` calibrates a rig with a LiDAR (or a camera reference) in two stages before any NeRF step: each
LiDAR from its own scans (``lidar_first``), then each camera against the map those scans make (``camera_registration``).
Started at the true calibration, a stage's fit moves only as far as its losses' minimum is from the truth: that
distance is the floor of the calibration as it is now done, the counterpart of ``moisst_ns.floor``'s NeRF floor (the
scene trained at the truth). The guards are not asked: a fit started at the truth is never significantly better than
its prior, so the floor is the fit's last estimate (``CameraResult.history``), not the guarded result.

The geometry the cameras register against is the LiDAR map; ``map_depth_errors`` measures it where the fit looks
(the image-gradient-weighted map points each camera frame sees through the z-buffer, at the true poses) against the
true surface along the same rays, given a ray caster of the true scene. Nothing here imports nerfstudio.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch
from jaxtyping import Float

from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig, camera_sensors, register_cameras
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, calibrate_lidars, lidar_sensors
from moisst_ns.stages.camera.lidar_map import lidar_map
from moisst_ns.stages.camera.photometric import Registration

RayCaster = Callable[[Float[np.ndarray, "num 3"], Float[np.ndarray, "num 3"]], Float[np.ndarray, "num"]]
"""``(origins m, unit directions) -> distance to the true surface along each ray, m (inf on a miss)``."""


def rig_at(rig: Rig, calibration: Calibration) -> Rig:
    """The same rig with every sensor's prior (extrinsic and time offset) replaced by ``calibration``'s."""
    sensors = {name: dataclasses.replace(spec, T_ref_sensor=np.asarray(calibration.T_ref_sensor[name], dtype=np.float64),
                                         time_offset=float(calibration.time_offset[name]))
               for name, spec in rig.sensors.items()}
    return dataclasses.replace(rig, sensors=sensors)


def stage_floor(rig: Rig, truth: Calibration, cameras: Optional[Sequence[str]] = None,
                log: Callable[[str], None] = print) -> Dict[str, object]:
    """Run both stages, with their default settings, from the true calibration and report how far their fits move
    from it. The camera registration's feature start is switched off (it is for the basin, and the start is the truth
    here), and so are the split-half and typical-error tests.

    Args:
        rig: the dataset (its priors are ignored).
        truth: the true calibration (``ground_truth.json``).
        cameras: the cameras to fit (default: every non-reference camera).
        log: where progress lines go.

    Returns:
        ``{"floor": {sensor: {"translation_cm", "rotation_deg", "time_ms"}}, "unfitted": [cameras that did not fit,
        with the reason], "lidar_s", "camera_s"}``.
    """
    at_truth = rig_at(rig, truth)
    start = time.perf_counter()
    lidars = lidar_sensors(at_truth)
    calibration = calibrate_lidars(at_truth, LidarFirstConfig(), log=log).calibration if lidars else Calibration.from_rig(at_truth)
    lidar_s = time.perf_counter() - start
    # the guards' extra solves and draws come after the descent and are not asked here
    config = CameraRegistrationConfig(feature_start=False, split_half=False, min_significance=0.0)
    floor = Calibration(truth.reference_sensor, dict(calibration.T_ref_sensor), dict(calibration.time_offset))
    unfitted: List[str] = []
    fitted = set(lidars)
    if camera_sensors(at_truth):
        # the map from the LiDAR at the truth: the camera floor is the camera stage's own, not LiDAR-first's
        result = register_cameras(at_truth, Calibration.from_rig(at_truth), config, sensors=cameras, log=log)
        for name, r in result.cameras.items():
            if not r.history:  # it did not fit (no map in view, too few frames): no floor to report
                unfitted.append(f"{name}: {r.note}")
                continue
            last = r.history[-1]  # the fit's last estimate, whatever the guards said
            floor.T_ref_sensor[name], floor.time_offset[name] = np.asarray(last["T_ref_sensor"]), float(last["time_offset"])
            fitted.add(name)
    errors = {name: e for name, e in calibration_report_errors(floor, truth).items() if name in fitted}
    return {"floor": errors, "unfitted": unfitted, "lidar_s": lidar_s, "camera_s": time.perf_counter() - start - lidar_s}


def map_depth_errors(rig: Rig, truth: Calibration, cast: RayCaster, frame_step: int = 5) -> Dict[str, float]:
    """Depth errors of the LiDAR map where the cameras' fits look, against the true surface.

    For every camera (the reference too) and every ``frame_step``-th frame, at the true calibration: the map points the
    fit would sample there (``Registration.pairs`` at full resolution: visible through the z-buffer, weighted by the
    image gradient), each compared with the true surface along the ray from the camera centre through it.

    Args:
        rig: the dataset, with at least one LiDAR.
        truth: the true calibration (the map and the camera poses are built from it).
        cast: the true scene's ray caster.
        frame_step: use every this many frames of each camera.

    Returns:
        ``{"map_points", "camera_rays", "median_abs_m", "p90_abs_m"}`` over the rays that hit a true surface.
    """
    config = CameraRegistrationConfig()
    at_truth = rig_at(rig, truth)
    world = lidar_map(at_truth, truth, config.map_voxel, config.min_range, log=lambda s: None)
    traj = ReferenceTrajectory.of(rig)
    errors = []
    for name, spec in rig.sensors.items():
        if spec.type != "camera":
            continue
        camera = CameraFrames.of(at_truth, name, [1])
        problem = Registration(traj, world, camera, None, truth, config)
        pairs = problem.pairs(np.zeros(7), 1, config.points_per_frame)
        keep = pairs.frame_a % frame_step == 0
        poses = problem.model.poses(torch.zeros(7, dtype=torch.float64)).numpy()
        origins = poses[pairs.frame_a[keep], :3, 3]
        rays = pairs.points[keep] - origins
        distance = np.linalg.norm(rays, axis=1)
        hit = cast(origins, rays / distance[:, None])
        ok = np.isfinite(hit)
        errors.append(np.abs(distance[ok] - hit[ok]))
    return {"map_points": len(world), **depth_error_stats(np.concatenate(errors) if errors else np.zeros(0))}


def depth_error_stats(errors: Float[np.ndarray, "num"]) -> Dict[str, float]:
    """``{"camera_rays", "median_abs_m", "p90_abs_m"}`` of absolute depth errors (metres; NaN figures when empty)."""
    if not errors.size:
        return {"camera_rays": 0, "median_abs_m": float("nan"), "p90_abs_m": float("nan")}
    return {"camera_rays": int(errors.size), "median_abs_m": float(np.median(errors)), "p90_abs_m": float(np.percentile(errors, 90))}
