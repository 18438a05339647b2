"""moisst-export, moisst-eval and moisst-report on a short run of a tiny rig with LiDAR, plus the projection math."""

import csv
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import torch
from PIL import Image

import moisst_ns.method_configs as method_configs
import moisst_ns.cli.report as report_module
from moisst_ns import runs
from moisst_ns.runs import folder
from moisst_ns.cli import evaluate, export
from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
from moisst_ns.report import write_report
from moisst_ns.report_images import draw_points, project_points
from moisst_ns.report_views import lidar_points_world, nearest_lidar_frames, sensor_poses
from moisst_ns.rig.format import RigFormatError, load_calibration, load_lidar_scan, load_rig
from moisst_ns.datasets.synth import SynthConfig, build_scene, make_path, make_rig

from helpers import tree_hash

BIN = Path(sys.executable).parent
LOG_EVERY = 3


def calibrate(rig: Path, out: Path, steps: int) -> Path:
    """run_calibration, logging the history every LOG_EVERY steps (so --history has several rows per sensor)."""
    original = method_configs.moisst_trainer_config

    def logging_often(*args, **kwargs):
        config = original(*args, **kwargs)
        config.pipeline.model.calibration_log_every = LOG_EVERY
        return config

    with mock.patch.object(method_configs, "moisst_trainer_config", logging_often):
        return run_calibration(CalibrateConfig(dataset=rig, output_dir=out, max_num_iterations=steps, seed=3))


def run_main(module, argv):
    """Run a console script's main() in-process; returns (exit code, stdout, stderr)."""
    from io import StringIO

    out, err = StringIO(), StringIO()
    code = 0
    with mock.patch.object(sys, "argv", ["prog", *map(str, argv)]), mock.patch.object(sys, "stdout", out), mock.patch.object(sys, "stderr", err):
        try:
            module.main()
        except SystemExit as exc:
            code = exc.code
    return code, out.getvalue(), err.getvalue()


RIG_CONFIG = dict(width=48, height=36, frames=6, perturb="paper", lidar=True)


@pytest.fixture(scope="module")
def tiny_rig(tmp_path_factory):
    return make_rig(SynthConfig(out=tmp_path_factory.mktemp("dataset") / "rig", **RIG_CONFIG))


