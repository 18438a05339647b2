"""A LiDAR as the reference sensor: its trajectory in reference_poses.txt, cameras calibrated relative to it."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
from moisst_ns.rig.format import load_calibration, load_rig, load_tum, write_tum
from moisst_ns.datasets.synth import SynthConfig, make_rig


def rebase_on_lidar(src: Path, dst: Path) -> None:
    """Rewrite a camera-referenced rig as a LiDAR-referenced one (same files, hard-linked).

    New trajectory: world_T_L(s) = Traj_cam(s + delta_L) @ cam_T_L at the old sample times shifted by -delta_L;
    new extrinsics L_T_i = cam_T_L^-1 @ cam_T_i; new offsets delta_i - delta_L (priors and truth alike).
    """
    rig = json.loads((src / "rig.json").read_text())
    truth = json.loads((src / "ground_truth.json").read_text())
    dst.mkdir(parents=True)
    for sub in ("images", "lidar"):
        for f in (src / sub).rglob("*"):
            if f.is_file():
                (dst / f.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
                (dst / f.relative_to(src)).hardlink_to(f)

    def rebase(spec: dict) -> None:
        cam_T_l = np.asarray(spec["lidar"]["T_ref_sensor"])
        d_l = spec["lidar"]["time_offset"]
        for name, s in spec.items():
            s["T_ref_sensor"] = (np.linalg.inv(cam_T_l) @ np.asarray(s["T_ref_sensor"])).tolist()
            s["time_offset"] = s["time_offset"] - d_l
        spec["lidar"]["T_ref_sensor"] = np.eye(4).tolist()

    true_cam_T_l, true_d_l = np.asarray(truth["sensors"]["lidar"]["T_ref_sensor"]), truth["sensors"]["lidar"]["time_offset"]
    stamps, positions, quats = load_tum(src / rig["trajectory"])
    rotations = Rotation.from_quat(quats).as_matrix()
    new_rot = rotations @ true_cam_T_l[:3, :3]
    new_pos = positions + rotations @ true_cam_T_l[:3, 3]
    write_tum(dst / rig["trajectory"], stamps - true_d_l, new_pos, Rotation.from_matrix(new_rot).as_quat())
    # priors: the LiDAR is now exact by definition, the cameras keep their own perturbation relative to the truth
    prior_spec = {n: {"T_ref_sensor": s["T_ref_sensor"], "time_offset": s["time_offset"]} for n, s in rig["sensors"].items()}
    prior_spec["lidar"] = {"T_ref_sensor": true_cam_T_l.tolist(), "time_offset": true_d_l}
    rebase(prior_spec)
    rebase(truth["sensors"])
    for name, s in rig["sensors"].items():
        s.update(prior_spec[name])
    rig["reference_sensor"] = truth["reference_sensor"] = "lidar"
    (dst / "rig.json").write_text(json.dumps(rig))
    (dst / "ground_truth.json").write_text(json.dumps(truth))


@pytest.fixture(scope="module")
def lidar_rig(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("lidar_ref")
    make_rig(SynthConfig(out=root / "cam", width=48, height=36, frames=6, perturb="paper", lidar_azimuth_steps=256, lidar_max_points=3000))
    rebase_on_lidar(root / "cam", root / "lidar")
    return root / "lidar"


def test_lidar_reference_rig_loads(lidar_rig):
    rig = load_rig(lidar_rig)
    assert rig.reference_sensor == "lidar"
    np.testing.assert_allclose(rig.sensors["lidar"].T_ref_sensor, np.eye(4), atol=1e-12)
    truth = load_calibration(lidar_rig / "ground_truth.json")
    assert truth.time_offset["lidar"] == 0.0
    # cam_front was the old reference: in the LiDAR frame it now sits at the inverse of the true cam_T_lidar
    assert np.linalg.norm(truth.T_ref_sensor["cam_front"][:3, 3]) > 0.1


def test_calibrate_with_lidar_reference(lidar_rig, tmp_path):
    """Every camera (the old reference included) is calibrated; the LiDAR stays the identity with delta 0.
    (``uncertainty=False``: after 16 steps the held-back check may rightly keep a camera's prior, which
    tests/test_trust.py covers; here the estimates themselves are under test.)"""
    run_calibration(CalibrateConfig(dataset=lidar_rig, output_dir=tmp_path / "out", max_num_iterations=16, seed=0, threads=2,
                                    report=False, uncertainty=False))
    estimate = load_calibration(tmp_path / "out" / "calibration.json")
    assert estimate.reference_sensor == "lidar"
    np.testing.assert_array_equal(estimate.T_ref_sensor["lidar"], np.eye(4))
    assert estimate.time_offset["lidar"] == 0.0
    rig = load_rig(lidar_rig)
    for name in ("cam_front", "cam_front_right", "cam_left"):
        moved = np.abs(estimate.T_ref_sensor[name] - rig.sensors[name].T_ref_sensor).max()
        assert np.isfinite(estimate.T_ref_sensor[name]).all() and 0 < moved < 0.5, (name, moved)
        assert estimate.time_offset[name] != rig.sensors[name].time_offset
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert set(summary["errors_after"]) == {"cam_front", "cam_front_right", "cam_left"}
