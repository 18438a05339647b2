"""The reference camera's own directions of travel against the reference trajectory's (docs/lab/2026-11-27-reference-motion.md):
for pairs of its frames 3 to 8 apart, the essential matrix's translation direction (SIFT, ratio test, RANSAC,
``cv2.recoverPose``) against the trajectory's, and the rotation ``W`` (about the camera's x and y) with
``t_camera = W^T t_trajectory`` (soft-L1); with OUT, a copy of RIG (hard links) whose trajectory is turned by ``W``.

Usage: .venv/bin/python scripts/lab/reference_direction.py RIG [OUT]
"""

import json
import os
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation as R


def main() -> None:
    root, out = sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None
    rig = json.loads(Path(root, "rig.json").read_text())
    cam = rig["reference_sensor"]
    s = rig["sensors"][cam]
    K = np.array([[s["fl_x"], 0, s["cx"]], [0, s["fl_y"], s["cy"]], [0, 0, 1]])
    dist = np.array([s.get("k1", 0), s.get("k2", 0), s.get("p1", 0), s.get("p2", 0)])
    poses = np.loadtxt(f"{root}/{rig['trajectory']}")

    def pose_at(t):  # the trajectory row of a frame's stamp (the converters write one per reference frame)
        row = poses[np.argmin(np.abs(poses[:, 0] - t))]
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R.from_quat(row[4:8]).as_matrix(), row[1:4]
        return M

    frames = sorted([f for f in rig["frames"] if f["sensor"] == cam], key=lambda f: f["timestamp"])
    sift, bf = cv2.SIFT_create(3000), cv2.BFMatcher()
    kd = [sift.detectAndCompute(cv2.imread(f"{root}/" + f["file_path"], 0), None) for f in frames]
    te, tt = [], []
    for i in range(len(frames)):
        for j in range(i + 3, min(len(frames), i + 9)):
            (ka, da), (kb, db) = kd[i], kd[j]
            m = [x for x, y in bf.knnMatch(da, db, k=2) if x.distance < 0.75 * y.distance]
            if len(m) < 30:
                continue
            pa = cv2.undistortPoints(np.float32([ka[x.queryIdx].pt for x in m]).reshape(-1, 1, 2), K, dist, P=K)
            pb = cv2.undistortPoints(np.float32([kb[x.trainIdx].pt for x in m]).reshape(-1, 1, 2), K, dist, P=K)
            E, inl = cv2.findEssentialMat(pb, pa, K, cv2.RANSAC, 0.999, 0.5)
            if E is None or E.shape != (3, 3):
                continue
            _, _, t, _ = cv2.recoverPose(E, pb, pa, K, mask=inl)  # x_a = R x_b + t
            rel = np.linalg.inv(pose_at(frames[i]["timestamp"])) @ pose_at(frames[j]["timestamp"])
            te.append(t.ravel() / np.linalg.norm(t))
            tt.append(rel[:3, 3] / np.linalg.norm(rel[:3, 3]))
    te, tt = np.array(te), np.array(tt)
    fit = least_squares(lambda w: (te - tt @ R.from_rotvec([w[0], w[1], 0.0]).as_matrix()).ravel(), np.zeros(2), loss="soft_l1", f_scale=0.01)
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * (fit.fun @ fit.fun) / max(len(fit.fun) - 2, 1)
    print(f"{root}: {len(te)} pairs; W about x, y {np.degrees(fit.x).round(3)} deg, sigma {np.degrees(np.sqrt(np.diag(cov))).round(3)} deg")
    if out:
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(root, out, copy_function=os.link, ignore=shutil.ignore_patterns(rig["trajectory"]))
        q = (R.from_quat(poses[:, 4:8]) * R.from_rotvec([fit.x[0], fit.x[1], 0.0])).as_quat()
        np.savetxt(f"{out}/{rig['trajectory']}", np.c_[poses[:, :4], q], fmt="%.9f", header=Path(root, rig["trajectory"]).read_text().splitlines()[0].lstrip("# "))


if __name__ == "__main__":
    main()
