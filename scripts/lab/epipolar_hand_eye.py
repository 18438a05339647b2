"""A camera's calibration from its own images' epipolar geometry, every match at once, against the reference trajectory.

Per-pair essential matrices (``hand_eye.py``) scatter 0.2-0.4 deg at 320x240. Here no relative pose is estimated:
for any calibration ``X = ref_T_c`` and offset delta the reference trajectory predicts the camera's relative pose
between two of its frames, ``B = X^-1 Traj(t_j + delta)^-1 Traj(t_k + delta) X``, hence its essential matrix; the
Sampson distance of every RANSAC-inlier match of every frame pair (pixels) is minimised over the 7 corrections
(soft L1). Lab experiment for issue 38.

Usage: .venv/bin/python scripts/lab/epipolar_hand_eye.py RIG [CAMERA ...] [--lag 3] [--rot-only]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.optimize import least_squares

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.camera_map import camera_matrix, distortion
from moisst_ns.stages.camera.camera_registration import camera_sensors
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.camera.feature_start import _sift
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, PARAMETERS, TEST_STEPS


def own_matches(images, intrinsics, lag, features=2000, ratio=0.8, ransac_px=1.0):
    import cv2

    K, dist = camera_matrix(intrinsics), distortion(intrinsics)
    keys = [_sift(np.asarray(image), features) for image in images]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    pair, a_all, b_all = [], [], []
    for j in range(len(images)):
        for k in range(j + 1, min(len(images), j + lag + 1)):
            (uv_j, d_j), (uv_k, d_k) = keys[j], keys[k]
            if d_j is None or d_k is None or len(uv_j) < 8 or len(uv_k) < 8:
                continue
            good = [m[0] for m in matcher.knnMatch(d_j, d_k, k=2) if len(m) == 2 and m[0].distance < ratio * m[1].distance]
            if len(good) < 15:
                continue
            a = cv2.undistortPoints(uv_j[[m.queryIdx for m in good]].reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
            b = cv2.undistortPoints(uv_k[[m.trainIdx for m in good]].reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
            E, mask = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=ransac_px / K[0, 0])
            if E is None or mask is None:
                continue
            keep = mask.ravel().astype(bool)
            if keep.sum() < 15:
                continue
            pair.append(np.stack([np.full(keep.sum(), j), np.full(keep.sum(), k)], axis=1))
            a_all.append(a[keep]), b_all.append(b[keep])
    return np.concatenate(pair), np.concatenate(a_all), np.concatenate(b_all), float(K[0, 0])


def skew(v):
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1), np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def sampson(theta, traj, stamps, prior, prior_offset, pairs, a, b, focal):
    th = torch.as_tensor(theta, dtype=torch.float64)
    X = calibrated_extrinsic(torch.as_tensor(prior, dtype=torch.float64), th[:3], th[3:6])
    poses = (traj(torch.as_tensor(stamps, dtype=torch.float64) + prior_offset + th[6]) @ X).numpy()
    inv = np.linalg.inv(poses)
    rel = inv[pairs[:, 0]] @ poses[pairs[:, 1]]  # frame k in frame j
    E = skew(rel[:, :3, 3]) @ rel[:, :3, :3]
    xj = np.concatenate([a, np.ones((len(a), 1))], 1)
    xk = np.concatenate([b, np.ones((len(b), 1))], 1)
    Ex = np.einsum("nij,nj->ni", E, xk)
    Etx = np.einsum("nji,nj->ni", E, xj)
    e = np.sum(xj * Ex, 1)
    return focal * e / np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2 + 1e-30)


def fit(theta0, free, fun, scale=1.0):
    def full(x):
        t = theta0.copy()
        t[free] = x
        return t

    sol = least_squares(lambda x: fun(full(x)), theta0[free], loss="soft_l1", f_scale=scale, diff_step=1e-6, method="trf", x_scale="jac")
    return full(sol.x), sol


def main():
    p = argparse.ArgumentParser()
    p.add_argument("rig")
    p.add_argument("cameras", nargs="*")
    p.add_argument("--lag", type=int, default=3)
    p.add_argument("--max-offset", type=float, default=0.3)
    p.add_argument("--rot-only", action="store_true")
    args = p.parse_args()
    rig = load_rig(args.rig)
    truth = load_calibration(rig.root / "ground_truth.json")
    traj = ReferenceTrajectory.of(rig)
    units = [100, 100, 100, 57.29578, 57.29578, 57.29578, 1000]
    for name in args.cameras or camera_sensors(rig):
        begun = time.time()
        spec = rig.sensors[name]
        frames = CameraFrames.of(rig, name, [1])
        pairs, a, b, focal = own_matches(frames.levels[1].intensity, spec.intrinsics, args.lag)
        prior, off = np.asarray(spec.T_ref_sensor, dtype=np.float64), float(spec.time_offset)
        fun = lambda t, keep=slice(None): sampson(t, traj, frames.stamps, prior, off, pairs[keep], a[keep], b[keep], focal)
        print(f"{name}: {len(a)} matches over {len(np.unique(pairs, axis=0))} pairs, {time.time() - begun:.0f} s", flush=True)
        grid = np.arange(-args.max_offset, args.max_offset + 1e-9, 0.01)
        best = None
        for d in grid:
            th, sol = fit(np.r_[0, 0, 0, 0, 0, 0, d], np.arange(3), fun)
            if best is None or sol.cost < best[1].cost:
                best = (th, sol)
        theta = best[0]
        theta, sol = fit(theta, np.r_[0, 1, 2, 6], fun)
        oracle = theta.copy()
        oracle[3:6] = np.asarray(truth.T_ref_sensor[name])[:3, 3] - prior[:3, 3]
        oracle, _ = fit(oracle, np.r_[0, 1, 2, 6], fun)
        for label, t in (("lever at prior", theta), ("lever at truth", oracle)):
            e = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name],
                                     calibrated_extrinsic(torch.as_tensor(prior), torch.as_tensor(t[:3]), torch.as_tensor(t[3:6])).numpy(), off + t[6])
            print(f"  {label}: rotation deg {np.round(np.rad2deg(e[3:6]), 3)}, delta {e[6] * 1000:.2f} ms", flush=True)
        if args.rot_only:
            continue
        theta, sol = fit(theta, np.arange(7), fun)
        scatter = 1.4826 * np.median(np.abs(sol.fun))
        cov = np.linalg.pinv(sol.jac.T @ sol.jac) * scatter ** 2
        sigma = np.sqrt(np.clip(np.diag(cov), 0, None))
        middle = len(frames.stamps) // 2
        halves = [pairs[:, 1] < middle, pairs[:, 0] >= middle]
        fits = [fit(theta, np.arange(7), lambda t, h=h: fun(t, h))[0] for h in halves]
        split = np.abs(fits[0] - fits[1]) / 2
        th = torch.as_tensor(theta)
        est = calibrated_extrinsic(torch.as_tensor(prior), th[:3], th[3:6]).numpy()
        before = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], prior, off)
        after = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], est, off + theta[6])
        print(f"RESULT {args.rig} {name} lag {args.lag}: {len(a)} matches, scatter {scatter:.3f} px, {time.time() - begun:.0f} s")
        for i, (q, bb, aa, u) in enumerate(zip(PARAMETERS, before, after, units)):
            j = JACOBIAN_ORDER[i]
            print(f"  {q:12s} prior {bb * u:9.3f}  after {aa * u:9.3f}  sigma {sigma[j] * u:8.3f}  split {split[j] * u:8.3f}  typical {TEST_STEPS[i] * u:.1f}")


if __name__ == "__main__":
    main()
