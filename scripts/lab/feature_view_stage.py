"""Experiment (docs/lab/2026-11-25-kitti-shared-view.md): the LiDAR-first stage with the reference camera's triangulated features (camera_map.feature_map) as
the shared view instead of depth edges (monkeypatched)."""
import sys, runpy
from dataclasses import dataclass, replace
import numpy as np, open3d as o3d
import moisst_ns.stages.lidar_first as lf
from moisst_ns.rig.format import Calibration
from moisst_ns.stages.camera_map import feature_map, FeatureMapConfig
from moisst_ns.stages.lidar_geometry import place_points, placement_jacobian, trajectory_at
RADIUS = float(sys.argv.pop(2)) if len(sys.argv) > 2 and sys.argv[2].replace('.', '').isdigit() else 0.3
@dataclass
class Rows:
    point: np.ndarray
    target: np.ndarray
    normal: np.ndarray
@dataclass
class FeatureView:
    tri: np.ndarray
    view: object = None
    rows: object = None
    scale: float = 0.0
    @classmethod
    def of(cls, rig, traj, scans):
        return cls(feature_map(rig, Calibration.from_rig(rig), FeatureMapConfig(patch_points=0), lambda l: None))
    def at(self, traj, ext, scans, pairs, plane):
        world = place_points(traj, ext, scans.points, scans.times)
        nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(world)); nns.knn_index()
        idx, d2 = nns.knn_search(o3d.core.Tensor(self.tri), 1)
        idx, d = idx.numpy()[:, 0].astype(np.int64), np.sqrt(d2.numpy()[:, 0])
        keep = (d < RADIUS) & scans.planar[idx]
        src = idx[keep]
        rot, _, _, _ = trajectory_at(traj, scans.times[src], ext.time_offset)
        n = np.einsum("nij,nj->ni", rot, scans.normals[src] @ ext.rotation.T)
        rows = Rows(src, self.tri[keep], n)
        r = feature_residuals(traj, ext, scans, None, rows, np.zeros(7))[0]
        return replace(self, rows=rows, scale=float(np.median(np.abs(plane)) / max(np.median(np.abs(r)), 1e-4)) if len(r) else 0.0)
def feature_residuals(traj, ext, scans, view, rows, increment):
    v, j = placement_jacobian(traj, ext, increment, scans.points[rows.point], scans.times[rows.point], rows.normal)
    return v - np.einsum("ni,ni->n", rows.normal, rows.target), j
# usage: python scripts/lab/feature_view_stage.py RIG [RADIUS_M] shared_view=True split_half=False
lf.SharedView = FeatureView
lf.view_residuals = feature_residuals
sys.argv = ["lidar_stage.py"] + sys.argv[1:]
runpy.run_path(str(__import__("pathlib").Path(__file__).resolve().parents[1] / "lidar_stage.py"), run_name="__main__")
