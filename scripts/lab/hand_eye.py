"""A camera's calibration from its own motion: hand-eye with a time offset, for cameras that share no view.

A camera that never sees what the reference sensor sees cannot be registered against its map, but its own images
tell its own motion. Between two of its frames ``j < k``: SIFT matches (``feature_start._sift``, Lowe's ratio test),
the essential matrix (``cv2.findEssentialMat`` on undistorted normalised points, RANSAC) and ``cv2.recoverPose``
give its relative rotation ``B_R`` and the direction ``b`` of its translation (the scale is not seen). The reference
trajectory gives the same motion for any calibration (rig format eq. 2): ``B = X^-1 A X``, ``A = Traj(t_j + delta)^-1
Traj(t_k + delta)``, ``X = ref_T_c``. The 7 corrections of paper eq. 12 (``calibrated_extrinsic``) minimise, robustly
(``scipy.optimize.least_squares``, soft L1), the rotation ``Log(B_R^T B_R(X))`` (radians) and the angle between ``b``
and the predicted direction (radians) of every pair: hand-eye calibration (Heng et al., CamOdoCal, IROS 2013; Taylor
and Nieto 2016 for the time offset), coarse to fine in delta (a grid over ``max_time_offset`` first).

What the drive leaves undetermined is said, not made up: a parameter whose sigma (the fit's covariance, scaled by
the residuals' robust scatter) exceeds a typical prior error (``observability.TEST_STEPS``: 10 cm, 1 deg, 10 ms) is
weak, held at its prior and the rest refitted (a flat drive leaves the vertical lever arm so; a straight one the
whole lever arm, which only rotations show). No nerfstudio import.

A lab experiment (docs/lab/2026-11-26-hand-eye.md), not used by the stages: measured short of issue 38's targets.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, List

import numpy as np
import torch
from jaxtyping import Float, Int
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.stages.camera.camera_map import camera_matrix, distortion
from moisst_ns.stages.trust.observability import analyse_drive
from moisst_ns.stages.camera.feature_start import _sift
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, PARAMETERS, TEST_STEPS

THETA_ORDER = JACOBIAN_ORDER
"""Where each of ``PARAMETERS`` (x y z roll pitch yaw delta) sits in theta (rotation vector, translation, delta)."""


@dataclass
class HandEyeConfig:
    """Settings of the motion-based (hand-eye) calibration of one camera."""

    features: int = 2000
    """SIFT features per frame."""
    ratio: float = 0.8
    """Lowe's ratio test."""
    max_lag: int = 3
    """Frame pairs up to this many frames apart."""
    ransac_px: float = 1.0
    """RANSAC threshold of the essential matrix, pixels."""
    method: str = "RANSAC"
    """OpenCV's robust estimator of the essential matrix (``RANSAC``, ``USAC_MAGSAC``, ``USAC_ACCURATE``...)."""
    min_inliers: int = 30
    """A pair is used when its essential matrix explains at least this many matches."""
    min_pairs: int = 6
    """Fewer usable pairs than this: not measured."""
    max_time_offset: float = 0.3
    """The delta grid spans the prior +- this, seconds."""
    grid_step: float = 0.01
    """Spacing of the delta grid, seconds."""


@dataclass
class CameraMotion:
    """A camera's own relative motions between frame pairs."""

    pairs: Int[np.ndarray, "num 2"]
    rotations: Float[np.ndarray, "num 3 3"]
    """``cj_R_ck``: frame k's orientation in frame j's."""
    directions: Float[np.ndarray, "num 3"]
    """Unit direction of frame k's position in frame j's."""
    inliers: Int[np.ndarray, "num"]


@dataclass
class HandEyeResult:
    """The fit's outcome for one camera."""

    sensor: str
    theta: Float[np.ndarray, "7"]
    """Corrections to the prior (rotation vector rad, translation m, delta s), weak ones 0."""
    sigma: List[float]
    """Standard deviation of each of ``PARAMETERS`` (m, rad, s; inf: not determined)."""
    weak: List[str]
    """The parameters held at their prior, with ``sigma`` above a typical prior error."""
    pairs: int
    rms_rad: float
    """Robust RMS of the rotation and direction residuals at the estimate, radians."""
    notes: List[str] = field(default_factory=list)


