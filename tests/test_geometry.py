"""Paper eq. 1 / 2 / 12 against closed-form poses, and gradients through them."""

import math

import numpy as np
import pytest
import roma
import torch

from moisst_ns.rig.geometry import (
    ReferenceTrajectory,
    calibrated_extrinsic,
    calibration_errors,
    interpolate_trajectory,
    make_pose,
    pose_to_xyz_rpy,
    sensor_pose,
)

F64 = torch.float64


def constant_twist_trajectory(num=6, dt=0.1):
    """Constant angular velocity about a tilted axis and constant linear velocity: SLERP/LERP are exact on it."""
    omega = torch.tensor([0.1, -0.2, 0.7], dtype=F64)
    velocity = torch.tensor([3.0, -1.0, 0.5], dtype=F64)
    times = torch.arange(num, dtype=F64) * dt
    rot = roma.rotvec_to_rotmat(times[:, None] * omega)
    trans = torch.tensor([1.0, 2.0, 3.0], dtype=F64) + times[:, None] * velocity
    return times, rot, trans, omega, velocity


def closed_form(t, omega, velocity):
    return roma.rotvec_to_rotmat(t[..., None] * omega), torch.tensor([1.0, 2.0, 3.0], dtype=F64) + t[..., None] * velocity


def test_interpolation_matches_closed_form_inside_and_extrapolated():
    times, rot, trans, omega, velocity = constant_twist_trajectory()
    t = torch.tensor([-0.35, -0.05, 0.0, 0.123, 0.25, 0.5, 0.61, 1.2], dtype=F64)  # before, inside, after
    pose = interpolate_trajectory(times, rot, trans, t)
    rot_true, trans_true = closed_form(t, omega, velocity)
    assert torch.allclose(pose[..., :3, :3], rot_true, atol=1e-12)
    assert torch.allclose(pose[..., :3, 3], trans_true, atol=1e-12)
    assert torch.allclose(pose[..., 3, :], torch.tensor([0, 0, 0, 1.0], dtype=F64).expand(len(t), 4))


def test_interpolation_hits_samples_exactly_and_is_piecewise():
    times = torch.tensor([0.0, 1.0, 3.0], dtype=F64)
    rot = roma.rotvec_to_rotmat(torch.tensor([[0, 0, 0.0], [0, 0, 0.5], [0, 0, -0.5]], dtype=F64))
    trans = torch.tensor([[0, 0, 0.0], [1, 0, 0], [1, 2, 0]], dtype=F64)
    pose = interpolate_trajectory(times, rot, trans, times)
    assert torch.allclose(pose[:, :3, :3], rot, atol=1e-12) and torch.allclose(pose[:, :3, 3], trans, atol=1e-12)
    # midpoint of the second segment: half of the relative rotation (-1 rad about z) and the mean position
    mid = interpolate_trajectory(times, rot, trans, torch.tensor(2.0, dtype=F64))
    assert torch.allclose(mid[:3, 3], torch.tensor([1.0, 1.0, 0.0], dtype=F64))
    assert torch.allclose(roma.rotmat_to_rotvec(mid[:3, :3]), torch.tensor([0, 0, 0.0], dtype=F64), atol=1e-12)
    # extrapolation after the end continues the last segment: t = 4 -> position (1, 3, 0), yaw -1.0
    end = interpolate_trajectory(times, rot, trans, torch.tensor(4.0, dtype=F64))
    assert torch.allclose(end[:3, 3], torch.tensor([1.0, 3.0, 0.0], dtype=F64))
    assert torch.allclose(roma.rotmat_to_rotvec(end[:3, :3])[2], torch.tensor(-1.0, dtype=F64))


def test_placing_points_by_rodrigues_is_eq1_applied_to_them():
    times, rot, trans, omega, velocity = constant_twist_trajectory()
    traj = ReferenceTrajectory(times, rot, trans)
    t = np.array([-0.35, -0.05, 0.0, 0.1, 0.123, 0.25, 0.5, 0.61, 1.2])  # before, inside, at a sample, after
    points = np.random.default_rng(0).normal(size=(len(t), 3)) * 20
    rot_true, trans_true = closed_form(torch.from_numpy(t), omega, velocity)
    expected = torch.einsum("nij,nj->ni", rot_true, torch.from_numpy(points)) + trans_true
    assert np.allclose(traj.placer(t)(points), expected.numpy(), atol=1e-10)
    rot_n, trans_n, _, _ = traj.pose_and_rates(t)
    assert np.allclose(traj.placer(t)(points), np.einsum("nij,nj->ni", rot_n, points) + trans_n, atol=1e-10)


def test_time_derivative_is_the_segment_velocity():
    times, rot, trans, omega, velocity = constant_twist_trajectory()
    t = torch.tensor([-0.2, 0.17, 0.33, 0.9], dtype=F64, requires_grad=True)
    pose = interpolate_trajectory(times, rot, trans, t)
    (dpos,) = torch.autograd.grad(pose[..., :3, 3] @ torch.tensor([1.0, 0, 0], dtype=F64), t, torch.ones(4, dtype=F64))
    assert torch.allclose(dpos, velocity[0].expand(4), atol=1e-10)
    # dR/dt = R [omega]_x for a constant body rate (omega is in the rotated frame, as rotvec products commute here)
    t2 = torch.tensor(0.27, dtype=F64, requires_grad=True)
    rot_t = interpolate_trajectory(times, rot, trans, t2)[:3, :3]
    jac = torch.stack([torch.autograd.grad(rot_t.reshape(-1)[k], t2, retain_graph=True)[0] for k in range(9)]).reshape(3, 3)
    expected = rot_t.detach() @ torch.tensor(
        [[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]], dtype=F64
    )
    assert torch.allclose(jac, expected, atol=1e-8)


