"""The calibration parameters of a rig and the poses they imply (paper eq. 10-12), in plain torch.

``RigCalibration`` holds, for every sensor, its prior extrinsic and time offset, and for every non-reference
sensor one extrinsic correction (rotation vector + translation, metres) and one time-offset correction
(seconds). Given a frame (sensor ``i``, own-clock stamp ``t``) it returns ``T_r(t + delta_i) @ ref_T_i``, a
differentiable function of the corrections, so a loss on anything rendered from that pose reaches them.

It does not import nerfstudio: the nerfstudio glue (``moisst_ns.calibration_optimizer``) maps these metric poses
into nerfstudio's normalised OpenGL world.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np
import roma
import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.world import WorldFrame
from moisst_ns.rig.geometry import (
    ReferenceTrajectory,
    calibrated_extrinsic,
    calibration_errors,
    interpolate_trajectory,
    sensor_pose,
)


@dataclass
class RigData:
    """Everything the calibration needs from a dataset, as numpy arrays (picklable, framework-free)."""

    sensor_names: List[str]
    """All sensors, in a fixed order; their index is the sensor index used everywhere."""
    sensor_types: List[str]
    """``camera`` or ``lidar`` per sensor."""
    reference_index: int
    """Index of the reference sensor."""
    prior_extrinsics: np.ndarray
    """(S, 4, 4) prior ``ref_T_i``, metres."""
    prior_time_offsets: np.ndarray
    """(S,) prior delta_i, seconds."""
    trajectory_stamps: np.ndarray
    """(K,) absolute reference-clock stamps of the trajectory samples."""
    trajectory_positions: np.ndarray
    """(K, 3) ``world_t_ref``."""
    trajectory_quats_xyzw: np.ndarray
    """(K, 4) ``world_q_ref``."""
    t0: float
    """Time origin, seconds (the first trajectory stamp): all relative times are ``stamp - t0``."""
    ground_truth: Optional[Calibration] = None
    """True calibration when the dataset ships ground_truth.json (for metrics only, never optimised against)."""
    dataset_priors: Optional[Calibration] = None
    """rig.json's priors when the run started from others (``dataparser.prior_calibration``: the LiDAR-first
    stage's estimate); None when ``prior_extrinsics`` are rig.json's."""
    trajectory_T_reference: Optional[np.ndarray] = None
    """The reference sensor's pose in the frame rig.json's trajectory is given in, when the stages found them to differ
    (``Calibration.trajectory_T_reference``); the trajectory arrays here are already carried to the reference sensor."""
    rig: Optional[Rig] = None
    """The loaded dataset (frames and files: the datamanager reads the LiDAR scans from it, not rig.json again)."""
    world: Optional[WorldFrame] = None
    """The normalisation into nerfstudio's model frame (set by the dataparser)."""
    frame_sensor_index: Optional[np.ndarray] = None
    """(F,) sensor index of every training camera frame, in the dataparser's camera order (set by the dataparser)."""
    frame_stamps: Optional[np.ndarray] = None
    """(F,) own-clock stamp of every training camera frame, seconds since ``t0`` (set by the dataparser)."""

    @classmethod
    def from_rig(cls, rig: Rig, ground_truth: Optional[Calibration] = None) -> "RigData":
        names = rig.sensor_names
        return cls(
            sensor_names=names,
            sensor_types=[rig.sensors[n].type for n in names],
            reference_index=names.index(rig.reference_sensor),
            prior_extrinsics=np.stack([rig.sensors[n].T_ref_sensor for n in names]),
            prior_time_offsets=np.array([rig.sensors[n].time_offset for n in names], dtype=np.float64),
            trajectory_stamps=rig.trajectory_stamps,
            trajectory_positions=rig.trajectory_positions,
            trajectory_quats_xyzw=rig.trajectory_quats_xyzw,
            t0=float(rig.trajectory_stamps[0]),
            ground_truth=ground_truth,
            rig=rig,
        )

    def trajectory(self) -> ReferenceTrajectory:
        return ReferenceTrajectory.from_tum(self.trajectory_stamps, self.trajectory_positions, self.trajectory_quats_xyzw, self.t0)


