"""Experiment (docs/lab/2026-11-25-kitti-shared-view.md): depth edges of a KITTI scan grouped into rings by azimuth
wraps (laser by laser) against elevation bins, scored by their distance to the reference image edges at the truth.
Usage: python scripts/lab/edge_rings.py RIG"""
import sys, numpy as np
from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.stages.lidar_first import LidarFirstConfig, load_scans, scan_pairs
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory
import moisst_ns.stages.lidar_view as lv
rig = load_rig(sys.argv[1]); truth = load_calibration(rig.root / "ground_truth.json")
name = next(n for n, s in rig.sensors.items() if s.type == "lidar")
traj, config = Trajectory.from_rig(rig), LidarFirstConfig()
scans = load_scans(rig, name, traj, config, lambda l: None)
view = lv.reference_view(rig, traj)
T = np.asarray(truth.T_ref_sensor[name]); ext = Extrinsic(T[:3,:3], T[:3,3], float(truth.time_offset[name]))
def wrap_edges(points):
    """lidar_view.depth_edges with rings = runs between azimuth wraps in stored order (KITTI's .bin: laser by laser)."""
    rng = np.linalg.norm(points, axis=1)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    ring = np.concatenate([[0], np.cumsum(np.abs(np.diff(azimuth)) > 180.0)])
    order = np.lexsort((azimuth, ring))
    r, az, rg = rng[order], azimuth[order], ring[order]
    same = (rg[1:] == rg[:-1]) & (np.abs(az[1:] - az[:-1]) < lv.NEIGHBOUR_DEG)
    jump = r[1:] - r[:-1]
    edge = np.zeros(len(points), dtype=bool)
    edge[1:] |= same & (jump < -(lv.JUMP[0] + lv.JUMP[1] * r[1:]))
    edge[:-1] |= same & (jump > lv.JUMP[0] + lv.JUMP[1] * r[:-1])
    return np.sort(order[edge])
for label, detect in (("wraps", wrap_edges), ("elev", lv.depth_edges)):
    edges = [detect(scans.points[scans.scan(k)]) for k in range(len(scans.stamps))]
    rows = lv.view_rows(traj, ext, scans, view, edges, np.arange(len(scans.stamps)), 0.05)
    d = lv.view_residuals(traj, ext, scans, view, rows, np.zeros(7))[0]
    print(label, sum(map(len, edges)), len(d), "median", np.median(d).round(2), "frac<2px", (d < 2).mean().round(3), "frac>=29", (d >= 29).mean().round(3))
# random points baseline
allpts = [np.arange(scans.scan(k).stop - scans.scan(k).start) for k in range(len(scans.stamps))]
rng=np.random.default_rng(0); allpts=[np.sort(rng.choice(a, 3000, replace=False)) for a in allpts]
rows = lv.view_rows(traj, ext, scans, view, allpts, np.arange(len(scans.stamps)), 0.05)
d = lv.view_residuals(traj, ext, scans, view, rows, np.zeros(7))[0]
print("random", len(d), "median", np.median(d).round(2), "frac<2px", (d < 2).mean().round(3))
