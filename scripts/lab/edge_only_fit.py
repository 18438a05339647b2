"""Experiment (docs/lab/2026-11-25-kitti-shared-view.md): LiDAR depth edges alone fitted from the prior against the
reference camera's edge distance transform, caps coarse to fine. Usage: python scripts/lab/edge_only_fit.py RIG CAPS FREE
(e.g. /tmp/k48 100,30,10 0,1,2,3,4: rotation and two translation components in the Jacobian order)."""
import sys, time, numpy as np
from scipy.optimize import least_squares
from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.stages.lidar_first import LidarFirstConfig, load_scans
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory
import moisst_ns.stages.lidar_view as lv
import roma, torch
rig = load_rig(sys.argv[1]); truth = load_calibration(rig.root / "ground_truth.json")
caps = [float(c) for c in sys.argv[2].split(",")]
free = np.array([int(c) for c in sys.argv[3].split(",")])
name = next(n for n, s in rig.sensors.items() if s.type == "lidar")
traj, config = Trajectory.from_rig(rig), LidarFirstConfig()
scans = load_scans(rig, name, traj, config, lambda l: None)
edges = [lv.depth_edges(scans.points[scans.scan(k)]) for k in range(len(scans.stamps))]
T = np.asarray(truth.T_ref_sensor[name]); gt = Extrinsic(T[:3,:3], T[:3,3], float(truth.time_offset[name]))
P = rig.sensors[name].T_ref_sensor; ext = Extrinsic(P[:3,:3], P[:3,3], rig.sensors[name].time_offset)
def err(e):
    dR = gt.rotation.T @ e.rotation
    ang = np.degrees(np.arccos(np.clip((np.trace(dR)-1)/2, -1, 1)))
    rv = np.degrees(roma.rotmat_to_rotvec(torch.from_numpy(dR)).numpy())
    return f"{100*np.linalg.norm(e.translation-gt.translation):.1f} cm {ang:.2f} deg ({(100*(e.translation-gt.translation)).round(1)} cm, rotvec {rv.round(2)}) delta {1000*(e.time_offset-gt.time_offset):.1f} ms"
print("prior", err(ext))
t0=time.time()
for cap in caps:
    lv.MAX_DISTANCE = cap
    view = lv.reference_view(rig, traj)
    for outer in range(4):
        rows = lv.view_rows(traj, ext, scans, view, edges, np.arange(len(scans.stamps)), 0.05)
        fun = lambda x: lv.view_residuals(traj, ext, scans, view, rows, x)
        cache = {}
        full = lambda y: np.zeros(7) if False else np.bincount(free, weights=y, minlength=7)
        res = least_squares(lambda y: fun(full(y))[0], np.zeros(len(free)), jac=lambda y: fun(full(y))[1][:, free], loss="soft_l1", f_scale=max(2.0, cap/10), x_scale=np.array([0.02,0.02,0.02,0.1,0.1,0.1,0.01])[free], max_nfev=30)
        ext = ext.updated(full(res.x))
        print(f"cap {cap} outer {outer}: rows {len(rows.point)} cost {res.cost/len(rows.point):.2f}", err(ext), f"{time.time()-t0:.0f}s", flush=True)
