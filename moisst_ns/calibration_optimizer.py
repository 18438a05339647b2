"""``CalibrationOptimizer``: nerfstudio's ``CameraOptimizer`` with MOISST's rig parameterisation (paper eq. 10-12).

Instead of one free pose correction per training frame, it holds one SE(3) correction and one time offset per
non-reference sensor (``moisst_ns.rig.calibration.RigCalibration``) and regenerates every training ray from
``T_r(t + delta_i) @ ref_T_i``. Being a ``CameraOptimizer``, nerfstudio's training viewer draws calibrated frusta
and ``ns-export cameras`` writes calibrated per-frame poses without further glue.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple, Type, Union

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle

from moisst_ns.rig.calibration import RigCalibration, RigData
from moisst_ns.rig.geometry import pose_to_xyz_rpy


@dataclass
class CalibrationOptimizerConfig(CameraOptimizerConfig):
    """Rig calibration: one extrinsic correction and one time offset per non-reference sensor (nerfstudio's inherited
    ``mode`` is not read: ``optimize_extrinsics``, ``optimize_time_offsets`` and ``frozen_sensors`` hold it)."""

    _target: Type = field(default_factory=lambda: CalibrationOptimizer)
    optimize_extrinsics: bool = True
    """Optimise the extrinsics (paper Table I / V: spatial)."""
    optimize_time_offsets: bool = True
    """Optimise the time offsets (paper Table II / V: temporal)."""
    max_translation: float = 2.0
    """Bound on each axis of the translation correction, metres (<= 0: unbounded)."""
    max_rotation_deg: float = 30.0
    """Bound on the rotation correction's angle, degrees (<= 0: unbounded)."""
    max_time_offset: float = 0.3
    """Bound on the time-offset correction, seconds (<= 0: unbounded)."""
    frozen_sensors: Tuple[str, ...] = ()
    """Sensors held at their priors (e.g. LiDARs calibrated by the LiDAR-first stage, whose estimate the NeRF's
    losses would only pull away from)."""


