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
    invert_pose,
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
    assert torch.allclose(invert_pose(world) @ world, torch.eye(4, dtype=F64), atol=1e-12)


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
