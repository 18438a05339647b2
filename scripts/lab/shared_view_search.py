"""Coordinate search of the shared view's median edge distance over what a drive's motion left undetermined, with an
acceptance rule per parameter: its 1-D profile's minimum is inside the grid, the cost one typical prior error (10 cm,
1 deg) either side rises by at least RISE, and the two halves of the drive put their minima within 2 typical errors
(the LiDAR stage's split-half rule). docs/lab/2026-11-25-kitti-shared-view.md, 2026-11-26 entry.

Usage: .venv/bin/python scripts/lab/shared_view_search.py synth RIG      (a moisst-synth rig: three moves from the truth)
       .venv/bin/python scripts/lab/shared_view_search.py kitti RIG NPZ  (KITTI raw rig, from a saved LiDAR-stage estimate,
                                                                          as scripts/lab/shared_view_grid.py saves it)
"""
import sys
import time

import numpy as np
from pathlib import Path
from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar_first import LidarFirstConfig, consistency_residuals, find_correspondences, load_scans, scan_pairs
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory
from moisst_ns.stages.lidar_view import SharedView, view_residuals
from moisst_ns.stages.observability import TEST_STEPS, JACOBIAN_ORDER
TYP = np.array(TEST_STEPS)[np.argsort(JACOBIAN_ORDER)]
SPAN = lambda c: (np.deg2rad(6.0), np.deg2rad(1.0)) if c < 3 else (0.6, 0.1)

RISE = 0.1
"""Least relative rise of the median edge distance one typical error either side of a minimum (a guess, not tuned)."""


def search(traj, ext, scans, shared, columns, rounds=3, rise=RISE, hold=2.0, log=print):
    scan_of = np.searchsorted(scans.offsets, shared.rows.point, side="right") - 1
    first = scans.stamps[scan_of] < np.median(scans.stamps)
    inc = np.zeros(7)
    def med(v):
        d = view_residuals(traj, ext, scans, shared.view, shared.rows, v)[0]
        return np.median(d), np.median(d[first]), np.median(d[~first])
    def profile(c, centre, span, step):
        vals = centre + np.arange(-span, span + step/2, step)
        costs = []
        for v in vals:
            i = inc.copy(); i[c] = v; costs.append(med(i))
        return vals, np.array(costs)
    status = {}
    cols = list(columns)
    for r in range(rounds):
        for c in cols:
            span, step = SPAN(c)
            vals, costs = profile(c, 0.0, span, step)
            k = int(np.argmin(costs[:, 0]))
            interior = 0 < k < len(vals) - 1
            # significance: the cost one typical error either side of the minimum
            i0 = inc.copy(); i0[c] = vals[k]
            lo, hi = i0.copy(), i0.copy(); lo[c] -= TYP[c]; hi[c] += TYP[c]
            m0, ml, mh = costs[k, 0], med(lo)[0], med(hi)[0]
            sig = min(ml, mh) / m0 - 1
            ka, kb = np.argmin(costs[:, 1]), np.argmin(costs[:, 2])
            apart = abs(vals[ka] - vals[kb]) / 2
            status[c] = (interior, sig, apart)
            if interior and sig >= rise and apart <= hold * TYP[c]:
                inc[c] = vals[k]
            log(f"round {r} col {c}: min at {vals[k]:+.3f} ({'interior' if interior else 'EDGE'}), rise {sig:+.2f}, halves apart {apart:.3f}; inc {np.round(inc,3)}")
    accepted = [c for c in cols if status[c][0] and status[c][1] >= rise and status[c][2] <= hold * TYP[c]]
    inc[[c for c in cols if c not in accepted]] = 0
    for c in accepted:  # refine
        span, step = SPAN(c)
        for _ in range(2):
            span, step = step, step / 4
            vals, costs = profile(c, inc[c], span, step)
            inc[c] = vals[np.argmin(costs[:, 0])]
    return accepted, inc

def setup(root, lidar):
    rig = load_rig(root); truth = load_calibration(Path(root) / 'ground_truth.json')
    T = np.asarray(truth.T_ref_sensor[lidar]); gt = Extrinsic(T[:3,:3].copy(), T[:3,3].copy(), float(truth.time_offset[lidar]))
    traj = Trajectory.from_rig(rig); config = LidarFirstConfig()
    scans = load_scans(rig, lidar, traj, config, log=lambda _: None)
    pairs, _ = scan_pairs(traj, scans, gt.time_offset, config)
    return rig, gt, traj, config, scans, pairs, SharedView.of(rig, traj, scans)

def run(gt, traj, config, scans, pairs, view, ext, cols):
    corr = find_correspondences(traj, ext, scans, pairs, config.radius_end, config)
    shared = view.at(traj, ext, scans, pairs, consistency_residuals(traj, ext, scans, corr, np.zeros(7))[0])
    t = time.time()
    acc, inc = search(traj, ext, scans, shared, cols)
    e = ext.updated(inc)
    d0 = parameter_difference(ext.matrix(), ext.time_offset, gt.matrix(), gt.time_offset)
    d = parameter_difference(e.matrix(), e.time_offset, gt.matrix(), gt.time_offset)
    print(f"  {len(shared.rows.point)} rows; accepted {acc}; before cm {np.round(np.array(d0[:3])*100,1)} deg {np.round(np.rad2deg(d0[3:6]),2)} -> after cm {np.round(np.array(d[:3])*100,1)} deg {np.round(np.rad2deg(d[3:6]),2)} ({time.time()-t:.0f} s)")

if sys.argv[1] == 'synth':
    rig, gt, traj, config, scans, pairs, view = setup(sys.argv[2], 'lidar')
    for moved in ([np.deg2rad(3), 0, 0, 0, 0.3, 0, 0], [0, 0, 0, 0, 0, 0.4, 0], [0,0,0,0,1.5,0,0]):
        print('moved', np.round(moved, 3))
        run(gt, traj, config, scans, pairs, view, gt.updated(np.array(moved)), [0, 4, 5])
else:
    rig, gt, traj, config, scans, pairs, view = setup(sys.argv[2], 'velodyne')
    d = np.load(sys.argv[3])
    run(gt, traj, config, scans, pairs, view, Extrinsic(d['rotation'], d['translation'], float(d['time_offset'])), [0, 4, 5])