def camera_motion(images: List[np.ndarray], intrinsics: dict, config: HandEyeConfig) -> CameraMotion:
    """Relative rotations and translation directions between the camera's frames, from its images alone.

    Args:
        images: the frames in time order (grey or colour, full resolution, values in [0, 1] or 0-255).
        intrinsics: the camera's rig.json intrinsics.
        config: settings.

    Returns:
        The pairs whose essential matrix has at least ``min_inliers`` inliers.
    """
    import cv2

    K, dist = camera_matrix(intrinsics), distortion(intrinsics)
    keys = [_sift(image, config.features) for image in images]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out = {"pairs": [], "rotations": [], "directions": [], "inliers": []}
    for j in range(len(images)):
        for k in range(j + 1, min(len(images), j + config.max_lag + 1)):
            (uv_j, d_j), (uv_k, d_k) = keys[j], keys[k]
            if d_j is None or d_k is None or len(uv_j) < 8 or len(uv_k) < 8:
                continue
            good = [m[0] for m in matcher.knnMatch(d_j, d_k, k=2) if len(m) == 2 and m[0].distance < config.ratio * m[1].distance]
            if len(good) < config.min_inliers:
                continue
            a = cv2.undistortPoints(uv_j[[m.queryIdx for m in good]].reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
            b = cv2.undistortPoints(uv_k[[m.trainIdx for m in good]].reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
            E, mask = cv2.findEssentialMat(a, b, np.eye(3), method=getattr(cv2, config.method), prob=0.999, threshold=config.ransac_px / K[0, 0])
            if E is None or E.shape != (3, 3):
                continue
            count, R, t, mask = cv2.recoverPose(E, a, b, np.eye(3), mask=mask)
            if count < config.min_inliers:
                continue
            # recoverPose: x_k = R x_j + t; frame k in frame j: rotation R^T, position -R^T t
            out["pairs"].append((j, k)), out["rotations"].append(R.T), out["inliers"].append(int(count))
            direction = -R.T @ t.reshape(3)
            out["directions"].append(direction / np.linalg.norm(direction))
    return CameraMotion(np.asarray(out["pairs"], dtype=np.int64).reshape(-1, 2), np.asarray(out["rotations"]).reshape(-1, 3, 3),
                        np.asarray(out["directions"]).reshape(-1, 3), np.asarray(out["inliers"], dtype=np.int64))


def motion_residuals(theta: Float[np.ndarray, "7"], traj: ReferenceTrajectory, stamps: Float[np.ndarray, "frames"],
                     prior: Float[np.ndarray, "4 4"], prior_offset: float, motion: CameraMotion) -> Float[np.ndarray, "num6"]:
    """Hand-eye residuals of every pair: ``Log(B_R^T B_R(X))`` and ``b x b(X)`` (radians, 3 + 3 per pair).

    Args:
        theta: corrections (rotation vector about the camera's axes rad, translation in the reference frame m, delta s).
        traj: the reference trajectory.
        stamps: the camera's frame stamps, seconds since ``t0``.
        prior: prior ``ref_T_c``.
        prior_offset: prior delta, seconds.
        motion: the camera's measured motions.

    Returns:
        Flattened (P, 6) residuals; the direction part is the sine of the angle between measured and predicted.
    """
    th = torch.as_tensor(theta, dtype=torch.float64)
    X = calibrated_extrinsic(torch.as_tensor(prior, dtype=torch.float64), th[:3], th[3:6])
    poses = traj(torch.as_tensor(stamps, dtype=torch.float64) + prior_offset + th[6]) @ X
    idx = torch.as_tensor(motion.pairs)
    rel = torch.linalg.inv(poses[idx[:, 0]]) @ poses[idx[:, 1]]
    rot_err = Rotation.from_matrix(np.transpose(motion.rotations, (0, 2, 1)) @ rel[:, :3, :3].numpy()).as_rotvec()
    predicted = rel[:, :3, 3].numpy()
    predicted = predicted / np.maximum(np.linalg.norm(predicted, axis=1, keepdims=True), 1e-9)
    return np.concatenate([rot_err, np.cross(motion.directions, predicted)], axis=1).reshape(-1)


def _solve(theta0: np.ndarray, free: np.ndarray, residuals: Callable[[np.ndarray], np.ndarray], scale: float):
    def full(x: np.ndarray) -> np.ndarray:
        theta = theta0.copy()
        theta[free] = x
        return theta

    solution = least_squares(lambda x: residuals(full(x)), theta0[free], loss="soft_l1", f_scale=scale, diff_step=1e-6, method="trf")
    return full(solution.x), solution


def hand_eye(traj: ReferenceTrajectory, sensor: str, stamps: Float[np.ndarray, "frames"], motion: CameraMotion,
             prior: Float[np.ndarray, "4 4"], prior_offset: float, config: HandEyeConfig,
             log: Callable[[str], None] = print) -> HandEyeResult:
    """The camera's 7 corrections from its own motion against the reference trajectory's.

    Args:
        traj: the reference trajectory.
        sensor: the camera's name (for the log).
        stamps: the camera's frame stamps, seconds since ``t0``.
        motion: ``camera_motion`` of its frames.
        prior: prior ``ref_T_c``.
        prior_offset: prior delta, seconds.
        config: settings.
        log: where progress lines go.

    Returns:
        The corrections, a sigma per parameter and the weak ones (held at the prior). Too few pairs: theta 0, every
        parameter weak, a note says why.
    """
    if len(motion.pairs) < config.min_pairs:
        note = f"{sensor}: {len(motion.pairs)} frame pairs with a usable essential matrix (< {config.min_pairs}): its own motion is not measured"
        log(f"[hand-eye] {note}")
        return HandEyeResult(sensor, np.zeros(7), [float("inf")] * 7, list(PARAMETERS), len(motion.pairs), float("nan"), [note])

    def residuals(theta: np.ndarray) -> np.ndarray:
        return motion_residuals(theta, traj, stamps, prior, prior_offset, motion)

    scale = 2e-3  # radians: the soft-L1 knee, about a pixel over 500 pixels of focal length
    grid = np.arange(-config.max_time_offset, config.max_time_offset + 1e-9, config.grid_step)
    costs = []
    for d in grid:  # coarse: the rotation alone at each delta (the lever arm hardly moves the rotations)
        theta, sol = _solve(np.array([0, 0, 0, 0, 0, 0, d], dtype=np.float64), np.arange(3), residuals, scale)
        costs.append((sol.cost, theta))
    theta = min(costs, key=lambda c: c[0])[1]
    drive = analyse_drive(traj, stamps + prior_offset, prior, sensor, "relative")
    weak = [d.name for d in drive.dofs if d.weak]
    notes = [f"the drive does not determine {', '.join(weak)} (its motion alone, hand-eye)"] if weak else []
    free = np.array([THETA_ORDER[i] for i, p in enumerate(PARAMETERS) if p not in weak])
    middle = len(stamps) // 2
    halves = [motion.pairs[:, 1] < middle, motion.pairs[:, 0] >= middle]
    while True:
        theta[[i for i in range(7) if i not in free]] = 0.0
        theta, sol = _solve(theta, free, residuals, scale)
        scatter = 1.4826 * float(np.median(np.abs(sol.fun)))
        sigma = np.full(7, np.inf)
        sigma[free] = np.sqrt(np.clip(np.diag(scatter**2 * np.linalg.pinv(sol.jac.T @ sol.jac)), 0, None))
        if all(h.sum() >= config.min_pairs for h in halves):  # what the halves of the drive disagree on (split half)
            fits = [_solve(theta, free, lambda t, h=h: motion_residuals(t, traj, stamps, prior, prior_offset, _subset(motion, h)), scale)[0]
                    for h in halves]
            sigma[free] = np.fmax(sigma[free], np.abs(fits[0] - fits[1])[free] / 2)
        sigma_p = [float(sigma[THETA_ORDER[i]]) for i in range(7)]
        drop = [THETA_ORDER[i] for i, p in enumerate(PARAMETERS) if THETA_ORDER[i] in free and not sigma_p[i] <= TEST_STEPS[i]]
        if not drop or len(drop) == len(free):
            break
        notes.append(f"{', '.join(PARAMETERS[THETA_ORDER.index(i)] for i in drop)}: sigma above a typical prior error, held at the prior")
        weak += [PARAMETERS[THETA_ORDER.index(i)] for i in drop]
        free = np.array([i for i in free if i not in drop])
    log(f"[hand-eye] {sensor}: {len(motion.pairs)} pairs, residual {np.degrees(scatter):.3f} deg; "
        + ", ".join(f"{p} {'weak' if p in weak else f'{s:.3g}'}" for p, s in zip(PARAMETERS, sigma_p)))
    return HandEyeResult(sensor, theta, sigma_p, weak, len(motion.pairs), scatter, notes)


def _subset(motion: CameraMotion, keep: np.ndarray) -> CameraMotion:
    return CameraMotion(motion.pairs[keep], motion.rotations[keep], motion.directions[keep], motion.inliers[keep])
