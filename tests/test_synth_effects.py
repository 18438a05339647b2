"""Tests of ``moisst-synth``'s real-world effects (moisst_ns/datasets/synth_effects.py, synth_render.py) and of the
optional per-camera ``readout_time`` of rig.json. Tiny rigs (64x48, 5 frames), generated once per module; each
effect's rig has the seed of the plain one, so the two differ by that effect alone."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import tyro
from PIL import Image
from scipy.spatial.transform import Rotation

from moisst_ns.datasets.synth import (
    PERIOD,
    SynthConfig,
    SynthError,
    _streams,
    build_scene,
    config_of_rig,
    intrinsics,
    make_path,
    make_rig,
)
from moisst_ns.datasets.synth_effects import (
    REALISTIC,
    Effects,
    apply_photometric,
    encode_jpeg,
    exposure_offsets,
    lidar_dropout_mask,
    make_movers,
    photometric_params,
    pixel_directions,
    resolve_effects,
    row_time_offsets,
    to_uint8,
    vignetting_factor,
)
from moisst_ns.datasets.synth_render import render_frame
from moisst_ns.rig.format import RigFormatError, load_calibration, load_lidar_scan, load_rig, rig_to_json
from moisst_ns.rig.geometry import ReferenceTrajectory, sensor_pose
from moisst_ns.rig.trajectory_noise import TrajectoryAccuracy, perturb_trajectory
from helpers import file_hashes, scene_distance

TINY = dict(width=64, height=48, frames=5, lidar_azimuth_steps=512, lidar_max_points=6000)
CAMERAS = ("cam_front", "cam_front_right", "cam_left")


def tiny(out: Path, **kw) -> SynthConfig:
    return SynthConfig(out=out, **{**TINY, **kw})


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    base = tmp_path_factory.mktemp("effects")
    zeros = dict(pose_noise=(0.0, 0.0), pose_drift=(0.0, 0.0), exposure=0.0, vignetting=0.0, distortion=(0.0, 0.0), movers=0,
                 motion_blur=0.0, jpeg_quality=None, lidar_noise=0.0, lidar_dropout=0.0, rolling_shutter=0.0)
    configs = {
        "plain": tiny(base / "plain"),
        "zeros": tiny(base / "zeros", **zeros),
        "pose": tiny(base / "pose", pose_noise=(1.0, 0.02), pose_drift=(3.0, 0.05), lidar=False),
        "photo": tiny(base / "photo", exposure=0.3, vignetting=0.3, lidar=False),
        "lens": tiny(base / "lens", distortion=(-0.12, 0.03), lidar=False),
        "rolling": tiny(base / "rolling", rolling_shutter=0.05, lidar=False),
        "movers": tiny(base / "movers", movers=8),
        "jpeg_lidar": tiny(base / "jpeg_lidar", jpeg_quality=90, lidar_noise=0.02, lidar_dropout=0.1),
    }
    return {name: (make_rig(cfg), cfg) for name, cfg in configs.items()}


@pytest.fixture(scope="module")
def scene(rigs):
    return build_scene(rigs["plain"][1])  # every rig here has seed 0: one scene


def pose_function(out: Path, sensor: str):
    """``stamps -> (N, 4, 4)`` true poses of a sensor (the rig's trajectory must be the exact one)."""
    rig, gt = load_rig(out), load_calibration(out / "ground_truth.json")
    traj = ReferenceTrajectory.of(rig)

    def world_T_at(stamps):
        t_rel = torch.as_tensor(np.asarray(stamps, dtype=np.float64) + gt.time_offset[sensor]) - traj.t0
        return sensor_pose(traj(t_rel), torch.as_tensor(gt.T_ref_sensor[sensor])).numpy()

    return world_T_at, gt.time_offset[sensor] - traj.t0


def image(out: Path, rel: str) -> np.ndarray:
    return np.asarray(Image.open(out / rel).convert("RGB"), dtype=np.float64)


# ----------------------------------------------------------------------------------------------------------------
# Switches


def test_switches_off_reproduce_the_original_path(rigs, scene):
    """Explicit zeros are the default (same files, rig.json included); the effects' renderer, with nothing on, is
    the plain pinhole render (the arithmetic the generator always used) to the bit."""
    assert file_hashes(rigs["plain"][0]) == file_hashes(rigs["zeros"][0])
    for name in ("plain", "zeros"):
        fx = resolve_effects(rigs[name][1])
        assert fx == Effects() and not fx.camera and not fx.trajectory and fx.summary() == {}
    cfg = rigs["plain"][1]
    world_T_at, _ = pose_function(rigs["plain"][0], "cam_left")
    pose = world_T_at([1000.25])[0]
    for ss in (1, 2):
        rgb, hit = render_frame(scene, intrinsics(cfg), lambda s: np.repeat(pose[None], len(s), axis=0), 1000.25, supersample=ss)
        ref_rgb, ref_hit = pinhole_render(scene, intrinsics(cfg), pose, ss)
        assert np.array_equal(to_uint8(rgb), ref_rgb) and np.array_equal(hit, ref_hit)


def pinhole_render(scene, intr, world_T_cam, ss):
    """The generator's original renderer (before the effects existed), kept as the reference of the test above."""
    w, h = int(intr["w"]), int(intr["h"])
    uu, vv = np.meshgrid((np.arange(w * ss) + 0.5) / ss, (np.arange(h * ss) + 0.5) / ss)
    dirs = np.stack([(uu - intr["cx"]) / intr["fl_x"], (vv - intr["cy"]) / intr["fl_y"], np.ones_like(uu)], axis=-1)
    dirs = dirs.reshape(-1, 3) @ world_T_cam[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rgb, hit = scene.colour(world_T_cam[:3, 3], dirs, 1.0 / (float(intr["fl_x"]) * ss))
    rgb = rgb.reshape(h, ss, w, ss, 3).mean(axis=(1, 3))
    return (np.clip(rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8), hit.reshape(h, ss, w, ss).mean(axis=(1, 3))


def test_realistic_turns_everything_on_but_the_rolling_shutter_and_explicit_switches_win(tmp_path):
    fx = resolve_effects(SynthConfig(out=tmp_path, realistic=True))
    assert fx == Effects(pose_noise=(1.0, 0.02), pose_drift=(3.0, 0.05), exposure=0.3, vignetting=0.3, distortion=(-0.12, 0.03),
                         movers=8, motion_blur=0.004, jpeg_quality=90, lidar_noise=0.02, lidar_dropout=0.1)
    assert set(REALISTIC) == {f for f in Effects.__dataclass_fields__ if f != "rolling_shutter"}
    fx = resolve_effects(SynthConfig(out=tmp_path, realistic=True, movers=0, pose_noise=(2.0, 0.1), lidar_noise=0.0, rolling_shutter=0.03))
    assert (fx.movers, fx.pose_noise, fx.lidar_noise, fx.rolling_shutter, fx.motion_blur) == (0, (2.0, 0.1), 0.0, 0.03, 0.004)
    assert "movers" not in fx.summary() and fx.summary()["rolling_shutter"] == 0.03
    assert resolve_effects(SynthConfig(out=tmp_path, realistic=True, jpeg_quality=0)).jpeg_quality is None  # PNG


def test_cli_parsing_of_the_effect_switches():
    cfg = tyro.cli(SynthConfig, args=["out", "--realistic", "--pose-noise", "2", "0.05", "--pose-drift", "4", "0.1", "--exposure", "0.2",
                                      "--vignetting", "0.1", "--distortion", "-0.1", "0.02", "--movers", "3", "--motion-blur", "0.008",
                                      "--jpeg-quality", "75", "--lidar-noise", "0.01", "--lidar-dropout", "0.2", "--rolling-shutter", "0.03"])
    assert cfg.realistic and cfg.pose_noise == (2.0, 0.05) and cfg.pose_drift == (4.0, 0.1) and cfg.distortion == (-0.1, 0.02)
    assert (cfg.exposure, cfg.vignetting, cfg.movers, cfg.motion_blur, cfg.jpeg_quality) == (0.2, 0.1, 3, 0.008, 75)
    assert (cfg.lidar_noise, cfg.lidar_dropout, cfg.rolling_shutter) == (0.01, 0.2, 0.03)
    default = tyro.cli(SynthConfig, args=["out"])
    assert resolve_effects(default) == Effects() and not default.realistic


@pytest.mark.parametrize("kw, phrase", [
    (dict(rolling_shutter=0.1), "--rolling-shutter must be in \\[0, 0.1\\)"), (dict(motion_blur=-0.001), "--motion-blur"),
    (dict(exposure=1.0), "--exposure must be in \\[0, 1\\)"), (dict(lidar_dropout=-0.1), "--lidar-dropout"),
    (dict(jpeg_quality=101), "--jpeg-quality must be in 1..100"), (dict(movers=-1), "--movers"),
    (dict(pose_noise=(float("nan"), 0.0)), "--pose-noise must be finite"), (dict(distortion=(-1.5, 0.0)), "cannot be inverted"),
    (dict(realistic=True, vignetting=2.0), "--vignetting"),
])
def test_bad_effect_values_are_refused_on_one_line(tmp_path, kw, phrase):
    with pytest.raises(SynthError, match=phrase) as info:
        make_rig(tiny(tmp_path / "x", **kw))
    assert "\n" not in str(info.value) and not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------------------------------------------
# The written trajectory


def test_pose_noise_and_drift_statistics():
    k = 3000  # 300 s at 10 Hz
    stamps, positions = 1000.0 + 0.1 * np.arange(k), np.random.default_rng(1).normal(0, 50, (k, 3))
    quats = Rotation.random(k, random_state=2).as_quat()
    quats *= np.where(quats[:, 3:4] < 0, -1.0, 1.0)

    def errors(noise, drift):
        p, q = perturb_trajectory(stamps, positions, quats, noise, drift, np.random.SeedSequence(5))
        assert np.all(q[:, 3] >= 0) and np.allclose(np.linalg.norm(q, axis=1), 1.0)
        return p - positions, (Rotation.from_quat(quats).inv() * Rotation.from_quat(q)).as_rotvec()

    white_p, white_r = errors((1.0, 0.02), (0.0, 0.0))
    np.testing.assert_allclose(white_p.std(axis=0), 0.01, rtol=0.06)
    np.testing.assert_allclose(white_r.std(axis=0), np.deg2rad(0.02), rtol=0.06)
    assert np.abs(white_p.mean(axis=0)).max() < 1e-3
    drift_p, drift_r = errors((0.0, 0.0), (3.0, 0.05))
    np.testing.assert_allclose(np.sqrt(np.mean(drift_p**2, axis=0)), 0.03, rtol=1e-9)  # RMS over the samples
    np.testing.assert_allclose(np.sqrt(np.mean(drift_r**2, axis=0)), np.deg2rad(0.05), rtol=1e-6)
    for d in (drift_p, drift_r):  # slow: periods of 3 s and more, so 0.1 s steps change it by <= 2 pi 0.1 / 3 of its size
        assert (np.diff(d, axis=0).std(axis=0) / d.std(axis=0)).max() < 0.25
    both_p, _ = errors((1.0, 0.02), (3.0, 0.05))  # white noise and drift come from separate streams
    np.testing.assert_allclose(both_p, white_p + drift_p, atol=1e-12)


def test_pose_noise_only_on_the_written_trajectory(rigs):
    out, cfg = rigs["pose"]
    plain = rigs["plain"][0]
    mine, theirs = file_hashes(out), file_hashes(plain)
    for rel, digest in mine.items():  # frames rendered at the true poses: the same images as without the noise
        if rel.startswith("images/"):
            assert theirs[rel] == digest, rel
    truth, exact_truth = load_calibration(out / "ground_truth.json"), load_calibration(plain / "ground_truth.json")
    assert all(np.array_equal(truth.T_ref_sensor[n], exact_truth.T_ref_sensor[n]) for n in CAMERAS)
    assert mine["reference_poses.txt"] != theirs["reference_poses.txt"]
    noisy, exact = load_rig(out), load_rig(plain)
    np.testing.assert_array_equal(noisy.trajectory_stamps, exact.trajectory_stamps)
    err = np.linalg.norm(noisy.trajectory_positions - exact.trajectory_positions, axis=1)
    assert 0.003 < err.mean() < 0.15, err
    meta = json.loads((out / "rig.json").read_text())["metadata"]
    assert meta["pose_noise"] == [1.0, 0.02] and meta["effects"]["pose_drift"] == [3.0, 0.05]
    assert resolve_effects(config_of_rig(meta)) == resolve_effects(cfg)
    # the trajectory's errors as its source would state them (m, deg), read back; the exact trajectory states none
    assert noisy.trajectory_accuracy == TrajectoryAccuracy(0.01, 0.02, 0.03, 0.05) and not exact.trajectory_accuracy.stated()
    assert "trajectory_accuracy" not in json.loads((plain / "rig.json").read_text())


# ----------------------------------------------------------------------------------------------------------------
# Images


def test_photometric_functions():
    intr = dict(w=64, h=48, cx=32.0, cy=24.0)
    vig = vignetting_factor(intr, 0.3)
    assert vig.shape == (48, 64) and vig.max() <= 1.0 and vig[24, 32] > 0.999
    assert 0.7 < vig[0, 0] < 0.72 and abs(vig[0, 0] - vig[47, 63]) < 1e-12
    params = photometric_params(np.random.default_rng(0), 3, 500, 0.3)
    lo, hi = params.min(axis=(0, 1)), params.max(axis=(0, 1))
    np.testing.assert_allclose(lo, 1.0 - 0.3 * np.array([1, 0.5, 0.25, 0.25, 0.25]), atol=0.01)
    np.testing.assert_allclose(hi, 1.0 + 0.3 * np.array([1, 0.5, 0.25, 0.25, 0.25]), atol=0.01)
    rgb = np.random.default_rng(1).uniform(0, 1, (48, 64, 3))
    p = np.array([1.2, 0.9, 1.05, 1.0, 0.95])
    np.testing.assert_allclose(apply_photometric(rgb, p, vig), np.clip(rgb * vig[..., None] * 1.2 * p[2:], 0, 1) ** 0.9)


def test_exposure_and_vignetting_in_the_rig(rigs, scene):
    out, cfg = rigs["photo"]
    plain = rigs["plain"][0]
    rig = load_rig(out)
    params = photometric_params(np.random.default_rng(_streams(cfg.seed)["exposure"]), 3, cfg.frames, 0.3)
    vig = vignetting_factor(intrinsics(cfg), 0.3)
    ratios = []
    for c, name in enumerate(CAMERAS):
        world_T_at, _ = pose_function(plain, name)
        for k, frame in enumerate(rig.frames_of(name)):
            mine = image(out, frame.file_path)
            if k == 2:  # exactly the camera response on the true-pose render
                rgb, _ = render_frame(scene, intrinsics(cfg), world_T_at, frame.timestamp)
                assert np.abs(to_uint8(apply_photometric(rgb, params[c, k], vig)) - mine).max() <= 1
            ratios.append(mine.mean() / image(plain, frame.file_path).mean())
    assert np.std(ratios) > 0.03  # the exposure changes from frame to frame
    mine, theirs = image(out, rig.frames_of("cam_left")[0].file_path), image(plain, rig.frames_of("cam_left")[0].file_path)
    corner = mine[:6, :8].mean() / theirs[:6, :8].mean()
    centre = mine[21:27, 28:36].mean() / theirs[21:27, 28:36].mean()
    assert corner / centre < 0.85


def test_distortion_rays_project_where_opencv_says():
    intr = dict(w=64, h=48, fl_x=51.2, fl_y=51.2, cx=32.0, cy=24.0)
    k = (-0.12, 0.03)
    K = np.array([[51.2, 0, 32.0], [0, 51.2, 24.0], [0, 0, 1]])
    rays = pixel_directions(intr, 2, k)  # 2x2 supersampled: sub-pixel centres
    points = rays.reshape(-1, 3) * np.random.default_rng(0).uniform(1, 30, (rays.shape[0] * rays.shape[1], 1))
    uv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, np.array([k[0], k[1], 0.0, 0.0]))
    uu, vv = np.meshgrid((np.arange(128) + 0.5) / 2, (np.arange(96) + 0.5) / 2)
    assert np.abs(uv.reshape(-1, 2) - np.stack([uu, vv], axis=-1).reshape(-1, 2)).max() < 1e-6
    pinhole = pixel_directions(intr)
    assert np.array_equal(pinhole[..., 0], np.meshgrid((np.arange(64) + 0.5 - 32.0) / 51.2, np.arange(48))[0])


def test_distorted_rig_round_trips_and_its_scene_points_project_with_opencv(rigs, scene):
    out, cfg = rigs["lens"]
    rig = load_rig(out)
    for name in CAMERAS:
        intr = rig.sensors[name].intrinsics
        assert intr["camera_model"] == "OPENCV" and (intr["k1"], intr["k2"], intr["p1"], intr["p2"]) == (-0.12, 0.03, 0.0, 0.0)
        assert rig_to_json(rig)["sensors"][name]["k1"] == -0.12
    intr = rig.sensors["cam_front_right"].intrinsics
    K = np.array([[intr["fl_x"], 0, intr["cx"]], [0, intr["fl_y"], intr["cy"]], [0, 0, 1]])
    dist = np.array([intr["k1"], intr["k2"], intr["p1"], intr["p2"]])
    frame = rig.frames_of("cam_front_right")[3]
    world_T_at, _ = pose_function(out, "cam_front_right")
    pose = world_T_at([frame.timestamp])[0]
    pixels = np.array([[0, 0], [63, 0], [0, 47], [63, 47], [32, 24], [10, 40]])
    rays = pixel_directions(intr, 1, (intr["k1"], intr["k2"]))[pixels[:, 1], pixels[:, 0]] @ pose[:3, :3].T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    points = pose[:3, 3] + rays * scene.cast(pose[:3, 3], rays)["t_hit"][:, None]  # the scene points those pixels see
    rvec, _ = cv2.Rodrigues(pose[:3, :3].T)
    uv, _ = cv2.projectPoints(points, rvec, -pose[:3, :3].T @ pose[:3, 3], K, dist)
    assert np.abs(uv.reshape(-1, 2) - (pixels + 0.5)).max() < 0.01
    # The image is that distorted render (re-rendered through rig.json's model); the pinhole render is not.
    mine = image(out, frame.file_path)
    again, _ = render_frame(scene, intr, world_T_at, frame.timestamp, distortion=(intr["k1"], intr["k2"]))
    assert np.abs(to_uint8(again) - mine).max() <= 1
    assert np.abs(image(rigs["plain"][0], frame.file_path) - mine)[:8].mean() > 5.0


def test_rolling_shutter_rows_at_their_own_times(rigs, scene):
    out, cfg = rigs["rolling"]
    plain = rigs["plain"][0]
    rig = load_rig(out)
    raw = json.loads((out / "rig.json").read_text())
    assert all(rig.sensors[n].readout_time == 0.05 and raw["sensors"][n]["readout_time"] == 0.05 for n in CAMERAS)
    assert "readout_time" not in json.loads((plain / "rig.json").read_text())["sensors"]["cam_left"]
    tau = row_time_offsets(48, 0.05)
    np.testing.assert_allclose(tau[[0, 47]], [-0.025, 0.025]) and np.testing.assert_allclose(tau[23] + tau[24], 0.0, atol=1e-15)
    middle, edges = [], []
    for name in CAMERAS:
        for frame in rig.frames_of(name):
            diff = np.abs(image(out, frame.file_path) - image(plain, frame.file_path)).mean(axis=(1, 2))
            middle.append(diff[22:26].mean())
            edges.append(np.r_[diff[:3], diff[-3:]].mean())
    assert np.mean(edges) > 2.0 and np.mean(middle) < 0.25 * np.mean(edges), (np.mean(middle), np.mean(edges))
    # Row r is the row r of a global-shutter frame at the stamp + tau_r.
    frame = rig.frames_of("cam_left")[2]
    world_T_at, _ = pose_function(out, "cam_left")
    mine = image(out, frame.file_path)
    for r in (0, 23, 47):
        glob, _ = render_frame(scene, intrinsics(cfg), world_T_at, frame.timestamp + tau[r])
        assert np.abs(to_uint8(glob)[r] - mine[r]).max() <= 2
    assert np.abs(image(plain, frame.file_path)[0] - mine[0]).mean() > 2.0


def test_motion_blur_is_the_mean_over_the_exposure(rigs, scene):
    world_T_at, _ = pose_function(rigs["plain"][0], "cam_left")  # the side camera: fast image motion
    intr = intrinsics(rigs["plain"][1])
    np.testing.assert_allclose(exposure_offsets(0.03), [-0.01, 0.0, 0.01])
    blurred, _ = render_frame(scene, intr, world_T_at, 1000.25, exposure=0.03)
    parts = [render_frame(scene, intr, world_T_at, 1000.25 + o)[0] for o in exposure_offsets(0.03)]
    np.testing.assert_allclose(blurred, np.mean(parts, axis=0), atol=1e-6)
    sharp = parts[1]
    assert np.abs(blurred - sharp).mean() > 0.002
    assert np.sum(np.diff(blurred, axis=1) ** 2) < 0.95 * np.sum(np.diff(sharp, axis=1) ** 2)  # smoothed along the motion


def test_jpeg_images(rigs):
    out, _ = rigs["jpeg_lidar"]
    rig = load_rig(out)  # checks every image's size (Pillow reads them)
    for frame in rig.frames:
        if frame.sensor in CAMERAS:
            assert frame.file_path.endswith(".jpg") and (out / frame.file_path).read_bytes()[:3] == b"\xff\xd8\xff"
    frame = rig.frames_of("cam_front")[1]
    diff = np.abs(image(out, frame.file_path) - image(rigs["plain"][0], frame.file_path.replace(".jpg", ".png")))
    assert 0.1 < diff.mean() < 4.0
    png = np.asarray(Image.open(rigs["plain"][0] / frame.file_path.replace(".jpg", ".png")))
    assert len(encode_jpeg(png, 30)) < len(encode_jpeg(png, 90))


# ----------------------------------------------------------------------------------------------------------------
# LiDAR


def test_lidar_noise_and_dropouts(rigs):
    out, cfg = rigs["jpeg_lidar"]
    plain = rigs["plain"][0]
    rig = load_rig(out)
    dropout_rng = np.random.default_rng(_streams(cfg.seed)["lidar_dropout"])
    fractions, range_errors = [], []
    for frame in rig.frames_of("lidar"):
        exact, exact_times, _ = load_lidar_scan(plain / frame.file_path)
        noisy, times, _ = load_lidar_scan(out / frame.file_path)
        keep = lidar_dropout_mask(len(exact), 0.1, dropout_rng)  # the same subset, then the same dropout draws
        fractions.append(1.0 - len(noisy) / len(exact))
        np.testing.assert_array_equal(times, exact_times[keep])
        a, b = exact[keep].astype(np.float64), noisy.astype(np.float64)
        np.testing.assert_allclose(a / np.linalg.norm(a, axis=1, keepdims=True), b / np.linalg.norm(b, axis=1, keepdims=True), atol=1e-5)
        range_errors.append(np.linalg.norm(b, axis=1) - np.linalg.norm(a, axis=1))
    assert all(0.085 < f < 0.115 for f in fractions), fractions
    errors = np.concatenate(range_errors)
    assert abs(errors.std() / 0.02 - 1.0) < 0.05 and abs(errors.mean()) < 0.002


def _box_distance(points, centre, heading, size):
    """Signed distance of world points to a box on the ground (heading about z), metres."""
    rel = points - centre
    c, s = np.cos(heading), np.sin(heading)
    local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=-1)
    q = np.abs(local) - 0.5 * size
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def test_movers_in_lidar_scans_and_images(rigs, scene):
    out, cfg = rigs["movers"]
    rig = load_rig(out)
    movers = make_movers(make_path(cfg), 8, (cfg.frames - 1) * PERIOD, len(scene.atlas.names),
                         np.random.default_rng(_streams(cfg.seed)["movers"]))
    world_T_at, to_path_time = pose_function(out, "lidar")
    seen = {}
    for k, frame in enumerate(rig.frames_of("lidar")):
        points, times, _ = load_lidar_scan(out / frame.file_path)
        poses = world_T_at(frame.timestamp + times)
        world = np.einsum("nij,nj->ni", poses[:, :3, :3], points.astype(np.float64)) + poses[:, :3, 3]
        moving = scene_distance(scene, world) > 0.05  # not on the static scene
        path_times = frame.timestamp + times[moving] + to_path_time
        centres, headings = movers.poses(path_times)
        dist = np.stack([_box_distance(world[moving], centres[:, m], headings[:, m], movers.size[m]) for m in range(8)], axis=1)
        assert np.abs(dist).min(axis=1).max() < 5e-3  # each such point is on a vehicle where it was at the point's time
        owner = np.abs(dist).argmin(axis=1)
        for m in np.unique(owner):
            if np.sum(owner == m) >= 20:
                seen.setdefault(m, {})[k] = world[moving][owner == m].mean(axis=0)
    assert len(seen) >= 2, seen
    shifts = [np.linalg.norm(s[max(s)] - s[min(s)]) for s in seen.values() if max(s) - min(s) >= 3]
    assert shifts and max(shifts) > 0.5, shifts  # the same vehicle, elsewhere a few scans later
    plain = rigs["plain"][0]
    changed = [np.mean(np.abs(image(out, f.file_path) - image(plain, f.file_path)).max(axis=2) > 10)
               for f in rig.frames if f.sensor in CAMERAS]
    assert max(changed) > 0.01  # and the cameras see them


# ----------------------------------------------------------------------------------------------------------------
# rig.json readout_time


def test_readout_time_in_rig_json(rigs, tmp_path):
    root = Path(shutil.copytree(rigs["plain"][0], tmp_path / "rig"))
    file = root / "rig.json"
    original = json.loads(file.read_text())

    def load_with(sensor, value):
        raw = json.loads(json.dumps(original))
        raw["sensors"][sensor]["readout_time"] = value
        file.write_text(json.dumps(raw))
        return load_rig(root)

    rig = load_with("cam_left", 0.03)
    assert rig.sensors["cam_left"].readout_time == 0.03 and rig.sensors["cam_front"].readout_time == 0.0
    assert "readout_time" not in rig.sensors["cam_left"].intrinsics
    again = rig_to_json(rig)["sensors"]
    assert again["cam_left"]["readout_time"] == 0.03 and "readout_time" not in again["cam_front"]
    assert load_with("cam_left", 0).sensors["cam_left"].readout_time == 0.0
    for sensor, value, phrase in [("cam_left", -0.01, "must be >= 0 seconds, got -0.01"), ("cam_left", "fast", "must be a finite number"),
                                  ("cam_left", True, "must be a finite number"), ("cam_left", float("inf"), "must be a finite number"),
                                  ("cam_front", 0.1, "must be < the camera's frame period 0.1 s, got 0.1"),
                                  ("cam_left", 0.25, "must be < the camera's frame period 0.1 s, got 0.25"),
                                  ("lidar", 0.01, "unknown key for a lidar")]:
        with pytest.raises(RigFormatError) as info:
            load_with(sensor, value)
        msg = str(info.value)
        assert "\n" not in msg and msg == f"{file}: sensors.{sensor}.readout_time: {info.value.problem}", msg
        assert phrase in info.value.problem, msg
