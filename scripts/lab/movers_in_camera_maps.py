"""Lab (2026-12-07, issues 34/35): what the LiDAR sees moving, left out of the maps the cameras are registered against.

    features RIG CAMERA none|moving|grown   one KITTI camera alone on image_00's feature map (the trajectory carried by
                                            the turn the stages find, the Velodyne at the factory calibration), the
                                            matches near the Velodyne's movers left out; needs
                                            docs/lab/2026-12-07-movers-in-camera-maps.patch applied
    lidar RIG all|static                    every camera of a synthetic rig on the LiDAR map at the LiDAR's true
                                            calibration, with or without its moving points

"grown": each scan's moving points grown to their DBSCAN cluster (ground plane off, eps 0.5 m, >= 5 % moving, < 15 m).
"""
import sys
import time

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

import moisst_ns.stages.camera.camera_registration as cr
import moisst_ns.stages.lidar.lidar_scans as ls
from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points


def grown(traj, ext, scans, moving_points=ls.moving_points):
    moving = moving_points(traj, ext, scans)
    out = moving.copy()
    for k in range(len(scans.stamps)):
        part = scans.scan(k)
        pts = scans.points[part]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        _, ground = cloud.segment_plane(0.2, 3, 200)
        rest = np.setdiff1d(np.arange(len(pts)), ground)
        labels = np.asarray(cloud.select_by_index(rest).cluster_dbscan(0.5, 5))
        for c in np.unique(labels[labels >= 0]):
            m = labels == c
            if moving[part][rest][m].sum() >= 3 and moving[part][rest][m].mean() >= 0.05 and np.ptp(pts[rest][m], axis=0).max() < 15:
                out[part.start + rest[m]] = True
    print(f"moving {moving.mean():.2%} of the points, grown to {out.mean():.2%}")
    return out


def report(res, truth, names):
    errs = calibration_report_errors(res.calibration, truth)
    for n in names:
        e = errs[n]
        err = parameter_difference(np.asarray(truth.T_ref_sensor[n]), truth.time_offset[n], np.asarray(res.calibration.T_ref_sensor[n]),
                                   res.calibration.time_offset[n])
        print(n, f"{e['translation_cm']:.2f} cm {e['rotation_deg']:.4f} deg {e['time_ms']:.2f} ms", " ".join(f"{p} {v:+.4f}" for p, v in zip(PARAMETERS, err)))


mode, folder, rest = sys.argv[1], sys.argv[2], sys.argv[3:]
rig, truth = load_rig(folder), load_calibration(folder + "/ground_truth.json")
start = time.time()
if mode == "features":
    camera, variant = rest
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad([0.587, -0.008, -0.004])).as_matrix()  # the turn the stages find on 0048
    rig.carry_trajectory(T)
    cal = Calibration.from_rig(rig)
    cal.T_ref_sensor["velodyne"], cal.time_offset["velodyne"] = np.asarray(truth.T_ref_sensor["velodyne"]).copy(), 0.0
    if variant == "none":
        cr._movers = lambda *a: []
    elif variant == "grown":
        ls.moving_points = grown
    res = cr.register_cameras(rig, cal, CameraRegistrationConfig(), sensors=[camera], lidar_undetermined={"velodyne": ["z"]},
                              log=lambda s: print(s) if "map" in s else None)
    report(res, truth, [camera])
else:
    (variant,) = rest
    cal = Calibration.from_rig(rig)
    cal.T_ref_sensor["lidar"], cal.time_offset["lidar"] = np.asarray(truth.T_ref_sensor["lidar"]), truth.time_offset["lidar"]
    traj = ReferenceTrajectory.of(rig)
    ext = Extrinsic(np.asarray(cal.T_ref_sensor["lidar"])[:3, :3], np.asarray(cal.T_ref_sensor["lidar"])[:3, 3], float(cal.time_offset["lidar"]))
    scans = ls.load_scans(rig, "lidar", traj, ls.LidarFirstConfig(), lambda s: None)
    keep = ~ls.moving_points(traj, ext, scans) if variant == "static" else np.ones(len(scans.points), bool)
    print(f"{(~keep).mean():.2%} of the points left out")

    def static_map(rig_, calibration, voxel, min_range, log=print):
        world = place_points(ReferenceTrajectory.of(rig_), ext, scans.points[keep], scans.times[keep])
        return np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world)).voxel_down_sample(voxel).points)

    cr.lidar_map = static_map
    res = cr.register_cameras(rig, cal, CameraRegistrationConfig(trajectory_draws=0), log=lambda s: None)
    report(res, truth, list(res.cameras))
print(f"{time.time() - start:.0f} s")
