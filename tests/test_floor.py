"""moisst-floor: scene trained at the truth, calibration released at the truth against the frozen scene."""

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from helpers import tree_hash
from moisst_ns.cli.floor import FloorConfig, floor_errors, run_floor
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
    floor = run_floor(FloorConfig(dataset=rig, output_dir=out, scene_steps=40, register_steps=10, log_every=5, average_last=2, threads=2, seed=0))
    assert tree_hash(rig) == digest
    result = json.loads((out / "floor.json").read_text())
    assert set(result["floor"]) == {"cam_front_right", "cam_left", "lidar"} == set(floor)
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


def test_floor_needs_ground_truth(rig, tmp_path, capsys):
    copy = tmp_path / "no_truth"
    shutil.copytree(rig, copy)
    (copy / "ground_truth.json").unlink()
    with pytest.raises(SystemExit):
        run_floor(FloorConfig(dataset=copy, output_dir=tmp_path / "o"))
    err = capsys.readouterr().err.strip()
    assert err.startswith("moisst-floor: error:") and "ground_truth.json: not found" in err and "\n" not in err


def test_floor_refuses_output_inside_dataset(rig, capsys):
    with pytest.raises(SystemExit):
        run_floor(FloorConfig(dataset=rig, output_dir=rig / "out"))
    assert "must not be inside the dataset folder" in capsys.readouterr().err
    assert not (rig / "out").exists()
