"""LiDAR rays against hand-computed values, the depth loss, and LiDAR input handling."""


import numpy as np
import pytest
import torch

from moisst_ns.calibration_optimizer import CalibrationOptimizer, CalibrationOptimizerConfig
from moisst_ns.data.datamanager import load_lidar_points
from moisst_ns.losses import lidar_depth_loss
from moisst_ns.rig.calibration import RigData
from moisst_ns.rig.format import RigFormatError
from moisst_ns.rig.world import WorldFrame


def straight_line_rig(lidar_delta=0.05, scale=0.5, center=(1.0, 0.0, 0.0)):
    """Reference moving along world x at 10 m/s with identity attitude; LiDAR 1 m above it, yawed 90 deg."""
    lidar_ext = np.eye(4)
    lidar_ext[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # Rz(90 deg)
    lidar_ext[:3, 3] = [0.0, 0.0, 1.0]
    data = RigData(
        sensor_names=["cam", "lidar"],
        sensor_types=["camera", "lidar"],
        reference_index=0,
        prior_extrinsics=np.stack([np.eye(4), lidar_ext]),
        prior_time_offsets=np.array([0.0, lidar_delta]),
        trajectory_stamps=np.array([100.0, 101.0]),
        trajectory_positions=np.array([[0.0, 0, 0], [10.0, 0, 0]]),
        trajectory_quats_xyzw=np.array([[0, 0, 0, 1.0], [0, 0, 0, 1.0]]),
        t0=100.0,
    )
    data.frame_sensor_index, data.frame_stamps = np.array([0]), np.array([0.0])
    data.world = WorldFrame(center=np.array(center), scale=scale)
    return CalibrationOptimizer(CalibrationOptimizerConfig(), num_cameras=1, device="cpu", rig=data)


def test_lidar_ray_origin_direction_and_per_point_time():
    opt = straight_line_rig()
    sensor = torch.tensor([1, 1])
    # frame stamped 0.2 s (since t0); points fired 0 and 10 ms into the sweep
    stamp = torch.tensor([0.2, 0.21], dtype=torch.float64)
    points = torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.0, -3.0]])
    origins, dirs = opt.lidar_rays(sensor, stamp, points)
    # reference at t + delta = 0.25 / 0.26 s -> x = 2.5 / 2.6 m; LiDAR 1 m up; model = 0.5 * (p - (1, 0, 0))
    assert torch.allclose(origins, torch.tensor([[0.75, 0.0, 0.5], [0.8, 0.0, 0.5]]), atol=1e-6)
    # LiDAR x axis is world y (yaw 90 deg); LiDAR -z is world -z
    assert torch.allclose(dirs, torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]), atol=1e-6)
    # the point lies at origin + range * scale * direction: (2.6 - 1) * 0.5 + ... checked through the world point
    world = origins[0] / 0.5 + torch.tensor([1.0, 0, 0]) + 2.0 * dirs[0]
    assert torch.allclose(world, torch.tensor([2.5, 2.0, 1.0]), atol=1e-6)


def test_lidar_rays_follow_delta_and_extrinsic_gradients():
    opt = straight_line_rig()
    origins, _ = opt.lidar_rays(torch.tensor([1]), torch.tensor([0.2], dtype=torch.float64), torch.tensor([[1.0, 0, 0]]))
    (g_delta,) = torch.autograd.grad(origins[0, 0], opt.rig.time_offset, retain_graph=True)
    assert g_delta[1] == pytest.approx(10.0 * 0.5, rel=1e-5)  # velocity 10 m/s times scale
    (g_trans,) = torch.autograd.grad(origins[0, 2], opt.rig.translation)
    assert torch.allclose(g_trans[1], torch.tensor([0.0, 0.0, 0.5]))
    assert torch.all(g_trans[0] == 0)  # the reference is never moved


def test_camera_and_lidar_rays_in_one_bundle():
    from nerfstudio.cameras.rays import RayBundle

    opt = straight_line_rig()
    bundle = RayBundle(
        origins=torch.zeros(3, 3),
        directions=torch.tensor([[0, 0, -1.0], [0, 0, -1.0], [1.0, 0, 0]]),
        pixel_area=torch.ones(3, 1),
        camera_indices=torch.zeros(3, 1, dtype=torch.long),
        metadata={
            "is_lidar": torch.tensor([[False], [False], [True]]),
            "lidar_point": torch.tensor([[0, 0, 0], [0, 0, 0], [4.0, 0, 0]]),
            "lidar_stamp": torch.tensor([[0.0], [0.0], [0.5]], dtype=torch.float64),
            "lidar_sensor": torch.tensor([[0], [0], [1]]),
        },
    )
    # the camera frame's prior pose: the reference at t = 0, x = 0 -> model (-0.5, 0, 0)
    opt.apply_to_raybundle(bundle)
    assert torch.allclose(bundle.origins[:2], torch.zeros(2, 3), atol=1e-6)  # zero correction: unchanged
    assert torch.allclose(bundle.origins[2], torch.tensor([(5.5 - 1.0) * 0.5, 0.0, 0.5]), atol=1e-6)
    assert torch.allclose(bundle.directions[2], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)


def test_depth_loss_known_values():
    loss = lidar_depth_loss(torch.tensor([1.0, 2.0, 4.0]), torch.tensor([1.0, 1.0, 2.0]))
    assert float(loss) == pytest.approx((0 + 1 + 4) / 3)


def write_rig(tmp_path, scan: np.ndarray, name="000000.npy"):
    import json

    from PIL import Image

    (tmp_path / "images").mkdir()
    (tmp_path / "lidar").mkdir()
    Image.new("RGB", (8, 6)).save(tmp_path / "images" / "0.png")
    np.save(tmp_path / "lidar" / name, scan)
    (tmp_path / "traj.txt").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n")
    lidar = np.eye(4).tolist()
    rig = {
        "format": "moisst-rig/1",
        "reference_sensor": "cam",
        "trajectory": "traj.txt",
        "sensors": {
            "cam": {"type": "camera", "T_ref_sensor": np.eye(4).tolist(), "camera_model": "PINHOLE", "w": 8, "h": 6, "fl_x": 5, "fl_y": 5, "cx": 4, "cy": 3},
            "velo": {"type": "lidar", "T_ref_sensor": lidar, "time_offset": 0.01},
        },
        "frames": [{"sensor": "cam", "timestamp": 0.5, "file_path": "images/0.png"}, {"sensor": "velo", "timestamp": 0.5, "file_path": f"lidar/{name}"}],
    }
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    from moisst_ns.rig.calibration import RigData
    from moisst_ns.rig.format import load_rig

    full = load_rig(tmp_path)
    return RigData.from_rig(full), full


def test_nan_points_are_dropped_and_counted(tmp_path, capsys):
    scan = np.array([[5.0, 0, 0], [np.nan, 1, 1], [0, 7.0, 0], [np.inf, 0, 0]], dtype=np.float32)
    data, full = write_rig(tmp_path, scan)
    points, stamps, sensors = load_lidar_points(data, full, 1.0, 80.0)
    assert points.shape == (2, 3) and torch.all(sensors == 1)
    assert torch.allclose(stamps, torch.tensor([0.5, 0.5], dtype=torch.float64))
    assert "dropped 2 points" in capsys.readouterr().out


def test_scan_empty_after_range_filter_is_an_error(tmp_path):
    data, full = write_rig(tmp_path, np.array([[0.2, 0, 0], [0, 0.5, 0]], dtype=np.float32))
    with pytest.raises(RigFormatError, match="no points left"):
        load_lidar_points(data, full, 1.0, 80.0)
