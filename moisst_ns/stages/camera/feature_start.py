"""Where a camera's photometric registration starts: its pose from image features matched to the reference camera's.

The photometric cost of ``camera_registration`` has a basin of about a pixel at its coarsest pyramid level; from the
paper's perturbation (±50 cm, ±5° per axis) a small image starts ten and more pixels away and can settle in a wrong
minimum. Features have no such basin. For every reference-camera frame, SIFT keypoints (``cv2``) take the 3D point of
the map that the reference camera sees at that pixel (its pose is known: eq. 1-2 with the identity; keypoints on a
depth edge are dropped); every frame of the camera to register is matched (Lowe's ratio test) against the reference
frames near it in time. Placed in the vehicle frame at each frame's time (the prior offset), all frames' matches share
one unknown pose, ``ref_T_c``: one ``cv2.solvePnPRansac`` over all of them gives it and the inlier matches (an offset
error moves the points of a frame about alike, like a lever-arm error). The inliers are then fitted by
the same projection as the photometric stage (eq. 1, 2, 12, ``photometric.CameraModel``): the 7 corrections
(rotation, translation, time offset) minimise the reprojection error, robustly (``scipy.optimize.least_squares``,
soft L1). A camera whose view the reference camera never shares (a side camera) finds too few frames and starts from
its prior as before. No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from moisst_ns.rig.geometry import ReferenceTrajectory, row_time
from moisst_ns.stages.camera.camera_guards import SCALE
from moisst_ns.stages.camera.camera_map import camera_matrix, distortion, ratio_matches, sift
from moisst_ns.stages.camera.lidar_map import PinholeModel, project, visible, world_to_camera
from moisst_ns.stages.camera.photometric import CameraFrames, CameraModel


@dataclass
class FeatureStartConfig:
    """Settings of the feature start."""

    features: int = 1500
    """SIFT features per frame."""
    ratio: float = 0.8
    """Lowe's ratio test."""
    window_s: float = 0.35
    """Reference frames within this time of a camera frame (at the prior offset) are its match candidates, seconds."""
    ransac_fraction: float = 0.01
    """RANSAC inlier threshold of ``solvePnPRansac`` as a fraction of the image width (at least 1.5 pixels)."""
    min_inliers: int = 10
    """...and at least this many matches per such frame on average (RANSAC inliers)."""
    min_frames: int = 5
    """The start is used when the pose explains matches in at least this many frames..."""
    max_rms_px: float = 2.0
    """...and the fit's inlier reprojection RMS is below this, pixels (full resolution), or below half the RANSAC
    threshold where that is larger: an error of a given angle grows with the image (KITTI raw's image_01 at its
    1242 px: 2.40 px on a fit 3.4 cm / 0.14 deg from the factory calibration)."""


@dataclass
class FeatureStart:
    """The fit's outcome."""

    theta: Optional[Float[np.ndarray, "7"]]
    """Corrections to the prior (rad, rad, rad, m, m, m, s), or None: start from the prior."""
    frames: int
    """Frames with a PnP pose."""
    matches: int
    """Inlier matches in the fit."""
    rms_px: float
    """Inlier reprojection RMS at the fit, pixels (nan when there was no fit)."""
    note: str
    """One line: what happened."""


def _grey(image: np.ndarray) -> np.ndarray:
    """A standardised image (any scale) as 8-bit grey for SIFT."""
    lo, hi = np.percentile(image, [0.5, 99.5])
    return np.clip((image - lo) / max(hi - lo, 1e-6) * 255.0, 0, 255).astype(np.uint8)


def _sift(image: np.ndarray, features: int) -> Tuple[np.ndarray, np.ndarray]:
    """``camera_map.sift`` of a standardised image (``_grey``), the keypoints ``(u, v)`` in the rig's pixel convention
    (centre of column ``i`` at ``i + 0.5``)."""
    keypoints, descriptors = sift(_grey(image), features)
    return keypoints + 0.5, descriptors


