"""Rig geometry of MOISST (paper section III-A/B), in plain torch + roma.

Nothing here imports nerfstudio. All poses are 4x4 homogeneous matrices ``world_T_sensor`` (a point in the
sensor frame maps to the world frame), metres and seconds, in the dataset's own frame.

Paper equations, by name:

* eq. 1, ``interpolate_trajectory``: the continuous reference trajectory ``T_r(t)`` (SLERP on rotation, LERP on
  translation, extrapolated past both ends by continuing the first/last segment's motion).
* eq. 2, ``sensor_pose``: ``world_T_i(t + delta_i) = T_r(t + delta_i) @ ref_T_i``.
* eq. 10-12, ``calibrated_extrinsic`` + ``sensor_pose``: the pose every ray of sensor ``i`` is regenerated from,
  as a differentiable function of the calibration parameters (extrinsic correction and ``delta_i``).
* ``row_time``: a rolling-shutter camera's pixel row is captured at ``stamp + row_time(v)`` (docs/rig-format.md), so
  its pose is ``T_r(stamp + row_time(v) + delta_i) @ ref_T_i``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional, Tuple

import numpy as np
import roma
import torch
from jaxtyping import Float, Int
from torch import Tensor


def make_pose(rotation: Float[Tensor, "*batch 3 3"], translation: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 4 4"]:
    """The 4x4 rigid transforms ``[[R, t], [0, 0, 0, 1]]`` of rotations and translations (any batch shape)."""
    batch = rotation.shape[:-2]
    pose = torch.zeros(*batch, 4, 4, dtype=rotation.dtype, device=rotation.device)
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = translation
    pose[..., 3, 3] = 1.0
    return pose


@dataclass
class ReferenceTrajectory:
    """Samples of the reference sensor's trajectory ``world_T_ref`` (the input of paper eq. 1).

    Times are relative to ``t0`` (float64: float32 cannot hold epoch seconds to the millisecond).
    """

    times: Float[Tensor, "num_poses"]
    """Sample times on the reference clock, seconds since ``t0``, strictly increasing (float64)."""
    rotations: Float[Tensor, "num_poses 3 3"]
    """``world_R_ref`` at each sample."""
    translations: Float[Tensor, "num_poses 3"]
    """``world_t_ref`` at each sample, metres."""
    t0: float = 0.0
    """Absolute time (seconds, reference clock) that ``times`` are relative to."""
    _steps: Optional[Float[Tensor, "segments 3"]] = field(default=None, init=False, repr=False, compare=False)
    """``Log(R_k^T R_{k+1})`` per segment, radians (computed on the first call)."""

    @classmethod
    def from_tum(cls, stamps, positions, quats_xyzw, t0: float | None = None) -> "ReferenceTrajectory":
        """Build from TUM columns (absolute stamps, ``tx ty tz``, ``qx qy qz qw``).

        Args:
            stamps: (K,) absolute timestamps, seconds.
            positions: (K, 3) translations, metres.
            quats_xyzw: (K, 4) unit quaternions, x, y, z, w (roma's convention).
            t0: time origin; the first stamp when None.

        Returns:
            The trajectory, float64.
        """
        stamps = torch.as_tensor(stamps, dtype=torch.float64)
        t0 = float(stamps[0]) if t0 is None else float(t0)
        quats = roma.quat_normalize(torch.as_tensor(quats_xyzw, dtype=torch.float64))
        return cls(
            times=stamps - t0,
            rotations=roma.unitquat_to_rotmat(quats),
            translations=torch.as_tensor(positions, dtype=torch.float64),
            t0=t0,
        )

    @classmethod
    def of(cls, rig) -> "ReferenceTrajectory":
        """The trajectory of a loaded ``rig.format.Rig`` (its TUM file's columns), ``t0`` its first stamp."""
        return cls.from_tum(rig.trajectory_stamps, rig.trajectory_positions, rig.trajectory_quats_xyzw)

    def __call__(self, t: Float[Tensor, "*batch"]) -> Float[Tensor, "*batch 4 4"]:
        """``T_r(t)``, paper eq. 1 (see ``interpolate_trajectory``), each segment's relative rotation computed once for
        the trajectory (``steps``: the same formula and values as per query time, faster for many)."""
        return interpolate_trajectory(self.times, self.rotations, self.translations, t, self.steps())

    def steps(self) -> Float[Tensor, "segments 3"]:
        """``Log(R_k^T R_{k+1})`` of every segment, radians (computed once)."""
        if self._steps is None:
            self._steps = roma.rotmat_to_rotvec(self.rotations[:-1].transpose(-1, -2) @ self.rotations[1:])
        return self._steps

    def rates(self, t: Float[Tensor, "*batch"]) -> Tuple[Float[Tensor, "*batch 3"], Float[Tensor, "*batch 3"]]:
        """The time derivative of eq. 1 at ``t``: ``dR/dt = R [omega]x`` and ``dp/dt = velocity``, constant within a
        segment (as ``interpolate_trajectory`` picks it, extrapolation included).

        Args:
            t: query times, seconds since ``t0``.

        Returns:
            (body angular rate ``omega``, rad/s, in the reference frame; velocity, m/s, world frame).
        """
        seg = torch.clamp(torch.searchsorted(self.times, t.detach().to(self.times.dtype), right=True) - 1, 0, len(self.times) - 2)
        span = (self.times[seg + 1] - self.times[seg])[..., None]
        return self.steps()[seg] / span, (self.translations[seg + 1] - self.translations[seg]) / span

    def pose_and_rates(self, t: Float[np.ndarray, "num"]) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 1 and ``rates`` in numpy at times ``t`` (seconds since ``t0``; the LiDAR stage places every point with it).

        Returns:
            (``world_R_ref`` (num, 3, 3), ``world_t_ref`` (num, 3) metres, body angular rate rad/s, velocity m/s).
        """
        rotations, translations = self.rotations.numpy(), self.translations.numpy()
        seg, alpha = self._segments(t)
        rot = rotations[seg] @ roma.rotvec_to_rotmat(torch.from_numpy(alpha[:, None] * self.steps().numpy()[seg])).numpy()
        omega, velocity = self.rates(torch.from_numpy(np.asarray(t, dtype=np.float64)))
        return rot, translations[seg] + alpha[:, None] * (translations[seg + 1] - translations[seg]), omega.numpy(), velocity.numpy()

    def _segments(self, t: Float[np.ndarray, "num"]) -> Tuple[Int[np.ndarray, "num"], Float[np.ndarray, "num"]]:
        """Each time's segment ``k`` and ``a = (t - t_k) / (t_{k+1} - t_k)`` (eq. 1; the end segments extrapolate)."""
        times = self.times.numpy()
        seg = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
        return seg, (t - times[seg]) / (times[seg + 1] - times[seg])

    def placer(self, t: Float[np.ndarray, "num"]) -> Callable[[Float[np.ndarray, "num 3"]], Float[np.ndarray, "num 3"]]:
        """Eq. 1 at times ``t`` (seconds since ``t0``) as a function of reference-frame points (metres): ``q -> R(t) q +
        p(t)``, with ``Exp(a w_k)`` applied to each point by Rodrigues' formula and ``R_k`` per segment (no matrix per
        point: on KITTI 0048's 1.3 M points the LiDAR stage peaks at 1.07 GB, 1.50 GB with a matrix per point, 1.40 GB
        with ``roma.quat_action``'s intermediates). A caller that places many point sets seen at the same times (the
        LiDAR stage's grid search) keeps the function."""
        seg, alpha = self._segments(t)
        rotvec = alpha[:, None] * self.steps().numpy()[seg]
        angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
        axis = rotvec / np.where(angle > 0, angle, 1.0)
        cos, sin = np.cos(angle), np.sin(angle)
        rotations, translations = self.rotations.numpy(), self.translations.numpy()
        groups = [(rows, rotations[k].T, translations[k] + alpha[rows, None] * (translations[k + 1] - translations[k]))
                  for k in np.unique(seg) for rows in [np.flatnonzero(seg == k)]]

        def place(points: Float[np.ndarray, "num 3"]) -> Float[np.ndarray, "num 3"]:
            turned = points * cos + np.cross(axis, points) * sin + axis * (np.sum(axis * points, axis=1, keepdims=True) * (1 - cos))
            out = np.empty_like(turned)
            for rows, rotation_t, position in groups:
                out[rows] = turned[rows] @ rotation_t + position
            return out

        return place


def interpolate_trajectory(
    times: Float[Tensor, "num_poses"],
    rotations: Float[Tensor, "num_poses 3 3"],
    translations: Float[Tensor, "num_poses 3"],
    t: Float[Tensor, "*batch"],
    steps: Optional[Float[Tensor, "segments 3"]] = None,
) -> Float[Tensor, "*batch 4 4"]:
    """Paper eq. 1: the continuous reference trajectory ``world_T_ref(t) = T_r(t)``.

    Between the two bracketing samples ``k, k+1`` with ``a = (t - t_k) / (t_{k+1} - t_k)``:
    ``R(t) = R_k Exp(a Log(R_k^T R_{k+1}))`` (SLERP) and ``p(t) = (1 - a) p_k + a p_{k+1}`` (LERP). Before the
    first / after the last sample the first / last segment is used with ``a < 0`` / ``a > 1``, which continues
    that segment's motion at constant angular and linear velocity. Differentiable with respect to ``t``.

    Args:
        times: strictly increasing sample times.
        rotations: rotation at each sample.
        translations: translation at each sample.
        t: query times, same clock and origin as ``times``; any shape.
        steps: ``Log(R_k^T R_{k+1})`` of every segment, radians, when precomputed (None: computed per query).

    Returns:
        ``world_T_ref`` at each query time, in the dtype of ``rotations``.
    """
    num = times.shape[0]
    if num < 2:
        raise ValueError("interpolate_trajectory needs at least 2 poses")
    t = t.to(times.dtype)
    seg: Int[Tensor, "*batch"] = torch.clamp(torch.searchsorted(times, t.detach(), right=True) - 1, 0, num - 2)
    t_k = times[seg]
    alpha = (t - t_k) / (times[seg + 1] - t_k)
    rot_k = rotations[seg]
    rel_rotvec = roma.rotmat_to_rotvec(rot_k.transpose(-1, -2) @ rotations[seg + 1]) if steps is None else steps[seg]
    rot = rot_k @ roma.rotvec_to_rotmat(alpha[..., None].to(rel_rotvec.dtype) * rel_rotvec)
    trans = translations[seg] + alpha[..., None].to(translations.dtype) * (translations[seg + 1] - translations[seg])
    return make_pose(rot, trans)


def sensor_pose(
    ref_pose: Float[Tensor, "*batch 4 4"], ref_T_sensor: Float[Tensor, "*batch 4 4"]
) -> Float[Tensor, "*batch 4 4"]:
    """Paper eq. 2: ``world_T_i(t + delta_i) = T_r(t + delta_i) @ ref_T_i``.

    Args:
        ref_pose: ``T_r(t + delta_i)``, the reference pose at the sensor frame's reference-clock time.
        ref_T_sensor: the sensor's extrinsic, pose of the sensor in the reference sensor's frame.

    Returns:
        ``world_T_sensor``.
    """
    return ref_pose @ ref_T_sensor


def row_time(row: Float[Tensor, "*batch"], readout: float | Float[Tensor, "*batch"], height: int) -> Float[Tensor, "*batch"]:
    """Capture time of a pixel row of a rolling-shutter image, seconds from the frame's stamp.

    Rows are read top to bottom in ``readout`` seconds and the stamp is the middle row's time: pixel row ``r``
    (0-based, its centre at ``v = r + 0.5``) at ``readout (r - (H - 1) / 2) / (H - 1)``, i.e. a point at continuous row
    coordinate ``v`` at ``readout (v - H / 2) / (H - 1)`` (``moisst-synth``'s ``row_time_offsets``). Pure arithmetic:
    torch tensors and numpy arrays alike; ``readout = 0`` (global shutter) gives 0 everywhere.

    Args:
        row: row coordinates ``v`` in the stored image's pixels (continuous from the top edge, the first row's centre at
            0.5; distorted pixels for an ``OPENCV`` camera).
        readout: the camera's ``readout_time``, seconds from the first row to the last (>= 0).
        height: the image's height ``H``, pixels (as stored, full resolution).

    Returns:
        Seconds to add to the frame's stamp (negative above the middle row).
    """
    return readout * (row - height / 2.0) / max(height - 1, 1)


ROW_ITERATIONS = 3
"""Fixed-point iterations of ``row_times``. Each shrinks the error by the fraction of the image height a point's
projection moves during one readout (under 0.1 for tens of ms on a vehicle): three leave it well under 0.01 px."""


def row_times(rows_at: Callable[[Float[Tensor, "*batch"]], Float[Tensor, "*batch"]], readout: float | Float[Tensor, "*batch"],
              height: int) -> Float[Tensor, "*batch"]:
    """The capture time of points seen by a rolling-shutter camera: ``tau = row_time(rows_at(tau))``.

    A point's row depends on the pose it is projected from, which depends on the row's time: the fixed point is found
    by iterating from the stamp (``tau = 0``, the global-shutter projection). Torch tensors and numpy arrays alike.

    Args:
        rows_at: ``tau -> v``: each point's row (stored image's pixels, as ``row_time`` takes it) when projected from
            the camera's pose at ``stamp + tau`` (``tau`` seconds; called with the scalar ``0.0`` first).
        readout: the camera's readout time, seconds.
        height: the image's height, pixels.

    Returns:
        ``tau`` per point, seconds from the stamp (the last iterate).
    """
    tau = row_time(rows_at(0.0), readout, height)
    for _ in range(ROW_ITERATIONS - 1):
        tau = row_time(rows_at(tau), readout, height)
    return tau


def calibrated_extrinsic(
    prior: Float[Tensor, "*batch 4 4"], rotvec: Float[Tensor, "*batch 3"], translation: Float[Tensor, "*batch 3"]
) -> Float[Tensor, "*batch 4 4"]:
    """The extrinsic ``ref_T_i`` being optimised in paper eq. 12: a prior plus a correction.

    ``R = R_prior Exp(rotvec)`` (rotation correction in the sensor's own frame) and ``t = t_prior + translation``
    (translation correction in the reference frame, metres). Zero correction gives the prior exactly.

    Args:
        prior: prior extrinsics.
        rotvec: rotation corrections as rotation vectors, radians.
        translation: translation corrections, metres, reference frame.

    Returns:
        The corrected extrinsics.
    """
    rot = prior[..., :3, :3] @ roma.rotvec_to_rotmat(rotvec.to(prior.dtype))
    return make_pose(rot, prior[..., :3, 3] + translation.to(prior.dtype))


def calibration_errors(
    estimate: Float[Tensor, "*batch 4 4"], truth: Float[Tensor, "*batch 4 4"]
) -> Tuple[Float[Tensor, "*batch"], Float[Tensor, "*batch"]]:
    """Errors of an extrinsic, as the paper reports them (section IV).

    Args:
        estimate: estimated ``ref_T_i``.
        truth: true ``ref_T_i``.

    Returns:
        (translation error in metres, L2 norm; rotation error in degrees, geodesic distance).
    """
    trans = torch.linalg.norm(estimate[..., :3, 3] - truth[..., :3, 3], dim=-1)
    rot = torch.rad2deg(roma.rotmat_geodesic_distance(estimate[..., :3, :3], truth[..., :3, :3]))
    return trans, rot


def pose_to_xyz_rpy(pose: Float[Tensor, "*batch 4 4"]) -> Float[Tensor, "*batch 6"]:
    """x, y, z (metres) and roll, pitch, yaw (degrees, extrinsic XYZ = R = Rz(yaw) Ry(pitch) Rx(roll)).

    Args:
        pose: rigid transforms.

    Returns:
        ``[x, y, z, roll, pitch, yaw]``.
    """
    rpy = roma.rotmat_to_euler("XYZ", pose[..., :3, :3], degrees=True)
    return torch.cat([pose[..., :3, 3], rpy], dim=-1)
