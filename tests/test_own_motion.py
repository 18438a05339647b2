"""A camera placed by its own motion: on the map (``moisst_ns.stages.camera.own_motion``), by its own tracks on the
trajectory alone (``own_tracks``), and its place in the camera stage."""

import time
from dataclasses import replace

import numpy as np
import pytest
import roma
import torch

from moisst_ns.datasets.synth import SynthConfig, make_rig
from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig, CameraResult, own_motion_result, register_cameras
from moisst_ns.stages.camera.lidar_map import lidar_map
from moisst_ns.stages.camera.own_tracks import OwnTracksConfig, fit_own_tracks, sampson_px, tracks, weak_by_motion
from moisst_ns.stages.camera.own_motion import MapSurface, OwnMatches, OwnMotionConfig, OwnMotionFit, fit_own_motion, own_cloud, own_matches
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER

# the reference camera's axes (OpenCV: x right, y down, z forward); a side camera looking left (its z = the
# reference's -x, its x forward), 0.8 m left of, 0.1 m above and 0.6 m behind it
SIDE = np.array([[0.0, 0.0, -1.0, -0.8], [0.0, 1.0, 0.0, -0.1], [1.0, 0.0, 0.0, -0.6], [0.0, 0.0, 0.0, 1.0]])


def _trajectory(turn: float, accel: float) -> ReferenceTrajectory:
    """Reference poses at 100 Hz for 4 s: forward (its z) from 4 m/s with ``accel`` m/s^2, turning about its y axis at
    ``turn`` rad/s; the reference frame's y points down, world z up is its -y."""
    t = np.arange(0.0, 4.0, 0.01)
    yaw = turn * t
    speed = 4.0 + accel * t
    heading = np.stack([np.sin(yaw), np.zeros_like(t), np.cos(yaw)], 1)
    step = np.concatenate([[np.zeros(3)], (speed[:-1, None] * heading[:-1] + speed[1:, None] * heading[1:]) / 2 * 0.01])
    positions = np.cumsum(step, 0)
    rotations = roma.rotvec_to_rotmat(torch.from_numpy(np.stack([np.zeros_like(t), yaw, np.zeros_like(t)], 1))).numpy()
    quats = roma.rotmat_to_unitquat(torch.from_numpy(rotations)).numpy()
    return ReferenceTrajectory.from_tum(t, positions, quats)


def _matches(traj: ReferenceTrajectory, X: np.ndarray, delta: float, world: np.ndarray, stamps: np.ndarray, rng):
    """Exact matches of ``world`` points between frames up to 3 apart of a camera at ``X`` and ``delta``, and the points."""
    poses = (traj(torch.from_numpy(stamps + delta)) @ torch.from_numpy(X)).numpy()
    parts = []
    for a in range(len(stamps)):
        for b in range(a + 1, min(a + 4, len(stamps))):
            index = rng.choice(len(world), 200, replace=False)
            pts = world[index]
            cams = [(pts - poses[f][:3, 3]) @ poses[f][:3, :3] for f in (a, b)]
            ok = (cams[0][:, 2] > 1.0) & (cams[1][:, 2] > 1.0)
            ok &= np.all(np.abs(cams[0][:, :2] / cams[0][:, 2:]) < 0.8, 1) & np.all(np.abs(cams[1][:, :2] / cams[1][:, 2:]) < 0.8, 1)
            parts.append((np.full(ok.sum(), a), np.full(ok.sum(), b), cams[0][ok, :2] / cams[0][ok, 2:], cams[1][ok, :2] / cams[1][ok, 2:], pts[ok], index[ok]))
    fa, fb, xa, xb, seen, index = (np.concatenate(c) for c in zip(*parts))
    keys = (fa * len(world) + index, fb * len(world) + index)  # one keypoint per point and frame: the tracks are the points
    return OwnMatches(fa, fb, xa, xb, np.zeros(len(fa)), np.zeros(len(fa)), stamps, 0.0, 240, *keys), seen


