"""A finished run opens again (torch >= 2.6 checkpoints), ns-export cameras writes calibrated poses, CLI errors."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
from moisst_ns.rig.format import load_calibration
from moisst_ns.datasets.synth import SynthConfig, make_rig

from helpers import tree_hash

BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("run")
    rig = root / "rig"
    make_rig(SynthConfig(out=rig, width=48, height=36, frames=6, perturb="paper", lidar=False))
    before = tree_hash(rig)
    config_path = run_calibration(CalibrateConfig(dataset=rig, output_dir=root / "out", max_num_iterations=12, seed=3))
    return rig, root / "out", config_path, before


def test_run_writes_calibration_and_leaves_dataset_untouched(short_run):
    rig, out, config_path, before = short_run
    assert tree_hash(rig) == before
    calib = load_calibration(out / "calibration.json")
    truth = load_calibration(rig / "ground_truth.json")
    assert set(calib.T_ref_sensor) == set(truth.T_ref_sensor)
    assert np.allclose(calib.T_ref_sensor[calib.reference_sensor], np.eye(4))
    assert config_path.is_file() and (config_path.parent / "calibration_history.csv").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["errors_after"]) == {"cam_front_right", "cam_left"}


def test_saved_run_loads_and_gives_the_same_calibration(short_run):
    from nerfstudio.utils.eval_utils import eval_setup

    rig, out, config_path, _ = short_run
    _, pipeline, _, step = eval_setup(config_path, test_mode="inference")
    assert step == 11
    loaded = pipeline.model.camera_optimizer.rig.estimate()
    written = load_calibration(out / "calibration.json")
    for name in written.T_ref_sensor:
        if name in written.trust and "prior is kept" in written.trust[name].reason:
            continue  # moisst-calibrate kept its prior (docs/uncertainty.md); the checkpoint holds the estimate
        assert np.allclose(loaded.T_ref_sensor[name], written.T_ref_sensor[name], atol=1e-9)
        assert loaded.time_offset[name] == pytest.approx(written.time_offset[name], abs=1e-12)


def test_ns_export_cameras_writes_calibrated_poses(short_run, tmp_path):
    from nerfstudio.utils.eval_utils import eval_setup

    rig, out, config_path, before = short_run
    subprocess.run([str(BIN / "ns-export"), "cameras", "--load-config", str(config_path), "--output-dir", str(tmp_path)], check=True, capture_output=True)
    frames = json.loads((tmp_path / "transforms_train.json").read_text())
    _, pipeline, _, _ = eval_setup(config_path, test_mode="inference")
    opt = pipeline.model.camera_optimizer
    with torch.no_grad():
        expected = opt.frame_c2w(torch.arange(len(frames)))[:, :3, :4].numpy()
        prior = opt.prior_c2w[:, :3, :4].numpy()
    got = np.array([f["transform"] for f in frames])
    assert np.allclose(got, expected, atol=1e-5)
    moved = np.abs(got - prior).max(axis=(1, 2))
    non_ref = opt.frame_sensor.numpy() != opt.rig.data.reference_index
    assert np.all(moved[~non_ref] < 1e-6) and np.all(moved[non_ref] > 1e-5)
    assert tree_hash(rig) == before


def test_calibrate_cli_errors_are_one_line(tmp_path, short_run):
    rig = short_run[0]
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "rig.json").write_text("{}")
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(bad), "--output-dir", str(tmp_path / "o")], capture_output=True, text=True)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert lines[-1] == f"moisst-calibrate: error: {bad / 'rig.json'}: format: missing"
    as_file = tmp_path / "file"
    as_file.write_text("x")
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(rig), "--output-dir", str(as_file)], capture_output=True, text=True)
    assert result.returncode == 2 and "is a file" in result.stderr.strip().splitlines()[-1]
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(rig), "--output-dir", str(rig / "x")], capture_output=True, text=True)
    assert result.returncode == 2 and "inside the dataset" in result.stderr
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(rig), "--output-dir", str(tmp_path / "o2"), "--no-extrinsics",
                             "--no-time-offsets"], capture_output=True, text=True)
    assert result.returncode == 2 and "leave nothing to calibrate" in result.stderr.strip().splitlines()[-1]


def test_same_seed_same_calibration(short_run, tmp_path):
    """Determinism (issue 7): the same dataset, seed and method give the same calibration.json."""
    rig, out, _, _ = short_run
    run_calibration(CalibrateConfig(dataset=rig, output_dir=tmp_path / "again", max_num_iterations=12, seed=3))
    first = load_calibration(out / "calibration.json")
    second = load_calibration(tmp_path / "again" / "calibration.json")
    for name in first.T_ref_sensor:
        assert np.abs(first.T_ref_sensor[name][:3, 3] - second.T_ref_sensor[name][:3, 3]).max() < 1e-5  # 1e-3 cm
        rot = first.T_ref_sensor[name][:3, :3].T @ second.T_ref_sensor[name][:3, :3]
        assert np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))) < 1e-4
        assert abs(first.time_offset[name] - second.time_offset[name]) < 1e-6  # 1e-3 ms


def test_stages_loaded_from_another_run_give_its_calibration(short_run, tmp_path):
    """``--stages-from OUT`` (the stages on one machine, the NeRF on another): the stages are loaded, not run, and the
    run ends with the calibration of the run that ran them (same seed); another rig's stages are refused in one line."""
    rig, out, _, _ = short_run
    run_calibration(CalibrateConfig(dataset=rig, output_dir=tmp_path / "loaded", max_num_iterations=12, seed=3, stages_from=out))
    assert not (tmp_path / "loaded" / "camera_registration").exists()
    first, second = load_calibration(out / "calibration.json"), load_calibration(tmp_path / "loaded" / "calibration.json")
    for name in first.T_ref_sensor:
        assert np.abs(first.T_ref_sensor[name] - second.T_ref_sensor[name]).max() < 1e-5
        assert abs(first.time_offset[name] - second.time_offset[name]) < 1e-6
    other = tmp_path / "other" / "camera_registration"
    other.mkdir(parents=True)
    summary = json.loads((out / "camera_registration" / "camera_registration.json").read_text())
    summary["sensors"] = {"ghost": next(iter(summary["sensors"].values()))}
    (other / "camera_registration.json").write_text(json.dumps(summary))
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(rig), "--output-dir", str(tmp_path / "o"), "--stages-from",
                             str(other.parent)], capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1] == (f"moisst-calibrate: error: {other / 'camera_registration.json'}: sensors: "
                                                      f"ghost not in {rig / 'rig.json'} (another rig's stages)")


