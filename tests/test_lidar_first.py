"""The LiDAR-first stage: placement and Jacobian against the rig math, closed-form residuals, observability flags,
de-skew of raw sweeps, bad input, and end-to-end runs on tiny synthetic rigs."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import roma
import torch
import yaml

from moisst_ns.cli.lidar_calibrate import LidarCalibrateConfig, run_lidar_calibration
from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import load_calibration, load_lidar_scan, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic, interpolate_trajectory
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar.lidar_first import Correspondences, LidarFirstConfig, LidarFirstError, ScanSet, calibrate_lidars, consistency_residuals
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points, placement_jacobian
from moisst_ns.stages.lidar.lidar_report import stage_sigma, stage_summary
from moisst_ns.stages.trust.observability import PARAMETERS, analyse_observability
from moisst_ns.datasets.synth import SynthConfig, build_scene, make_rig
from helpers import scene_distance, tree_hash


def rotz(deg: float) -> np.ndarray:
    return roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, np.deg2rad(deg)], dtype=torch.float64)).numpy()


def numpy_trajectory(times, rotations, translations) -> ReferenceTrajectory:
    """A ``ReferenceTrajectory`` of numpy samples (float64)."""
    return ReferenceTrajectory(*(torch.from_numpy(np.asarray(a, dtype=np.float64)) for a in (times, rotations, translations)))


def random_trajectory(rng: np.random.Generator, num: int = 12) -> ReferenceTrajectory:
    rotvecs = np.cumsum(rng.normal(0, 0.05, (num, 3)), axis=0)
    rot = roma.rotvec_to_rotmat(torch.from_numpy(rotvecs)).numpy()
    return numpy_trajectory(np.cumsum(rng.uniform(0.05, 0.15, num)), rot, np.cumsum(rng.normal(0, 1.0, (num, 3)), axis=0))


def test_placement_is_paper_eq_1_2():
    """``place_points`` equals the rig geometry's eq. 1 (``interpolate_trajectory``, extrapolation included) and eq. 2."""
    rng = np.random.default_rng(0)
    traj = random_trajectory(rng)
    ext = Extrinsic(rotz(30.0), np.array([0.5, -0.2, 1.0]), 0.04)
    points = rng.normal(0, 10, (200, 3))
    times = rng.uniform(float(traj.times[0]) - 0.3, float(traj.times[-1]) + 0.3, 200)
    world_T_ref = interpolate_trajectory(traj.times, traj.rotations, traj.translations, torch.from_numpy(times + ext.time_offset))
    expected = (world_T_ref @ torch.from_numpy(ext.matrix()))[:, :3, :3] @ torch.from_numpy(points)[..., None]
    expected = expected[..., 0] + (world_T_ref @ torch.from_numpy(ext.matrix()))[:, :3, 3]
    assert np.abs(place_points(traj, ext, points, times) - expected.numpy()).max() < 1e-9


