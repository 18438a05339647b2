"""Paper eq. 1-2 per LiDAR point, vectorised in numpy, and its analytic Jacobian (for the LiDAR-first stage).

``place_points`` is ``x = T_r(t + delta) @ ref_T_L @ p`` for every point at its own firing time, eq. 1 being
``ReferenceTrajectory.placer``; the Jacobian evaluates ``ReferenceTrajectory.pose_and_rates`` once per distinct time.
No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Tuple, Union

import numpy as np
import roma
import torch
from jaxtyping import Float, Int

from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import parameter_difference


@dataclass
class PointTimes:
    """Per-point times kept as indices into their distinct values: a sweep fires a few thousand distinct times for
    tens of thousands of points (a compensated scan one), so eq. 1 is evaluated once per distinct time."""

    unique: Float[np.ndarray, "num_unique"]
    index: Int[np.ndarray, "num"]

    @classmethod
    def of(cls, times: Float[np.ndarray, "num"]) -> "PointTimes":
        unique, index = np.unique(times, return_inverse=True)
        return cls(unique, index.reshape(-1))

    def __getitem__(self, selection) -> "PointTimes":
        """The selected points, keeping only the distinct times they use (a few hundred rows of a 100 k-point
        sweep must not evaluate the trajectory at all of its times)."""
        used, index = np.unique(self.index[selection], return_inverse=True)
        return PointTimes(self.unique[used], index.reshape(-1))

    def __len__(self) -> int:
        return len(self.index)


def trajectory_at(traj: ReferenceTrajectory, times, offset: float):
    """``traj.pose_and_rates(times + offset)`` for an array of times or ``PointTimes``."""
    if isinstance(times, PointTimes):
        return tuple(a[times.index] for a in traj.pose_and_rates(times.unique + offset))
    return traj.pose_and_rates(np.asarray(times) + offset)


def right_jacobian(rotvec: Float[np.ndarray, "3"]) -> Float[np.ndarray, "3 3"]:
    """Right Jacobian of SO(3)'s exponential: ``Exp(w + e) ~ Exp(w) Exp(J_r(w) e)``."""
    theta = float(np.linalg.norm(rotvec))
    k = np.array([[0.0, -rotvec[2], rotvec[1]], [rotvec[2], 0.0, -rotvec[0]], [-rotvec[1], rotvec[0], 0.0]])
    if theta < 1e-6:
        return np.eye(3) - 0.5 * k + k @ k / 6.0
    return np.eye(3) - (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * (k @ k)


@dataclass
class Extrinsic:
    """A LiDAR's calibration: ``ref_T_L`` as rotation + translation (metres) and ``delta_L`` (seconds)."""

    rotation: Float[np.ndarray, "3 3"]
    translation: Float[np.ndarray, "3"]
    time_offset: float

    def updated(self, increment: Float[np.ndarray, "7"]) -> "Extrinsic":
        """``R Exp(w)``, ``t + v``, ``delta + d`` for ``increment = (w, v, d)``."""
        rot = self.rotation @ roma.rotvec_to_rotmat(torch.from_numpy(np.asarray(increment[:3], dtype=np.float64))).numpy()
        return Extrinsic(rot, self.translation + increment[3:6], self.time_offset + float(increment[6]))

    def matrix(self) -> Float[np.ndarray, "4 4"]:
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = self.rotation, self.translation
        return pose


def prior_residuals(ext: Extrinsic, prior: Extrinsic, increment: Float[np.ndarray, "7"],
                    sigma: Float[np.ndarray, "7"]) -> Tuple[Float[np.ndarray, "7"], Float[np.ndarray, "7 7"]]:
    """How far ``ext.updated(increment)`` lies from ``prior``, per parameter in units of its prior sigma.

    Args:
        ext: the current estimate.
        prior: rig.json's extrinsic and delta.
        increment: ``(w, v, d)`` on ``ext`` (radians, metres, seconds; Jacobian order).
        sigma: prior standard deviation of each parameter, same order and units.

    Returns:
        ``(Log(R_p^T R), t - t_p, delta - delta_p) / sigma`` and its exact Jacobian in ``increment``
        (``J_r(r)^-1 J_r(w)`` for the rotation, identity for the rest, each row divided by its sigma).
    """
    moved = ext.updated(increment)
    apart = parameter_difference(prior.matrix(), prior.time_offset, moved.matrix(), moved.time_offset)  # PARAMETERS order
    diff = np.asarray(apart[3:6] + apart[:3] + apart[6:])
    jac = np.eye(7)
    jac[:3, :3] = np.linalg.solve(right_jacobian(diff[:3]), right_jacobian(np.asarray(increment[:3], dtype=np.float64)))
    return diff / sigma, jac / sigma[:, None]


def placer_at(traj: ReferenceTrajectory, times: Union[Float[np.ndarray, "num"], PointTimes], offset: float) -> Callable:
    """``traj.placer`` (eq. 1 as a function of reference-frame points) at each point's own time plus ``offset``."""
    at = times.unique[times.index] if isinstance(times, PointTimes) else np.asarray(times)
    return traj.placer(at + offset)


def place_points(traj: ReferenceTrajectory, ext: Extrinsic, points: Float[np.ndarray, "num 3"], times: Union[Float[np.ndarray, "num"], PointTimes],
                 placer: Optional[Callable] = None) -> Float[np.ndarray, "num 3"]:
    """Paper eq. 1-2 per point: ``x = T_r(t + delta) @ ref_T_L @ p``.

    Args:
        traj: the reference trajectory.
        ext: the LiDAR's calibration.
        points: points in the LiDAR frame, metres.
        times: each point's own-clock firing time, seconds since the trajectory's ``t0``.
        placer: ``placer_at(traj, times, ext.time_offset)`` when the caller keeps it (many extrinsics, one time offset).

    Returns:
        World points, metres.
    """
    return (placer or placer_at(traj, times, ext.time_offset))(points @ ext.rotation.T + ext.translation)


def placement_jacobian(
    traj: ReferenceTrajectory, ext: Extrinsic, increment: Float[np.ndarray, "7"], points: Float[np.ndarray, "num 3"],
    times: Union[Float[np.ndarray, "num"], PointTimes], normals: Float[np.ndarray, "num 3"],
) -> Tuple[Float[np.ndarray, "num"], Float[np.ndarray, "num 7"]]:
    """``n . x`` and its derivative with respect to ``increment = (w, v, d)`` of ``ext.updated(increment)``.

    With ``R_L = R_c Exp(w)``, ``q = R_L p + t_L``, ``x = R_r q + p_r`` at ``t + delta``:
    ``dx/dv = R_r``, ``dx/dw = -R_r R_L [p]x J_r(w)``, ``dx/dd = R_r [omega]x q + velocity`` (omega the body rate of
    the trajectory segment, eq. 1's SLERP).

    Args:
        traj, ext: trajectory and the calibration being linearised around.
        increment: the current increment.
        points, times: as in ``place_points``.
        normals: the direction each point is projected on (world frame).

    Returns:
        (``n . x`` per point, metres; its Jacobian, metres per radian / metre / second).
    """
    cur = ext.updated(increment)
    rot, trans, omega, vel = trajectory_at(traj, times, cur.time_offset)
    ref = points @ cur.rotation.T + cur.translation
    x = np.einsum("nij,nj->ni", rot, ref) + trans
    u = np.einsum("nji,nj->ni", rot, normals)  # R_r^T n
    jac = np.empty((len(points), 7))
    jac[:, :3] = np.cross(points, u @ cur.rotation) @ right_jacobian(np.asarray(increment[:3], dtype=np.float64))
    jac[:, 3:6] = u
    jac[:, 6] = np.einsum("ni,ni->n", u, np.cross(omega, ref)) + np.einsum("ni,ni->n", normals, vel)
    return np.einsum("ni,ni->n", normals, x), jac