@pytest.fixture(scope="module")
def run(tiny_rig, tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    rig = tiny_rig
    before = tree_hash(rig)
    config_path = calibrate(rig, root / "calib", 12)
    exported = export.run_export(export.ExportConfig(load_config=config_path, output_dir=root / "exported"))
    _, pipeline, step, _ = folder.open_run(config_path)
    code, _, err = run_main(report_module, [config_path.parent])  # default output: RUN/report
    assert code == 0, err
    return {"rig": rig, "before": before, "config": config_path, "out": exported, "pipeline": pipeline, "step": step,
            "report": config_path.parent / "report"}


# --- moisst-export --------------------------------------------------------------------------------------------


def test_export_calibration_json_equals_the_model_estimate(run):
    """The model's estimate, except the sensors moisst-calibrate reverted to their prior (verdict 'not converged',
    'the prior is kept'): the export carries calibration.json's decision and trust fields."""
    estimate = run["pipeline"].model.camera_optimizer.rig.estimate()
    written = load_calibration(run["out"] / "calibration.json")
    assert run["step"] == 11
    assert written.reference_sensor == estimate.reference_sensor
    assert list(written.T_ref_sensor) == list(estimate.T_ref_sensor) == ["cam_front", "cam_front_right", "cam_left", "lidar"]
    calibrated = load_calibration(run["config"].parents[2] / "calibration.json")
    assert set(calibrated.trust) == {"cam_front_right", "cam_left", "lidar"} and calibrated.trust == written.trust
    prior = folder.prior_calibration(run["pipeline"].model.camera_optimizer.rig.data)
    for name in estimate.T_ref_sensor:
        kept = name in written.trust and "prior is kept" in written.trust[name].reason
        expected = prior if kept else estimate  # rig.json's prior (for a LiDAR too, not the LiDAR-first estimate)
        assert np.array_equal(written.T_ref_sensor[name], expected.T_ref_sensor[name]), name
        assert written.time_offset[name] == expected.time_offset[name]
        # and it is the calibration moisst-calibrate wrote at the end of training
        assert np.allclose(calibrated.T_ref_sensor[name], written.T_ref_sensor[name], atol=1e-9)


def test_rig_calibrated_json_is_valid_next_to_the_dataset(run, tmp_path):
    """Paths stay dataset-relative (load_rig refuses paths leaving the json's folder): valid in a copy of the dataset."""
    original = load_rig(run["rig"])
    estimate = load_calibration(run["out"] / "calibration.json")
    copy = tmp_path / "rig_copy"
    shutil.copytree(run["rig"], copy)
    shutil.copy(run["out"] / "rig.calibrated.json", copy / "rig.json")
    shutil.copy(run["out"] / "rig.calibrated.json", copy / "rig.calibrated.json")
    for calibrated in (load_rig(copy), load_rig(copy / "rig.calibrated.json")):  # as rig.json, or under its own name
        assert calibrated.reference_sensor == original.reference_sensor
        assert calibrated.trajectory_file == original.trajectory_file
        assert [(f.sensor, f.timestamp, f.file_path) for f in calibrated.frames] == [(f.sensor, f.timestamp, f.file_path) for f in original.frames]
        for name, sensor in calibrated.sensors.items():
            assert np.array_equal(sensor.T_ref_sensor, estimate.T_ref_sensor[name])
            assert sensor.time_offset == estimate.time_offset[name]
            assert sensor.intrinsics == original.sensors[name].intrinsics
    moved = [n for n in original.sensors if not np.array_equal(original.sensors[n].T_ref_sensor, estimate.T_ref_sensor[n])]
    kept = [n for n, t in estimate.trust.items() if "prior is kept" in t.reason]  # moisst-calibrate reverted them
    assert moved == [n for n in ("cam_front_right", "cam_left", "lidar") if n not in kept]
    with pytest.raises(RigFormatError, match="file not found"):  # away from the dataset its paths do not resolve
        load_rig(run["out"] / "rig.calibrated.json")


def test_summary_json_estimates_and_change_from_prior(run):
    from moisst_ns.rig.geometry import pose_to_xyz_rpy

    summary = json.loads((run["out"] / "summary.json").read_text())
    calib = run["pipeline"].model.camera_optimizer.rig
    estimate = load_calibration(run["out"] / "calibration.json")  # the model's, or the prior where moisst-calibrate kept it
    assert summary["reference_sensor"] == "cam_front" and summary["run"]["step"] == 11
    assert set(summary["errors_after"]) == {"cam_front_right", "cam_left", "lidar"}
    from moisst_ns.runs.folder import prior_calibration

    priors = prior_calibration(calib.data)  # rig.json's, although the NeRF started the LiDAR from the LiDAR-first stage
    assert calib.data.dataset_priors is not None
    for i, name in enumerate(calib.data.sensor_names):
        entry = summary["sensors"][name]
        expected = pose_to_xyz_rpy(torch.as_tensor(estimate.T_ref_sensor[name])).numpy()
        assert [entry["estimate"][k] for k in ("x", "y", "z", "roll", "pitch", "yaw")] == pytest.approx(expected, abs=1e-9)
        assert entry["estimate"]["delta_ms"] == pytest.approx(estimate.time_offset[name] * 1000, abs=1e-9)
        prior = priors.T_ref_sensor[name]
        assert entry["prior"]["x"] == pytest.approx(prior[0, 3], abs=1e-12)
        assert entry["prior"]["delta_ms"] == pytest.approx(priors.time_offset[name] * 1000, abs=1e-9)
        for k in ("x", "y", "z", "delta_ms"):
            assert entry["change"][k] == pytest.approx(entry["estimate"][k] - entry["prior"][k], abs=1e-9)
        relative = prior[:3, :3].T @ estimate.T_ref_sensor[name][:3, :3]
        angle = math.degrees(math.acos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
        assert entry["change"]["rotation_deg"] == pytest.approx(angle, abs=1e-5)
        shift = 100 * np.linalg.norm(estimate.T_ref_sensor[name][:3, 3] - prior[:3, 3])
        assert entry["change"]["translation_cm"] == pytest.approx(shift, abs=1e-9)
        if name == "cam_front":
            assert entry["change"]["rotation_deg"] == 0 and entry["change"]["translation_cm"] == 0
        elif name not in estimate.trust or "prior is kept" not in estimate.trust[name].reason:
            held = set()  # the LiDAR-first stage holds what the halves of this 0.6 s drive disagree on at the prior
            for record in run["config"].parents[2].rglob("lidar_first.json"):
                held |= set((json.loads(record.read_text())["sensors"].get(name, {}).get("held_check") or {}).get("held", []))
            assert entry["change"]["rotation_deg"] > 1e-4
            assert entry["change"]["translation_cm"] > 1e-3 or {"x", "y", "z"} <= held, (name, held)
        else:
            assert entry["change"]["rotation_deg"] == 0 and entry["change"]["translation_cm"] == 0
        if name != "cam_front":
            assert entry["trust"]["verdict"] == estimate.trust[name].verdict
    markdown = (run["out"] / "summary.md").read_text()
    assert "## Change from the prior" in markdown and "| lidar | lidar |" in markdown


def test_export_never_writes_into_the_dataset(run):
    assert tree_hash(run["rig"]) == run["before"]


def test_export_cli_errors_are_one_line(run, tmp_path):
    config = run["config"]
    no_checkpoint = tmp_path / "no_checkpoint"
    shutil.copytree(config.parent, no_checkpoint, ignore=shutil.ignore_patterns("nerfstudio_models", "report"))
    empty_checkpoint = tmp_path / "empty_checkpoint"
    shutil.copytree(no_checkpoint, empty_checkpoint)
    (empty_checkpoint / "nerfstudio_models").mkdir()
    other_method = tmp_path / "other_method"
    other_method.mkdir()
    text = config.read_text()
    assert "!!python/object:moisst_ns.model.MoisstModelConfig" in text
    text = text.replace("!!python/object:moisst_ns.model.MoisstModelConfig", "!!python/object:nerfstudio.models.nerfacto.NerfactoModelConfig")
    text = text.replace("!!python/name:moisst_ns.model.MoisstModel ''", "!!python/name:nerfstudio.models.nerfacto.NerfactoModel ''")
    (other_method / "config.yml").write_text(text)
    shutil.copytree(config.parent / "nerfstudio_models", other_method / "nerfstudio_models")
    as_file = tmp_path / "file"
    as_file.write_text("x")
    cases = [
        (tmp_path / "missing" / "config.yml", tmp_path / "o1", "config not found"),
        (no_checkpoint / "config.yml", tmp_path / "o2", "no checkpoint"),
        (empty_checkpoint / "config.yml", tmp_path / "o3", "no checkpoint"),
        (other_method / "config.yml", tmp_path / "o4", "NerfactoModel, not MoisstModel"),
        (config, as_file, "is a file"),
        (config, run["rig"] / "export", "inside the dataset"),
    ]
    for load_config, output_dir, expected in cases:
        code, _, err = run_main(export, ["--load-config", load_config, "--output-dir", output_dir])
        lines = err.strip().splitlines()
        assert code == 2, (expected, err)
        assert len(lines) == 1 and lines[0].startswith("moisst-export: error: ") and expected in lines[0], (expected, err)
        if output_dir != as_file:
            assert not output_dir.exists()
    with pytest.raises(runs.RunError, match="not MoisstModel"):
        folder.load_run_config(other_method / "config.yml")
    assert not (run["rig"] / "export").exists()
    # the console script itself
    result = subprocess.run([str(BIN / "moisst-export"), "--load-config", str(tmp_path / "nope.yml"), "--output-dir", str(tmp_path / "o")],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == f"moisst-export: error: {tmp_path / 'nope.yml'}: config not found (pass the run's config.yml, e.g. OUT/moisst-lite/run/config.yml)"


# --- moisst-eval ----------------------------------------------------------------------------------------------


def test_moisst_eval_gives_the_errors_of_the_export_summary(run):
    calibration, truth = run["out"] / "calibration.json", run["rig"] / "ground_truth.json"
    result = subprocess.run([str(BIN / "moisst-eval"), str(calibration), str(truth), "--json"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    errors = json.loads(result.stdout)
    expected = json.loads((run["out"] / "summary.json").read_text())["errors_after"]
    assert set(errors) == set(expected) == {"cam_front_right", "cam_left", "lidar"}
    for name in expected:
        for key in ("translation_cm", "rotation_deg", "time_ms"):
            assert errors[name][key] == pytest.approx(expected[name][key], rel=1e-12, abs=1e-12)
    table = subprocess.run([str(BIN / "moisst-eval"), str(calibration), str(truth)], capture_output=True, text=True)
    assert table.returncode == 0
    lidar = next(line for line in table.stdout.splitlines() if line.strip().startswith("lidar "))
    e = expected["lidar"]
    assert lidar.split() == ["lidar", f"{e['translation_cm']:.2f}", f"{e['rotation_deg']:.3f}", f"{e['time_ms']:.2f}"]


def read_csv_tail(path: Path, last: int):
    rows = {}
    with path.open() as handle:
        for row in csv.DictReader(handle):
            rows.setdefault(row["sensor"], []).append(row)
    return {name: values[-last:] for name, values in rows.items()}


def test_moisst_eval_history_mean_and_std_are_numpys(run):
    run_dir = run["config"].parent
    history = run_dir / "calibration_history.csv"
    for last in (3, 100):
        result = subprocess.run([str(BIN / "moisst-eval"), "--history", str(run_dir), "--last", str(last), "--json"], capture_output=True, text=True)
        assert result.returncode == 0, result.stderr
        stats = json.loads(result.stdout)
        tails = read_csv_tail(history, last)
        assert set(stats) == set(tails) == {"cam_front_right", "cam_left", "lidar"}
        stage_rows = len(json.loads((run["config"].parents[2] / "lidar_first" / "lidar_first.json").read_text())["sensors"]["lidar"]["history"])
        for name, rows in tails.items():
            logged = 4 + (stage_rows if name == "lidar" else 0)  # steps 0, 3, 6, 9 (and the LiDAR-first stage's -N..-1)
            assert stats[name]["rows"] == len(rows) == min(last, logged)
            assert stats[name]["first_step"] == int(rows[0]["step"]) and stats[name]["last_step"] == 9
            columns = ["err_translation_cm", "err_rotation_deg", "err_time_ms", "x", "y", "z", "roll", "pitch", "yaw", "delta_ms"]
            assert list(stats[name]["mean"]) == columns
            for c in columns:
                values = np.array([float(r[c]) for r in rows])
                assert stats[name]["mean"][c] == pytest.approx(np.mean(values), rel=1e-12, abs=1e-15)
                assert stats[name]["std"][c] == pytest.approx(np.std(values), rel=1e-9, abs=1e-15)
            if name == "lidar" and last <= 4:  # held at the LiDAR-first estimate during the NeRF
                assert stats[name]["std"]["x"] == 0 and stats[name]["std"]["delta_ms"] < 1e-9
            else:
                assert stats[name]["std"]["x"] > 0
    table = subprocess.run([str(BIN / "moisst-eval"), "--history", str(run_dir), "--last", "2"], capture_output=True, text=True)
    assert table.returncode == 0 and "last 2 logged rows" in table.stdout and "delta_ms (ms)" in table.stdout


def test_moisst_eval_errors_are_one_line(run, tmp_path):
    truth = run["rig"] / "ground_truth.json"
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{\n  'nope': 1\n}")
    no_errors = tmp_path / "run_without_truth"
    no_errors.mkdir()
    lines = (run["config"].parent / "calibration_history.csv").read_text().splitlines()
    assert lines[0].split(",")[9:] == ["err_translation_cm", "err_rotation_deg", "err_time_ms", "elapsed_s"]
    blanked = [",".join(line.split(",")[:9] + ["", "", ""] + line.split(",")[12:]) for line in lines[1:]]  # as logged without ground truth
    (no_errors / "calibration_history.csv").write_text("\n".join([lines[0]] + blanked) + "\n")
    cases = [
        ([tmp_path / "missing.json", truth], "missing.json: (file): file not found"),
        ([bad_json, truth], "bad.json: line 2, column 3: invalid JSON: Expecting property name enclosed in double quotes"),
        ([truth], "expected CALIBRATION.json GROUND_TRUTH.json"),
        (["--history", tmp_path / "nowhere"], "calibration_history.csv not found"),
        (["--history", no_errors, "--columns", "errors"], "no error columns"),
        (["--history", run["config"].parent, "--last", "0"], "--last: must be >= 1"),
        ([truth, truth, "--history", run["config"].parent], "--history takes no"),
    ]
    for argv, expected in cases:
        code, _, err = run_main(evaluate, argv)
        got = err.strip().splitlines()
        assert code == 2 and len(got) == 1 and got[0].startswith("moisst-eval: error: ") and expected in got[0], (argv, err)
    # without error values the estimates are still reported
    code, out, _ = run_main(evaluate, ["--history", no_errors, "--json"])
    assert code == 0 and list(json.loads(out)["lidar"]["mean"]) == ["x", "y", "z", "roll", "pitch", "yaw", "delta_ms"]


# --- projection -----------------------------------------------------------------------------------------------


INTR = {"fl_x": 100.0, "fl_y": 100.0, "cx": 50.0, "cy": 50.0, "w": 100, "h": 100}


def test_project_points_known_point_and_masks():
    points = np.array([[1.0, 2.0, 10.0], [1.0, 2.0, -10.0], [0.0, 0.0, 0.0], [6.0, 0.0, 10.0], [0.0, 0.0, 5.0], [4.9999, -4.9999, 10.0]])
    uv, depth, mask = project_points(points, np.eye(4), INTR)
    assert uv[0] == pytest.approx([60.0, 70.0]) and depth[0] == 10.0 and mask[0]
    assert not mask[1] and np.isnan(uv[1]).all() and depth[1] == -10.0  # behind the camera
    assert not mask[2]  # at the camera centre
    assert uv[3] == pytest.approx([110.0, 50.0]) and not mask[3]  # beyond the right edge (u >= w)
    assert uv[4] == pytest.approx([50.0, 50.0]) and mask[4]  # the optical axis hits the principal point
    assert mask[5] and uv[5] == pytest.approx([99.999, 0.001])  # last column / first row: still in the image
    # moving the camera: the same camera-frame point, seen from a posed camera, projects to the same pixel
    angle = 0.7
    pose = np.eye(4)
    pose[:3, :3] = [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    pose[:3, 3] = [3.0, -1.0, 2.0]
    world = points[:1] @ pose[:3, :3].T + pose[:3, 3]
    uv_posed, depth_posed, mask_posed = project_points(world, pose, INTR)
    assert uv_posed[0] == pytest.approx([60.0, 70.0]) and depth_posed[0] == pytest.approx(10.0) and mask_posed[0]
    # OpenCV radial distortion as nerfstudio applies it: x (1 + k1 r^2)
    uv_k1, _, _ = project_points(points[:1], np.eye(4), {**INTR, "k1": 0.1})
    assert uv_k1[0] == pytest.approx([50 + 100 * 0.1 * 1.005, 50 + 100 * 0.2 * 1.005])


def test_draw_points_nearest_on_top():
    image = np.zeros((4, 5, 3), dtype=np.uint8)
    uv = np.array([[2.5, 1.5], [2.9, 1.1], [0.5, 3.5]])
    out = draw_points(image, uv, np.array([10.0, 2.0, 6.0]), np.array([True, True, False]), vmin=2.0, vmax=10.0)
    assert image.sum() == 0  # input untouched
    from moisst_ns.report_images import depth_colors

    near = depth_colors(np.array([2.0]), 2.0, 10.0)[0]
    assert np.array_equal(out[1, 2], near)  # two points in pixel (2, 1): the nearer wins
    assert out[3, 0].sum() == 0 and (out.reshape(-1, 3).sum(1) > 0).sum() == 1  # masked point not drawn


def test_report_module_does_not_import_nerfstudio():
    code = "import sys, moisst_ns.report; sys.exit(any(m.startswith('nerfstudio') for m in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_lidar_points_with_the_true_calibration_land_on_the_camera_surfaces(tiny_rig):
    """The projection chain (de-skew, sensor poses, pinhole) against the synthetic scene: a camera ray through each
    projected LiDAR point hits the scene at the point's depth with the truth, not with the perturbed priors."""
    from moisst_ns.rig.calibration import RigCalibration, RigData

    rig = load_rig(tiny_rig)
    truth = load_calibration(tiny_rig / "ground_truth.json")
    config = SynthConfig(out=tiny_rig, **RIG_CONFIG)
    scene = build_scene(config, make_path(config))
    data = RigData.from_rig(rig)
    calib = RigCalibration(data)
    names = data.sensor_names
    with_truth = RigData.from_rig(rig)
    with_truth.prior_extrinsics = np.stack([truth.T_ref_sensor[n] for n in names])
    with_truth.prior_time_offsets = np.array([truth.time_offset[n] for n in names])
    for label, rig_calib in (("truth", RigCalibration(with_truth)), ("prior", calib)):
        for camera in ("cam_front", "cam_left"):
            frame, intr = rig.frames_of(camera)[2], rig.sensors[camera].intrinsics
            ((lidar, lidar_frame),) = nearest_lidar_frames(rig, rig_calib, camera, frame.timestamp)
            points, times, _ = load_lidar_scan(rig.root / lidar_frame.file_path)
            assert times is not None
            world = lidar_points_world(rig_calib, names.index(lidar), lidar_frame.timestamp - data.t0, points, times, prior=True)
            pose = sensor_poses(rig_calib, names.index(camera), np.full(1, frame.timestamp - data.t0), prior=True)[0]
            uv, depth, mask = project_points(world, pose, intr)
            assert mask.sum() > 1000
            rays = np.stack([(uv[mask, 0] - intr["cx"]) / intr["fl_x"], (uv[mask, 1] - intr["cy"]) / intr["fl_y"], np.ones(mask.sum())], -1)
            norm = np.linalg.norm(rays, axis=1)
            hit = scene.cast(np.repeat(pose[None, :3, 3], len(rays), 0), (rays / norm[:, None]) @ pose[:3, :3].T)["t_hit"] / norm
            close = np.abs(hit - depth[mask]) < 0.01
            if label == "truth":
                assert close.mean() > 0.9  # the rest is occluded from the camera
            else:
                assert close.mean() < 0.05


# --- moisst-report --------------------------------------------------------------------------------------------


def test_report_outputs(run):
    report_dir = run["report"]
    report = (report_dir / "report.md").read_text()
    linked = [line.split("](")[1].split(")")[0] for line in report.splitlines() if "](" in line]
    linked += [part.split(")")[0] for line in report.splitlines() for part in line.split("](")[2:]]
    assert linked and all((report_dir / path).is_file() for path in linked)
    for camera in ("cam_front", "cam_front_right", "cam_left"):
        prior = sorted((report_dir / "overlays").glob(f"{camera}_0*_prior.png"))
        calibrated = sorted((report_dir / "overlays").glob(f"{camera}_0*_calibrated.png"))
        assert len(prior) == len(calibrated) == 3
        for path in prior + calibrated:
            with Image.open(path) as img:
                assert img.size == (48, 36)
            assert f"overlays/{path.name}" in report
        with Image.open(report_dir / "overlays" / f"{camera}_0000_side_by_side.png") as img:
            assert img.size == (2 * 48 + 4, 36 + 14)
        for kind in ("rendered", "rendered_depth", "rendered_lidar"):
            with Image.open(report_dir / "renders" / f"{camera}_0000_{kind}.png") as img:
                assert img.size == (48, 36)
    # the overlays draw points: the calibrated panel differs from the bare image
    with Image.open(run["rig"] / "images" / "cam_front" / "000000.png") as img:
        bare = np.asarray(img.convert("RGB"))
    with Image.open(report_dir / "overlays" / "cam_front_0000_calibrated.png") as img:
        assert (np.asarray(img) != bare).any(axis=-1).mean() > 0.2
    assert sorted(p.name for p in (report_dir / "convergence").glob("*.png")) == ["cam_front_right.png", "cam_left.png", "lidar.png"]
    last = read_csv_tail(run["config"].parent / "calibration_history.csv", 1)
    row = next(line for line in report.splitlines() if line.startswith("| lidar |"))
    assert row.split("|")[2].strip() == "9" and f"{float(last['lidar'][0]['x']):.4f}" in row
    # the verdict: before/after errors of every non-reference sensor, and which to trust
    verdicts = json.loads((report_dir / "report.json").read_text())["verdicts"]
    assert sorted(verdicts) == ["cam_front_right", "cam_left", "lidar"]
    assert all("errors_before" in v and "errors_after" in v and isinstance(v["trust"], bool) for v in verdicts.values())
    assert "## Verdict" in report and "**Trust: " in report
    before_after = next(line for line in report.splitlines() if line.startswith("| lidar | ") and line.count("|") == 4)
    b = verdicts["lidar"]["errors_before"]
    assert before_after.split("|")[2].strip() == f"{b['translation_cm']:.2f} / {b['rotation_deg']:.3f} / {b['time_ms']:.2f}"
    assert tree_hash(run["rig"]) == run["before"]


def test_report_with_a_pipeline_in_memory_keeps_its_mode(run, tmp_path):
    """What moisst-calibrate can call at the end of training: no reload, the model is left in training mode."""
    pipeline = run["pipeline"]
    pipeline.model.train()
    try:
        report = write_report(run["config"], tmp_path / "r", pipeline=pipeline, frames_per_camera=1)
        assert pipeline.model.training
    finally:
        pipeline.model.eval()
    assert len(list((tmp_path / "r" / "overlays").glob("*_side_by_side.png"))) == 3
    assert len(list((tmp_path / "r" / "renders").glob("*_rendered.png"))) == 3
    assert "checkpoint step" not in report.read_text()


def test_report_refuses_an_output_inside_the_dataset(run):
    with pytest.raises(runs.RunError, match="inside the dataset"):
        write_report(run["config"], run["rig"] / "report")
    assert not (run["rig"] / "report").exists()


def test_report_without_lidar_says_so(tmp_path):
    rig = make_rig(SynthConfig(out=tmp_path / "rig", width=48, height=36, frames=4, perturb="paper", lidar=False))
    config_path = calibrate(rig, tmp_path / "calib", 4)
    report = write_report(config_path, tmp_path / "report")
    text = report.read_text()
    assert "The rig has no LiDAR" in text
    assert not (tmp_path / "report" / "overlays").exists() and not (tmp_path / "report" / "renders").exists()
    assert sorted(p.name for p in (tmp_path / "report" / "convergence").glob("*.png")) == ["cam_front_right.png", "cam_left.png"]
