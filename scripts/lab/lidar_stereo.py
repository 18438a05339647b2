"""Lab: a LiDAR placed against what two cameras triangulate at the same instant (issue 34).

Per frame, SIFT matches between the reference camera and another camera stamped at the same instant are triangulated
in the reference camera's frame with the cameras' calibration (CAMS: a calibration.json, default the rig's
ground_truth.json); no trajectory between frames enters (only over the few ms of the cameras' offsets). Each
triangulated point must lie on the LiDAR's surface of the same frame (its scan placed with eq. 1-2): point-to-plane
residuals, weighted by the stereo depth noise along the plane's normal, Huber, fitted in the LiDAR's rotation and lever
arm (time offset held) and one depth scale per camera pair (the baseline's error, which the LiDAR's range pins).

Usage: .venv/bin/python scripts/lab/lidar_stereo.py RIG [START] [CAMS]
START: ``prior`` (rig.json), ``truth``, or a calibration.json for the LiDAR's start. Prints the LiDAR's error per axis
from the truth after each outer iteration, the scales, and the fit of each half of the drive.
"""

from __future__ import annotations

import sys
import time

import cv2
import numpy as np
import open3d as o3d
import torch

from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.camera_map import camera_matrix, distortion
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points, placement_jacobian
from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig, load_scans

PIXEL_SIGMA = 0.5  # px, a matched keypoint's position noise
PLANE_SIGMA = 0.02  # m


def stereo_points(rig, traj, cams, ref, other, max_depth=40.0):
    """Per reference frame: (its time since t0, points in the reference camera's frame, their depth sigma along the ray, unit rays)."""
    t0 = float(rig.trajectory_stamps[0])
    fa = sorted(rig.frames_of(ref), key=lambda f: f.timestamp)
    fb = sorted(rig.frames_of(other), key=lambda f: f.timestamp)
    tb = np.array([f.timestamp for f in fb]) + float(cams.time_offset[other]) - float(cams.time_offset[ref])
    Ka, da = camera_matrix(rig.sensors[ref].intrinsics), distortion(rig.sensors[ref].intrinsics)
    Kb, db = camera_matrix(rig.sensors[other].intrinsics), distortion(rig.sensors[other].intrinsics)
    sift, matcher = cv2.SIFT_create(nfeatures=4000), cv2.BFMatcher(cv2.NORM_L2)
    out = []
    for k, f in enumerate(fa):
        j = int(np.argmin(np.abs(tb - f.timestamp)))
        if abs(tb[j] - f.timestamp) > 0.05:
            continue
        pa = (traj(torch.tensor([f.timestamp - t0 + float(cams.time_offset[ref])], dtype=torch.float64))[0].numpy()
              @ np.asarray(cams.T_ref_sensor[ref], dtype=np.float64))
        pb = (traj(torch.tensor([fb[j].timestamp - t0 + float(cams.time_offset[other])], dtype=torch.float64))[0].numpy()
              @ np.asarray(cams.T_ref_sensor[other], dtype=np.float64))
        a_T_b = np.linalg.inv(pa) @ pb
        ia = cv2.imread(str(rig.root / f.file_path), cv2.IMREAD_GRAYSCALE)
        ib = cv2.imread(str(rig.root / fb[j].file_path), cv2.IMREAD_GRAYSCALE)
        ka, dsa = sift.detectAndCompute(ia, None)
        kb, dsb = sift.detectAndCompute(ib, None)
        if dsa is None or dsb is None or len(ka) < 8 or len(kb) < 8:
            continue
        m = [p for p, q in (x for x in matcher.knnMatch(dsa, dsb, k=2) if len(x) == 2) if p.distance < 0.8 * q.distance]
        if len(m) < 8:
            continue
        xa = np.array([ka[p.queryIdx].pt for p in m]).reshape(-1, 1, 2)
        xb = np.array([kb[p.trainIdx].pt for p in m]).reshape(-1, 1, 2)
        na, nb = cv2.undistortPoints(xa, Ka, da).reshape(-1, 2), cv2.undistortPoints(xb, Kb, db).reshape(-1, 2)
        b_T_a = np.linalg.inv(a_T_b)
        hom = cv2.triangulatePoints(np.eye(4)[:3], b_T_a[:3], na.T, nb.T)
        X = (hom[:3] / hom[3]).T
        Xb = X @ b_T_a[:3, :3].T + b_T_a[:3, 3]
        # reprojection in b (the epipolar check: a wrong match does not triangulate consistently)
        err = np.linalg.norm(Xb[:, :2] / Xb[:, 2:] - nb, axis=1) * Kb[0, 0]
        ok = (X[:, 2] > 2.0) & (X[:, 2] < max_depth) & (Xb[:, 2] > 2.0) & (err < 1.0)
        baseline = np.linalg.norm(a_T_b[:3, 3])
        ray = X / np.linalg.norm(X, axis=1, keepdims=True)
        sigma = np.linalg.norm(X, axis=1) ** 2 / (Ka[0, 0] * baseline) * PIXEL_SIGMA  # along the ray, m
        out.append((f.timestamp - t0, X[ok], sigma[ok], ray[ok], pa))
    return out