def test_reference_trajectory_from_tum_uses_relative_times():
    stamps = np.array([1000.0, 1000.1, 1000.2])
    quats = np.array([[0, 0, 0, 1.0], [0, 0, math.sin(0.05), math.cos(0.05)], [0, 0, math.sin(0.1), math.cos(0.1)]])
    traj = ReferenceTrajectory.from_tum(stamps, np.zeros((3, 3)), quats)
    assert traj.t0 == 1000.0 and torch.allclose(traj.times, torch.tensor([0.0, 0.1, 0.2], dtype=F64))
    # yaw grows 0.1 rad per 0.1 s: at t = 0.05 s yaw is 0.05 rad
    yaw = roma.rotmat_to_rotvec(traj(torch.tensor(0.05, dtype=F64))[:3, :3])[2]
    assert abs(float(yaw) - 0.05) < 1e-12


def test_sensor_pose_is_eq2_and_zero_correction_is_the_prior():
    ref = make_pose(roma.rotvec_to_rotmat(torch.tensor([0.1, 0.2, 0.3], dtype=F64)), torch.tensor([1.0, 2, 3], dtype=F64))
    prior = make_pose(roma.rotvec_to_rotmat(torch.tensor([0.0, 1.5, 0], dtype=F64)), torch.tensor([0.5, 0, -0.2], dtype=F64))
    ext = calibrated_extrinsic(prior, torch.zeros(3), torch.zeros(3))
    assert torch.equal(ext, prior)
    world = sensor_pose(ref, ext)
    point = torch.tensor([0.3, -0.4, 2.0, 1.0], dtype=F64)
    assert torch.allclose(world @ point, ref @ (prior @ point))
    assert torch.allclose(torch.linalg.inv(world) @ world, torch.eye(4, dtype=F64), atol=1e-12)


def test_calibrated_extrinsic_composition_and_errors():
    prior = torch.eye(4, dtype=F64)
    est = calibrated_extrinsic(prior, torch.tensor([0.0, 0.0, math.radians(2.0)]), torch.tensor([0.03, 0.04, 0.0]))
    trans, rot = calibration_errors(est, prior)
    assert abs(float(trans) - 0.05) < 1e-7 and abs(float(rot) - 2.0) < 1e-5
    xyzrpy = pose_to_xyz_rpy(est)
    assert torch.allclose(xyzrpy, torch.tensor([0.03, 0.04, 0.0, 0.0, 0.0, 2.0], dtype=F64), atol=1e-6)


def test_interpolation_needs_two_poses():
    with pytest.raises(ValueError):
        interpolate_trajectory(torch.zeros(1, dtype=F64), torch.eye(3, dtype=F64)[None], torch.zeros(1, 3, dtype=F64), torch.zeros(1))


def test_per_frame_pose_errors_of_known_extrinsic_errors():
    """A translation error v of the extrinsic moves every frame by |v|; a rotation error rotates every frame by
    its angle; a time error moves frames along the trajectory by speed x dt (constant twist: exact)."""
    from moisst_ns.rig.calibration import RigData, frame_pose_errors, frame_poses
    from moisst_ns.rig.format import Calibration

    times, rot, trans, _, _ = constant_twist_trajectory(num=8)
    quats = roma.rotmat_to_unitquat(rot).numpy()
    data = RigData(sensor_names=["ref", "cam"], sensor_types=["camera", "camera"], reference_index=0,
                   prior_extrinsics=np.stack([np.eye(4)] * 2), prior_time_offsets=np.zeros(2),
                   trajectory_stamps=times.numpy() + 100.0, trajectory_positions=trans.numpy(), trajectory_quats_xyzw=quats, t0=100.0)
    true_ext = make_pose(roma.rotvec_to_rotmat(torch.tensor([0.1, 0.2, -0.1], dtype=F64)), torch.tensor([0.5, -0.3, 1.2], dtype=F64)).numpy()
    truth = Calibration("ref", {"ref": np.eye(4), "cam": true_ext}, {"ref": 0.0, "cam": 0.02})
    stamps = 100.0 + np.linspace(0.05, 0.6, 7)
    true_poses = frame_poses(data, truth, "cam", stamps)
    assert frame_pose_errors(true_poses, true_poses)["translation_cm"] == 0.0
    shifted = true_ext.copy()
    shifted[:3, 3] += [0.03, 0.0, -0.04]
    err = frame_pose_errors(frame_poses(data, Calibration("ref", {"ref": np.eye(4), "cam": shifted}, truth.time_offset), "cam", stamps), true_poses)
    assert err["translation_cm"] == pytest.approx(5.0, abs=1e-9) and err["translation_cm_std"] == pytest.approx(0.0, abs=1e-9)
    assert err["rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    turned = true_ext.copy()
    turned[:3, :3] = true_ext[:3, :3] @ roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, math.radians(2.0)], dtype=F64)).numpy()
    err = frame_pose_errors(frame_poses(data, Calibration("ref", {"ref": np.eye(4), "cam": turned}, truth.time_offset), "cam", stamps), true_poses)
    assert err["rotation_deg"] == pytest.approx(2.0, abs=1e-9)
    late = Calibration("ref", truth.T_ref_sensor, {"ref": 0.0, "cam": 0.03})
    err = frame_pose_errors(frame_poses(data, late, "cam", stamps), true_poses)
    # 10 ms late on a constant twist: rotation error |omega| * 0.01 rad for every frame
    assert err["rotation_deg"] == pytest.approx(math.degrees(0.01 * math.sqrt(0.1**2 + 0.2**2 + 0.7**2)), abs=1e-9)
