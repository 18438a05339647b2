"""``ns-train moisst-lite`` is ``moisst-calibrate`` (issue 36): one code path, ``MoisstPipeline``.

A tiny rig (64x48, 6 frames per sensor, 3 cameras and a LiDAR of 3000 points a scan), 20 steps, seed 0, one torch thread: the LiDAR-first
stage runs, the camera registration keeps both cameras' priors (6 frames are too few for it), the NeRF calibrates
them, then the held-back checks and the report. ``ns-train`` must leave the same calibration.json in its run folder as
``moisst-calibrate`` leaves in OUT; the finished run loads, exports, is served by ``ns-viewer`` and resumes without
running the stages again.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from moisst_ns.datasets.synth import SynthConfig, make_rig
from moisst_ns.rig.format import load_calibration

from helpers import tree_hash

BIN = Path(sys.executable).parent
STEPS, SEED = 20, 0
ENV = dict(os.environ, OMP_NUM_THREADS="1")


def start(log: Path, *argv, cwd=None) -> subprocess.Popen:
    """``argv`` started, its output into ``log`` (a file: two runs side by side never wait on a full pipe)."""
    return subprocess.Popen([str(BIN / argv[0]), *map(str, argv[1:])], cwd=cwd, env=ENV, stdout=log.open("w"), stderr=subprocess.STDOUT)


def run(*argv, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / argv[0]), *map(str, argv[1:])], cwd=cwd, env=ENV, capture_output=True, text=True)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The two runs side by side (one thread each): ``ns-train moisst-lite`` and ``moisst-calibrate``."""
    root = tmp_path_factory.mktemp("ns_train")
    rig = make_rig(SynthConfig(out=root / "rig", width=64, height=48, frames=6, seed=0, lidar_azimuth_steps=256, lidar_max_points=3000))
    trained = start(root / "ns-train.log", "ns-train", "moisst-lite", "--data", rig, "--max-num-iterations", STEPS, "--machine.seed", SEED,
                    "--vis", "tensorboard", "--viewer.quit-on-train-completion", "True", "--output-dir", root / "outputs", cwd=root)
    calibrated = start(root / "calibrate.log", "moisst-calibrate", rig, "--output-dir", root / "calibrated", "--max-num-iterations", STEPS,
                       "--seed", SEED, "--threads", 1)
    assert trained.wait() == 0, (root / "ns-train.log").read_text()[-3000:]
    assert calibrated.wait() in (0, 3), (root / "calibrate.log").read_text()[-3000:]  # 3: a sensor not converged (20 steps)
    (folder,) = (root / "outputs" / "rig" / "moisst-lite").iterdir()  # <output-dir>/<experiment>/<method>/<timestamp>
    return {"rig": rig, "run": folder, "out": root / "calibrated", "stages": tree_hash(folder / "lidar_first") + tree_hash(folder / "camera_registration")}


def test_the_run_folder_holds_calibration_summary_and_report(runs):
    folder = runs["run"]
    for name in ("calibration.json", "summary.json", "report/report.md", "lidar_first/calibration.json",
                 "camera_registration/camera_registration.json", "calibration_history.csv", "config.yml"):
        assert (folder / name).is_file(), name
    calibration = load_calibration(folder / "calibration.json")
    assert set(calibration.trust) == {"cam_front_right", "cam_left", "lidar"}
    assert all(t.verdict for t in calibration.trust.values())
    assert calibration.trust["lidar"].sigmas() is not None  # sigma from the LiDAR-first stage
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["iterations"] == STEPS and summary["seed"] == SEED and set(summary["verdicts"]) == set(calibration.trust)
    assert "lidar" in summary["lidar_first"] and set(summary["camera_registration"]) == {"cam_front_right", "cam_left"}


def test_ns_train_gives_the_calibration_of_moisst_calibrate(runs):
    """The issue's target: <= 0.01 cm / 0.001 deg / 0.01 ms apart (measured: identical files)."""
    a, b = load_calibration(runs["run"] / "calibration.json"), load_calibration(runs["out"] / "calibration.json")
    assert set(a.T_ref_sensor) == set(b.T_ref_sensor)
    for name in a.T_ref_sensor:
        A, B = np.asarray(a.T_ref_sensor[name]), np.asarray(b.T_ref_sensor[name])
        assert 100 * np.linalg.norm(A[:3, 3] - B[:3, 3]) <= 0.01, name
        assert np.degrees(np.arccos(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2, -1, 1))) <= 0.001, name
        assert 1000 * abs(a.time_offset[name] - b.time_offset[name]) <= 0.01, name
    assert {n: t.to_json() for n, t in a.trust.items()} == {n: t.to_json() for n, t in b.trust.items()}
    verdicts = [json.loads((f / "summary.json").read_text())["verdicts"] for f in (runs["run"], runs["out"])]
    assert verdicts[0] == verdicts[1]