def _error(prior, prior_offset, theta, truth, truth_offset):
    """The estimate minus the truth: translation m, rotation rad, delta s (``parameter_difference``)."""
    X = calibrated_extrinsic(torch.from_numpy(prior), torch.from_numpy(theta[:3]), torch.from_numpy(theta[3:6])).numpy()
    return np.asarray(parameter_difference(truth, truth_offset, X, prior_offset + theta[6]))


def _perturbed() -> np.ndarray:
    """The side camera's extrinsic 30 cm and 3 deg off on every axis."""
    prior = SIDE.copy()
    prior[:3, :3] = SIDE[:3, :3] @ roma.rotvec_to_rotmat(torch.tensor(np.deg2rad([3.0, -3.0, 3.0]))).numpy()
    prior[:3, 3] += [0.3, -0.3, 0.3]
    return prior


def _street(spacing: float = 0.1) -> np.ndarray:
    """Reference-frame world (y down): the ground 1.6 m below, a façade 6 m to the left, cross walls every 12 m."""
    u = np.arange(-5.0, 60.0, spacing)
    h = np.arange(-1.6, 3.0, spacing)
    ground = np.stack(np.meshgrid(np.arange(-10.0, 7.0, spacing), [1.6], u), -1).reshape(-1, 3)
    facade = np.stack(np.meshgrid([-6.0], -h, u), -1).reshape(-1, 3)
    walls = [np.stack(np.meshgrid(np.arange(-6.0, -3.0, spacing), -h, [z]), -1).reshape(-1, 3) for z in np.arange(4.0, 60.0, 12.0)]
    return np.concatenate([ground, facade] + walls)


def test_the_own_cloud_is_the_seen_points_and_moves_with_the_lever_arm_and_the_offset():
    """At the true calibration the matches triangulate to the points they were made from (1e-6 m); on a straight drive
    at constant speed a lever-arm correction moves the cloud by the trajectory's rotation of it and an offset
    correction by the velocity times it (the motion alone cannot tell them apart: the map has to)."""
    traj, rng = _trajectory(0.0, 0.0), np.random.default_rng(0)
    world = _street(0.5)
    stamps = np.arange(0.2, 2.0, 0.1)
    matches, seen = _matches(traj, SIDE, 0.02, world, stamps, rng)
    cloud, ok = own_cloud(np.r_[np.zeros(6), 0.02], matches, traj, SIDE, 0.0)
    assert ok.mean() > 0.95 and len(cloud) > 500
    np.testing.assert_allclose(cloud[ok], seen[ok], atol=1e-6)
    shift = np.array([0.05, -0.03, 0.2])
    moved, _ = own_cloud(np.r_[np.zeros(3), shift, 0.02], matches, traj, SIDE, 0.0)
    np.testing.assert_allclose(moved[ok] - cloud[ok], np.broadcast_to(shift, cloud[ok].shape), atol=1e-6)  # no turn: R = I
    later, _ = own_cloud(np.r_[np.zeros(6), 0.03], matches, traj, SIDE, 0.0)
    np.testing.assert_allclose(later[ok] - cloud[ok], np.broadcast_to([0.0, 0.0, 0.04], cloud[ok].shape), atol=1e-6)  # 4 m/s x 10 ms


def test_exact_matches_on_a_turning_accelerating_drive_place_the_camera_from_a_coarse_prior():
    """Exact matches against an exact map of planes, a drive that turns and speeds up (which separates the offset from
    the along-track lever arm): from 30 cm / 3 deg / 80 ms the fit ends at the truth (measured 1e-13 m / rad / s),
    its held-back loss far below the prior's."""
    traj, rng = _trajectory(0.15, 1.0), np.random.default_rng(1)
    world = _street(0.1)
    stamps = np.arange(0.3, 3.2, 0.1)
    matches, _ = _matches(traj, SIDE, 0.03, world, stamps, rng)
    prior = _perturbed()
    fit = fit_own_motion(traj, matches, MapSurface.of(world, 0.3), prior, 0.11, OwnMotionConfig(min_points=200), lambda s: None)
    d = _error(prior, 0.11, fit.theta, SIDE, 0.03)
    assert np.all(np.abs(d) < 1e-6), d
    assert fit.loss_estimate < 0.2 * fit.loss_prior


