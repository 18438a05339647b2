"""moisst-fleet: manifest validation, consensus and moved-sensor flags (pure), and real fleets of tiny drives on Ray."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from moisst_ns.fleet import FleetError
from moisst_ns.fleet.consensus import (COMPONENTS, SIGMA_FLOOR, DriveEstimate, SensorEstimate, fleet_spread,
                                       sigma_from_uncertainty, vehicle_consensus, weighted_median)
from moisst_ns.fleet.manifest import load_manifest

from helpers import tree_hash

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------------ manifest


def _fake_dataset(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "rig.json").write_text("{}")
    return folder


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_manifest_reads_drives_overrides_and_relative_paths(tmp_path):
    _fake_dataset(tmp_path / "data" / "a")
    _fake_dataset(tmp_path / "data" / "b")
    m = load_manifest(_write(tmp_path / "fleet.toml", """
[calibrate]
max_num_iterations = 50
report = false
[[drive]]
id = "a"
vehicle = "van"
dataset = "data/a"
[[drive]]
id = "b"
vehicle = "van"
dataset = "data/b"
max_num_iterations = 80
max_time_offset = 1
"""))
    assert [(d.id, d.vehicle, d.dataset) for d in m.drives] == [("a", "van", tmp_path / "data/a"), ("b", "van", tmp_path / "data/b")]
    assert m.drives[0].options == {"max_num_iterations": 50, "report": False}
    assert m.drives[1].options == {"max_num_iterations": 80, "report": False, "max_time_offset": 1.0}


@pytest.mark.parametrize("body, field", [
    ('[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "nowhere"\n', "drive[0] (a).dataset: 'nowhere'"),
    ('[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\n[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\n',
     "drive[1] (a).id: 'a' duplicates drive[0]"),
    ('[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\nmax_iters = 3\n', "drive[0] (a): unknown key 'max_iters'"),
    ('[calibrate]\nmethod = "nerfacto"\n[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\n', "calibrate.method: must be one of"),
    ('[calibrate]\nthreads = 2\n[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\n', "calibrate.threads: set by moisst-fleet"),
    ('[[drive]]\nid = "a"\ndataset = "data/a"\n', "drive[0].vehicle: missing"),
])
def test_manifest_errors_are_one_line_naming_file_and_field(tmp_path, body, field):
    _fake_dataset(tmp_path / "data" / "a")
    manifest = _write(tmp_path / "fleet.toml", body)
    with pytest.raises(FleetError) as err:
        load_manifest(manifest)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{manifest}: ") and field in message, message


@pytest.mark.parametrize("body, field", [
    ('[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "nowhere"\n', "drive[0] (a).dataset"),
    ('[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\n[[drive]]\nid = "a"\nvehicle = "v2"\ndataset = "data/a"\n', "drive[1] (a).id"),
    ('[[drive]]\nid = "a"\nvehicle = "van"\ndataset = "data/a"\nfoo = 1\n', "unknown key 'foo'"),
])
def test_cli_rejects_a_bad_manifest_before_any_work(tmp_path, body, field):
    _fake_dataset(tmp_path / "data" / "a")
    manifest = _write(tmp_path / "fleet.toml", body)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "moisst_ns.cli.fleet", str(manifest), "--output-dir", str(out)],
                          capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"moisst-fleet: error: {manifest}: ") and field in lines[0], proc.stderr
    assert not out.exists()  # nothing started


# ------------------------------------------------------------------------------------------------ consensus


def _pose(rotvec_deg, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec_deg, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


BASE = {"cam_b": (np.array([0.0, 85.0, 0.0]), np.array([-0.6, 0.3, -0.8]), 0.04),
        "lidar": (np.array([90.0, 0.0, -90.0]), np.array([-0.1, -0.4, -0.3]), -0.03)}


def _drive(name: str, noise: dict, knock_deg: float = 0.0) -> DriveEstimate:
    """A drive's estimates: the base mounts plus per-sensor (dt m, drot deg, ddelta s) noise; cam_b turned by
    ``knock_deg`` about the reference y axis."""
    sensors = {"cam_a": SensorEstimate(np.eye(4), 0.0)}
    for sensor, (rv, t, delta) in BASE.items():
        dt, dr, dd = noise.get(sensor, (0.0, 0.0, 0.0))
        T = _pose(rv, t + dt)
        turn = (knock_deg if sensor == "cam_b" else 0.0) + dr
        T[:3, :3] = Rotation.from_rotvec([0.0, turn, 0.0], degrees=True).as_matrix() @ T[:3, :3]
        sensors[sensor] = SensorEstimate(T, delta + dd)
    return DriveEstimate(name, sensors)


SIGMA = {n: np.array([0.01, 0.01, 0.01, 0.1, 0.1, 0.1, 0.001]) for n in BASE}


def test_weighted_median():
    assert weighted_median(np.array([3.0, 1.0, 2.0]), np.ones(3)) == 2.0
    assert weighted_median(np.array([1.0, 2.0]), np.ones(2)) == 1.5
    assert weighted_median(np.array([1.0, 2.0, 10.0]), np.array([1.0, 1.0, 5.0])) == 10.0


def test_moved_camera_is_flagged_between_the_right_drives_and_nothing_else():
    noise = [{"cam_b": (0.002, 0.05, 0.0002), "lidar": (-0.003, -0.04, 0.0)},
             {"cam_b": (-0.001, -0.03, -0.0003), "lidar": (0.002, 0.06, 0.0001)},
             {"cam_b": (0.0, 0.02, 0.0001), "lidar": (0.0, -0.05, -0.0002)},
             {"cam_b": (0.001, -0.04, 0.0), "lidar": (0.001, 0.02, 0.0)}]
    drives = [_drive(f"d{k + 1}", n, knock_deg=1.0 if k >= 2 else 0.0) for k, n in enumerate(noise)]
    vc = vehicle_consensus(drives, "cam_a", SIGMA, flag_sigma=5.0)
    # cam_b: before = median(+0.05, -0.03) = +0.01, after = median(1.02, 0.96) = 0.99 -> +0.98 deg; σ of a two-drive
    # median 0.1/sqrt(2) on each side -> 0.98 / 0.1 = 9.8 σ
    assert [m.line() for m in vc.moves()] == ["cam_b moved between drive d2 and drive d3 (rot_y +0.98°, 9.8 σ)"]
    cam = vc.sensors["cam_b"]
    assert cam.used == ["d3", "d4"]  # the consensus is the mount as it is now
    assert [cam.verdict[d] for d in ("d1", "d2", "d3", "d4")] == ["old mount", "old mount", "ok", "ok"]
    np.testing.assert_allclose(cam.deviation["d3"][4], 0.03, atol=1e-9)  # 1.02 - 0.99
    assert vc.sensors["lidar"].move is None and set(vc.sensors["lidar"].verdict.values()) == {"ok"}
    np.testing.assert_allclose(vc.sensors["lidar"].time_offset, -0.03, atol=1e-12)  # median of -0.2, 0, 0, +0.1 ms


def test_one_bad_drive_deviates_but_moves_nothing():
    noise = [{"cam_b": (0.0, 0.02, 0.0)}, {"cam_b": (0.0, -0.02, 0.0)}, {"cam_b": (0.3, 3.0, 0.02)},
             {"cam_b": (0.0, 0.01, 0.0)}, {"cam_b": (0.0, -0.01, 0.0)}]
    drives = [_drive(f"d{k + 1}", n) for k, n in enumerate(noise)]
    vc = vehicle_consensus(drives, "cam_a", SIGMA, flag_sigma=5.0)
    cam = vc.sensors["cam_b"]
    assert vc.moves() == [] and cam.used == ["d1", "d2", "d3", "d4", "d5"]
    assert [cam.verdict[f"d{k}"] for k in range(1, 6)] == ["ok", "ok", "deviates", "ok", "ok"]
    np.testing.assert_allclose(cam.T_ref_sensor[:3, 3], BASE["cam_b"][1], atol=1e-12)  # the bad drive did not pull it
    np.testing.assert_allclose(cam.z["d3"][[0, 4, 6]], [30.0, 29.9, 20.0], rtol=1e-6)  # rot_y: (3.0 - 0.01) / 0.1


def test_drives_own_uncertainty_replaces_the_spread():
    drives = [_drive("d1", {}), _drive("d2", {}, knock_deg=1.0)]
    assert [m.line() for m in vehicle_consensus(drives, "cam_a", SIGMA).moves()] == \
        ["cam_b moved between drive d1 and drive d2 (rot_y +1.00°, 7.1 σ)"]
    for d in drives:  # each drive says its rotation is only good to 0.5°: a 1° step is 1.4 σ
        d.sensors["cam_b"].sigma = sigma_from_uncertainty({"translation_m": [0.01] * 3, "rotation_deg": [0.5] * 3, "time_offset_s": 0.001})
    vc = vehicle_consensus(drives, "cam_a", SIGMA)
    assert vc.moves() == [] and vc.sensors["cam_b"].verdict == {"d1": "ok", "d2": "ok"}
    assert sigma_from_uncertainty({"translation_m": [0.01] * 3}) is None


def test_rotation_sigma_is_turned_onto_the_reference_axes():
    entry = {"translation_m": [0.01, 0.02, 0.03], "rotation_deg": [0.1, 0.2, 0.3], "time_offset_s": 0.001}
    np.testing.assert_allclose(sigma_from_uncertainty(entry), [0.01, 0.02, 0.03, 0.1, 0.2, 0.3, 0.001])
    quarter = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # sensor x = reference y, sensor y = -reference x
    np.testing.assert_allclose(sigma_from_uncertainty(entry, quarter), [0.01, 0.02, 0.03, 0.2, 0.1, 0.3, 0.001], atol=1e-12)
    tilt = Rotation.from_euler("x", 45, degrees=True).as_matrix()  # sensor y, z share the reference y, z half and half
    half = np.sqrt(0.5 * 0.2**2 + 0.5 * 0.3**2)
    np.testing.assert_allclose(sigma_from_uncertainty(entry, tilt)[3:6], [0.1, half, half])


def test_a_not_converged_sensor_is_left_out_of_its_drive(tmp_path):
    from moisst_ns.fleet.report import load_estimate
    from moisst_ns.rig.format import Calibration

    path = tmp_path / "calibration.json"
    Calibration("cam_a", {n: np.eye(4) for n in ("cam_a", "cam_b", "lidar")}, {"cam_a": 0.0, "cam_b": 0.01, "lidar": 0.0}).write(path)
    raw = json.loads(path.read_text())
    raw["sensors"]["cam_b"]["verdict"] = "not converged"
    raw["sensors"]["lidar"]["verdict"] = "converged"
    path.write_text(json.dumps(raw))
    estimate, reference, left_out = load_estimate("d1", path)
    assert reference == "cam_a" and left_out == ["cam_b"] and "cam_b" not in estimate.sensors and "lidar" in estimate.sensors


def test_fleet_spread_is_per_sensor_pooled_over_vehicles():
    dt = [0.01, -0.01, 0.02, -0.02, 0.04, -0.04]  # cam_b: pairs of drives ±1, ±2, ±4 cm on every axis, 3 vehicles
    vehicles = {f"v{k}": [_drive("a", {"cam_b": (dt[2 * k], 0.0, 0.0), "lidar": (0.0001, 0.0, 0.0)}),
                          _drive("b", {"cam_b": (dt[2 * k + 1], 0.0, 0.0)})] for k in range(3)}
    sigma = fleet_spread(vehicles, {v: "cam_a" for v in vehicles})
    # cam_b translation residuals |1|,|2|,|4| cm (six of each) * sqrt(2 / 1): median 2 cm; rotation and time agree
    np.testing.assert_allclose(sigma["cam_b"][:3], 1.4826 * 0.02 * np.sqrt(2), rtol=1e-9)
    np.testing.assert_allclose(sigma["cam_b"][3:], SIGMA_FLOOR[3:])
    np.testing.assert_allclose(sigma["lidar"], SIGMA_FLOOR)  # the LiDAR's 0.05 mm is below the floor
    assert COMPONENTS[6] == "time_offset" and set(sigma) == {"cam_b", "lidar"}


# ------------------------------------------------------------------------------------------------ fleets on Ray


TINY = dict(width=32, height=24, frames=6, lidar_beams=8, lidar_azimuth_steps=128, lidar_max_points=512)


@pytest.fixture(scope="module")
def tiny_drives(tmp_path_factory):
    """Three tiny drives: two of vehicle ``van`` (one rig, two paths) and one of ``car``."""
    from moisst_ns.datasets.synth import SynthConfig, make_rig

    root = tmp_path_factory.mktemp("drives")
    for name, seed, rig_seed in (("van-1", 11, 1), ("van-2", 12, 1), ("car-1", 21, 2)):
        make_rig(SynthConfig(out=root / name, seed=seed, rig_seed=rig_seed, **TINY))
    return root


def _manifest(path: Path, drives, steps: int = 3, extra: str = "") -> Path:
    text = f"[calibrate]\nmax_num_iterations = {steps}\nreport = false\n{extra}"
    for drive_id, vehicle, dataset in drives:
        text += f'\n[[drive]]\nid = "{drive_id}"\nvehicle = "{vehicle}"\ndataset = "{dataset}"\n'
    return _write(path, text)


def test_without_ray_the_fleet_stops_with_one_line(tmp_path, monkeypatch):
    """Ray is an optional dependency (pyproject's ``fleet`` extra): without it, one line saying how to add it."""
    from moisst_ns.fleet.run import FleetConfig, start_ray

    monkeypatch.setitem(sys.modules, "ray", None)  # ``import ray`` raises ImportError
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")  # start_ray sets it; restored after
    with pytest.raises(FleetError, match=r"^moisst-fleet needs Ray, an optional dependency: make install-fleet") as err:
        start_ray(FleetConfig(tmp_path / "fleet.toml", output_dir=tmp_path / "out"), tmp_path / "shim")
    assert "\n" not in str(err.value)


def test_a_corrupted_drive_fails_alone_and_the_fleet_completes(tmp_path, tiny_drives):
    import shutil

    from moisst_ns.fleet.run import FleetConfig, run_fleet

    bad = tmp_path / "bad"
    shutil.copytree(tiny_drives / "car-1", bad)
    image = sorted((bad / "images" / "cam_left").glob("*.png"))[2]
    image.write_bytes(b"not a png")
    before = {name: tree_hash(tiny_drives / name) for name in ("van-1", "van-2")}
    manifest = _manifest(tmp_path / "fleet.toml", [("van-1", "van", tiny_drives / "van-1"), ("bad-1", "car", bad),
                                                   ("van-2", "van", tiny_drives / "van-2")])
    out = tmp_path / "out"
    lines = []
    fleet = run_fleet(FleetConfig(manifest, output_dir=out, cpus=2, cpus_per_drive=1, retries=1), report=lines.append)
    rows = {r["id"]: r for r in fleet["drives"]}
    assert [rows[d]["status"] for d in ("van-1", "bad-1", "van-2")] == ["done", "failed", "done"]
    reason = rows["bad-1"]["reason"]
    assert "\n" not in reason and image.name in reason, reason
    assert any(line.startswith("bad-1 FAILED: ") for line in lines), lines
    for d in ("van-1", "van-2"):
        assert (out / "van" / d / "fleet_done.json").is_file() and (out / "van" / d / "calibration.json").is_file()
        assert set(rows[d]["sensors"]) == {"cam_front_right", "cam_left", "lidar"} and rows[d]["wall_s"] > 0
    assert not (out / "car" / "bad-1" / "fleet_done.json").exists()
    saved = json.loads((out / "fleet.json").read_text())
    assert saved["vehicles"]["van"]["drives"] == ["van-1", "van-2"] and saved["vehicles"]["car"]["calibration"] is None
    assert (out / "van" / "calibration.json").is_file() and "| bad-1 | car | failed: " in (out / "fleet.md").read_text()
    # 3 steps on 32x24 images: the cameras are "not converged" and left out; the LiDAR (its own stage) is combined
    combined = {n for block in saved["vehicles"].values() for n in block["sensors"]}
    for d in ("van-1", "van-2"):
        verdicts = {n: e.get("verdict") for n, e in json.loads((out / "van" / d / "calibration.json").read_text())["sensors"].items()}
        for name, entry in rows[d]["sensors"].items():
            assert (entry["verdict"] == "not converged (left out)") == (verdicts[name] == "not converged"), (d, name, entry)
    assert all(any(rows[d]["sensors"][n]["verdict"] != "not converged (left out)" for d in ("van-1", "van-2")) for n in combined)
    assert "lidar" in combined and sorted(p.name for p in (out / "plots").iterdir()) == sorted(f"{n}.png" for n in combined)
    assert {name: tree_hash(tiny_drives / name) for name in ("van-1", "van-2")} == before  # datasets never written


def _fleet_cmd(manifest: Path, out: Path):
    return [sys.executable, "-m", "moisst_ns.cli.fleet", str(manifest), "--output-dir", str(out), "--cpus", "1"]


def test_a_killed_fleet_run_resumes_with_only_the_missing_drives(tmp_path, tiny_drives):
    manifest = _manifest(tmp_path / "fleet.toml", [("van-1", "van", tiny_drives / "van-1"), ("van-2", "van", tiny_drives / "van-2"),
                                                   ("car-1", "car", tiny_drives / "car-1")], steps=30,
                         extra="lidar_first = false\n")  # car-1's 512-point scans are too sparse for the LiDAR stage
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(_fleet_cmd(manifest, out), cwd=ROOT, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    first = out / "van" / "van-1" / "fleet_done.json"
    deadline = time.monotonic() + 900  # a safety net, not a timing assertion
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.5)
    assert first.exists(), proc.communicate()[0] if proc.poll() is not None else "first drive never finished"
    os.killpg(proc.pid, signal.SIGKILL)  # the driver and its local Ray (one drive at a time: the 2nd was running)
    proc.wait()
    assert not (out / "car" / "car-1" / "fleet_done.json").exists() and not (out / "fleet.json").exists()
    marker = first.read_bytes()
    log_stat = (out / "van" / "van-1" / "calibrate.log").stat().st_mtime_ns
    rerun = subprocess.run(_fleet_cmd(manifest, out), cwd=ROOT, env=env, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "1 drive(s) already finished" in rerun.stdout and "2 drive(s) to calibrate on Ray" in rerun.stdout, rerun.stdout
    fleet = json.loads((out / "fleet.json").read_text())
    assert [(r["id"], r["status"], r["resumed"]) for r in fleet["drives"]] == \
        [("van-1", "done", True), ("van-2", "done", False), ("car-1", "done", False)]
    assert first.read_bytes() == marker and (out / "van" / "van-1" / "calibrate.log").stat().st_mtime_ns == log_stat
