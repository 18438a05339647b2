"""KITTI raw converter (``moisst-kitti-raw-to-rig``) on the real drive 2011_09_26_drive_0048 in ../shared/data.

Beside the format checks, two tests read the physics off the data: the Velodyne's spin direction (two scans placed in
the world agree better with clockwise per-point times than with counter-clockwise ones) and the factory calibration
(LiDAR depth edges land on image edges, and far better than at the paper-perturbed prior).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from moisst_ns.datasets.kitti360_io import read_key_values
from moisst_ns.datasets.kitti_raw import KittiRawConfig, KittiRawError, convert, oxts_poses, read_timestamps, sweep_times
from moisst_ns.rig.format import load_calibration, load_lidar_scan, load_rig, load_tum

from helpers import KITTI_DRIVE, KITTI_RAW, needs_kitti_raw, tree_hash

SYNC = KITTI_RAW / KITTI_DRIVE / "2011_09_26" / KITTI_DRIVE
CALIB = KITTI_RAW / "2011_09_26_calib" / "2011_09_26"
SENSOR_DIRS = ("image_00", "image_01", "image_02", "image_03", "velodyne_points", "oxts")


@pytest.fixture(scope="module")
def data_hash():
    return tree_hash(KITTI_RAW)


@pytest.fixture(scope="module")
def small(tmp_path_factory, data_hash):
    """Frames 0-3, every sensor, paper-perturbed priors."""
    config = KittiRawConfig(root=KITTI_RAW, drive=KITTI_DRIVE, out=tmp_path_factory.mktemp("raw") / "rig", first_frame=0, last_frame=3,
                            downscale=4, points_per_scan=5000, perturb="paper", seed=0)
    return convert(config)


@pytest.fixture(scope="module")
def full(tmp_path_factory, data_hash):
    """The whole drive: image_00 at full size, every Velodyne point, factory calibration."""
    config = KittiRawConfig(root=KITTI_RAW, drive=KITTI_DRIVE, out=tmp_path_factory.mktemp("raw") / "full", cameras=("image_00",))
    return convert(config)


def _pose(values) -> np.ndarray:
    """``R: ...`` (9) and ``T: ...`` (3) of a calib file as a 4x4."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = values["R"].reshape(3, 3), values["T"]
    return pose


def _factory():
    cam = read_key_values(CALIB / "calib_cam_to_cam.txt")
    rect = np.eye(4)
    rect[:3, :3] = cam["R_rect_00"].reshape(3, 3)
    return cam, rect, _pose(read_key_values(CALIB / "calib_velo_to_cam.txt")), _pose(read_key_values(CALIB / "calib_imu_to_velo.txt"))


def test_sweep_times_run_clockwise_from_the_front():
    points = np.array([[10.0, 0.0, 0.0], [0.0, 5.0, 1.0], [0.0, -5.0, 0.0], [-3.0, 1e-9, 0.0], [-3.0, -1e-9, 0.0]])
    np.testing.assert_allclose(sweep_times(points, 0.1), [0.0, -0.025, 0.025, -0.05, 0.05], atol=1e-9)
    np.testing.assert_allclose(sweep_times(points, 0.1, clockwise=False), [0.0, 0.025, -0.025, 0.05, -0.05], atol=1e-9)