@pytest.fixture(scope="module")
def rig160(tmp_path_factory):
    """A 160x120 street rig of 30 frames, priors perturbed as in the paper (86.6 cm / 8.8 deg / 100 ms)."""
    return make_rig(SynthConfig(out=tmp_path_factory.mktemp("own") / "rig", seed=1, width=160, height=120, frames=30, perturb="paper"))


def test_a_side_camera_is_placed_by_its_own_images_against_the_lidar_map(rig160):
    """The side camera of a rendered street rig from the paper's perturbation, the LiDAR map at the truth: within
    3 cm / 0.2 deg / 2 ms (measured 1.30 cm / 0.065 deg / 0.42 ms), every parameter within 3 sigma (measured 1.5)."""
    rig, truth = load_rig(rig160), load_calibration(rig160 / "ground_truth.json")
    config = OwnMotionConfig()
    surface = MapSurface.of(lidar_map(rig, truth, 0.05, 2.0, lambda s: None), config.normal_radius)
    prior, offset = np.asarray(rig.sensors["cam_left"].T_ref_sensor), float(rig.sensors["cam_left"].time_offset)
    fit = fit_own_motion(ReferenceTrajectory.of(rig), own_matches(rig, "cam_left", config), surface, prior, offset, config, lambda s: None)
    d = _error(prior, offset, fit.theta, truth.T_ref_sensor["cam_left"], truth.time_offset["cam_left"])
    assert np.linalg.norm(d[:3]) < 0.03 and np.rad2deg(np.linalg.norm(d[3:6])) < 0.2 and abs(d[6]) < 0.002, d
    sigma = fit.sigma[list(JACOBIAN_ORDER)]
    assert np.all(np.abs(d) < 3 * sigma), np.abs(d) / sigma


def _kept(prior: np.ndarray) -> CameraResult:
    return CameraResult("cam_left", prior, 0.1, prior, 0.1, [float("inf")] * 7, 1.0, 1.0, True, note="a wrong minimum", history=[{"correction": [0.0] * 7}])


def _fit(split: float, loss: float) -> OwnMotionFit:
    theta = np.array([0.01, -0.02, 0.0, 0.1, -0.05, 0.2, -0.03])
    return OwnMotionFit(theta, np.full(7, 1e-3), np.full(7, split), np.full(7, 3e-3), np.full(7, 2e-3), 5000, 0.4, loss)


@pytest.mark.parametrize("split, loss, bound, why", [(1e-4, 0.05, 2.0, ""), (0.5, 0.05, 2.0, "the two halves of the drive place it apart on roll, pitch, yaw, x, y, z"),
                                                   (1e-4, 0.5, 2.0, "held-back loss 0.5 m is no lower than the prior's 0.4 m"),
                                                   (1e-4, 0.05, 0.15, "its own motion puts it beyond its bound on z")])
def test_a_camera_left_at_its_prior_takes_its_own_motions_fit_only_where_its_guards_pass(split, loss, bound, why):
    """The stage's use of the fit: its corrections applied to the prior (eq. 12), sigma the largest of its four parts, the
    photometric fit's reason kept in ``start``; the prior again, the note saying why, when the drive's halves lie 0.5 m /
    rad / s apart (over 2x a typical error), the held-back loss is no lower than the prior's, or the fit's 0.2 m lies
    beyond a translation bound of 0.15 m."""
    prior = SIDE.copy()
    r = own_motion_result(_fit(split, loss), _kept(prior), CameraRegistrationConfig(max_translation=bound), lambda s: None, time.perf_counter())
    assert r.kept_prior is bool(why)
    if not why:
        theta = _fit(split, loss).theta
        expected = calibrated_extrinsic(torch.from_numpy(prior), torch.from_numpy(theta[:3]), torch.from_numpy(theta[3:6])).numpy()
        np.testing.assert_allclose(r.estimate, expected, atol=1e-12)
        assert r.time_offset == pytest.approx(0.1 - 0.03) and r.sigma == pytest.approx([3e-3] * 7)  # the baseline part, the largest
        assert r.start.startswith("own motion (5000 ") and "a wrong minimum" in r.start and r.note == ""
    else:
        np.testing.assert_array_equal(r.estimate, prior)
        assert r.note.startswith("a wrong minimum; by its own motion: ") and why in r.note, r.note


