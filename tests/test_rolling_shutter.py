"""Rolling shutter on the calibration side: a row's time (``geometry.row_time``), projections from the row's pose
(camera-registration stage, the LiDAR stage's shared view), the NeRF's camera rays, and ``estimate_readout``."""

import json
from dataclasses import replace

import numpy as np
import pytest
import roma
import torch

from moisst_ns.datasets.synth import SynthConfig, build_scene, make_rig
from moisst_ns.datasets.synth_effects import row_time_offsets
from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, row_time, row_times
from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig, register_cameras
from moisst_ns.stages.camera.lidar_map import PinholeModel
from moisst_ns.stages.camera.photometric import CameraModel
from helpers import planar_distance_view

READOUT = 0.03


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory):
    """``moisst-synth DIR --seed 0 --frames 12 --width 96 --height 72 --rolling-shutter 0.03`` (paper perturbation)."""
    return make_rig(SynthConfig(out=tmp_path_factory.mktemp("rolling") / "rig", seed=0, frames=12, width=96, height=72, rolling_shutter=READOUT))


def test_row_time_exact_values():
    """Row ``r`` of ``H`` at ``R (r - (H-1)/2) / (H-1)``: the first row -R/2, the middle of the image 0, the last row
    +R/2; exactly the generator's ``row_time_offsets``, numpy and torch alike; 0 for a global shutter."""
    rows = np.arange(72) + 0.5
    np.testing.assert_array_equal(row_time(rows, READOUT, 72), row_time_offsets(72, READOUT))
    assert row_time(0.5, READOUT, 72) == -0.015 and row_time(36.0, READOUT, 72) == 0.0 and row_time(71.5, READOUT, 72) == 0.015
    assert row_time(1.5, 0.071, 72) == pytest.approx(-0.0345, abs=1e-15)  # row 1: 0.071 (1 - 35.5) / 71
    assert torch.equal(row_time(torch.tensor([0.5, 71.5], dtype=torch.float64), READOUT, 72), torch.tensor([-0.015, 0.015], dtype=torch.float64))
    np.testing.assert_array_equal(row_time(rows, 0.0, 72), np.zeros(72))
    # the fixed point of a point moving 40 rows per second down the image, v(tau) = 20 + 40 tau: three iterations
    # from the stamp land within 1e-5 rows of tau = R (20 - 36) / (71 - 40 R)
    tau = row_times(lambda t: 20.0 + 40.0 * np.asarray(t), READOUT, 72)
    assert abs(tau - READOUT * -16.0 / (71.0 - 40.0 * READOUT)) * 40.0 < 1e-5


def vehicle(frames: int = 30):
    """A trajectory sampled at 10 Hz like a drive: 10 m/s forward, yawing 0.3 rad/s, a little pitch and roll."""
    times = torch.arange(frames, dtype=torch.float64) * 0.1
    yaw = 0.3 * times
    rot = roma.rotvec_to_rotmat(torch.stack([0.02 * torch.sin(3 * times), 0.01 * torch.cos(2 * times), yaw], dim=-1))
    trans = torch.stack([10.0 * torch.cumsum(torch.cos(yaw), 0) * 0.1, 10.0 * torch.cumsum(torch.sin(yaw), 0) * 0.1, 0.05 * torch.sin(times)], dim=-1)
    return ReferenceTrajectory(times, rot, trans)