def test_oxts_poses_follow_the_devkit():
    # lat 0 (scale 1): 1e-3 deg of longitude is er * 1e-3 * pi / 180 m east; yaw 90 deg turns x into y
    poses = oxts_poses(np.array([[0.0, 0.0, 10.0, 0.0, 0.0, 0.0], [1e-3, 1e-3, 12.0, 0.0, 0.0, np.pi / 2]]))
    metres = 6378137.0 * 1e-3 * np.pi / 180.0
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(poses[1, :3, 3], [metres, metres, 2.0], rtol=1e-9)
    np.testing.assert_allclose(poses[1, :3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@needs_kitti_raw
def test_rig_sensors_frames_and_factory_calibration(small):
    rig, truth = load_rig(small), load_calibration(small / "ground_truth.json")
    assert rig.reference_sensor == "image_00"
    assert list(rig.sensors) == ["image_00", "image_01", "image_02", "image_03", "velodyne"]
    assert all(len(rig.frames_of(s)) == 4 for s in rig.sensors)
    T = truth.T_ref_sensor
    np.testing.assert_allclose(T["image_01"][:3, 3], [0.537, 0.0, 0.0], atol=1e-3)
    np.testing.assert_array_equal(T["image_01"][:3, :3], np.eye(3))
    np.testing.assert_allclose(T["image_02"][:3, 3], [-0.06, 0.0, 0.0], atol=5e-3)  # colour pair 6 cm left of cam 0
    cam, rect, velo, _ = _factory()
    np.testing.assert_array_equal(T["velodyne"], rect @ velo)
    assert all(v == 0.0 for v in truth.time_offset.values())
    # priors: the paper's perturbation (+-0.5 m per axis, +-0.1 s) of the factory calibration
    for name in ("image_01", "velodyne"):
        np.testing.assert_allclose(np.abs(rig.sensors[name].T_ref_sensor[:3, 3] - T[name][:3, 3]), 0.5, atol=1e-12)
        assert abs(rig.sensors[name].time_offset) == pytest.approx(0.1)
    intr = rig.sensors["image_02"].intrinsics
    P = cam["P_rect_02"].reshape(3, 4)
    assert (intr["w"], intr["h"]) == (1242 // 4, 375 // 4)
    assert intr["fl_x"] == pytest.approx(P[0, 0] / 4) and intr["cx"] == pytest.approx((P[0, 2] + 0.5) / 4)


@needs_kitti_raw
def test_trigger_stamps_and_per_point_times(small):
    rig = load_rig(small)
    meta = json.loads((small / "rig.json").read_text())["metadata"]
    assert meta["stamps"] == "trigger" and "velodyne" in meta["camera_stamps"]
    velo = read_timestamps(SYNC / "velodyne_points" / "timestamps.txt")
    origin = read_timestamps(SYNC / "image_00" / "timestamps.txt")[0]
    for name in rig.sensors:
        np.testing.assert_allclose([f.timestamp for f in rig.frames_of(name)], (velo[:4] - origin) * 1e-9, atol=1e-9)
    start, end = (read_timestamps(SYNC / "velodyne_points" / f"timestamps_{w}.txt") for w in ("start", "end"))
    for k, frame in enumerate(rig.frames_of("velodyne")):
        points, times, _ = load_lidar_scan(small / frame.file_path)
        raw = np.fromfile(SYNC / "velodyne_points" / "data" / f"{k:010d}.bin", dtype=np.float32).reshape(-1, 4)[:, :3]
        raw_rows = {row.tobytes() for row in raw}
        assert len(points) == 5000 and all(row.tobytes() in raw_rows for row in points)  # a subset of the raw sweep
        np.testing.assert_allclose(times, -np.arctan2(points[:, 1], points[:, 0]) / (2 * np.pi) * (end[k] - start[k]) * 1e-9, atol=1e-9)


@needs_kitti_raw
def test_reference_trajectory_is_the_oxts_carried_to_camera_0(full):
    stamps, positions, quats = load_tum(full / "reference_poses.txt")
    oxts = sorted((SYNC / "oxts" / "data").glob("*.txt"))
    assert len(stamps) == len(oxts) == 22
    origin = read_timestamps(SYNC / "image_00" / "timestamps.txt")[0]
    np.testing.assert_allclose(stamps, (read_timestamps(SYNC / "oxts" / "timestamps.txt") - origin) * 1e-9, atol=1e-9)
    _, rect, velo, imu = _factory()
    import roma

    rotations = roma.unitquat_to_rotmat(torch.from_numpy(quats)).numpy()
    packets = np.array([np.loadtxt(file)[:6] for file in oxts])
    scale, er = np.cos(np.radians(packets[0, 0])), 6378137.0
    mercator = np.stack([scale * er * np.radians(packets[:, 1]),
                         scale * er * np.log(np.tan(np.pi / 4 + np.radians(packets[:, 0]) / 2)), packets[:, 2]], axis=1)
    for k, (roll, pitch, yaw) in enumerate(packets[:, 3:]):
        c, s = np.cos([roll, pitch, yaw]), np.sin([roll, pitch, yaw])
        rx = np.array([[1, 0, 0], [0, c[0], -s[0]], [0, s[0], c[0]]])
        ry = np.array([[c[1], 0, s[1]], [0, 1, 0], [-s[1], 0, c[1]]])
        rz = np.array([[c[2], -s[2], 0], [s[2], c[2], 0], [0, 0, 1]])
        world_imu = np.eye(4)
        world_imu[:3, :3], world_imu[:3, 3] = rz @ ry @ rx, mercator[k] - mercator[0]
        world_ref = world_imu @ np.linalg.inv(imu) @ np.linalg.inv(velo) @ np.linalg.inv(rect)
        np.testing.assert_allclose(positions[k], world_ref[:3, 3], atol=1e-6)
        np.testing.assert_allclose(rotations[k], world_ref[:3, :3], atol=1e-5)
    length = np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()
    assert 15.0 < length < 20.0, length


def _placed_scans(rig, clockwise: bool):
    """Every Velodyne scan (points beyond 3 m) placed in the world at the factory calibration, eq. 1-2 per point."""
    from moisst_ns.rig.geometry import ReferenceTrajectory
    from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, PointTimes, place_points

    traj, T = ReferenceTrajectory.of(rig), rig.sensors["velodyne"].T_ref_sensor
    ext = Extrinsic(T[:3, :3], T[:3, 3], 0.0)
    out = []
    for frame in rig.frames_of("velodyne"):
        points, times, _ = load_lidar_scan(rig.root / frame.file_path)
        keep = np.linalg.norm(points[:, :2], axis=1) > 3.0
        points, times = points[keep].astype(np.float64), np.round(times[keep], 4)  # 0.1 ms (< 1 mm): 1000 poses, not 120 k
        stamps = frame.timestamp - rig.trajectory_stamps[0] + (times if clockwise else -times)
        world = place_points(traj, ext, points, PointTimes.of(stamps))
        side = (np.abs(points[:, 1]) > np.abs(points[:, 0])) & (points[:, 2] > -1.2)  # beside the car, above the road
        out.append((world, side))
    return out


@needs_kitti_raw
def test_spin_direction_is_clockwise_from_the_data(full):
    """Consecutive scans placed with clockwise per-point times agree better than with counter-clockwise ones.

    The two hypotheses move a point by twice its time offset times the speed (~8 m/s) along the drive; between two
    scans that differs most for points beside the car (their azimuth changes most), so those are compared: median
    distance from 3000 of them to the nearest point of the next scan, averaged over the 21 consecutive pairs.
    """
    from scipy.spatial import cKDTree

    rig = load_rig(full)
    medians = {}
    for clockwise in (True, False):
        scans = _placed_scans(rig, clockwise)
        per_pair = []
        for k in range(len(scans) - 1):
            world, side = scans[k]
            query = world[side][np.random.default_rng(k).choice(side.sum(), min(3000, side.sum()), replace=False)]
            per_pair.append(np.median(cKDTree(scans[k + 1][0]).query(query)[0]))
        medians[clockwise] = np.array(per_pair)
    print(f"median NN distance, mean over pairs: clockwise {medians[True].mean():.4f} m, "
          f"counter-clockwise {medians[False].mean():.4f} m; clockwise better in {(medians[True] < medians[False]).sum()}/21")
    assert medians[True].mean() < 0.98 * medians[False].mean(), medians
    assert (medians[True] < medians[False]).sum() >= 14, medians


@needs_kitti_raw
def test_lidar_depth_edges_land_on_image_edges_at_the_factory_calibration(full, small):
    """Velodyne depth edges (range jumps > 1 m along a ring, the near side, < 25 m) projected into image_00 of the same
    frame: their mean distance to the nearest Canny edge, relative to that of all projected points, is far lower at the
    factory calibration than at the paper-perturbed prior."""
    import cv2

    rig = load_rig(full)
    intr = rig.sensors["image_00"].intrinsics
    K = np.array([[intr["fl_x"], 0.0, intr["cx"] - 0.5], [0.0, intr["fl_y"], intr["cy"] - 0.5], [0.0, 0.0, 1.0]])

    def edge_ratio(T, k):
        points, _, _ = load_lidar_scan(full / rig.frames_of("velodyne")[k].file_path)
        rng = np.linalg.norm(points, axis=1)
        jump = np.flatnonzero(np.abs(np.diff(rng)) > 1.0)
        near = np.where(rng[jump] < rng[jump + 1], jump, jump + 1)
        near = np.unique(near[rng[near] < 25.0])
        grey = cv2.imread(str(full / rig.frames_of("image_00")[k].file_path), cv2.IMREAD_GRAYSCALE)
        far_from_edge = cv2.distanceTransform(255 - cv2.Canny(cv2.GaussianBlur(grey, (0, 0), 2.0), 30, 90), cv2.DIST_L2, 3)

        def mean_distance(p):
            cam = p.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            cam = cam[cam[:, 2] > 1.0]
            uv = np.round(cam[:, :2] / cam[:, 2:] @ K[:2, :2].T + K[:2, 2]).astype(int)
            inside = (uv >= 0).all(axis=1) & (uv[:, 0] < grey.shape[1]) & (uv[:, 1] < grey.shape[0])
            return np.minimum(far_from_edge[uv[inside, 1], uv[inside, 0]], 20.0).mean()

        return mean_distance(points[near]) / mean_distance(points)

    truth = rig.sensors["velodyne"].T_ref_sensor
    prior = load_rig(small).sensors["velodyne"].T_ref_sensor
    at_truth = np.array([edge_ratio(truth, k) for k in range(0, 22, 3)])
    at_prior = np.array([edge_ratio(prior, k) for k in range(0, 22, 3)])
    print(f"depth-edge / all-points distance to image edges: truth {np.round(at_truth, 3)}, prior {np.round(at_prior, 3)}")
    assert at_truth.mean() < 0.8 and at_truth.mean() < 0.9 * at_prior.mean(), (at_truth, at_prior)
    assert (at_truth < at_prior).sum() >= 6, (at_truth, at_prior)


def _pykitti_tree(base: Path) -> Path:
    """ROOT/DATE/calib_*.txt (copies) and ROOT/DATE/KITTI_DRIVE/<sensor> (links to the shared data's folders)."""
    day = base / "2011_09_26"
    (day / KITTI_DRIVE).mkdir(parents=True)
    for calib in CALIB.glob("calib_*.txt"):
        (day / calib.name).write_bytes(calib.read_bytes())
    for name in SENSOR_DIRS:
        os.symlink(SYNC / name, day / KITTI_DRIVE / name)
    return base


@needs_kitti_raw
def test_pykitti_layout_gives_the_same_rig(tmp_path, small):
    root = _pykitti_tree(tmp_path / "kitti")
    out = convert(KittiRawConfig(root=root, drive=KITTI_DRIVE, out=tmp_path / "rig", first_frame=0, last_frame=3, downscale=4,
                                 points_per_scan=5000, perturb="paper", seed=0))
    mine, ref = json.loads((out / "rig.json").read_text()), json.loads((small / "rig.json").read_text())
    assert mine["metadata"]["layout"] == "pykitti" and ref["metadata"]["layout"] == "download"
    assert mine["sensors"] == ref["sensors"] and mine["frames"] == ref["frames"]
    assert (out / "reference_poses.txt").read_text() == (small / "reference_poses.txt").read_text()
    np.testing.assert_array_equal(np.load(out / "lidar/velodyne/0000000002.npz")["points"],
                                  np.load(small / "lidar/velodyne/0000000002.npz")["points"])


@needs_kitti_raw
def test_recorded_stamps_are_each_sensors_own_and_rot10_priors(tmp_path):
    out = convert(KittiRawConfig(root=KITTI_RAW, drive=KITTI_DRIVE, out=tmp_path / "rig", first_frame=5, last_frame=6, downscale=4,
                                 cameras=("image_02",), lidar=False, stamps="recorded", perturb="rot10"))
    rig, truth = load_rig(out), load_calibration(out / "ground_truth.json")
    assert sorted(rig.sensors) == ["image_00", "image_02"]
    rel = truth.T_ref_sensor["image_02"][:3, :3].T @ rig.sensors["image_02"].T_ref_sensor[:3, :3]
    assert 16.0 < np.degrees(np.arccos((np.trace(rel) - 1) / 2)) < 18.0  # three 10 deg rotations compose to ~17.2 deg
    origin = read_timestamps(SYNC / "image_00" / "timestamps.txt")[0]
    for name in rig.sensors:
        own = read_timestamps(SYNC / name / "timestamps.txt")[5:7]
        np.testing.assert_allclose([f.timestamp for f in rig.frames_of(name)], (own - origin) * 1e-9, atol=1e-9)
    from PIL import Image

    assert Image.open(out / rig.frames_of("image_00")[0].file_path).mode == "RGB"  # grey camera written as 3 channels


@needs_kitti_raw
@pytest.mark.parametrize(
    "edit, overrides, file_part, message",
    [
        (lambda r: (r / "2011_09_26" / "calib_velo_to_cam.txt").unlink(), {}, "calib_velo_to_cam.txt", "not found"),
        (lambda r: (r / "2011_09_26" / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0\n"), {},
         "calib_imu_to_velo.txt: T", "expected 3 numbers"),
        (lambda r: (r / "2011_09_26" / KITTI_DRIVE / "image_03").unlink(), {}, "image_03/timestamps.txt", "not found"),
        (lambda r: None, {"cameras": ("image_00", "image_07")}, "--cameras", "unknown camera 'image_07'"),
        (lambda r: None, {"last_frame": 22}, "image_00/timestamps.txt: frame count", "frame 22 requested"),
        (lambda r: None, {"drive": "2011_09_26_drive_0099_sync"}, "drive folder", "not found"),
    ],
    ids=["missing-calib-file", "short-calib-line", "missing-camera-folder", "unknown-camera", "frame-beyond-drive", "no-drive"],
)
def test_bad_input_gets_one_line_naming_the_file(tmp_path, edit, overrides, file_part, message):
    root = _pykitti_tree(tmp_path / "kitti")
    edit(root)
    config = KittiRawConfig(root=root, drive=KITTI_DRIVE, out=tmp_path / "rig", downscale=4, points_per_scan=100)
    for key, value in overrides.items():
        setattr(config, key, value)
    with pytest.raises(KittiRawError) as err:
        convert(config)
    text = str(err.value)
    assert "\n" not in text and file_part in text and message in text, text
    assert not (tmp_path / "rig").exists()


@needs_kitti_raw
def test_cli_error_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "moisst_ns.cli.kitti_raw_to_rig", str(KITTI_RAW), KITTI_DRIVE, "--out", str(tmp_path / "o"),
                           "--cameras", "image_09"], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("moisst-kitti-raw-to-rig: error:") and "image_09" in lines[0], proc.stderr


@needs_kitti_raw
def test_nothing_is_written_into_the_dataset(data_hash, small, full, tmp_path):
    with pytest.raises(KittiRawError, match="must not be inside the KITTI raw folder"):
        convert(KittiRawConfig(root=KITTI_RAW, drive=KITTI_DRIVE, out=KITTI_RAW / "rig", last_frame=0))
    assert not (KITTI_RAW / "rig").exists()
    assert tree_hash(KITTI_RAW) == data_hash