def test_exact_tracks_on_a_steady_turn_give_the_rotation_and_say_the_lever_arm_and_offset_are_undetermined():
    """Exact matches of a drive that turns about the reference's y axis at a steady rate: they chain into tracks of one
    point each, the epipolar residual vanishes at the truth, and from 30 cm / 3 deg / 80 ms the fit ends at the true
    rotation (1e-6 rad) with no residual left. The relative motions of a steady turn all turn about one axis at one
    rate, which leaves the lever arm along that axis free and lets the offset trade with the lever arm (the fit ends
    centimetres off with zero residual): the formal sigma of the lever arm and the offset is unbounded, which the stage's
    verdict reads as not determined. The short and the long tracks, each fitted alone, end at the same rotation."""
    traj, rng = _trajectory(0.15, 1.0), np.random.default_rng(1)
    matches, _ = _matches(traj, SIDE, 0.03, _street(1.0), np.arange(0.3, 3.2, 0.1), rng)
    chained = tracks(matches)
    points = len(_street(1.0))
    assert len(np.unique(chained.track * points + chained.key % points)) == chained.count  # each track one point
    assert len(chained.key) == len(np.unique(np.r_[matches.key_a, matches.key_b]))  # every keypoint matched, once
    assert np.abs(sampson_px(np.r_[np.zeros(6), 0.03], matches, 200.0, traj, SIDE, 0.0)).max() < 1e-6
    prior = _perturbed()
    fit = fit_own_tracks(traj, matches, 200.0, prior, 0.11, OwnTracksConfig(), lambda s: None)
    d = _error(prior, 0.11, fit.theta, SIDE, 0.03)
    assert np.all(np.abs(d[3:6]) < 1e-6), d
    assert fit.loss_estimate < 1e-4 < 0.5 < fit.loss_prior
    assert np.all(np.isinf(fit.sigma_formal[3:])) and np.all(fit.sigma_formal[:3] < 1e-6)
    assert np.all(fit.sigma_baseline[:3] < 1e-6)  # the short and the long tracks, each fitted alone, agree on the rotation


def test_the_resolution_part_of_own_tracks_is_half_the_change_from_keypoints_found_at_half_resolution():
    """``fit_own_tracks(..., halved=)``: the same fit on the matches of keypoints found at 1/2 resolution, from its own
    start; half the change of the corrections is the resolution part of sigma (``camera_guards.resolution_spread``),
    which sigma then covers. Here the halved keypoints all sit 1 px (f = 200 px) to the right, a bias every track
    shares, which moves the fit; the fit itself is the one without ``halved``, whose resolution part is zero."""
    traj, rng = _trajectory(0.15, 1.0), np.random.default_rng(1)
    matches, _ = _matches(traj, SIDE, 0.03, _street(1.0), np.arange(0.3, 2.0, 0.1), rng)
    halved = replace(matches, xy_a=matches.xy_a + [1 / 200, 0.0], xy_b=matches.xy_b + [1 / 200, 0.0])
    prior = _perturbed()
    fit = fit_own_tracks(traj, matches, 200.0, prior, 0.11, OwnTracksConfig(), lambda s: None, halved=halved)
    alone = fit_own_tracks(traj, halved, 200.0, prior, 0.11, OwnTracksConfig(), lambda s: None)
    np.testing.assert_allclose(fit.sigma_resolution, np.abs(fit.theta - alone.theta) / 2, rtol=0, atol=1e-12)
    assert fit.sigma_resolution.max() > 1e-3, fit.sigma_resolution
    assert np.all(fit.sigma >= fit.sigma_resolution)
    without = fit_own_tracks(traj, matches, 200.0, prior, 0.11, OwnTracksConfig(), lambda s: None)
    assert np.all(without.sigma_resolution == 0) and np.all(without.theta == fit.theta)