def camera_and_points(readout: float):
    prior = np.eye(4)
    prior[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # forward-looking
    prior[:3, 3] = [0.5, -0.3, 1.2]
    full = PinholeModel(80.0, 80.0, 48.0, 36.0, 96, 72)
    camera = CameraModel(vehicle(), prior, 0.02, np.array([0.95, 1.4, 2.05]), readout, full)
    poses = camera.poses(torch.zeros(7, dtype=torch.float64)).numpy()
    frame = np.repeat([0, 1, 2], 4)
    rng = np.random.default_rng(0)
    local = np.c_[rng.uniform(-4, 4, (12, 2)), rng.uniform(4, 25, 12)]  # in front of the camera, 4-25 m
    points = np.einsum("nij,nj->ni", poses[frame, :3, :3], local) + poses[frame, :3, 3]
    return camera, full, points, frame


@pytest.mark.parametrize("factor", [1, 2])
def test_a_rolling_projection_is_the_global_projection_at_the_rows_time(factor):
    """Each point's pixel with readout R equals the global-shutter pixel from the pose at ``stamp + row_time(v)`` of
    its own row ``v`` (the fixed point converged to under 0.01 px), at full resolution and on a pyramid level (rows
    timed in full-resolution pixels); the rows spread over the image so the times differ by up to R."""
    camera, full, points, frame = camera_and_points(READOUT)
    model = PinholeModel.of({"fl_x": 80.0, "fl_y": 80.0, "cx": 48.0, "cy": 36.0, "w": 96, "h": 72}, factor)
    theta = np.array([0.01, -0.02, 0.015, 0.1, -0.05, 0.02, 0.013])
    uv, _ = camera.pixels(theta, model, points, frame, jacobian=False)
    tau = row_time(uv[:, 1] * factor, READOUT, 72)
    assert tau.max() - tau.min() > 0.5 * READOUT
    at_row = CameraModel(camera.traj, camera.prior.numpy(), 0.02, camera.stamps.numpy()[frame] + tau)
    uv_global, _ = at_row.pixels(theta, model, points, np.arange(len(points)), jacobian=False)
    assert np.abs(uv - uv_global).max() < 0.01 / factor
    stamp_only, _ = CameraModel(camera.traj, camera.prior.numpy(), 0.02, camera.stamps.numpy()).pixels(theta, model, points, frame, False)
    assert np.abs(uv - stamp_only).max() > 0.2 / factor  # the readout matters (forward camera, 10 m/s)


def test_rolling_jacobian_follows_the_row_and_the_readout():
    """``d pixel / d theta`` with 8 corrections (the 8th the readout's) equals central differences: the implicit
    derivative through the row's time (the pose's time derivative times ``dtau/dtheta``)."""
    camera, full, points, frame = camera_and_points(READOUT)
    theta = np.array([0.01, -0.02, 0.015, 0.1, -0.05, 0.02, 0.013, 0.004])
    _, jac = camera.pixels(theta, full, points, frame, jacobian=True)
    numeric = np.zeros_like(jac)
    for i in range(8):
        step = np.zeros(8)
        step[i] = 1e-6
        plus, _ = camera.pixels(theta + step, full, points, frame, jacobian=False)
        minus, _ = camera.pixels(theta - step, full, points, frame, jacobian=False)
        numeric[:, :, i] = (plus - minus) / 2e-6
    assert np.abs(jac[:, :, 7]).max() > 5.0  # pixels per second of readout
    scale = np.abs(jac).max(axis=(0, 1))  # per correction
    assert np.all(np.abs(jac - numeric) <= 1e-3 * scale), (np.abs(jac - numeric).max(axis=(0, 1)) / scale)
    # without a readout, the 8-correction model is the global shutter's
    global_camera = CameraModel(camera.traj, camera.prior.numpy(), 0.02, camera.stamps.numpy(), 0.0, full)
    eight, _ = global_camera.pixels(np.r_[theta[:7], 0.0], full, points, frame, jacobian=False)
    seven, _ = global_camera.pixels(theta[:7], full, points, frame, jacobian=False)
    np.testing.assert_allclose(eight, seven, atol=1e-9)


def test_shared_view_projects_lidar_edges_from_the_rows_pose(rig_folder):
    """The LiDAR stage's shared view: with the reference camera's readout, each LiDAR edge point is seen from the pose
    at its row's time: its edge distance differs from the global shutter's (by tenths of a pixel)."""
    from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, SharedView, load_scans, scan_pairs
    from moisst_ns.stages.lidar.lidar_geometry import Extrinsic
    from moisst_ns.stages.lidar.lidar_view import view_residuals

    rig, truth = load_rig(rig_folder), load_calibration(rig_folder / "ground_truth.json")
    T = np.asarray(truth.T_ref_sensor["lidar"])
    ext = Extrinsic(T[:3, :3].copy(), T[:3, 3].copy(), float(truth.time_offset["lidar"]))
    traj, config = ReferenceTrajectory.of(rig), LidarFirstConfig()
    scans = load_scans(rig, "lidar", traj, config, log=lambda _: None)
    pairs, _ = scan_pairs(traj, scans, ext.time_offset, config)
    shared = SharedView.of(rig, traj, scans)
    assert shared.view.readout == READOUT
    shared = shared.at(traj, ext, scans, pairs)
    rows = shared.rows
    assert len(rows.point) >= 10 and len(np.unique(rows.frame)) >= 5
    view = planar_distance_view(shared.view)  # a plane per frame: a pose change shows as a distance change
    increment = np.array([0.002, -0.001, 0.003, 0.02, -0.01, 0.03, 0.004])
    value = view_residuals(traj, ext, scans, view, rows, increment)
    global_value = view_residuals(traj, ext, scans, replace(view, readout=0.0), rows, increment)
    assert np.abs(value - global_value).max() > 0.05


def test_nerf_camera_rays_are_posed_at_their_rows_time(rig_folder):
    """The datamanager stamps each camera ray with its row's time (``row_time`` of the pixel row's centre, LiDAR rays
    0); the calibration optimiser, at the true calibration, poses the rays there: they see the stored colours
    (mean error measured 0.41 of 255 with the row times, 2.6 at the stamps), and a map-range frame is seen alike."""
    from moisst_ns.calibration_optimizer import CalibrationOptimizer, CalibrationOptimizerConfig
    from moisst_ns.method_configs import moisst_trainer_config
    from moisst_ns.stages.camera.map_range import opengl_to_opencv, rolling_camera_points

    config = moisst_trainer_config("moisst-lite", 100).pipeline.datamanager
    config.data = config.dataparser.data = rig_folder
    torch.manual_seed(0)
    manager = config.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
    bundle, batch = manager.next_train(99)
    n = batch["ray_layout"].num_camera
    assert torch.equal(bundle.metadata["row_time"][:n, 0], row_time(batch["indices"][:, 1].double() + 0.5, READOUT, 72))
    assert bool((bundle.metadata["row_time"][n:] == 0).all())
    data = manager.train_dataparser_outputs.metadata["moisst_rig"]
    optimizer = CalibrationOptimizer(CalibrationOptimizerConfig(), num_cameras=len(manager.train_dataset.cameras), device="cpu", rig=data)
    optimizer.rig.set_corrections_to(load_calibration(rig_folder / "ground_truth.json"))
    meta = json.loads((rig_folder / "rig.json").read_text())["metadata"]
    scene = build_scene(SynthConfig(out=rig_folder, **{k: meta[k] for k in ("seed", "frames", "width", "height", "layout")}))
    stored = batch["image"][:n, :3].double().numpy() * 255.0
    errors = []
    for rows in (bundle.metadata["row_time"][:n], torch.zeros(n, 1, dtype=torch.float64)):
        camera = bundle[torch.arange(n)]
        camera.metadata["row_time"] = rows
        with torch.no_grad():
            optimizer.apply_to_raybundle(camera)
        origins = camera.origins.double().numpy() / data.world.scale + data.world.center
        rgb, _ = scene.colour(origins, camera.directions.double().numpy(), 1.0 / float(manager.train_dataset.cameras.fx[0]))
        errors.append(np.abs(np.clip(rgb, 0, 1) * 255.0 - stored).mean())
    assert errors[0] < 0.7 and errors[1] > 2.0, errors
    # a map-range frame: each map point from the prior pose at its row's time (the reference camera: prior = truth)
    world = np.array([[5.0, 2.0, 1.0], [20.0, -3.0, 0.5], [12.0, 1.0, -1.0]]) + data.trajectory()(torch.tensor([0.3]))[0, :3, 3].numpy()
    frame = int(np.flatnonzero(data.frame_sensor_index == data.reference_index)[3])
    cam = rolling_camera_points(data, frame, READOUT, world) / data.world.scale
    k = manager.train_dataset.cameras
    tau = row_time(float(k.fy[frame]) * cam[:, 1] / cam[:, 2] + float(k.cy[frame]), READOUT, 72)
    assert np.ptp(tau) > 0.2 * READOUT
    c2w = optimizer.frame_c2w(torch.full((3,), frame), prior=True, row_time=torch.from_numpy(tau)).numpy()
    at_rows = np.stack([opengl_to_opencv(c2w[k, :3], data.world.points_to_model(torch.from_numpy(world[k:k + 1])).numpy())[0] for k in range(3)])
    np.testing.assert_allclose(cam * data.world.scale, at_rows, atol=1e-3 * data.world.scale)


def stage(rig_folder, readout=None, **config):
    """The camera stage on the forward-right camera, the LiDAR at the truth (what the LiDAR-first stage delivers);
    ``readout``: every camera's readout forced to this (None: rig.json's). Returns (result, errors)."""
    rig, truth = load_rig(rig_folder), load_calibration(rig_folder / "ground_truth.json")
    if readout is not None:
        for spec in rig.sensors.values():
            spec.readout_time = readout
    start = Calibration.from_rig(rig)
    start.T_ref_sensor, start.time_offset = dict(start.T_ref_sensor), dict(start.time_offset)
    start.T_ref_sensor["lidar"], start.time_offset["lidar"] = truth.T_ref_sensor["lidar"], truth.time_offset["lidar"]
    result = register_cameras(rig, start, CameraRegistrationConfig(**config), sensors=["cam_front_right"], log=lambda s: None)
    return result.cameras["cam_front_right"], calibration_report_errors(result.calibration, truth)["cam_front_right"]


@pytest.fixture(scope="module")
def with_readout(rig_folder):
    return stage(rig_folder)


def test_the_camera_stage_with_the_readout_ends_closer_to_the_truth(rig_folder, with_readout):
    """From the paper perturbation, the forward-right camera with rig.json's readout (30 ms) ends at 2.26 cm /
    0.072 deg / 2.45 ms; with every readout forced to 0 (a global-shutter model of the same images) at 2.40 cm / 0.086
    deg / 5.12 ms: the time offset absorbs the rows' times. Measured over four sample seeds (``seed``): 2.45-3.14 ms
    with the readout, 5.02-5.44 ms without; the translation, 2.3-3.9 cm either way, and the rotation are this 96x72 rig's
    noise (on 2026-12-01's install: 0.081 deg with the readout, 0.074 without; time 4.83 ms without) (on the
    320x240 rig of 20 frames: 0.08 cm / 0.004 deg / 0.14 ms with the readout, 1.94 cm / 0.011 deg / 2.14 ms without)."""
    result, errors = with_readout
    assert result.readout_time == READOUT and result.readout_estimate is None and not result.kept_prior
    assert errors["time_ms"] < 3.5 and errors["translation_cm"] < 4.0 and errors["rotation_deg"] < 0.12, errors
    _, global_errors = stage(rig_folder, readout=0.0)
    assert global_errors["time_ms"] > 4.5, global_errors


def test_estimate_readout_says_when_the_drive_cannot_determine_it(rig_folder, with_readout):
    """``estimate_readout`` fits the readout as an 8th correction at the two finest levels from rig.json's 30 ms. On
    this 12-frame 96x72 rig the drive does not determine it: measured 10.8 ms, sigma 5.0 ms (the rows' times trade
    against the time offset, and the estimate moves with the resolution); the camera keeps rig.json's readout and is
    registered again with it: the same result as without ``estimate_readout``. (On 320x240 rigs of 20 frames it
    recovers it: 29.92 ms, sigma 0.79 ms, from 0 on a weaving drive; 28.6 ms from 0 on the gently curving one, whose
    sigma of 6.1 ms says the drive does not determine it.)"""
    result, errors = stage(rig_folder, estimate_readout=True)
    assert result.readout_prior == READOUT and result.readout_time == READOUT
    assert result.readout_sigma > 0.003 and result.readout_note.startswith("the drive does not determine the readout time")
    assert 0.0 <= result.readout_estimate < 0.1 and len(result.sigma) == 7
    given, given_errors = with_readout
    np.testing.assert_array_equal(result.estimate, given.estimate)
    assert errors == given_errors and result.time_offset == given.time_offset


def test_an_estimated_readout_is_an_8th_correction_within_its_bounds(rig_folder):
    """The joint fit itself (one descent, no guards): 8 corrections in the history, the readout's within
    ``[0, 0.999 frame period)`` at every iteration, held where it started at the coarser levels."""
    from moisst_ns.rig.geometry import ReferenceTrajectory as Traj
    from moisst_ns.stages.camera.camera_registration import _descend
    from moisst_ns.stages.camera.lidar_map import lidar_map
    from moisst_ns.stages.camera.photometric import CameraFrames, Registration

    rig, truth = load_rig(rig_folder), load_calibration(rig_folder / "ground_truth.json")
    config = CameraRegistrationConfig(estimate_readout=True, fine_iterations=1, outer_iterations=1, max_evaluations=8)
    world = lidar_map(rig, truth, config.map_voxel, config.min_range, log=lambda s: None)
    traj = Traj.of(rig)
    problem = Registration(traj, world, CameraFrames.of(rig, "cam_front_right", [4, 2, 1]), CameraFrames.of(rig, "cam_front", [4, 2, 1]), truth, config)
    theta, history, _, _ = _descend(problem, config, lambda s: None, np.r_[np.zeros(7), -READOUT])  # from a readout of 0
    assert [h["level"] for h in history] == [4, 2, 1] and all(len(h["correction"]) == 8 for h in history)
    assert history[0]["readout_time"] == 0.0 and all(0.0 <= h["readout_time"] < 0.0999 for h in history)
    assert history[-1]["readout_time"] > 0.0


@pytest.mark.parametrize("switch", [False, True])
def test_estimate_readout_switch_reaches_the_camera_stage(rig_folder, tmp_path, monkeypatch, switch):
    """``moisst-calibrate --estimate-readout`` / ``ns-train ... --pipeline.estimate-readout``: ``prepare_stages`` hands the
    switch to the camera-registration stage's config (and only there: the LiDAR stage's config has no such field)."""
    import dataclasses

    import moisst_ns.stage_run as stage_run
    from moisst_ns.calibrate import CalibrateConfig
    from moisst_ns.method_configs import moisst_trainer_config

    seen = {}

    def lidar_stage(rig, prior, truth, out, options):  # records the options; no stage runs
        seen["lidar"] = options

    def camera_stage(rig, lidar, truth, out, options):
        seen["camera"] = CameraRegistrationConfig(**options)

    monkeypatch.setattr(stage_run, "run_lidar_first", lidar_stage)
    monkeypatch.setattr(stage_run, "run_camera_registration", camera_stage)
    monkeypatch.setattr(stage_run, "apply_stage_results", lambda pipeline, run: None)
    pipeline = moisst_trainer_config("moisst-lite").pipeline
    pipeline.datamanager.data = rig_folder
    pipeline.estimate_readout = switch
    stage_run.prepare_stages(pipeline, tmp_path, 0, None)
    assert seen["camera"].estimate_readout is switch and "estimate_readout" not in seen["lidar"]
    assert "estimate_readout" in {f.name for f in dataclasses.fields(CalibrateConfig)}