def test_ns_export_cameras_and_pointcloud_of_the_finished_run(runs, tmp_path):
    config = runs["run"] / "config.yml"
    cwd = runs["run"].parents[3]  # ns-export finds the checkpoint from the folder ns-train ran in
    cameras = run("ns-export", "cameras", "--load-config", config, "--output-dir", tmp_path / "cameras", cwd=cwd)
    assert cameras.returncode == 0, cameras.stderr[-3000:]
    assert len(json.loads((tmp_path / "cameras" / "transforms_train.json").read_text())) == 18
    cloud = run("ns-export", "pointcloud", "--load-config", config, "--output-dir", tmp_path / "cloud", "--num-points", 500,
                "--num-rays-per-batch", 1024, cwd=cwd)  # default normals: the model's (density gradient)
    assert cloud.returncode == 0, cloud.stdout[-3000:] + cloud.stderr[-3000:]
    assert (tmp_path / "cloud" / "point_cloud.ply").stat().st_size > 0
    # loading the run (as ns-viewer and ns-eval do) ran no stage again
    assert "[lidar-first]" not in cameras.stdout + cloud.stdout
    assert tree_hash(runs["run"] / "lidar_first") + tree_hash(runs["run"] / "camera_registration") == runs["stages"]


def test_ns_viewer_serves_the_finished_run(runs):
    """``ns-viewer --load-config`` of the finished run loads it (no stage runs again) and serves the viewer over HTTP
    until stopped; a crash while loading (the model's calibration panel, the rig's frusta) ends it before it serves."""
    import select
    import signal
    import socket
    import time
    import urllib.request

    with socket.socket() as s:  # a free port
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = subprocess.Popen([str(BIN / "ns-viewer"), "--load-config", str(runs["run"] / "config.yml"), "--viewer.websocket-port", str(port)],
                              cwd=runs["run"].parents[3], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    output, deadline = "", time.time() + 300
    try:
        while f"http://0.0.0.0:{port}" not in output and viewer.poll() is None and time.time() < deadline:
            if select.select([viewer.stdout], [], [], 1.0)[0]:
                output += viewer.stdout.readline()
        assert viewer.poll() is None, output[-3000:]  # still running: loaded without an error
        assert f"http://0.0.0.0:{port}" in output, output[-3000:]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as page:
            assert page.status == 200
        assert "[lidar-first]" not in output and "Traceback" not in output
    finally:
        viewer.send_signal(signal.SIGINT)
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            viewer.kill()


def test_a_resumed_run_loads_the_stages_of_the_run_it_continues(runs, tmp_path, capsys):
    """As ``ns-train moisst-lite --data RIG --load-dir RUN/nerfstudio_models`` (a new run folder): the stages come
    from RUN, the calibration from its checkpoint."""
    import torch

    from moisst_ns.method_configs import moisst_trainer_config

    torch.set_num_threads(1)
    config = moisst_trainer_config("moisst-lite")
    config.max_num_iterations, config.vis, config.machine.seed = STEPS, "tensorboard", SEED
    config.pipeline.datamanager.data = runs["rig"]
    config.output_dir, config.experiment_name, config.timestamp = tmp_path, "rig", "resumed"
    config.load_dir = runs["run"] / "nerfstudio_models"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    out = capsys.readouterr().out
    assert "[lidar-first]" not in out and f"lidar_first: loaded from {runs['run'] / 'lidar_first'}" in out
    assert trainer._start_step == STEPS
    pipeline = trainer.pipeline
    assert pipeline.stage_run.lidar["sensors"].keys() == {"lidar"} and pipeline.model.camera_optimizer.config.frozen_sensors == ("lidar",)
    assert config.pipeline.datamanager.dataparser.prior_calibration == runs["run"] / "camera_registration" / "calibration.json"
    assert not (tmp_path / "rig" / "moisst-lite" / "resumed" / "lidar_first").exists()
    assert tree_hash(runs["run"] / "lidar_first") + tree_hash(runs["run"] / "camera_registration") == runs["stages"]