def test_jacobian_matches_autograd_through_eq_12():
    """The analytic Jacobian of ``n . x`` equals torch autograd through eq. 1 and eq. 12 (``calibrated_extrinsic``),
    at a non-zero increment (so the right Jacobian of Exp matters)."""
    rng = np.random.default_rng(1)
    traj = random_trajectory(rng)
    ext = Extrinsic(rotz(-20.0), np.array([1.0, 0.3, -0.5]), -0.03)
    points, normals = rng.normal(0, 8, (50, 3)), rng.normal(0, 1, (50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    times = rng.uniform(float(traj.times[1]), float(traj.times[-2]), 50)
    increment = np.array([0.3, -0.2, 0.25, 0.1, -0.2, 0.05, 0.012])
    value, jac = placement_jacobian(traj, ext, increment, points, times, normals)

    inc = torch.tensor(increment, requires_grad=True)
    pose = calibrated_extrinsic(torch.from_numpy(ext.matrix()), inc[:3], inc[3:6])
    world_T_ref = interpolate_trajectory(traj.times, traj.rotations, traj.translations, torch.from_numpy(times) + ext.time_offset + inc[6])
    world = (world_T_ref @ pose)[:, :3, :3] @ torch.from_numpy(points)[..., None]
    world = world[..., 0] + (world_T_ref @ pose)[:, :3, 3]
    projected = (world * torch.from_numpy(normals)).sum(-1)
    expected = torch.stack([torch.autograd.grad(projected[i], inc, retain_graph=True)[0] for i in range(len(points))])
    assert np.abs(value - projected.detach().numpy()).max() < 1e-9
    assert np.abs(jac - expected.numpy()).max() < 1e-6 * max(1.0, np.abs(expected.numpy()).max())


def corner_world(rng: np.random.Generator, num: int = 300):
    """Points on three planes (ground z=0, walls x=6 and y=-5) and their normals."""
    ground = np.c_[rng.uniform(-4, 5, num), rng.uniform(-4, 4, num), np.zeros(num)]
    wall_x = np.c_[np.full(num, 6.0), rng.uniform(-4, 4, num), rng.uniform(0, 3, num)]
    wall_y = np.c_[rng.uniform(-4, 5, num), np.full(num, -5.0), rng.uniform(0, 3, num)]
    normals = np.repeat(np.eye(3)[[2, 0, 1]], num, axis=0)
    return np.concatenate([ground, wall_x, wall_y]), normals


def two_scan_problem(lever_error: np.ndarray):
    """Two scans of the corner, 0.5 s apart, the vehicle turning 30 deg about z and moving 2 m; the LiDAR's true
    extrinsic is known, its estimate off by ``lever_error``. Correspondences: every world point with itself."""
    rng = np.random.default_rng(2)
    world, normals = corner_world(rng)
    traj = numpy_trajectory(np.array([0.0, 0.5, 1.0]), np.stack([rotz(0.0), rotz(30.0), rotz(60.0)]),
                      np.array([[0.0, 0.0, 0.0], [2.0, 0.5, 0.0], [4.0, 1.5, 0.0]]))
    truth = Extrinsic(rotz(90.0), np.array([0.5, 0.0, 1.8]), 0.0)
    poses = [traj.pose_and_rates(np.array([t]))[:2] for t in (0.0, 0.5)]
    # LiDAR-frame points of the same world points seen from each scan: p = R_L^T (R_r^T (x - p_r) - t_L)
    local = [((world - pos[0]) @ rot[0]) @ truth.rotation - truth.translation @ truth.rotation for rot, pos in poses]
    num = len(world)
    scans = ScanSet("lidar", np.concatenate(local), np.r_[np.zeros(num), np.full(num, 0.5)], np.array([0, num, 2 * num]),
                    np.array([0.0, 0.5]), np.zeros((2 * num, 3)), np.ones(2 * num, bool), np.zeros(2 * num), [np.arange(num), np.arange(num, 2 * num)],
                    ["a", "b"], True)
    corr = Correspondences(np.arange(num), np.arange(num, 2 * num), normals, np.ones(num), num)
    wrong = Extrinsic(truth.rotation, truth.translation + lever_error, 0.0)
    return traj, truth, wrong, scans, corr, normals, poses


def test_two_scans_of_a_corner_closed_form():
    """Point-to-plane residuals are 0 at the truth and ``n . (R_a - R_b) d`` for a lever-arm error ``d``."""
    d = np.array([0.3, -0.2, 0.4])
    traj, truth, wrong, scans, corr, normals, poses = two_scan_problem(d)
    at_truth, _ = consistency_residuals(traj, truth, scans, corr, np.zeros(7))
    assert np.abs(at_truth).max() < 1e-9
    residuals, _ = consistency_residuals(traj, wrong, scans, corr, np.zeros(7))
    expected = normals @ ((poses[0][0][0] - poses[1][0][0]) @ d)
    assert np.abs(residuals - expected).max() < 1e-9
    # the vertical part of d never shows (both poses rotate about z only): closed form says n . (R_a - R_b) e_z = 0
    vertical, _ = consistency_residuals(traj, Extrinsic(truth.rotation, truth.translation + [0, 0, 0.5], 0.0), scans, corr, np.zeros(7))
    assert np.abs(vertical).max() < 1e-9


def observability_of(traj: ReferenceTrajectory, times: np.ndarray, ext: Extrinsic, seed: int = 3):
    """Observability on a box-shaped world of many plane orientations, scans at ``times``, every pair within 2 s."""
    rng = np.random.default_rng(seed)
    jacs = []
    for i, ta in enumerate(times):
        for tb in times[i + 1:]:
            if tb - ta > 2.0:
                continue
            x = rng.uniform(-15, 15, (60, 3)) + traj.pose_and_rates(np.array([ta]))[1]
            n = rng.normal(0, 1, (60, 3))
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            local = []
            for t in (ta, tb):
                rot, pos, _, _ = traj.pose_and_rates(np.full(60, t))
                ref = np.einsum("nji,nj->ni", rot, x - pos)
                local.append((ref - ext.translation) @ ext.rotation)
            _, ja = placement_jacobian(traj, ext, np.zeros(7), local[0], np.full(60, ta), n)
            _, jb = placement_jacobian(traj, ext, np.zeros(7), local[1], np.full(60, tb), n)
            jacs.append(ja - jb)
    jac = np.concatenate(jacs)
    obs = analyse_observability(jac, np.full(len(jac), 0.005), np.ones(len(jac)), traj, times, ext.rotation)
    return obs


def drive(heading, speed, pitch_roll_deg=0.0, duration=6.0):
    t = np.linspace(0, duration, 121)
    psi, v = heading(t), speed(t)
    xy = np.c_[np.cumsum(v * np.cos(psi)), np.cumsum(v * np.sin(psi))] * (t[1] - t[0])
    tilt = np.deg2rad(pitch_roll_deg) * np.sin(2 * np.pi * t / 2.0)
    rotvecs = np.c_[tilt, np.deg2rad(pitch_roll_deg) * np.cos(2 * np.pi * t / 3.0), psi]
    rot = roma.rotvec_to_rotmat(torch.from_numpy(rotvecs)).numpy()
    return numpy_trajectory(t, rot, np.c_[xy, np.zeros(len(t))])


EXT = Extrinsic(rotz(10.0), np.array([1.2, 0.1, 1.9]), 0.02)
TIMES = np.arange(0.1, 5.9, 0.2)


def test_observability_straight_constant_speed_drive():
    """No rotation and no speed change: the lever arm and the time offset are flagged, and so is the rotation about
    the direction of travel (the LiDAR is yawed 10 deg, so that axis mixes its roll and pitch); yaw is not."""
    obs = observability_of(drive(lambda t: 0 * t, lambda t: 8 + 0 * t), TIMES, EXT)
    assert obs.weak == ["x", "y", "z", "roll", "pitch", "time_offset"]
    assert "velocity changes by only 0.00 m/s" in obs.dofs[PARAMETERS.index("time_offset")].reason
    assert "along the sensor's (0.98, -0.17, 0.00) direction and turns only 0.0 deg" in obs.dofs[PARAMETERS.index("roll")].reason


def test_observability_flat_drive():
    """Turns and speed changes on a flat road: only the vertical lever arm (z, world up here) is flagged."""
    obs = observability_of(drive(lambda t: 0.8 * np.sin(t / 2), lambda t: 6 + 2 * np.sin(t)), TIMES, EXT)
    assert obs.weak == ["z"]
    assert "turns only 0.0 deg about its axes other than z" in obs.dofs[2].reason
    # pitching and rolling by a few degrees makes the vertical observable too
    assert observability_of(drive(lambda t: 0.8 * np.sin(t / 2), lambda t: 6 + 2 * np.sin(t), pitch_roll_deg=4.0), TIMES, EXT).weak == []


TINY = dict(width=48, height=36, frames=20, lidar_azimuth_steps=512, lidar_max_points=6000)


@pytest.fixture(scope="module")
def tiny_rigs(tmp_path_factory):
    base = tmp_path_factory.mktemp("lidar_first")
    return {
        "raw": make_rig(SynthConfig(out=base / "raw", seed=3, perturb="paper", **TINY)),
        "compensated": make_rig(SynthConfig(out=base / "comp", seed=4, perturb="paper", layout="plaza", lidar_scans="compensated", **TINY)),
    }


def test_deskew_of_a_raw_sweep(tiny_rigs, tmp_path):
    """Placed point by point at its firing time, a raw sweep lies on the scene; placed at the stamp it does not. A
    compensated scan (no times) lies on the scene placed at its stamp."""
    rig = load_rig(tiny_rigs["raw"])
    truth = load_calibration(rig.root / "ground_truth.json")
    scene = build_scene(SynthConfig(out=tmp_path, seed=3, **TINY))
    traj = ReferenceTrajectory.of(rig)
    ext = Extrinsic(truth.T_ref_sensor["lidar"][:3, :3], truth.T_ref_sensor["lidar"][:3, 3], truth.time_offset["lidar"])
    frame = rig.frames_of("lidar")[10]
    points, times, _ = load_lidar_scan(rig.root / frame.file_path)
    stamp = frame.timestamp - rig.trajectory_stamps[0]
    deskewed = scene_distance(scene, place_points(traj, ext, points.astype(np.float64), stamp + times))
    skewed = scene_distance(scene, place_points(traj, ext, points.astype(np.float64), np.full(len(points), stamp)))
    assert np.percentile(deskewed, 99) < 2e-3
    assert np.percentile(skewed, 90) > 0.1  # measured 0.21 m (ground points slide along the ground and stay on it)

    crig = load_rig(tiny_rigs["compensated"])
    ctruth = load_calibration(crig.root / "ground_truth.json")
    cext = Extrinsic(ctruth.T_ref_sensor["lidar"][:3, :3], ctruth.T_ref_sensor["lidar"][:3, 3], ctruth.time_offset["lidar"])
    cframe = crig.frames_of("lidar")[10]
    cpoints, ctimes, _ = load_lidar_scan(crig.root / cframe.file_path)
    assert ctimes is None
    cscene = build_scene(SynthConfig(out=tmp_path, seed=4, layout="plaza", **TINY))
    placed = place_points(ReferenceTrajectory.of(crig), cext, cpoints.astype(np.float64), np.full(len(cpoints), cframe.timestamp - crig.trajectory_stamps[0]))
    assert np.percentile(scene_distance(cscene, placed), 99) < 2e-3


@pytest.mark.parametrize("kind", ["raw", "compensated"])
def test_end_to_end_from_the_paper_perturbation(tiny_rigs, kind):
    """From 86.6 cm / 8.8 deg / 100 ms to within the issue's bounds (1 cm / 0.02 deg / 0.5 ms) on a 2 s tiny drive."""
    rig = load_rig(tiny_rigs[kind])
    truth = load_calibration(rig.root / "ground_truth.json")
    result = calibrate_lidars(rig, LidarFirstConfig(), log=lambda _: None)
    errors = calibration_report_errors(result.calibration, truth)["lidar"]
    assert errors["translation_cm"] < 1.0 and errors["rotation_deg"] < 0.02 and errors["time_ms"] < 0.5, errors
    assert result.lidars["lidar"].deskewed == (kind == "raw")
    for name in ("cam_front_right", "cam_left"):  # cameras stay at their priors
        assert np.array_equal(result.calibration.T_ref_sensor[name], rig.sensors[name].T_ref_sensor)


def test_cli_writes_outputs_and_never_the_dataset(tiny_rigs, tmp_path, capsys):
    dataset = tiny_rigs["raw"]
    before = tree_hash(dataset)
    summary = run_lidar_calibration(LidarCalibrateConfig(dataset=dataset, output_dir=tmp_path / "out"))
    assert tree_hash(dataset) == before
    out = tmp_path / "out"
    calib = load_calibration(out / "calibration.json")
    assert set(calib.T_ref_sensor) == {"cam_front", "cam_front_right", "cam_left", "lidar"}
    stored = json.loads((out / "lidar_first.json").read_text())
    assert stored["sensors"]["lidar"]["errors_after"] == summary["sensors"]["lidar"]["errors_after"]
    assert [d["name"] for d in stored["sensors"]["lidar"]["observability"]] == list(PARAMETERS)
    assert len(stored["sensors"]["lidar"]["history"]) >= 3
    assert (out / "lidar_first.md").is_file() and (out / "lidar_first_convergence.png").stat().st_size > 1000
    text = capsys.readouterr().out
    assert "errors after the LiDAR-first stage:" in text and "observability" in text


def copy_rig(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def edit_rig(root: Path, edit) -> None:
    data = json.loads((root / "rig.json").read_text())
    edit(data)
    (root / "rig.json").write_text(json.dumps(data))


def test_bad_input_one_line_errors(tiny_rigs, tmp_path):
    src = tiny_rigs["raw"]
    # fewer than 3 scans
    few = copy_rig(src, tmp_path / "few")
    edit_rig(few, lambda d: d.update(frames=[f for f in d["frames"] if f["sensor"] != "lidar" or f["file_path"].endswith(("000000.npz", "000001.npz"))]))
    with pytest.raises(LidarFirstError, match=r"rig.json: sensors.lidar: needs at least 3 usable scans, got 2 of 2$"):
        calibrate_lidars(load_rig(few), LidarFirstConfig(), log=lambda _: None)
    # scans outside the trajectory's time span
    late = copy_rig(src, tmp_path / "late")
    edit_rig(late, lambda d: [f.update(timestamp=f["timestamp"] + 100.0) for f in d["frames"] if f["sensor"] == "lidar"])
    with pytest.raises(LidarFirstError, match=r"needs at least 3 usable scans, got 0 of 20 \(.*outside the reference trajectory's time span by more than 0.2 s"):
        calibrate_lidars(load_rig(late), LidarFirstConfig(), log=lambda _: None)
    # no overlap: a trajectory 1000x too fast puts consecutive scans hundreds of metres apart
    fast = copy_rig(src, tmp_path / "fast")
    rows = [line.split() for line in (fast / "reference_poses.txt").read_text().splitlines() if not line.startswith("#")]
    (fast / "reference_poses.txt").write_text("\n".join(" ".join([r[0], *(str(1000 * float(v)) for v in r[1:4]), *r[4:]]) for r in rows) + "\n")
    with pytest.raises(LidarFirstError, match=r"sensors.lidar: the scans do not overlap"):
        calibrate_lidars(load_rig(fast), LidarFirstConfig(), log=lambda _: None)
    # a scan of NaN points
    nan = copy_rig(src, tmp_path / "nan")
    np.savez(nan / "lidar/lidar/000004.npz", points=np.full((100, 3), np.nan, np.float32))
    with pytest.raises(LidarFirstError, match=r"000004.npz: points: no points left after dropping non-finite points"):
        calibrate_lidars(load_rig(nan), LidarFirstConfig(), log=lambda _: None)
    # not a LiDAR
    with pytest.raises(LidarFirstError, match=r"sensors.cam_left: not a non-reference LiDAR of this rig \(LiDARs: \['lidar'\]\)"):
        calibrate_lidars(load_rig(src), LidarFirstConfig(), sensors=["cam_left"], log=lambda _: None)


def test_cli_bad_input_exits_with_one_line(tiny_rigs, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        run_lidar_calibration(LidarCalibrateConfig(dataset=tmp_path / "missing", output_dir=tmp_path / "o"))
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("moisst-lidar-calibrate: error:") and "\n" not in err
    with pytest.raises(SystemExit):
        run_lidar_calibration(LidarCalibrateConfig(dataset=tiny_rigs["raw"], output_dir=tiny_rigs["raw"] / "out"))
    assert "must not be inside the dataset folder" in capsys.readouterr().err


def test_calibrate_runs_the_stage_first_and_holds_the_lidar(tiny_rigs, tmp_path):
    """``moisst-calibrate`` runs the stage into OUT/lidar_first, starts the NeRF from its estimate, holds the LiDAR
    there (the NeRF's estimate equals the stage's exactly) and records the stage's iterations at negative steps of
    the history; ``--no-lidar-first`` does none of it."""
    from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
    from moisst_ns.runs.history import read_history

    dataset = tiny_rigs["raw"]
    before = tree_hash(dataset)
    out = tmp_path / "out"
    config_path = run_calibration(CalibrateConfig(dataset=dataset, output_dir=out, max_num_iterations=12, seed=0, threads=2, report=False))
    assert tree_hash(dataset) == before
    stage = load_calibration(out / "lidar_first" / "calibration.json")
    final = load_calibration(out / "calibration.json")
    np.testing.assert_allclose(final.T_ref_sensor["lidar"], stage.T_ref_sensor["lidar"], atol=1e-9)
    assert final.time_offset["lidar"] == pytest.approx(stage.time_offset["lidar"], abs=1e-9)
    truth = load_calibration(dataset / "ground_truth.json")
    assert calibration_report_errors(final, truth)["lidar"]["translation_cm"] < 1.0
    history = read_history(config_path.parent / "calibration_history.csv")
    steps = history["lidar"]["step"]
    stage_rows = int((steps < 0).sum())
    assert stage_rows == len(json.loads((out / "lidar_first" / "lidar_first.json").read_text())["sensors"]["lidar"]["history"])
    assert list(steps[:stage_rows]) == list(range(-stage_rows, 0)) and steps[stage_rows] >= 0
    assert history["lidar"]["err_translation_cm"][0] > 10 and history["lidar"]["err_translation_cm"][stage_rows - 1] < 1.0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["lidar_first"]["lidar"]["errors_after"]["translation_cm"] < 1.0
    # the stage's iterations open the history, but a held LiDAR never moved in the NeRF: not "still moving"
    assert "lidar" not in summary["still_moving"] and summary["verdicts"]["lidar"].get("verdict") != "not converged"
    # by default the LiDAR map's range supervises the rays of every camera whose pose is known: the reference camera
    # and the cameras the stages hold (registered, or held at their prior), and no other
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    registered = json.loads((out / "camera_registration" / "camera_registration.json").read_text())["sensors"]
    held = [n for n, e in registered.items() if not e["kept_prior"] or e.get("held_there")]
    assert config.pipeline.model.map_range_mult == 10.0
    assert sorted(config.pipeline.datamanager.map_range_sensors) == sorted(["cam_front", *held])

    plain = tmp_path / "plain"
    plain_config = run_calibration(CalibrateConfig(dataset=dataset, output_dir=plain, max_num_iterations=4, seed=0, threads=2, report=False, lidar_first=False))
    assert not (plain / "lidar_first").exists() and "lidar_first" not in json.loads((plain / "summary.json").read_text())
    assert yaml.load(plain_config.read_text(), Loader=yaml.Loader).pipeline.datamanager.map_range_sensors == ()  # no stage placed the LiDAR


def test_release_check_flags_a_wrong_held_time_offset(tiny_rigs):
    """Held 100 ms off, the time offset disagrees with the scans (released, it moves back by about 100 ms) and the
    extrinsic, which absorbed it, gets a sigma that covers its error within 3 sigma (its formal sigma alone is
    conditional on the held value: hundreds of times too small), and so does the held offset; held at the truth,
    nothing is flagged and the extrinsic is right."""
    import dataclasses

    from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, calibrate_lidar

    rig = load_rig(tiny_rigs["raw"])
    truth = load_calibration(rig.root / "ground_truth.json")
    held = LidarFirstConfig(estimate_time_offset=False)
    wrong = calibrate_lidar(rig, "lidar", held, log=lambda s: None)
    check = wrong.held_check
    assert check["held"] == ["time_offset"] and check["inconsistent"] == ["time_offset"]
    assert check["note"].startswith("held at its prior, time_offset disagree with the scans (released, they move by time_offset ")
    true_shift = truth.time_offset["lidar"] - rig.sensors["lidar"].time_offset
    assert abs(check["released_change"][6] - true_shift) < 0.005, (check["released_change"][6], true_shift)
    error = np.abs(parameter_difference(truth.T_ref_sensor["lidar"], truth.time_offset["lidar"], wrong.estimate.matrix(), wrong.estimate.time_offset))
    formal = np.array([d.sigma for d in wrong.observability.dofs])
    sigma = np.fmax(formal, check["sigma_release"])
    assert np.max(error[:6] / formal[:6]) > 10 and np.all(error <= 3 * sigma), (error, formal, sigma)  # the held delta too

    spec = dataclasses.replace(rig.sensors["lidar"], time_offset=truth.time_offset["lidar"])
    right = calibrate_lidar(dataclasses.replace(rig, sensors={**rig.sensors, "lidar": spec}), "lidar", held, log=lambda s: None)
    assert right.held_check["inconsistent"] == [] and right.held_check["note"] == ""
    assert calibration_report_errors_of(right, truth)["translation_cm"] < 1.0


def calibration_report_errors_of(result, truth):
    from moisst_ns.rig.format import Calibration

    estimate = Calibration(truth.reference_sensor, {**truth.T_ref_sensor, result.sensor: result.estimate.matrix()},
                           {**truth.time_offset, result.sensor: result.estimate.time_offset})
    return calibration_report_errors(estimate, truth)[result.sensor]


def test_split_half_spread_exact_values():
    """Half the difference of the two halves' fits, each half fitted on the pairs wholly inside it; NaN (not measured)
    when a half has no pair or cannot be fitted."""
    from moisst_ns.stages.lidar.lidar_first import split_half_spread

    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [1, 4]])
    seen = []

    def fit(p, b):
        seen.append(p.tolist())
        shift = 0.02 if p.min() >= 3 else 0.0
        return Extrinsic(np.eye(3), np.array([shift, 0.0, 0.0]), 0.004 if shift else 0.001)

    spread = split_half_spread(fit, pairs, np.ones(len(pairs)), 6)
    assert seen == [[[0, 1], [1, 2]], [[3, 4], [4, 5]]]  # pairs across the middle (2-3, 1-4) are in neither half
    np.testing.assert_allclose(spread, [0.01, 0, 0, 0, 0, 0, 0.0015], atol=1e-12)
    assert np.all(np.isnan(split_half_spread(fit, np.array([[0, 5]]), np.ones(1), 6)))
    assert np.all(np.isnan(split_half_spread(lambda p, b: None, pairs, np.ones(len(pairs)), 6)))


def test_trajectory_spread_is_the_rms_effect_of_new_draws_of_the_stated_errors(tiny_rigs):
    """Each draw is the rig's trajectory plus one more draw of its stated errors (seeds 0 .. draws-1), the rig itself
    untouched; the spread is, per sensor, the RMS over the fits of their difference from the estimate: here a fit that
    follows the mean position shift exactly and a delta of 1 ms per centimetre of it. A failed fit is left out; none
    fitted: NaN."""
    from moisst_ns.rig.trajectory_noise import TrajectoryAccuracy, trajectory_spread

    rig = load_rig(tiny_rigs["raw"])
    rig.trajectory_accuracy = TrajectoryAccuracy(noise_m=0.01, drift_m=0.03, drift_deg=0.05)
    given = rig.trajectory_positions.copy()
    estimate = {"a": (np.eye(4), 0.0), "b": (np.eye(4), 0.5)}
    shifts = []

    def fit(drawn):
        shift = (drawn.trajectory_positions - given).mean(axis=0)
        shifts.append(shift)
        pose = np.eye(4)
        pose[:3, 3] = shift
        return {"a": None if len(shifts) == 2 else (pose, 0.1 * shift[0]), "b": None}

    spread = trajectory_spread(fit, rig, estimate, 4)
    kept = np.array([s for i, s in enumerate(shifts) if i != 1])
    assert len(shifts) == 4 and np.abs(kept).max() > 1e-3  # the draws differ from the given trajectory, by centimetres
    np.testing.assert_array_equal(rig.trajectory_positions, given)
    np.testing.assert_allclose(spread["a"][:3], np.sqrt(np.mean(kept**2, axis=0)), rtol=1e-9)
    np.testing.assert_allclose(spread["a"][6], 0.1 * np.sqrt(np.mean(kept[:, 0] ** 2)), rtol=1e-9)
    np.testing.assert_allclose(spread["a"][3:6], 0.0, atol=1e-12)
    assert np.all(np.isnan(spread["b"]))
    again = []
    trajectory_spread(lambda drawn: again.append((drawn.trajectory_positions - given).mean(axis=0)) or {}, rig, estimate, 4)
    np.testing.assert_array_equal(np.array(again), np.array(shifts))  # the same draws every time (seeds 0 .. 3)


@pytest.mark.slow
def test_the_trajectorys_stated_errors_cover_what_its_drift_costs(tmp_path):
    """A trajectory with 1 cm / 0.02 deg of white noise and 3 cm / 0.05 deg of drift (``--realistic``'s), stated in
    rig.json: the tiny drive's lateral lever arm (x) ends 35 cm off at 7x the sigma of the formal, split-half and
    release parts (measured: the drift biases both halves alike); with the part its stated errors put into the estimate
    (six draws) every parameter is within 3 sigma. The estimate itself does not change."""
    out = make_rig(SynthConfig(out=tmp_path / "noisy", seed=3, perturb="paper", pose_noise=(1.0, 0.02), pose_drift=(3.0, 0.05), **TINY))
    rig = load_rig(out)
    truth = load_calibration(out / "ground_truth.json")
    config = LidarFirstConfig()
    result = calibrate_lidars(rig, config, log=lambda _: None)
    entry = stage_summary(result, config, result.calibration, None)["sensors"]["lidar"]
    error = np.abs(parameter_difference(truth.T_ref_sensor["lidar"], truth.time_offset["lidar"], result.calibration.T_ref_sensor["lidar"],
                                        result.calibration.time_offset["lidar"]))
    with_part = np.array(stage_sigma(entry)[0])
    without = np.array(stage_sigma({k: v for k, v in entry.items() if k != "sigma_trajectory"})[0])
    assert np.max(error / without) > 5 and np.all(error <= 3 * with_part), (error, without, with_part)
    assert stage_sigma(entry)[1].endswith("and the trajectory's errors")


def test_split_half_sigma_covers_a_short_drive_the_formal_sigma_does_not(tiny_rigs, tmp_path):
    """Six scans (0.6 s, about 2 m of nearly straight driving): the lever arm is barely determined, the estimate is
    centimetres to decimetres off with a formal sigma many times smaller; the halves of the drive disagree by as much,
    so every parameter's error is within 3x the larger of the two sigmas."""
    from moisst_ns.stages.lidar.lidar_first import calibrate_lidar

    short = copy_rig(tiny_rigs["raw"], tmp_path / "short")
    keep = tuple(f"{k:06d}.npz" for k in range(6))
    edit_rig(short, lambda d: d.update(frames=[f for f in d["frames"] if f["sensor"] != "lidar" or f["file_path"].endswith(keep)]))
    rig = load_rig(short)
    truth = load_calibration(rig.root / "ground_truth.json")
    result = calibrate_lidar(rig, "lidar", LidarFirstConfig(), log=lambda s: None)
    error = np.abs(parameter_difference(truth.T_ref_sensor["lidar"], truth.time_offset["lidar"], result.estimate.matrix(), result.estimate.time_offset))
    formal = np.array([d.sigma for d in result.observability.dofs])
    split = np.array(result.sigma_split)
    assert np.max(error / formal) > 5, (error, formal)
    assert np.all(error <= 3 * np.fmax(formal, split)), (error, formal, split)



def test_a_straight_drive_keeps_at_the_prior_what_it_does_not_determine(tmp_path):
    """On a straight drive at constant speed the lever arm and delta are not determined (flagged weak); the prior
    (``prior_sigma``) keeps them at rig.json's values instead of letting them run off along the flat direction (the
    along-track lever arm ran 3.4 m off with open3d 0.19 and 16 m with 0.20 before it), while pitch and yaw, which
    the drive does determine, move from 4.8 deg to under 0.06 deg; the LiDAR ends no farther from the truth than its
    prior in translation, rotation and time."""
    from moisst_ns.stages.lidar.lidar_first import calibrate_lidar

    rig = load_rig(make_rig(SynthConfig(out=tmp_path / "straight", seed=3, perturb="paper", drive="straight", **TINY)))
    truth = load_calibration(rig.root / "ground_truth.json")
    result = calibrate_lidar(rig, "lidar", LidarFirstConfig(), log=lambda s: None)
    weak = {d.name for d in result.observability.dofs if d.weak}
    assert {"x", "time_offset"} <= weak, weak
    from_prior = parameter_difference(result.prior.matrix(), result.prior.time_offset, result.estimate.matrix(), result.estimate.time_offset)
    assert all(abs(c) < 1e-4 for p, c in zip(PARAMETERS, from_prior) if p in ("x", "y", "z", "time_offset")), from_prior
    before = parameter_difference(truth.T_ref_sensor["lidar"], truth.time_offset["lidar"], result.prior.matrix(), result.prior.time_offset)
    error = parameter_difference(truth.T_ref_sensor["lidar"], truth.time_offset["lidar"], result.estimate.matrix(), result.estimate.time_offset)
    for name in ("pitch", "yaw"):
        k = PARAMETERS.index(name)
        assert abs(before[k]) > 0.05 and abs(error[k]) < 1e-3, (name, before[k], error[k])
    after = calibration_report_errors_of(result, truth)
    prior = calibration_report_errors_of(dataclasses.replace(result, estimate=result.prior), truth)
    assert all(after[k] <= prior[k] + 1e-3 for k in ("translation_cm", "rotation_deg", "time_ms")), (after, prior)

def test_undetermined_is_what_was_held_and_not_placed_or_has_a_spread_over_a_typical_error():
    """``LidarResult.undetermined``: held at the prior because the halves disagree and not placed by the shared view,
    or a split-half / placed sigma above a typical prior error (10 cm, 1 deg, 10 ms); ``motion_undetermined`` (what the
    camera stage's ``map_source`` reads) counts the placed ones too; a parameter the user holds is neither; exact lists."""
    from moisst_ns.stages.lidar.lidar_first import LidarResult

    def result(held, split, accepted, by_user=()):
        return LidarResult("lidar", None, None, [], None, 0, False, [], 0.0, held_check={"held": held + list(by_user), "held_apart": held},
                           sigma_split=split, view_search={"accepted": accepted})

    split = [0.19, 0.03, 0.0, 0.014, 0.002, 0.001, 0.006]  # KITTI raw 0048's: x 19 cm apart, the roll placed
    assert result(["x", "z", "roll"], split, [0]).undetermined() == ["x", "z"]  # roll is Jacobian column 0
    assert result(["x", "z", "roll"], split, [0]).motion_undetermined() == ["x", "z", "roll"]  # placed by the view, not the motion
    assert result(["y", "roll"], [0.0, 0.12, 0.0, 0.0, 0.0, 0.0, 0.0], [0, 4]).undetermined() == ["y"]  # placed, sigma over 10 cm
    assert result(["x", "z", "roll"], split, []).undetermined() == ["x", "z", "roll"]
    assert result([], [0.05, 0.12, 0.0, 0.0, 0.0, 0.02, 0.011], []).undetermined() == ["y", "yaw", "time_offset"]
    assert result(["z"], split, [], by_user=["x", "y", "roll", "pitch", "yaw"]).undetermined() == ["x", "z"]  # x by its spread
    assert LidarResult("lidar", None, None, [], None, 0, False, [], 0.0).undetermined() == []


def test_prior_residuals_are_the_distance_to_the_prior_in_sigmas_with_an_exact_jacobian():
    """``prior_residuals``: zero at the prior, ``(Log(R_p^T R), t - t_p, delta - delta_p) / sigma`` away from it, and a
    Jacobian that matches central differences to 1e-8 at a rotation 20 deg from the prior."""
    from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, prior_residuals

    rng = np.random.default_rng(0)
    sigma = np.array([0.17] * 3 + [1.0] * 3 + [0.1])
    prior = Extrinsic(rotz(30.0), np.array([0.1, -0.2, 1.5]), 0.02)
    assert np.allclose(prior_residuals(prior, prior, np.zeros(7), sigma)[0], 0.0, atol=1e-12)
    ext = Extrinsic(prior.rotation @ rotz(20.0), prior.translation + [0.3, 0.0, -0.1], 0.07)
    res, jac = prior_residuals(ext, prior, np.zeros(7), sigma)
    assert np.allclose(res * sigma, [0, 0, np.deg2rad(20.0), 0.3, 0.0, -0.1, 0.05], atol=1e-12), res * sigma
    inc = rng.normal(0, 0.05, 7)
    numeric = np.stack([(prior_residuals(ext, prior, inc + e, sigma)[0] - prior_residuals(ext, prior, inc - e, sigma)[0]) / 2e-6
                        for e in np.eye(7) * 1e-6], axis=1)
    assert np.abs(prior_residuals(ext, prior, inc, sigma)[1] - numeric).max() < 1e-8


def test_a_parameter_held_at_the_prior_carries_the_priors_sigma():
    """``held_sigma``: the prior's sigma (``prior_sigma``) for a parameter held because the halves disagree and not
    placed by the shared view, 0 elsewhere (exact, ``PARAMETERS`` order); ``lidar_report.stage_sigma`` takes the
    largest of it, the formal, split-half and release parts, and reads a record written before it existed."""
    from moisst_ns.stages.lidar.lidar_first import held_sigma
    from moisst_ns.stages.lidar.lidar_report import stage_sigma

    assert held_sigma([4, 5, 0], [0], (1.0, 0.17, 0.1)) == [0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]  # y, z held; roll placed
    assert held_sigma([1, 6], [], (1.0, 0.17, 0.1)) == [0.0, 0.0, 0.0, 0.0, 0.17, 0.0, 0.1]  # pitch and delta
    assert held_sigma([], [], (1.0, 0.17, 0.1)) == [0.0] * 7
    formal = [0.01, 0.02, 0.03, 0.001, 0.002, 0.003, 0.004]
    check = {"sigma_release": [0.0, 0.14, 0.0, 0.0, 0.0, 0.05, 0.0], "sigma_held": held_sigma([4], [], (1.0, 0.17, 0.1))}
    entry = {"observability": [{"sigma": s} for s in formal], "sigma_split_half": [0.05] + [None] * 6, "held_check": check}
    sigma, source = stage_sigma(entry)
    assert np.allclose(sigma, [0.05, 1.0, 0.03, 0.001, 0.002, 0.05, 0.004]) and source.endswith("and release")
    del check["sigma_held"]  # a record of an older run
    assert np.allclose(stage_sigma(entry)[0], [0.05, 0.14, 0.03, 0.001, 0.002, 0.05, 0.004])