def main() -> None:
    rig = load_rig(sys.argv[1])
    truth = load_calibration(rig.root / "ground_truth.json")
    start = sys.argv[2] if len(sys.argv) > 2 else "prior"
    cams = load_calibration(sys.argv[3]) if len(sys.argv) > 3 else truth
    prior = Calibration.from_rig(rig)
    init = truth if start == "truth" else prior if start == "prior" else load_calibration(start)
    lidar = next(n for n, s in rig.sensors.items() if s.type == "lidar")
    ref = rig.reference_sensor
    others = [n for n, s in rig.sensors.items() if s.type == "camera" and n != ref]
    traj = ReferenceTrajectory.of(rig)
    clock = time.time()
    scans = load_scans(rig, lidar, traj, LidarFirstConfig(), log=lambda s: None)
    sets = {o: stereo_points(rig, traj, cams, ref, o) for o in others}
    for o, s in sets.items():
        print(f"{o}: {sum(len(x[1]) for x in s)} stereo points in {len(s)} frames, baseline "
              f"{np.linalg.norm(np.asarray(cams.T_ref_sensor[o])[:3, 3] - np.asarray(cams.T_ref_sensor[ref])[:3, 3]):.3f} m", flush=True)
    ext = Extrinsic(np.asarray(init.T_ref_sensor[lidar])[:3, :3].copy(), np.asarray(init.T_ref_sensor[lidar])[:3, 3].copy(),
                    float(init.time_offset[lidar]))
    pairs = [o for o in others if np.linalg.norm(np.asarray(cams.T_ref_sensor[o])[:3, 3]) > 0.2]
    print(f"pairs used: {pairs}; load {time.time() - clock:.0f} s", flush=True)

    def fit(ext, frames_kept, radii=(2.0, 1.0, 0.5, 0.3, 0.2, 0.2, 0.15, 0.15), verbose=True):
        scales = {o: 1.0 for o in pairs}
        for it, radius in enumerate(radii):
            rows_p, rows_n, rows_X, rows_s, rows_c, rows_w = [], [], [], [], [], []
            for o in pairs:
                for t, X, sig, ray, pa in sets[o]:
                    k = int(np.argmin(np.abs(scans.stamps + ext.time_offset - t)))
                    if k not in frames_kept or abs(scans.stamps[k] + ext.time_offset - t) > 0.05:
                        continue
                    part = scans.scan(k)
                    world = place_points(traj, ext, scans.points[part], scans.times[part])
                    cam = (world - pa[:3, 3]) @ pa[:3, :3]
                    tree = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(cam))
                    tree.knn_index()
                    idx, d2 = tree.knn_search(o3d.core.Tensor(scales[o] * X), 1)
                    idx, d2 = idx.numpy()[:, 0].astype(np.int64), d2.numpy()[:, 0]
                    g = idx + part.start
                    keep = (d2 < radius**2) & scans.planar[g]
                    n_w = scans.normals[g[keep]] @ ext.rotation.T
                    n_w = np.einsum("ij,nj->ni", pa[:3, :3], n_w)  # world (the trajectory's rotation over the sweep ignored for the normal)
                    along = np.abs(np.einsum("ni,ni->n", n_w @ pa[:3, :3], ray[keep]))
                    w = 1.0 / np.sqrt(PLANE_SIGMA**2 + scans.thickness[g[keep]] ** 2 + (along * sig[keep] * scales[o]) ** 2)
                    rows_p.append(g[keep]), rows_n.append(n_w), rows_X.append(X[keep]), rows_w.append(w)
                    rows_c.append(np.repeat(pa[None], keep.sum(), axis=0)), rows_s.append(np.full(keep.sum(), pairs.index(o)))
            if not rows_p:
                return ext, scales, 0
            g = np.concatenate(rows_p)
            n_w, X, w = np.concatenate(rows_n), np.concatenate(rows_X), np.concatenate(rows_w)
            pose, which = np.concatenate(rows_c), np.concatenate(rows_s)
            for _ in range(3):  # Gauss-Newton, Huber (IRLS) on the weighted residuals
                s = np.array([scales[o] for o in pairs])[which]
                feat_w = np.einsum("nij,nj->ni", pose[:, :3, :3], s[:, None] * X) + pose[:, :3, 3]
                nx, jac = placement_jacobian(traj, ext, np.zeros(7), scans.points[g], scans.times[g], n_w)
                r = w * (np.einsum("ni,ni->n", n_w, feat_w) - nx)
                J = np.zeros((len(g), 6 + len(pairs)))
                J[:, :6] = -w[:, None] * jac[:, :6]
                dsc = w * np.einsum("ni,ni->n", n_w, np.einsum("nij,nj->ni", pose[:, :3, :3], X))
                J[np.arange(len(g)), 6 + which] = dsc
                huber = np.where(np.abs(r) < 1.5, 1.0, 1.5 / np.maximum(np.abs(r), 1e-12))
                H = (J * huber[:, None]).T @ J
                step = -np.linalg.solve(H + 1e-9 * np.eye(len(H)), (J * huber[:, None]).T @ r)
                ext = ext.updated(np.concatenate([step[:6], [0.0]]))
                for i, o in enumerate(pairs):
                    scales[o] += step[6 + i]
            if verbose:
                d = np.array(parameter_difference(ext.matrix(), ext.time_offset, truth.T_ref_sensor[lidar], truth.time_offset[lidar]))
                print(f"  it {it} radius {radius}: {len(g)} rows, robust rms {np.sqrt(np.mean(np.minimum(r**2, 2.25))):.3f}; "
                      f"error per axis cm {np.round(d[:3] * 100, 2)} deg {np.round(np.rad2deg(d[3:6]), 3)}; "
                      f"scales {', '.join(f'{o} {v:.4f}' for o, v in scales.items())}", flush=True)
        return ext, scales, len(g)

    frames = set(range(len(scans.stamps)))
    d0 = np.array(parameter_difference(ext.matrix(), ext.time_offset, truth.T_ref_sensor[lidar], truth.time_offset[lidar]))
    print(f"start {start}: per axis cm {np.round(d0[:3] * 100, 2)} deg {np.round(np.rad2deg(d0[3:6]), 3)}", flush=True)
    whole, scales, rows = fit(ext, frames)
    half = len(scans.stamps) // 2
    import os
    if os.environ.get("PER_BLOCK"):
        size = int(os.environ["PER_BLOCK"])
        for b in range(0, len(scans.stamps), size):
            e, s, n = fit(whole, set(range(b, b + size)), radii=(0.3, 0.2, 0.15, 0.15), verbose=False)
            d = np.array(parameter_difference(e.matrix(), e.time_offset, truth.T_ref_sensor[lidar], truth.time_offset[lidar]))
            print(f"block {b}: {n} rows, per axis cm {np.round(d[:3] * 100, 2)} deg {np.round(np.rad2deg(d[3:6]), 3)}", flush=True)
    for name, kept in (("first half", set(range(half))), ("second half", set(range(half, len(scans.stamps))))):
        e, s, n = fit(whole, kept, radii=(0.3, 0.2, 0.15, 0.15), verbose=False)
        d = np.array(parameter_difference(e.matrix(), e.time_offset, truth.T_ref_sensor[lidar], truth.time_offset[lidar]))
        print(f"{name}: {n} rows, per axis cm {np.round(d[:3] * 100, 2)} deg {np.round(np.rad2deg(d[3:6]), 3)}", flush=True)
    d = np.array(parameter_difference(whole.matrix(), whole.time_offset, truth.T_ref_sensor[lidar], truth.time_offset[lidar]))
    print(f"RESULT {sys.argv[1:]}: {np.linalg.norm(d[:3]) * 100:.2f} cm {np.rad2deg(np.linalg.norm(d[3:6])):.3f} deg; "
          f"per axis cm {np.round(d[:3] * 100, 2)} deg {np.round(np.rad2deg(d[3:6]), 3)}; wall {time.time() - clock:.0f} s", flush=True)


if __name__ == "__main__":
    main()