def test_own_tracks_name_weak_what_the_drive_turns_about_and_nothing_on_a_drive_that_rocks():
    """A camera placed by its own tracks sees its lever arm only through the drive's turns: on the steady turn about the
    reference's vertical the drive's own-motion observability names the lever arm and the offset weak (the fit's formal
    sigma is unbounded there, the test above); the same poses rocked by 3 deg in roll and pitch name nothing."""
    traj = _trajectory(0.15, 1.0)
    matches, _ = _matches(traj, SIDE, 0.03, _street(1.0), np.arange(0.3, 3.2, 0.1), np.random.default_rng(1))
    lines = []
    assert weak_by_motion(traj, matches, SIDE, 0.0, lines.append, "cam_left") == ["x", "y", "z", "time_offset"]
    assert lines[1].startswith("[own-tracks] cam_left: y weakly observable from this drive: the reference frame turns only 0.0 deg")
    t = np.asarray(traj.times)
    poses = traj(torch.from_numpy(t)).numpy()
    rock = roma.rotvec_to_rotmat(torch.from_numpy(np.stack([0.05 * np.sin(2 * t), np.zeros_like(t), 0.05 * np.sin(3 * t)], 1))).numpy()
    rocked = ReferenceTrajectory.from_tum(t, poses[:, :3, 3], roma.rotmat_to_unitquat(torch.from_numpy(poses[:, :3, :3] @ rock)).numpy())
    assert weak_by_motion(rocked, matches, SIDE, 0.0, lines.append) == []


@pytest.mark.slow
def test_the_side_camera_of_a_camera_only_rig_is_placed_by_its_own_tracks(tmp_path):
    """The stage on the default camera-only street rig of seed 1 (320x240, 50 frames), priors perturbed as in the paper
    (86.6 cm / 8.8 deg / 100 ms): the side camera, which shares no view with the reference camera, is placed by its own
    tracks on the trajectory within 4 cm / 0.1 deg / 2 ms (measured 2.46 cm / 0.019 deg / 0.42 ms), every parameter
    within 3 sigma, its held-back loss below the prior's, its vertical lever arm named weak (this drive is flat); with
    ``own_motion`` off it keeps its prior, held there."""
    folder = make_rig(SynthConfig(out=tmp_path / "rig", seed=1, perturb="paper", lidar=False))
    rig, truth = load_rig(folder), load_calibration(folder / "ground_truth.json")
    start = Calibration.from_rig(rig)
    side = register_cameras(rig, start, CameraRegistrationConfig(), sensors=["cam_left"], log=lambda s: None).cameras["cam_left"]
    assert not side.kept_prior and not side.held_there and side.start.startswith("own motion (") and "tracks" in side.start
    assert side.weak == ["y"]  # the vertical lever arm: this flat drive turns 2.8 deg about the other axes
    d = np.asarray(parameter_difference(truth.T_ref_sensor["cam_left"], truth.time_offset["cam_left"], side.estimate, side.time_offset))
    assert np.linalg.norm(d[:3]) < 0.04 and np.rad2deg(np.linalg.norm(d[3:6])) < 0.1 and abs(d[6]) < 0.002, d
    assert np.all(np.abs(d) < 3 * np.asarray(side.sigma)[list(JACOBIAN_ORDER)])
    assert side.cost_estimate < side.cost_prior
    held = register_cameras(rig, start, CameraRegistrationConfig(own_motion=False), sensors=["cam_left"], log=lambda s: None).cameras["cam_left"]
    assert held.kept_prior and held.held_there and "shares no view with cam_front" in held.note
