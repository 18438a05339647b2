"""moisst-floor: scene trained at the truth, calibration released at the truth against the frozen scene."""

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from helpers import tree_hash
from moisst_ns.floor import FloorConfig, FloorError, camera_depth_errors, floor_errors, run_floor
from moisst_ns.rig.calibration import RigCalibration, RigData
from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.datasets.synth import SynthConfig, make_rig


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("floor") / "rig"
    make_rig(SynthConfig(out=root, width=48, height=36, frames=6, perturb="paper", lidar_azimuth_steps=256, lidar_max_points=3000))
    return root


def test_set_corrections_to_the_truth_gives_the_truth(rig):
    """From perturbed priors, RigCalibration.set_corrections_to(ground truth) reproduces ground_truth.json."""
    data = RigData.from_rig(load_rig(rig), load_calibration(rig / "ground_truth.json"))
    calibration = RigCalibration(data)
    before = calibration.errors()
    assert min(e["translation_cm"] for n, e in before.items() if n != "cam_front") > 50.0
    calibration.set_corrections_to(data.ground_truth)
    after = calibration.errors()
    for name, err in after.items():
        assert err["translation_cm"] < 1e-5 and err["rotation_deg"] < 1e-4 and err["time_ms"] < 1e-5, (name, err)  # float32 parameters


def test_floor_errors_average_the_last_logs():
    rows = [{"step": s, "sensor": n, "translation_cm": float(s), "rotation_deg": 2.0 * s, "time_ms": 0.5}
            for s in (1, 2, 3, 4) for n in ("a", "b")]
    floor = floor_errors(rows, 2)
    assert floor["a"] == {"translation_cm": 3.5, "rotation_deg": 7.0, "time_ms": 0.5}
    assert set(floor) == {"a", "b"}


def test_floor_run(rig, tmp_path):
    """The scene trains at the truth, registration starts exactly there and moves the calibration; the dataset is not written."""
    digest = tree_hash(rig)
    out = tmp_path / "floor"
    returned = run_floor(FloorConfig(dataset=rig, output_dir=out, scene_steps=40, register_steps=10, log_every=5,
                                     average_last=2, threads=2, seed=0, depth_check_rays=500))
    floor = returned["floor"]
    assert tree_hash(rig) == digest
    result = json.loads((out / "floor.json").read_text())
    assert result == json.loads(json.dumps(returned))
    assert set(result["floor"]) == {"cam_front_right", "cam_left", "lidar"} == set(floor)
    depth = result["depth"]  # a 40-step scene is far from the surfaces, but every figure is measured
    assert depth["camera_rays"] > 0 and depth["lidar_rays"] > 0
    assert 0.0 < depth["median_abs_m"] < 100.0 and 0.0 < depth["lidar_median_abs_m"] < 100.0
    assert result["scene_steps"] == 40 and result["register_steps"] == 10
    with (out / "floor_history.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["step"] for r in rows] == [str(s) for s in (0, 0, 0, 5, 5, 5, 10, 10, 10)]
    start = [r for r in rows if r["step"] == "0"]
    for r in start:  # released at the truth
        assert float(r["translation_cm"]) < 1e-3 and float(r["rotation_deg"]) < 1e-3 and float(r["time_ms"]) < 1e-3, r
    end = [r for r in rows if r["step"] == "10"]
    assert all(float(r["translation_cm"]) > 1e-3 for r in end)  # the calibration losses did move every sensor
    for name, err in floor.items():
        assert all(np.isfinite(v) for v in err.values())
    assert (out / "moisst-lite" / "scene" / "config.yml").is_file()
    stages = result["stages"]  # the stages' floor too; 6 frames are too few for the camera stage, so only the LiDAR's
    assert set(stages["floor"]) == {"lidar"} and all(np.isfinite(v) for v in stages["floor"]["lidar"].values())
    assert [u.split(":")[0] for u in stages["unfitted"]] == ["cam_front_right", "cam_left"] and "6 frames" in stages["unfitted"][0]
    assert stages["map_depth"]["map_points"] > 1000


def test_floor_with_the_map_range_records_the_scene_weight_and_releases_at_the_truth(rig, tmp_path):
    """``--map-range-mult``: the scene trains with every camera's map range (the truth loaded as the prior), the term is
    dropped for the release, and floor.json records the weight the scene trained with."""
    out = tmp_path / "floor"
    run_floor(FloorConfig(dataset=rig, output_dir=out, scene_steps=20, register_steps=5, log_every=5, average_last=1,
                          threads=2, seed=0, depth_check_rays=200, stages=False, map_range_mult=0.5))
    result = json.loads((out / "floor.json").read_text())
    assert result["map_range_mult"] == 0.5
    with (out / "floor_history.csv").open() as handle:
        start = [r for r in csv.DictReader(handle) if r["step"] == "0"]
    assert len(start) == 3 and all(float(r["translation_cm"]) < 1e-3 and float(r["time_ms"]) < 1e-3 for r in start)


def test_stage_floor_alone(rig, tmp_path):
    """--no-nerf measures only the stages' floor: no scene is trained, no NeRF figures are written."""
    result = run_floor(FloorConfig(dataset=rig, output_dir=tmp_path / "f", nerf=False, threads=1))
    assert set(result) == {"method", "stages"} and not (tmp_path / "f" / "moisst-lite").exists()
    with pytest.raises(FloorError, match="leave nothing to measure"):
        run_floor(FloorConfig(dataset=rig, output_dir=tmp_path / "g", nerf=False, stages=False))


def test_floor_needs_ground_truth(rig, tmp_path, capsys):
    copy = tmp_path / "no_truth"
    shutil.copytree(rig, copy)
    (copy / "ground_truth.json").unlink()
    with pytest.raises(FloorError, match="ground_truth.json: not found"):
        run_floor(FloorConfig(dataset=copy, output_dir=tmp_path / "o"))


def test_floor_refuses_output_inside_dataset(rig):
    with pytest.raises(FloorError, match="must not be inside the dataset folder"):
        run_floor(FloorConfig(dataset=rig, output_dir=rig / "out"))
    assert not (rig / "out").exists()


def test_floor_cli_error_is_one_line(rig, tmp_path):
    """moisst-floor turns a missing ground truth into one line on stderr and exit code 2."""
    import subprocess
    import sys

    copy = tmp_path / "no_truth"
    shutil.copytree(rig, copy)
    (copy / "ground_truth.json").unlink()
    proc = subprocess.run([sys.executable, "-m", "moisst_ns.cli.floor", str(copy), "--output-dir", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("moisst-floor: error:") and "ground_truth.json: not found" in last


def test_camera_depth_errors_only_count_rays_in_the_lidar_field():
    rendered = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    true = np.array([1.5, 2.0, np.inf, 10.0, 4.0])
    field = np.array([True, True, True, False, True])
    out = camera_depth_errors(rendered, true, field)
    assert out["camera_rays"] == 3 and out["median_abs_m"] == 0.5
    assert out["p90_abs_m"] == pytest.approx(np.percentile([0.5, 0.0, 1.0], 90))
    assert camera_depth_errors(rendered, true, np.zeros(5, dtype=bool))["camera_rays"] == 0
