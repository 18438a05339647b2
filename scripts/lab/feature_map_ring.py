"""A camera-only rig's forward-right camera on the reference camera's feature map with other rings around each
feature (``FeatureMapConfig.patch_points`` x ``patch_radius_px``: 8 x 1 px, 8 x 3 px, none; the default is 8 x 2 px,
which ``scripts/camera_stage.py`` gives): each parameter's error and the stage's sigma, in mm, mrad and ms.

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/feature_map_ring.py RIG
(docs/lab/2026-12-07-sift-keypoint-bias.md ran it with docs/lab/2026-12-07-pyrdown-centres.patch applied.)
"""
import dataclasses
import sys
from pathlib import Path

import numpy as np
import roma
import torch

import moisst_ns.stages.camera.camera_registration as registration
from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.trust import PARAMETERS
from moisst_ns.stages.camera.camera_map import FeatureMapConfig
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig, register_cameras
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER

folder, name = Path(sys.argv[1]), "cam_front_right"
rig, truth = load_rig(folder), load_calibration(folder / "ground_truth.json")
for count, radius in [(8, 1.0), (8, 3.0), (0, 2.0)]:
    registration.FeatureMapConfig = dataclasses.make_dataclass(
        "Ring", [("patch_points", int, dataclasses.field(default=count)), ("patch_radius_px", float, dataclasses.field(default=radius))],
        bases=(FeatureMapConfig,))
    r = register_cameras(rig, Calibration.from_rig(rig), CameraRegistrationConfig(), sensors=[name], log=lambda s: None).cameras[name]
    true_T, est_T = np.asarray(truth.T_ref_sensor[name]), np.asarray(r.estimate)
    rotation = roma.rotmat_to_rotvec(torch.from_numpy(est_T[:3, :3].T @ true_T[:3, :3])).numpy()
    error = np.r_[est_T[:3, 3] - true_T[:3, 3], rotation, r.time_offset - truth.time_offset[name]]
    sigma = np.array([r.sigma[j] for j in JACOBIAN_ORDER])
    print(f"{count} x {radius:g} px{' (prior kept)' if r.kept_prior else ''}: "
          + " ".join(f"{p} {e * 1e3:.2f} ({s * 1e3:.2f})" for p, e, s in zip(PARAMETERS, error, sigma)), flush=True)