def test_still_moving_flags_a_drifting_sensor(tmp_path):
    from moisst_ns.runs.history import still_moving

    lines = ["step,sensor,x,y,z,roll,pitch,yaw,delta_ms"]
    for step in range(10):
        lines.append(f"{step},steady,0.5,0,0,0,0,10,30")
        lines.append(f"{step},drifting,{0.5 + 0.01 * step},0,0,0,0,10,30")
    (tmp_path / "h.csv").write_text("\n".join(lines) + "\n")
    assert set(still_moving(tmp_path / "h.csv")) == {"drifting"}


def test_resume_restores_calibration_and_optimiser_state(tmp_path):
    """Kill-and-resume (issue 7): a run resumed from its step-8 checkpoint continues from the saved calibration
    and Adam state, and ends where an uninterrupted run ends (up to sampling randomness, which is not restored)."""
    import shutil

    from moisst_ns.method_configs import moisst_trainer_config

    rig = tmp_path / "rig"
    make_rig(SynthConfig(out=rig, width=48, height=36, frames=6, perturb="paper", lidar=False))
    full = tmp_path / "full"
    run_calibration(CalibrateConfig(dataset=rig, output_dir=full, max_num_iterations=16, seed=5, save_every=8))
    ckpt_dir = full / "moisst-lite" / "run" / "nerfstudio_models"
    assert (ckpt_dir / "step-000000008.ckpt").is_file()
    # the "killed" run: the same folder with only the step-8 checkpoint
    part = tmp_path / "part"
    shutil.copytree(full, part)
    for ckpt in (part / "moisst-lite" / "run" / "nerfstudio_models").glob("*.ckpt"):
        if ckpt.name != "step-000000008.ckpt":
            ckpt.unlink()
    saved = torch.load(ckpt_dir / "step-000000008.ckpt", map_location="cpu")  # also checks torch>=2.6 loading
    # set up the resumed trainer and check the state it starts from
    from moisst_ns.stage_run import seed_everything

    config = moisst_trainer_config("moisst-lite", 16)
    config.pipeline.datamanager.data = rig
    config.pipeline.datamanager.dataparser.data = rig
    config.output_dir, config.experiment_name, config.timestamp, config.vis = part, ".", "run", "tensorboard"
    config.load_dir = part / "moisst-lite" / "run" / "nerfstudio_models"
    seed_everything(5)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    assert trainer._start_step == 9
    rig_params = trainer.pipeline.model.camera_optimizer.rig
    for name in ("rotvec", "translation", "time_offset"):
        key = next(k for k in saved["pipeline"] if k.endswith(f"camera_optimizer.rig.{name}"))
        assert torch.equal(getattr(rig_params, name).detach(), saved["pipeline"][key])
    state = trainer.optimizers.optimizers["calibration_translation"].state_dict()["state"][0]
    assert torch.equal(state["exp_avg_sq"], saved["optimizers"]["calibration_translation"]["state"][0]["exp_avg_sq"])
    # and the resumed run ends close to the uninterrupted one, with the stages loaded from the run's folder, not run again
    stages = tree_hash(part / "camera_registration")
    run_calibration(CalibrateConfig(dataset=rig, output_dir=part, max_num_iterations=16, seed=5, resume=True))
    assert tree_hash(part / "camera_registration") == stages and trainer.pipeline.stage_run.cameras is not None
    a = load_calibration(full / "calibration.json")
    b = load_calibration(part / "calibration.json")
    for name in a.T_ref_sensor:
        assert np.linalg.norm(a.T_ref_sensor[name][:3, 3] - b.T_ref_sensor[name][:3, 3]) < 0.01
        assert abs(a.time_offset[name] - b.time_offset[name]) < 1e-3


