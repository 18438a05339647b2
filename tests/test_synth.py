"""Tests of ``moisst-synth`` (moisst_ns/datasets/synth.py): tiny rigs, generated once per module."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro
from PIL import Image

from moisst_ns.rig.format import load_calibration, load_lidar_scan, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, sensor_pose
from moisst_ns.datasets.synth import (
    SynthError,
    PERIOD,
    SynthConfig,
    build_scene,
    intrinsics,
    make_path,
    make_rig,
    make_truth,
    reference_trajectory_samples,
)
from moisst_ns.datasets.synth_rig import perturbation_rotation
from helpers import file_hashes, render_still, scene_distance

TINY = dict(width=64, height=48, frames=8, lidar_azimuth_steps=512, lidar_max_points=6000)


def tiny(out: Path, **kw) -> SynthConfig:
    return SynthConfig(out=out, **{**TINY, **kw})


@pytest.fixture(scope="module")
def rigs(tmp_path_factory):
    base = tmp_path_factory.mktemp("synth")
    configs = {
        "a": tiny(base / "a", seed=0, perturb="paper"),
        "a2": tiny(base / "a2", seed=0, perturb="paper"),
        "b": tiny(base / "b", seed=1, perturb="paper"),
        "none": tiny(base / "none", seed=2, perturb="none", layout="plaza"),
    }
    return {name: (make_rig(cfg), cfg) for name, cfg in configs.items()}


def trajectory(rig) -> ReferenceTrajectory:
    return ReferenceTrajectory.of(rig)


def world_T(traj: ReferenceTrajectory, stamps, ref_T_sensor: np.ndarray, delta: float) -> np.ndarray:
    t_rel = torch.as_tensor(np.asarray(stamps, dtype=np.float64) + delta) - traj.t0
    return sensor_pose(traj(t_rel), torch.as_tensor(ref_T_sensor)).numpy()


def test_same_seed_identical_bytes_different_seed_differs(rigs):
    ha, ha2, hb = (file_hashes(rigs[n][0]) for n in ("a", "a2", "b"))
    assert ha == ha2 and len(ha) == 3 + 4 * TINY["frames"]
    assert set(ha) == set(hb)
    assert all(ha[k] != hb[k] for k in ("rig.json", "ground_truth.json", "images/cam_left/000000.png", "lidar/lidar/000000.npz"))


def test_validates_and_layout(rigs):
    for name in ("a", "none"):
        out, cfg = rigs[name]
        rig = load_rig(out)
        assert rig.reference_sensor == "cam_front"
        assert rig.sensor_names == ["cam_front", "cam_front_right", "cam_left", "lidar"]
        assert rig.sensors["lidar"].type == "lidar"
        assert all(len(rig.frames_of(s)) == cfg.frames for s in rig.sensors)
        ref_stamps = [f.timestamp for f in rig.frames_of("cam_front")]
        np.testing.assert_array_equal(ref_stamps, rig.trajectory_stamps)  # reference frames = trajectory samples
        assert rig.trajectory_stamps[0] == 1000.0
        intr = rig.sensors["cam_left"].intrinsics
        assert intr["fl_x"] == 0.8 * cfg.width and intr["cx"] == cfg.width / 2 and intr["cy"] == cfg.height / 2
        gt = load_calibration(out / "ground_truth.json")
        assert set(gt.T_ref_sensor) == set(rig.sensors)
        np.testing.assert_array_equal(gt.T_ref_sensor["cam_front"], np.eye(4))
        assert gt.time_offset["cam_front"] == 0.0
        # Each sensor triggers at its own phase of the 10 Hz cycle.
        phases = {s: round(rig.frames_of(s)[0].timestamp - 1000.0, 9) for s in rig.sensors}
        assert len(set(phases.values())) == 4
        assert all(np.allclose(np.diff([f.timestamp for f in rig.frames_of(s)]), PERIOD) for s in rig.sensors)


def test_paper_perturbation(rigs):
    out, _ = rigs["a"]
    rig, gt = load_rig(out), load_calibration(out / "ground_truth.json")
    combos = [perturbation_rotation(s, 5.0) for s in itertools.product((-1.0, 1.0), repeat=3)]
    np.testing.assert_array_equal(rig.sensors["cam_front"].T_ref_sensor, np.eye(4))
    assert rig.sensors["cam_front"].time_offset == 0.0
    for name in ("cam_front_right", "cam_left", "lidar"):
        prior, truth = rig.sensors[name].T_ref_sensor, gt.T_ref_sensor[name]
        np.testing.assert_allclose(np.abs(prior[:3, 3] - truth[:3, 3]), 0.5, atol=1e-12)
        rel = truth[:3, :3].T @ prior[:3, :3]
        assert min(np.abs(rel - c).max() for c in combos) < 1e-12
        assert abs(abs(rig.sensors[name].time_offset - gt.time_offset[name]) - 0.1) < 1e-12
    # Signs are random: not all the same across the sensors' 9 translation signs.
    signs = np.concatenate([np.sign(rig.sensors[n].T_ref_sensor[:3, 3] - gt.T_ref_sensor[n][:3, 3]) for n in ("cam_front_right", "cam_left", "lidar")])
    assert 0 < (signs > 0).sum() < 9


def test_perturb_magnitudes_configurable(tmp_path):
    from moisst_ns.datasets.synth import make_priors

    cfg = tiny(tmp_path / "x", perturb="paper", perturb_translation=0.2, perturb_rotation=2.0, perturb_time=0.05)
    truth = make_truth(cfg)
    priors = make_priors(cfg, truth)
    prior, delta = priors["cam_left"]
    np.testing.assert_allclose(np.abs(prior[:3, 3] - truth["cam_left"].T_ref_sensor[:3, 3]), 0.2, atol=1e-12)
    assert abs(abs(delta - truth["cam_left"].time_offset) - 0.05) < 1e-12
    angle = np.degrees(np.arccos((np.trace(truth["cam_left"].T_ref_sensor[:3, :3].T @ prior[:3, :3]) - 1) / 2))
    assert 2.0 < angle < 4.0  # three 2-degree rotations compose to ~3.5 degrees


def test_perturb_none_priors_are_truth(rigs):
    out, _ = rigs["none"]
    rig, gt = load_rig(out), load_calibration(out / "ground_truth.json")
    for name, spec in rig.sensors.items():
        np.testing.assert_array_equal(spec.T_ref_sensor, gt.T_ref_sensor[name])
        assert spec.time_offset == gt.time_offset[name]


def test_true_offsets_and_extrinsics_vary_with_seed(tmp_path):
    truths = [make_truth(tiny(tmp_path / "x", seed=s)) for s in range(6)]
    for truth in truths:
        for name in ("cam_front_right", "cam_left", "lidar"):
            assert 0.02 <= abs(truth[name].time_offset) <= 0.06
        assert np.sign(truth["cam_left"].time_offset) == -np.sign(truth["cam_front_right"].time_offset)
        t_fr = truth["cam_front_right"].T_ref_sensor[:3, 3]
        assert 0.45 < t_fr[0] < 0.65 and abs(t_fr[1]) < 0.05 and abs(t_fr[2]) < 0.05  # ~0.55 m to the right
        t_l = truth["lidar"].T_ref_sensor[:3, 3]
        assert -0.5 < t_l[1] < -0.3  # above the reference camera (OpenCV y is down)
        z_left = truth["cam_left"].T_ref_sensor[:3, 2]  # cam_left's optical axis in the reference camera frame
        assert np.degrees(np.arccos(z_left[2])) > 75 and z_left[0] < -0.9  # looks to the left (-x)
    t = np.stack([tr["cam_left"].T_ref_sensor for tr in truths])
    assert np.ptp(t[:, :3, 3], axis=0).max() > 0.01 and np.ptp(t[:, :3, 3], axis=0).max() < 0.07
    assert len({tr["lidar"].time_offset for tr in truths}) == len(truths)
    no_lidar = make_truth(tiny(tmp_path / "x", seed=0, lidar=False))
    assert set(no_lidar) == {"cam_front", "cam_front_right", "cam_left"}
    assert no_lidar["cam_left"].time_offset == truths[0]["cam_left"].time_offset


def test_path_turns_and_changes_speed(tmp_path):
    cfg = SynthConfig(out=tmp_path / "x")  # default 50 frames: no rendering needed
    truth = make_truth(cfg)
    stamps, positions, quats = reference_trajectory_samples(cfg, make_path(cfg), truth)
    assert len(stamps) == 50
    speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / np.diff(stamps)
    assert speed.min() < 5.0 and speed.max() > 8.0
    traj = ReferenceTrajectory.from_tum(stamps, positions, quats)
    forward = traj.rotations[:, :, 2].numpy()  # optical axis in the world
    heading = np.degrees(np.unwrap(np.arctan2(forward[:, 1], forward[:, 0])))
    assert abs(heading[-1] - heading[0]) > 30.0
    assert abs(np.median(forward[:, 2])) < 0.1  # forward-looking, roughly level


def test_lidar_scans(rigs):
    out, _ = rigs["a"]
    rig = load_rig(out)
    for frame in rig.frames_of("lidar"):
        points, times, dropped = load_lidar_scan(out / frame.file_path)
        with np.load(out / frame.file_path) as raw:
            assert raw["points"].dtype == np.float32 and raw["times"].dtype == np.float64
        assert dropped == 0 and 1000 < len(points) <= TINY["lidar_max_points"]
        assert times.min() >= 0.0 and times.max() < PERIOD
        assert np.all(np.diff(times) >= 0)  # firing order
        rng = np.linalg.norm(points, axis=1)
        assert rng.min() >= 0.5 - 1e-4 and rng.max() <= 60.0 + 1e-4
        elev = np.degrees(np.arcsin(np.clip(points[:, 2] / rng, -1, 1)))
        assert len(np.unique(np.round(elev, 1))) >= 32
        assert elev.min() > -25.2 and elev.max() < 10.2
        azim = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        assert np.ptp(azim) > 300  # 360-degree scan


def test_lidar_points_lie_on_scene_geometry(rigs):
    """A point fired tau after the stamp t, moved to the world with T_r(t + delta + tau) @ ref_T_L, is on a surface."""
    out, cfg = rigs["a"]
    rig, gt = load_rig(out), load_calibration(out / "ground_truth.json")
    scene = build_scene(cfg)
    traj = trajectory(rig)
    frame = rig.frames_of("lidar")[3]
    points, times, _ = load_lidar_scan(out / frame.file_path)

    def distances(delta):
        poses = world_T(traj, frame.timestamp + times, gt.T_ref_sensor["lidar"], delta)
        world = np.einsum("nij,nj->ni", poses[:, :3, :3], points.astype(np.float64)) + poses[:, :3, 3]
        return scene_distance(scene, world)

    true = distances(gt.time_offset["lidar"])
    assert np.max(true) < 2e-3, np.max(true)
    # The check has power: the wrong time offset, or ignoring the per-point times, puts points off the surfaces.
    assert np.mean(distances(gt.time_offset["lidar"] + 0.03) > 0.02) > 0.2
    poses = world_T(traj, np.full(len(times), frame.timestamp), gt.T_ref_sensor["lidar"], gt.time_offset["lidar"])
    world = np.einsum("nij,nj->ni", poses[:, :3, :3], points.astype(np.float64)) + poses[:, :3, 3]
    assert np.mean(scene_distance(scene, world) > 0.02) > 0.2


def test_camera_frames_follow_the_model(rigs):
    """Re-rendering at T_r(t + delta) @ ref_T_i from the written files reproduces the image; a wrong delta does not."""
    out, cfg = rigs["a"]
    rig, gt = load_rig(out), load_calibration(out / "ground_truth.json")
    scene = build_scene(cfg)
    traj = trajectory(rig)
    intr = intrinsics(cfg)
    for name in ("cam_front", "cam_front_right", "cam_left"):
        frame = rig.frames_of(name)[5]
        image = np.asarray(Image.open(out / frame.file_path)).astype(np.float64)
        pose = world_T(traj, [frame.timestamp], gt.T_ref_sensor[name], gt.time_offset[name])[0]
        again, _ = render_still(scene, intr, pose)
        assert np.abs(again - image).mean() < 0.5
        wrong = world_T(traj, [frame.timestamp], gt.T_ref_sensor[name], gt.time_offset[name] + 0.05)[0]
        assert np.abs(render_still(scene, intr, wrong)[0] - image).mean() > 3.0


def test_images_are_textured_not_sky(rigs):
    for name in ("a", "b", "none"):
        out, cfg = rigs[name]
        rig = load_rig(out)
        for frame in rig.frames:
            if rig.sensors[frame.sensor].type != "camera":
                continue
            gray = np.asarray(Image.open(out / frame.file_path).convert("L"), dtype=np.float64)
            assert gray.std() > 12.0, (name, frame.file_path, gray.std())
    # Hit fraction (geometry rather than sky) of every camera at the first and last frame.
    out, cfg = rigs["a"]
    rig, gt = load_rig(out), load_calibration(out / "ground_truth.json")
    scene, traj = build_scene(cfg), trajectory(rig)
    for name in ("cam_front", "cam_front_right", "cam_left"):
        for frame in (rig.frames_of(name)[0], rig.frames_of(name)[-1]):
            pose = world_T(traj, [frame.timestamp], gt.T_ref_sensor[name], gt.time_offset[name])[0]
            _, hit = render_still(scene, intrinsics(cfg), pose)
            assert hit.mean() > 0.6, (name, frame.timestamp, hit.mean())


def test_refuses_non_empty_out_unless_overwrite(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    with pytest.raises(SynthError, match="not empty"):
        make_rig(tiny(out, frames=2, lidar=False))
    make_rig(tiny(out, frames=3, lidar=False, overwrite=True))
    assert (out / "keep.txt").read_text() == "x"
    make_rig(tiny(out, frames=2, lidar=False, overwrite=True))  # stale frames of the larger run are removed
    rig = load_rig(out)
    assert "lidar" not in rig.sensors and len(rig.frames) == 6
    assert len(list((out / "images" / "cam_left").iterdir())) == 2


def test_cli_parsing():
    cfg = tyro.cli(SynthConfig, args=["/tmp/some_out", "--seed", "3", "--frames", "7", "--width", "80", "--height", "60",
                                      "--perturb", "none", "--no-lidar", "--layout", "plaza", "--perturb-translation", "0.3",
                                      "--perturb-rotation", "2", "--perturb-time", "0.05", "--overwrite"])
    assert cfg.out == Path("/tmp/some_out") and cfg.seed == 3 and cfg.frames == 7 and (cfg.width, cfg.height) == (80, 60)
    assert cfg.perturb == "none" and cfg.lidar is False and cfg.layout == "plaza" and cfg.overwrite
    assert (cfg.perturb_translation, cfg.perturb_rotation, cfg.perturb_time) == (0.3, 2.0, 0.05)
    default = tyro.cli(SynthConfig, args=["x"])
    assert default.perturb == "paper" and default.lidar and default.layout == "street" and default.frames == 50