class RigCalibration(nn.Module):
    """Extrinsic and time-offset corrections of every non-reference sensor (paper eq. 12's unknowns).

    Parameters (float32, one row per sensor, the reference's row is held at zero):
    ``rotvec`` (S, 3) radians, ``translation`` (S, 3) metres, ``time_offset`` (S,) seconds: corrections added to the
    priors. Poses are computed in float64.
    """

    def __init__(self, data: RigData):
        super().__init__()
        self.data = data
        num = len(data.sensor_names)
        traj = data.trajectory()
        self.register_buffer("traj_times", traj.times, persistent=False)
        self.register_buffer("traj_rotations", traj.rotations, persistent=False)
        self.register_buffer("traj_translations", traj.translations, persistent=False)
        self.register_buffer("prior_extrinsics", torch.as_tensor(data.prior_extrinsics, dtype=torch.float64), persistent=False)
        self.register_buffer("prior_time_offsets", torch.as_tensor(data.prior_time_offsets, dtype=torch.float64), persistent=False)
        trainable = torch.ones(num, dtype=torch.bool)
        trainable[data.reference_index] = False
        self.register_buffer("trainable", trainable, persistent=False)
        self.rotvec = nn.Parameter(torch.zeros(num, 3))
        self.translation = nn.Parameter(torch.zeros(num, 3))
        self.time_offset = nn.Parameter(torch.zeros(num))

    def _masked(self, param: Tensor) -> Tensor:
        mask = self.trainable.to(param.dtype)
        return param * (mask if param.dim() == 1 else mask[:, None])

    def extrinsics(self) -> Float[Tensor, "num_sensors 4 4"]:
        """Current ``ref_T_i`` of every sensor (the reference's is the identity), float64, metres."""
        return calibrated_extrinsic(self.prior_extrinsics, self._masked(self.rotvec), self._masked(self.translation))

    def time_offsets(self) -> Float[Tensor, "num_sensors"]:
        """Current delta_i of every sensor (the reference's is 0), float64, seconds."""
        return self.prior_time_offsets + self._masked(self.time_offset).to(torch.float64)

    def reference_pose(self, t: Float[Tensor, "*batch"]) -> Float[Tensor, "*batch 4 4"]:
        """``T_r(t)`` (paper eq. 1) at reference-clock times relative to ``t0``."""
        return interpolate_trajectory(self.traj_times, self.traj_rotations, self.traj_translations, t)

    def sensor_poses(
        self, sensor: Int[Tensor, "*batch"], stamp: Float[Tensor, "*batch"]
    ) -> Float[Tensor, "*batch 4 4"]:
        """Paper eq. 10: ``world_T_i = T_r(t + delta_i) @ ref_T_i`` for frames of sensor ``i`` stamped ``t``.

        Args:
            sensor: sensor index of each frame (or LiDAR point).
            stamp: its own-clock time relative to ``t0`` (float64), e.g. a frame stamp plus a per-point offset.

        Returns:
            ``world_T_sensor`` in metres, float64, differentiable w.r.t. the corrections.
        """
        deltas = self.time_offsets()[sensor]
        extrinsics = self.extrinsics()[sensor]
        return sensor_pose(self.reference_pose(stamp.to(torch.float64) + deltas), extrinsics)

    def prior_sensor_poses(self, sensor: Int[Tensor, "*batch"], stamp: Float[Tensor, "*batch"]) -> Float[Tensor, "*batch 4 4"]:
        """Eq. 2 with the priors (what the dataset says before calibration)."""
        ref = self.reference_pose(stamp.to(torch.float64) + self.prior_time_offsets[sensor])
        return sensor_pose(ref, self.prior_extrinsics[sensor])

    @torch.no_grad()
    def clamp_(self, max_translation: float, max_rotation: float, max_time_offset: float) -> None:
        """Project the corrections back into their bounds (metres, radians, seconds; <= 0 means unbounded)."""
        if max_translation > 0:
            self.translation.clamp_(-max_translation, max_translation)
        if max_rotation > 0:
            norm = self.rotvec.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            self.rotvec.mul_(torch.clamp(max_rotation / norm, max=1.0))
        if max_time_offset > 0:
            self.time_offset.clamp_(-max_time_offset, max_time_offset)

    @torch.no_grad()
    def set_corrections_to(self, calibration: Calibration) -> None:
        """Set every non-reference sensor's corrections so that the current calibration is ``calibration`` (eq. 12
        inverted): ``R = R_prior Exp(w)`` gives ``w = Log(R_prior^T R)``, ``t = t_prior + v`` gives
        ``v = t - t_prior``, and the offset correction is ``delta - delta_prior``.

        Args:
            calibration: extrinsics and time offsets of (at least) every non-reference sensor, same reference.
        """
        for i, name in enumerate(self.data.sensor_names):
            if i == self.data.reference_index:
                continue
            target = torch.as_tensor(calibration.T_ref_sensor[name], dtype=torch.float64, device=self.prior_extrinsics.device)
            prior = self.prior_extrinsics[i]
            self.rotvec[i] = roma.rotmat_to_rotvec(prior[:3, :3].T @ target[:3, :3]).to(self.rotvec)
            self.translation[i] = (target[:3, 3] - prior[:3, 3]).to(self.translation)
            self.time_offset[i] = float(calibration.time_offset[name]) - float(self.prior_time_offsets[i])

    @torch.no_grad()
    def estimate(self) -> Calibration:
        """The current calibration, metres and seconds in the dataset frame."""
        ext = self.extrinsics().cpu().numpy()
        off = self.time_offsets().cpu().numpy()
        names = self.data.sensor_names
        return Calibration(names[self.data.reference_index], {n: ext[i] for i, n in enumerate(names)}, {n: float(off[i]) for i, n in enumerate(names)},
                           trajectory_T_reference=self.data.trajectory_T_reference)

    @torch.no_grad()
    def errors(self) -> Optional[Dict[str, Dict[str, float]]]:
        """Per-sensor errors against the ground truth, when known: translation (cm), rotation (deg), time (ms)."""
        return calibration_report_errors(self.estimate(), self.data.ground_truth) if self.data.ground_truth else None


