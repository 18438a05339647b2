"""Standard deviations of least-squares parameters from residuals and their Jacobian (Gauss-Newton / Fisher).

Per parameter the larger of the classical ``s^2 H^-1`` and the cluster-robust (sandwich, Liang & Zeger 1986, the
clusters e.g. the frames) estimate, ``H = J^T J``; inf along a direction ``H`` does not constrain; and what a camera
fitted to a LiDAR's map inherits from that LiDAR's sigma (``inherited_sigma``). docs/uncertainty.md, section 2,
explains and measures them. Pure numpy: nothing here imports nerfstudio.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from jaxtyping import Float, Int


@dataclass
class LeastSquaresSigma:
    """Standard deviations of the parameters of a least-squares fit."""

    sigma: Float[np.ndarray, "p"]
    """Reported standard deviation per parameter: max of classical and cluster-robust (parameter units)."""
    classical: Float[np.ndarray, "p"]
    """``sqrt(diag(s^2 H^-1))``."""


def least_squares_sigma(
    jacobian: Float[np.ndarray, "n p"], residuals: Float[np.ndarray, "n"], clusters: Int[np.ndarray, "n"],
) -> LeastSquaresSigma:
    """Classical and cluster-robust standard deviations at a least-squares solution.

    Args:
        jacobian: ``d r / d x`` (residual units per parameter unit).
        residuals: residuals at the solution.
        clusters: cluster label of every residual (residuals of one cluster may be correlated).

    Returns:
        ``LeastSquaresSigma``.
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    res = np.asarray(residuals, dtype=np.float64)
    n, p = jac.shape
    info = jac.T @ jac
    vals, vecs = np.linalg.eigh(info)
    keep = vals > 1e-10 * max(float(vals.max()), 1e-300)  # below: a direction H does not constrain (sigma inf)
    inv = (vecs[:, keep] / vals[keep]) @ vecs[:, keep].T
    free = np.abs(vecs[:, ~keep]).max(axis=1) > 1e-6 if (~keep).any() else np.zeros(p, dtype=bool)
    s2 = float(res @ res) / max(n - p, 1)
    classical = np.sqrt(np.maximum(np.diag(inv) * s2, 0.0))
    labels, index = np.unique(np.asarray(clusters), return_inverse=True)
    groups = len(labels)
    if groups >= 2:
        scores = np.zeros((groups, p))
        np.add.at(scores, index, jac * res[:, None])
        meat = scores.T @ scores * groups / (groups - 1)
        robust = np.sqrt(np.maximum(np.diag(inv @ meat @ inv), 0.0))
    else:
        robust = np.full(p, np.nan)
    sigma = np.fmax(classical, robust)
    sigma[free] = np.inf
    classical[free] = np.inf
    return LeastSquaresSigma(sigma, classical)


def inherited_sigma(ref_T_lidar: Float[np.ndarray, "4 4"], ref_T_camera: Float[np.ndarray, "4 4"],
                    lidar_sigma: Float[np.ndarray, "7"]) -> Float[np.ndarray, "7"]:
    """The standard deviations a camera registered against a LiDAR's map inherits from that LiDAR's own.

    A LiDAR placed with errors ``(v, w, d)`` (translation in the reference frame, rotation about its own axes, time
    offset) places every map point at ``p + v + [R_L w]x (p - t_L)`` (and ``d`` later along the drive): on a straight
    drive, a rigid move of the whole map, which a camera fitted to that map follows, ``v_c = v + [R_L w]x (t_c - t_L)``,
    ``w_c = R_c^T R_L w``, ``d_c = d``. Measured on KITTI raw 0048: the map 131 cm off took image_01 92 cm off while its
    own sigma said 3-5 cm. The LiDAR's parameters are taken independent (the variances add through the linear map), so
    this is the camera's error when it follows the map entirely: an upper bound where it follows it in part.

    Args:
        ref_T_lidar: the LiDAR's extrinsic.
        ref_T_camera: the camera's extrinsic.
        lidar_sigma: the LiDAR's sigma, trust order ``x, y, z, roll, pitch, yaw, time_offset`` (m, rad, s); inf allowed.

    Returns:
        The camera's inherited sigma, same order and units (inf where an infinite LiDAR sigma reaches it).
    """
    lever = np.asarray(ref_T_camera, dtype=np.float64)[:3, 3] - np.asarray(ref_T_lidar, dtype=np.float64)[:3, 3]
    rot_l, rot_c = np.asarray(ref_T_lidar, dtype=np.float64)[:3, :3], np.asarray(ref_T_camera, dtype=np.float64)[:3, :3]
    skew = np.array([[0.0, -lever[2], lever[1]], [lever[2], 0.0, -lever[0]], [-lever[1], lever[0], 0.0]])
    jac = np.zeros((7, 7))
    jac[:3, :3], jac[:3, 3:6] = np.eye(3), -skew @ rot_l  # [R_L w]x lever = -[lever]x R_L w
    jac[3:6, 3:6], jac[6, 6] = rot_c.T @ rot_l, 1.0
    sigma = np.asarray(lidar_sigma, dtype=np.float64)
    infinite = np.any((np.abs(jac) > 1e-12) & ~np.isfinite(sigma)[None, :], axis=1)
    return np.where(infinite, np.inf, np.sqrt((jac**2) @ np.where(np.isfinite(sigma), sigma, 0.0) ** 2))