class CalibrationOptimizer(CameraOptimizer):
    """Rig-level pose optimiser. ``rig`` is None only in the instance nerfacto's ``populate_modules`` builds and
    ``MoisstModel`` replaces at once (never used)."""

    config: CalibrationOptimizerConfig

    def __init__(
        self,
        config: CalibrationOptimizerConfig,
        num_cameras: int,
        device: Union[torch.device, str],
        rig: Optional[RigData] = None,
        **kwargs,
    ) -> None:
        super().__init__(config, num_cameras, device)  # nerfstudio's (its own parameters only with a ``mode`` not "off")
        self.rig: Optional[RigCalibration] = None
        if rig is None:
            return
        self.rig = RigCalibration(rig)
        for name in self.config.frozen_sensors:
            if name not in rig.sensor_names:
                raise ValueError(f"frozen_sensors: {name!r} is not a sensor of the rig {rig.sensor_names}")
            self.rig.trainable[rig.sensor_names.index(name)] = False
        if rig.frame_sensor_index is None or rig.frame_stamps is None or rig.world is None:
            raise ValueError("the rig's camera frames and world frame are not set (build RigData with the moisst-rig dataparser)")
        frame_sensor = torch.as_tensor(rig.frame_sensor_index, dtype=torch.long)
        if frame_sensor.shape[0] != num_cameras:
            raise ValueError(f"rig has {frame_sensor.shape[0]} camera frames, the dataset {num_cameras}")
        self.register_buffer("frame_sensor", frame_sensor, persistent=False)
        self.register_buffer("frame_stamps", torch.as_tensor(rig.frame_stamps, dtype=torch.float64), persistent=False)
        self.world = rig.world
        self.world_scale = float(rig.world.scale)
        with torch.no_grad():
            self.register_buffer("prior_c2w", self.frame_c2w(torch.arange(num_cameras), prior=True), persistent=False)
        self.set_trainable(True)

    # --- parameter handling -------------------------------------------------------------------------------------

    def set_trainable(self, enabled: bool) -> None:
        """Freeze or release the calibration (used by the warm-up schedule)."""
        self.rig.rotvec.requires_grad_(enabled and self.config.optimize_extrinsics)
        self.rig.translation.requires_grad_(enabled and self.config.optimize_extrinsics)
        self.rig.time_offset.requires_grad_(enabled and self.config.optimize_time_offsets)

    def project(self) -> None:
        """Keep the corrections inside their bounds (call after every optimiser step)."""
        self.rig.clamp_(self.config.max_translation, np.deg2rad(self.config.max_rotation_deg), self.config.max_time_offset)

    # --- poses --------------------------------------------------------------------------------------------------

    def frame_c2w(self, indices: Int[Tensor, "num"], prior: bool = False, row_time: Optional[Float[Tensor, "num"]] = None) -> Float[Tensor, "num 4 4"]:
        """Calibrated (or prior) camera-to-world of training frames, nerfstudio frame, float64 (eq. 10); with ``row_time``
        (seconds after each frame's stamp: a rolling-shutter row's, ``geometry.row_time``) at those times."""
        assert self.rig is not None
        indices = indices.to(self.frame_sensor.device)
        sensor, stamp = self.frame_sensor[indices], self.frame_stamps[indices]
        if row_time is not None:
            stamp = stamp + row_time.to(stamp)
        fn = self.rig.prior_sensor_poses if prior else self.rig.sensor_poses
        return self.world.camera_to_model(fn(sensor, stamp))  # metric OpenCV -> nerfstudio's normalised OpenGL

    def forward(self, indices: Int[Tensor, "camera_indices"]) -> Float[Tensor, "camera_indices 3 4"]:
        """Per training frame, ``prior_c2w^-1 @ calibrated_c2w`` (a 3x4 in the camera frame), as the viewer expects."""
        if indices.numel() == 0:
            return torch.eye(4, device=indices.device)[None, :3, :4].tile(indices.shape[0], 1, 1)
        indices = indices.reshape(-1).long()
        delta = torch.linalg.inv(self.prior_c2w[indices.to(self.prior_c2w.device)]) @ self.frame_c2w(indices)
        return delta[:, :3, :4].float()

    def apply_to_raybundle(self, raybundle: RayBundle) -> None:
        """Regenerate training rays from the current calibration (paper Fig. 2).

        Camera rays are re-posed exactly (origin to the calibrated centre, direction rotated by
        ``R_calibrated R_prior^T``), a rolling-shutter camera's onto the pose at its row's time
        (``metadata["row_time"]``, seconds after the stamp, set by ``MoisstDataManager``). LiDAR rays
        (``metadata["is_lidar"]``) are built from scratch: origin ``T_r(t + delta_L) @ ref_T_L`` at the point's own
        time, direction through the point.
        """
        if raybundle.camera_indices is None:
            return
        meta = raybundle.metadata
        rows = meta.get("row_time")
        if "is_lidar" not in meta or not bool(meta["is_lidar"].any()):
            raybundle.origins, raybundle.directions = self.camera_rays(raybundle.camera_indices, raybundle.origins, raybundle.directions, rows)
            return
        lid = meta["is_lidar"][:, 0]
        origins, directions = raybundle.origins.clone(), raybundle.directions.clone()
        if not bool(lid.all()):
            origins[~lid], directions[~lid] = self.camera_rays(raybundle.camera_indices[~lid], raybundle.origins[~lid], raybundle.directions[~lid],
                                                               None if rows is None else rows[~lid])
        origins[lid], directions[lid] = self.lidar_rays(meta["lidar_sensor"][lid, 0], meta["lidar_stamp"][lid, 0], meta["lidar_point"][lid])
        raybundle.origins, raybundle.directions = origins, directions

    def camera_rays(self, camera_indices: Int[Tensor, "num 1"], origins: Float[Tensor, "num 3"], directions: Float[Tensor, "num 3"],
                    row_time: Optional[Float[Tensor, "num 1"]] = None):
        """Re-pose camera rays generated at the prior poses (their frames' stamps) onto the calibrated poses, at
        ``row_time`` seconds after the stamps where given (a rolling shutter's rows)."""
        idx = camera_indices.reshape(-1).long()
        rows = torch.zeros(len(idx), dtype=torch.float64, device=idx.device) if row_time is None else row_time.reshape(-1)
        unique_key, inverse = torch.unique(torch.stack([idx.to(rows.dtype), rows], dim=-1), dim=0, return_inverse=True)  # (frame, row time)
        unique = unique_key[:, 0].long()
        calibrated = self.frame_c2w(unique, row_time=unique_key[:, 1])
        prior = self.prior_c2w[unique.to(self.prior_c2w.device)]
        rot = (calibrated[:, :3, :3] @ prior[:, :3, :3].transpose(-1, -2)).to(directions)[inverse]
        new_origins = origins - prior[inverse, :3, 3].to(origins) + calibrated[inverse, :3, 3].to(origins)
        return new_origins, (rot @ directions[..., None])[..., 0]

    def lidar_rays(
        self, sensor: Int[Tensor, "num"], stamp: Float[Tensor, "num"], points: Float[Tensor, "num 3"]
    ) -> Tuple[Float[Tensor, "num 3"], Float[Tensor, "num 3"]]:
        """LiDAR rays in the model frame: from the LiDAR centre at each point's time, through the point.

        Args:
            sensor: LiDAR sensor index per point.
            stamp: own-clock time of each point relative to t0 (frame stamp + per-point offset), float64.
            points: points in the LiDAR frame, metres.

        Returns:
            (origins, unit directions) in nerfstudio's normalised world; the range in model units is
            ``|point| * world_scale``.
        """
        assert self.rig is not None
        pose = self.rig.sensor_poses(sensor, stamp)
        origins = self.world.points_to_model(pose[:, :3, 3])
        dirs = (pose[:, :3, :3] @ points.to(pose.dtype)[..., None])[..., 0]
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        return origins.float(), dirs.float()

    def apply_to_camera(self, camera: Cameras) -> Tensor:
        """Calibrated camera-to-world (3x4) of a training camera carrying ``metadata["cam_idx"]``."""
        if camera.metadata is None or "cam_idx" not in camera.metadata:
            return camera.camera_to_worlds
        idx = torch.as_tensor([int(camera.metadata["cam_idx"])])
        return self.frame_c2w(idx)[:, :3, :4].to(camera.camera_to_worlds)

    # --- nerfstudio hooks ----------------------------------------------------------------------------------------

    def get_metrics_dict(self, metrics_dict: dict) -> None:
        """Per-sensor estimates and, with ground truth, errors (cm, deg, ms)."""
        metrics_dict.update({f"calib/{name}/{key}": value for name, values in self.sensor_summary().items() for key, value in values.items()})

    @torch.no_grad()
    def sensor_summary(self) -> Dict[str, Dict[str, float]]:
        """``{sensor: {x, y, z (m), roll, pitch, yaw (deg), delta_ms, [translation_cm, rotation_deg, time_ms]}}``."""
        assert self.rig is not None
        xyzrpy = pose_to_xyz_rpy(self.rig.extrinsics()).cpu().numpy()
        deltas = self.rig.time_offsets().cpu().numpy()
        errors = self.rig.errors() or {}
        out = {}
        for i, name in enumerate(self.rig.data.sensor_names):
            if i == self.rig.data.reference_index:
                continue
            entry = dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), map(float, xyzrpy[i])))
            entry["delta_ms"] = float(deltas[i] * 1000.0)
            if name in errors:
                entry.update({f"err_{k}": v for k, v in errors[name].items()})
            out[name] = entry
        return out

    @torch.no_grad()
    def change_summary(self) -> list:
        """One short string per non-reference sensor: current delta and change of the extrinsic from the prior."""
        assert self.rig is not None
        out = []
        deltas = self.rig.time_offsets()
        for i, name in enumerate(self.rig.data.sensor_names):
            if i == self.rig.data.reference_index:
                continue
            moved_cm = float(self.rig.translation[i].norm()) * 100.0
            turned_deg = float(np.rad2deg(float(self.rig.rotvec[i].norm())))
            out.append(f"{name} delta {float(deltas[i]) * 1000:+.1f} ms, moved {moved_cm:.1f} cm / {turned_deg:.2f} deg")
        return out

    def get_param_groups(self, param_groups: dict) -> None:
        param_groups["calibration_rotation"] = [self.rig.rotvec]
        param_groups["calibration_translation"] = [self.rig.translation]
        param_groups["calibration_time"] = [self.rig.time_offset]
