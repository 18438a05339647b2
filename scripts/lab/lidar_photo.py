"""Lab (issue 34): a LiDAR placed by photo-consistency across the reference camera's frames. A LiDAR point placed in
the world with the extrinsic (eq. 1-2, per-point times) must read the same grey level in every reference frame that
sees it (the poses are known); a wrong extrinsic moves the point, and through the parallax between frames a few metres
apart its projections read different grey levels. Coarse to fine over the reference camera's pyramid, a robust
least-squares fit of the extrinsic's columns COLUMNS (increment order: rotation vector 0-2, translation 3-5, time
offset 6) from START.

Usage: .venv/bin/python scripts/lab/lidar_photo.py RIG START [COLUMNS] [--baselines 2,4] [--huber 0.5]
START: ``truth+I:V,I:V`` (the ground truth moved by increment V on column I) or a calibration JSON (e.g. the LiDAR
stage's, ``scripts/lidar_stage.py RIG save=PATH``). Prints the error per axis (cm, deg, ms) after each level.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.optimize import least_squares

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.photometric import CameraFrames
from moisst_ns.stages.camera.lidar_map import bilinear, project, pyramid_factors, visible
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points
from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig, load_scans

STEP = np.array([1e-4] * 3 + [1e-3] * 3 + [1e-4])
SCALE = np.array([0.01] * 3 + [0.05] * 3 + [0.01])


def error(ext: Extrinsic, truth) -> np.ndarray:
    d = np.array(parameter_difference(ext.matrix(), ext.time_offset, truth[0], truth[1]))
    return np.r_[d[:3] * 100, np.rad2deg(d[3:6]), d[6] * 1000]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("rig")
    ap.add_argument("start")
    ap.add_argument("columns", nargs="?", default="0,1,2,3,4,5")
    ap.add_argument("--baselines", default="2,4", help="partner frames this far (driving distance, m) ahead and behind")
    ap.add_argument("--huber", type=float, default=0.5)
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--min-depth", type=float, default=3.0)
    ap.add_argument("--max-depth", type=float, default=40.0)
    ap.add_argument("--profile", default="", help="COL:SPAN: the mean Huber cost, rows drawn at START, along one column instead of a fit")
    args = ap.parse_args()
    rig = load_rig(args.rig)
    truth = load_calibration(rig.root / "ground_truth.json")
    lidar = next(n for n, s in rig.sensors.items() if s.type == "lidar")
    ref = truth.reference_sensor
    t_truth = (np.asarray(truth.T_ref_sensor[lidar]), float(truth.time_offset[lidar]))
    if args.start.startswith("truth"):
        inc = np.zeros(7)
        for item in filter(None, args.start[len("truth+"):].split(",")):
            i, v = item.split(":")
            inc[int(i)] = float(v)
        ext = Extrinsic(t_truth[0][:3, :3], t_truth[0][:3, 3], t_truth[1]).updated(inc)
    else:
        start = load_calibration(args.start)
        pose = np.asarray(start.T_ref_sensor[lidar])
        ext = Extrinsic(pose[:3, :3], pose[:3, 3], float(start.time_offset[lidar]))
    columns = np.array([int(c) for c in args.columns.split(",")])
    clock = time.time()
    traj = ReferenceTrajectory.of(rig)
    scans = load_scans(rig, lidar, traj, LidarFirstConfig(), log=lambda s: None)
    chosen = np.concatenate(scans.sources)
    points, times = scans.points[chosen], scans.times[chosen]
    camera = CameraFrames.of(rig, ref, pyramid_factors(int(rig.sensors[ref].intrinsics["w"]), 40))
    stamps = camera.stamps + float(rig.sensors[ref].time_offset)
    rot, pos, _, _ = traj.pose_and_rates(stamps)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))]
    baselines = [float(b) for b in args.baselines.split(",")]
    point_time = times.unique[times.index]
    nearest = np.abs(point_time[:, None] - stamps[None, :]).argmin(axis=1)
    print(f"{len(points)} points, {len(stamps)} frames of {ref}, load {time.time() - clock:.0f} s; start error {np.round(error(ext, t_truth), 2)}")

    def camera_points(world, frame):
        return np.einsum("nji,nj->ni", rot[frame], world - pos[frame])

    def pairs_at(ext: Extrinsic, model):
        world = place_points(traj, ext, points, times)
        seen = np.zeros((len(stamps), len(points)), dtype=bool)
        for j in range(len(stamps)):
            cam = camera_points(world, np.full(len(points), j))
            uv, depth = (a.numpy() for a in project(model, torch.from_numpy(cam)))
            full_uv = uv * (camera.model.width / model.width)
            seen[j] = visible(full_uv, depth, camera.model, max_depth=args.max_depth) & (depth > args.min_depth)
        rows_p, rows_a, rows_b = [], [], []
        for sign in (-1, 1):
            for b in baselines:
                partner = np.array([np.searchsorted(arc, arc[j] + b) if sign > 0 else np.searchsorted(arc, arc[j] - b, side="right") - 1
                                    for j in range(len(stamps))])
                ok_frame = (partner >= 0) & (partner < len(stamps))
                k = np.where(ok_frame, partner, 0)[nearest]
                keep = ok_frame[nearest] & seen[nearest, np.arange(len(points))] & seen[k, np.arange(len(points))]
                rows_p.append(np.flatnonzero(keep)), rows_a.append(nearest[keep]), rows_b.append(k[keep])
        return np.concatenate(rows_p), np.concatenate(rows_a), np.concatenate(rows_b)

    if args.profile:
        col, span = args.profile.split(":")
        for factor in sorted(camera.levels)[:2]:
            stack, model = camera.levels[factor], camera.levels[factor].model
            rp, ra, rb = pairs_at(ext, model)
            line = []
            for v in np.linspace(-float(span), float(span), 9):
                inc = np.zeros(7)
                inc[int(col)] = v
                world = place_points(traj, ext.updated(inc), points[rp], times[rp])
                va, _, oka = bilinear(stack, ra, project(model, torch.from_numpy(camera_points(world, ra)))[0].numpy())
                vb, _, okb = bilinear(stack, rb, project(model, torch.from_numpy(camera_points(world, rb)))[0].numpy())
                ok = oka & okb
                r = np.abs(va - vb)[ok]
                huber = np.where(r < args.huber, 0.5 * r**2, args.huber * (r - 0.5 * args.huber)).mean()
                line.append(f"{v:+.3f}: Huber {huber:.4f}, 1 - r {1 - np.corrcoef(va[ok], vb[ok])[0, 1]:.4f}")
            print(f"profile 1/{factor} col {col} ({len(rp)} rows): " + "  ".join(line), flush=True)
        return
    for factor in sorted(camera.levels, reverse=True):
        stack = camera.levels[factor]
        model = stack.model
        for outer in range(args.iterations):
            rp, ra, rb = pairs_at(ext, model)
            p_rows, t_rows = points[rp], times[rp]

            def uvs(inc):
                world = place_points(traj, ext.updated(inc), p_rows, t_rows)
                return [project(model, torch.from_numpy(camera_points(world, f)))[0].numpy() for f in (ra, rb)]

            def residuals(x, jac=False):
                inc = np.zeros(7)
                inc[columns] = x
                ua, ub = uvs(inc)
                va, ga, oka = bilinear(stack, ra, ua)
                vb, gb, okb = bilinear(stack, rb, ub)
                ok = oka & okb
                r = np.where(ok, va - vb, 0.0)
                if not jac:
                    return r
                J = np.zeros((len(r), len(columns)))
                for c, col in enumerate(columns):
                    e = np.zeros(7)
                    e[col] = STEP[col]
                    pa, pb = uvs(inc + e)
                    ma, mb = uvs(inc - e)
                    J[:, c] = np.einsum("ni,ni->n", ga, (pa - ma) / (2 * STEP[col])) - np.einsum("ni,ni->n", gb, (pb - mb) / (2 * STEP[col]))
                return J * ok[:, None]

            before = ext
            sol = least_squares(residuals, np.zeros(len(columns)), jac=lambda x: residuals(x, True), loss="huber", f_scale=args.huber,
                                x_scale=SCALE[columns], max_nfev=20, method="trf")
            inc = np.zeros(7)
            inc[columns] = sol.x
            ext = ext.updated(inc)
            moved = np.abs(error(ext, (before.matrix(), before.time_offset)))
            print(f"1/{factor} it {outer}: {len(rp)} rows, cost {sol.cost / max(len(rp), 1):.4f}, {sol.nfev} ev; error {np.round(error(ext, t_truth), 2)} "
                  f"(moved {np.round(moved, 2)}) {time.time() - clock:.0f} s", flush=True)
            if moved[:3].max() < 0.2 and moved[3:6].max() < 0.005:
                break
    e = error(ext, t_truth)
    print(f"RESULT {args.rig} {args.start} cols {args.columns}: {np.linalg.norm(e[:3]):.2f} cm {np.linalg.norm(e[3:6]):.3f} deg {abs(e[6]):.2f} ms; "
          f"per axis {np.round(e, 2)}; {time.time() - clock:.0f} s")


if __name__ == "__main__":
    main()