def test_time_offset_bound_is_reported(short_run, tmp_path, capsys):
    """--max-time-offset bounds delta's change; a sensor that runs into it is reported, not silently absurd."""
    rig = short_run[0]
    run_calibration(CalibrateConfig(dataset=rig, output_dir=tmp_path / "b", max_num_iterations=12, seed=3, max_time_offset=0.001, report=False))
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    calib = load_calibration(tmp_path / "b" / "calibration.json")
    prior = json.loads((rig / "rig.json").read_text())["sensors"]
    for name, offset in calib.time_offset.items():
        assert abs(offset - prior[name]["time_offset"]) <= 0.001 + 1e-9
    assert set(summary["hit_bounds"]) and all("time offset" in " ".join(v) for v in summary["hit_bounds"].values())
    assert "ran into its bound" in capsys.readouterr().out


def test_scene_only_run_length_when_the_stages_hold_every_sensor():
    from moisst_ns.calibrate import scene_only_steps

    rig = Path("rig")
    assert scene_only_steps(CalibrateConfig(dataset=rig)) == 2000
    assert scene_only_steps(CalibrateConfig(dataset=rig, method="moisst")) == 10000
    assert scene_only_steps(CalibrateConfig(dataset=rig, max_num_iterations=600)) == 600
    assert scene_only_steps(CalibrateConfig(dataset=rig, max_num_iterations=600, scene_steps=50)) == 50