def reference_landmarks(world: Float[np.ndarray, "num 3"], pose: Float[np.ndarray, "4 4"], image: np.ndarray, model: PinholeModel,
                        features: int, max_depth_spread: float = 0.05,
                        projected: Optional[Tuple[np.ndarray, np.ndarray]] = None) -> Tuple[Float[np.ndarray, "k 3"], Optional[np.ndarray]]:
    """The reference frame's SIFT keypoints that land on the map, as world points with their descriptors.

    Args:
        world: map points, metres.
        pose: the frame's ``world_T_camera``.
        image: the frame (full resolution).
        model: intrinsics (full resolution).
        features: SIFT features per frame.
        max_depth_spread: a keypoint whose 3x3 pixels hold map points whose depths differ by more than this fraction
            sits on a depth edge (its 3D point is ambiguous) and is dropped.
        projected: the map's pixels and depths in this frame when already known (a rolling-shutter camera: each point
            from its row's pose, ``CameraModel.project``); None: projected from ``pose``.

    Returns:
        (world points of the keypoints: the nearest visible map point within the keypoint's 3x3 pixels; their
        descriptors), both empty when none lands on the map.
    """
    uv_kp, descriptors = _sift(image, features)
    if not len(uv_kp):
        return np.zeros((0, 3)), None
    if projected is None:
        pose_t = torch.from_numpy(np.asarray(pose, dtype=np.float64))[None].expand(len(world), 4, 4)
        uv, depth = (a.numpy() for a in project(model, world_to_camera(pose_t, torch.from_numpy(world))))
    else:
        uv, depth = projected
    seen = np.flatnonzero(visible(uv, depth, model))
    w, h = model.width, model.height
    nearest = np.full(w * h, -1, dtype=np.int64)
    order = seen[np.argsort(-depth[seen])]  # far to near: the nearest point of a pixel is written last
    nearest[(uv[order, 1].astype(np.int64)) * w + uv[order, 0].astype(np.int64)] = order
    col, row = uv_kp[:, 0].astype(np.int64), uv_kp[:, 1].astype(np.int64)
    cand = np.stack([nearest[np.clip(row + dy, 0, h - 1) * w + np.clip(col + dx, 0, w - 1)] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=1)
    found = cand >= 0
    d = depth[np.maximum(cand, 0)]
    near, far = np.where(found, d, np.inf).min(axis=1), np.where(found, d, -np.inf).max(axis=1)
    keep = np.isfinite(near) & (far <= (1.0 + max_depth_spread) * near)  # not on a depth edge: one surface under the keypoint
    best = cand[np.arange(len(cand)), np.argmin(np.where(found, d, np.inf), axis=1)]
    return world[best[keep]], descriptors[keep]


def feature_start(traj: ReferenceTrajectory, world: Float[np.ndarray, "num 3"], camera: CameraFrames, reference: CameraFrames,
                  reference_pose: Float[np.ndarray, "4 4"], reference_offset: float, prior: Float[np.ndarray, "4 4"], prior_offset: float,
                  intrinsics: dict, bounds: Float[np.ndarray, "7"], config: FeatureStartConfig,
                  log: Callable[[str], None] = print) -> FeatureStart:
    """The camera's 7 corrections from features matched to the reference camera's map-anchored keypoints.

    Args:
        traj: the reference trajectory.
        world: the map, metres.
        camera: the camera to register (its full-resolution level is used).
        reference: the reference camera's frames.
        reference_pose: the reference camera's extrinsic (normally the identity).
        reference_offset: its time offset, seconds.
        prior: the camera's prior extrinsic ``ref_T_c``.
        prior_offset: its prior time offset, seconds.
        intrinsics: the camera's rig.json intrinsics.
        bounds: the stage's bounds on the corrections (|theta| <= bounds).
        config: settings.
        log: where progress lines go.

    Returns:
        The start (``theta`` None when the features do not determine it).
    """
    import cv2

    name = camera.sensor
    ref_model = CameraModel(traj, reference_pose, reference_offset, reference.stamps, reference.readout, reference.model)
    ref_poses = ref_model.poses(torch.zeros(7, dtype=torch.float64)).numpy()
    ref_images = reference.levels[1].intensity
    landmarks: List[Tuple[np.ndarray, Optional[np.ndarray]]] = [
        reference_landmarks(world, ref_poses[j], ref_images[j], reference.model, config.features,
                            projected=ref_model.project(np.zeros(7), reference.model, world, np.full(len(world), j)) if reference.readout else None)
        for j in range(len(ref_poses))]
    K, dist = camera_matrix(intrinsics), distortion(intrinsics)
    threshold = max(1.5, config.ransac_fraction * camera.model.width)
    model = CameraModel(traj, prior, prior_offset, camera.stamps, camera.readout, camera.model)
    base = traj(torch.from_numpy(camera.stamps + prior_offset)).numpy()  # world_T_ref at each frame (prior offset)
    height = camera.model.height
    points, frames, observed, local = [], [], [], []
    for i, image in enumerate(camera.levels[1].intensity):
        near = [j for j in range(len(ref_poses)) if abs(reference.stamps[j] + reference_offset - camera.stamps[i] - prior_offset) <= config.window_s
                and landmarks[j][1] is not None and len(landmarks[j][0])]
        uv_kp, descriptors = _sift(image, config.features)
        if not near or len(uv_kp) < 4:
            continue
        for j in near:  # the ratio test within one reference frame: the same point in two frames is no ambiguity
            query, train = ratio_matches(descriptors, landmarks[j][1], config.ratio)
            if len(query):
                world_pts = landmarks[j][0][train]
                points.append(world_pts)
                observed.append(uv_kp[query])
                frames.append(np.full(len(query), i))
                # the same points in the vehicle frame at this frame's time (prior offset): every frame's matches then
                # share one unknown pose, ref_T_c (an offset error moves them all about alike: a lever-arm error)
                if camera.readout:  # each match at its observed row's time
                    rows = row_time(observed[-1][:, 1], camera.readout, height)
                    inv = np.linalg.inv(traj(torch.from_numpy(camera.stamps[i] + prior_offset + rows)).numpy())
                    local.append(np.einsum("nij,nj->ni", inv[:, :3, :3], world_pts) + inv[:, :3, 3])
                else:
                    inv = np.linalg.inv(base[i])
                    local.append(world_pts @ inv[:3, :3].T + inv[:3, 3])
    if not points or len(np.unique(np.concatenate(frames))) < config.min_frames:
        return FeatureStart(None, len(np.unique(np.concatenate(frames))) if frames else 0, 0, float("nan"),
                            f"too few frames match the reference camera's features (the start needs {config.min_frames}): starting from the prior")
    points, frames, observed, local = (np.concatenate(x) for x in (points, frames, observed, local))
    # MAGSAC++ scores a pose over every threshold up to this one: where every match lies within it (KITTI raw 0048's
    # image_01 on the carried trajectory: 12 647 of 12 647), plain RANSAC's count cannot tell poses apart, and the 73
    # mismatches MAGSAC++ leaves out pulled the fit below 25 cm off (RMS 2.97 px: no start, the camera held at its prior)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(local, observed - 0.5, K, dist, reprojectionError=threshold, iterationsCount=2000,
                                                 confidence=0.999, flags=cv2.USAC_MAGSAC)
    inl = inliers.ravel() if ok and inliers is not None else np.zeros(0, dtype=np.int64)
    used = len(np.unique(frames[inl]))
    if len(inl) < config.min_inliers * config.min_frames or used < config.min_frames:
        return FeatureStart(None, used, len(inl), float("nan"), f"one pose explains only {len(inl)} matches in {used} frames "
                            f"(the start needs {config.min_inliers * config.min_frames} in {config.min_frames}): starting from the prior")
    c_T_ref = np.eye(4)
    c_T_ref[:3, :3], c_T_ref[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    ref_T_c = np.linalg.inv(c_T_ref)
    start = np.zeros(7)
    start[:3] = Rotation.from_matrix(prior[:3, :3].T @ ref_T_c[:3, :3]).as_rotvec()
    start[3:6] = ref_T_c[:3, 3] - prior[:3, 3]
    start = np.clip(start, -bounds, bounds)
    points, frames, observed = points[inl], frames[inl], observed[inl]

    def residuals(theta):
        return (model.pixels(theta, camera.model, points, frames, jacobian=False)[0] - observed).ravel()

    def jacobian(theta):
        return model.pixels(theta, camera.model, points, frames, jacobian=True)[1].reshape(-1, 7)

    fit = least_squares(residuals, start, jac=jacobian, method="trf", loss="soft_l1", f_scale=1.0, x_scale=SCALE[:7],
                        bounds=(-bounds, bounds), max_nfev=50)
    err = np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)
    rms = float(np.sqrt(np.mean(np.square(err[err < 3 * threshold])))) if np.any(err < 3 * threshold) else float("inf")
    inliers = int((err < threshold).sum())
    if rms > max(config.max_rms_px, threshold / 2) or inliers < config.min_inliers * config.min_frames:
        return FeatureStart(None, used, inliers, rms, f"the feature fit does not hold ({inliers} matches within "
                            f"{threshold:.1f} px, RMS {rms:.2f} px): starting from the prior")
    log(f"[camera-registration] {name}: feature start from {used} frames, {inliers} matches, RMS {rms:.2f} px: "
        f"{np.linalg.norm(fit.x[3:6]) * 100:.1f} cm / {np.rad2deg(np.linalg.norm(fit.x[:3])):.2f} deg / {fit.x[6] * 1000:.1f} ms from the prior")
    return FeatureStart(fit.x, used, inliers, rms, "")