def calibration_report_errors(estimate: Calibration, truth: Calibration) -> Dict[str, Dict[str, float]]:
    """Translation error (cm, L2), rotation error (deg, geodesic) and time error (ms, absolute) per sensor.

    Args:
        estimate: an estimated calibration.
        truth: the ground truth (same reference sensor).

    Returns:
        ``{sensor: {"translation_cm", "rotation_deg", "time_ms"}}`` for every sensor present in both.
    """
    if estimate.reference_sensor != truth.reference_sensor:
        raise ValueError(f"reference sensors differ: {estimate.reference_sensor!r} vs {truth.reference_sensor!r}")
    out = {}
    for name, est in estimate.T_ref_sensor.items():
        if name not in truth.T_ref_sensor:
            continue
        trans, rot = calibration_errors(torch.as_tensor(est, dtype=torch.float64), torch.as_tensor(truth.T_ref_sensor[name], dtype=torch.float64))
        out[name] = {
            "translation_cm": float(trans) * 100.0,
            "rotation_deg": float(rot),
            "time_ms": abs(estimate.time_offset[name] - truth.time_offset[name]) * 1000.0,
        }
    return out


def frame_poses(data: RigData, calibration: Calibration, sensor: str, stamps: np.ndarray) -> Float[Tensor, "num_frames 4 4"]:
    """Eq. 2 with a given calibration: ``world_T_sensor`` of a sensor's frames (metres, float64).

    Args:
        data: the rig (its reference trajectory).
        calibration: extrinsics and time offsets to use (an estimate, the priors or the truth).
        sensor: sensor name.
        stamps: (N,) the frames' own-clock timestamps, absolute seconds.

    Returns:
        (N, 4, 4) poses.
    """
    traj = data.trajectory()
    t = torch.as_tensor(np.asarray(stamps, dtype=np.float64) - data.t0 + calibration.time_offset[sensor])
    return sensor_pose(traj(t), torch.as_tensor(calibration.T_ref_sensor[sensor], dtype=torch.float64))


def frame_pose_errors(
    poses: Float[Tensor, "num_frames 4 4"], truth: Float[Tensor, "num_frames 4 4"]
) -> Dict[str, float]:
    """Per-frame pose errors (paper Table VI): mean and std over frames of the translation (cm) and rotation (deg)
    distance between estimated and true ``world_T_sensor``.

    Args:
        poses: estimated poses of a sensor's frames.
        truth: their true poses.

    Returns:
        ``{"translation_cm", "translation_cm_std", "rotation_deg", "rotation_deg_std"}``.
    """
    trans, rot = calibration_errors(poses.to(torch.float64), truth.to(torch.float64))
    trans = trans * 100.0
    return {"translation_cm": float(trans.mean()), "translation_cm_std": float(trans.std(unbiased=False)),
            "rotation_deg": float(rot.mean()), "rotation_deg_std": float(rot.std(unbiased=False))}
