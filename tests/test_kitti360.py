"""KITTI-360 loader and converter, on a tiny sequence written in the dataset's exact layout from a synthetic rig."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from moisst_ns.datasets.kitti360 import (
    Kitti360Config,
    Kitti360Error,
    MeiCamera,
    convert,
    read_mei_yaml,
    read_timestamps,
)
from moisst_ns.rig.calibration import RigCalibration, RigData
from moisst_ns.rig.format import load_calibration, load_lidar_scan, load_rig, load_tum

from helpers import render_still, tree_hash
from kitti360_sample import NAMES, SEQUENCE, SKIPPED_POSE, mei_unproject, write_sample

CAMS = ("image_00", "image_01", "image_02")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    base = tmp_path_factory.mktemp("kitti360")
    info = write_sample(base / "KITTI-360", native=None)
    info["hash"] = tree_hash(info["root"])
    return info


def _convert(sample, out: Path, **kwargs) -> Path:
    config = Kitti360Config(root=sample["root"], sequence=SEQUENCE, out=out, last_frame=7, cameras=CAMS,
                            fisheye_size=(64, 48), fisheye_fov=90.0, **kwargs)
    return convert(config)


@pytest.fixture(scope="module")
def converted(sample, tmp_path_factory):
    return _convert(sample, tmp_path_factory.mktemp("conv") / "rig")


def test_priors_and_ground_truth_are_the_dataset_calibration_exactly(sample, converted):
    rig = load_rig(converted)
    truth = load_calibration(converted / "ground_truth.json")
    assert rig.reference_sensor == "image_00" and sorted(rig.sensors) == sorted(NAMES)
    for name, expected in sample["truth"].items():
        np.testing.assert_allclose(rig.sensors[name].T_ref_sensor, expected, atol=1e-12)
        np.testing.assert_allclose(truth.T_ref_sensor[name], expected, atol=1e-12)
        assert rig.sensors[name].time_offset == 0.0 and truth.time_offset[name] == 0.0
    native = load_rig(sample["native"]).sensors["cam_front"].intrinsics
    for cam in ("image_00", "image_01"):
        intr = rig.sensors[cam].intrinsics
        for key in ("w", "h", "fl_x", "fl_y", "cx", "cy"):
            assert intr[key] == pytest.approx(native[key], abs=1e-12), (cam, key)
    # image_02 is rectified to the requested pinhole: 90 deg horizontal FOV over 64 px
    assert rig.sensors["image_02"].intrinsics["fl_x"] == pytest.approx(32.0, abs=1e-9)


def test_timestamps_are_exact_on_the_reference_clock(sample, converted):
    rig = load_rig(converted)
    origin = sample["stamps"]["image_00"][0]
    for name in NAMES:
        got = np.array([f.timestamp for f in rig.frames_of(name)])
        np.testing.assert_allclose(got, sample["stamps"][name] - origin, atol=2e-9)
    assert read_timestamps(sample["root"] / "data_2d_raw" / SEQUENCE / "image_00" / "timestamps.txt").dtype == np.int64


@pytest.mark.parametrize("source", ["cam0_to_world", "poses"])
def test_reference_trajectory_is_recovered_from_either_pose_file(sample, tmp_path, source):
    root = sample["root"]
    if source == "poses":  # without cam0_to_world.txt the loader composes poses.txt with the calibration
        root = tmp_path / "K"
        shutil.copytree(sample["root"], root)
        (root / "data_poses" / SEQUENCE / "cam0_to_world.txt").unlink()
        sample = dict(sample, root=root)
    out = _convert(sample, tmp_path / "rig")
    stamps, positions, quats = load_tum(out / "reference_poses.txt")
    keep = sample["pose_frames"]
    origin = sample["stamps"]["image_00"][0]
    np.testing.assert_allclose(stamps, sample["stamps"]["image_00"][keep] - origin, atol=2e-9)
    np.testing.assert_allclose(positions, sample["reference_poses"][keep, :3, 3], atol=1e-9)
    import roma

    rot = roma.unitquat_to_rotmat(torch.from_numpy(quats)).numpy()
    np.testing.assert_allclose(rot, sample["reference_poses"][keep, :3, :3], atol=1e-9)


def test_sensor_poses_match_the_native_rig(sample, converted):
    """Same world poses for every frame as the synthetic rig it came from: the calibration problem is the same."""
    conv, native = load_rig(converted), load_rig(sample["native"])
    gt_native = load_calibration(sample["native"] / "ground_truth.json")
    pc = RigCalibration(RigData.from_rig(conv, None))
    pn = RigCalibration(RigData.from_rig(native, gt_native))
    for kitti, name in NAMES.items():
        if kitti == "image_02":
            continue
        fc, fn = conv.frames_of(kitti), native.frames_of(name)
        dc, dn = pc.data, pn.data
        with torch.no_grad():
            wc = pc.prior_sensor_poses(torch.full((len(fc),), dc.sensor_names.index(kitti)),
                                       torch.tensor([f.timestamp - dc.t0 for f in fc], dtype=torch.float64))
            # native priors are the truth (perturb none); shift its clock by the true offset as the sample does
            wn = pn.prior_sensor_poses(torch.full((len(fn),), dn.sensor_names.index(name)),
                                       torch.tensor([f.timestamp - dn.t0 for f in fn], dtype=torch.float64))
        # frames between the poses around the skipped one interpolate over a longer gap: leave them out
        t = np.array([f.timestamp for f in fc])
        gap = (sample["stamps"]["image_00"][[SKIPPED_POSE - 1, SKIPPED_POSE + 1]] - sample["stamps"]["image_00"][0])
        away = (t <= gap[0]) | (t >= gap[1])
        assert away.sum() >= 5
        np.testing.assert_allclose(wc.numpy()[away], wn.numpy()[away], atol=1e-6)


def test_velodyne_scans_are_copied_points_exact(sample, converted):
    conv, native = load_rig(converted), load_rig(sample["native"])
    for fc, fn in zip(conv.frames_of("velodyne"), native.frames_of("lidar")):
        pc, _, _ = load_lidar_scan(converted / fc.file_path)
        pn, _, _ = load_lidar_scan(sample["native"] / fn.file_path)
        np.testing.assert_array_equal(pc, pn)


def test_fisheye_is_rectified_onto_the_right_pinhole_view(sample, converted):
    """The rectified fisheye image matches a direct pinhole render at the true pose far better than one 2 deg off."""
    from PIL import Image

    from moisst_ns.rig.geometry import ReferenceTrajectory
    from moisst_ns.datasets.synth import SynthConfig, build_scene, make_path
    from moisst_ns.datasets.synth_rig import rot_y

    rig = load_rig(converted)
    config = SynthConfig(out=sample["native"], width=64, height=48, frames=8, seed=3)
    scene = build_scene(config, make_path(config))
    traj = ReferenceTrajectory.from_tum(*load_tum(rig.root / rig.trajectory_file))
    intr, T = rig.sensors["image_02"].intrinsics, rig.sensors["image_02"].T_ref_sensor
    off = np.eye(4)
    off[:3, :3] = rot_y(np.deg2rad(2.0))
    good, bad = [], []
    for f in rig.frames_of("image_02")[:3]:
        pose = traj(torch.tensor([f.timestamp], dtype=torch.float64) - traj.t0)[0].numpy() @ T
        image = np.asarray(Image.open(rig.root / f.file_path), dtype=np.float64)
        good.append(np.abs(image - render_still(scene, intr, pose, 2)[0]).mean())
        bad.append(np.abs(image - render_still(scene, intr, pose @ off, 2)[0]).mean())
    assert np.mean(good) < 6.0, good
    assert np.mean(good) < 0.5 * np.mean(bad), (good, bad)


def test_mei_projection_matches_hand_values_and_round_trips():
    cam = MeiCamera(xi=1.0, k1=0.0, k2=0.0, p1=0.0, p2=0.0, gamma1=100.0, gamma2=90.0, u0=50.0, v0=40.0, width=100, height=80)
    uv, ok = cam.project(np.array([[1.0, 0.0, 1.0], [0.0, -2.0, 0.0], [0.0, 0.0, -1.0]]))
    # (1,0,1)/sqrt2 -> x = 0.70711 / (0.70711 + 1) = 0.41421; (0,-1,0) -> y = -1 / (0 + 1)
    np.testing.assert_allclose(uv[0], [50.0 + 100.0 * (np.sqrt(2) - 1), 40.0], atol=1e-9)
    np.testing.assert_allclose(uv[1], [50.0, 40.0 - 90.0], atol=1e-9)
    assert ok.tolist() == [True, True, False]  # straight behind: z + xi = 0
    distorted = MeiCamera(xi=1.3, k1=0.05, k2=0.01, p1=2e-4, p2=-1e-4, gamma1=60.0, gamma2=58.0, u0=47.5, v0=48.0, width=96, height=96)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(200, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.2
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    uv, ok = distorted.project(dirs)
    assert ok.all()
    np.testing.assert_allclose(mei_unproject(distorted, uv), dirs, atol=1e-8)


def test_paper_perturbation_of_the_priors(sample, tmp_path):
    out = _convert(sample, tmp_path / "rig", perturb="paper", seed=5)
    rig, truth = load_rig(out), load_calibration(out / "ground_truth.json")
    for name in ("image_01", "image_02", "velodyne"):
        d = rig.sensors[name].T_ref_sensor[:3, 3] - truth.T_ref_sensor[name][:3, 3]
        np.testing.assert_allclose(np.abs(d), 0.5, atol=1e-12)
        assert abs(rig.sensors[name].time_offset) == pytest.approx(0.1)
        rel = truth.T_ref_sensor[name][:3, :3].T @ rig.sensors[name].T_ref_sensor[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
        assert 8.0 < angle < 9.0  # three 5 deg rotations about x, y, z compose to ~8.7 deg
    np.testing.assert_array_equal(rig.sensors["image_00"].T_ref_sensor, np.eye(4))


def test_kitti_folder_is_never_written(sample, converted, tmp_path):
    from moisst_ns.data.kitti360_dataparser import MoisstKitti360DataParserConfig

    parser = MoisstKitti360DataParserConfig(data=sample["root"], sequence=SEQUENCE, last_frame=7, cameras=CAMS,
                                            cache_dir=tmp_path / "cache").setup()
    outputs = parser.get_dataparser_outputs("train")
    assert len(outputs.cameras) == 3 * 8
    rig_json = next((tmp_path / "cache").glob("*/rig.json"))
    before = rig_json.stat().st_mtime_ns
    parser.get_dataparser_outputs("val")  # cached conversion reused
    assert rig_json.stat().st_mtime_ns == before
    assert tree_hash(sample["root"]) == sample["hash"]
    with pytest.raises(Kitti360Error, match="must not be inside the KITTI-360 folder"):
        _convert(sample, sample["root"] / "out")
    assert tree_hash(sample["root"]) == sample["hash"]


def _broken(sample, tmp_path, edit) -> Path:
    root = tmp_path / "K"
    shutil.copytree(sample["root"], root)
    edit(root)
    return root


SEQ_DIR = Path("data_2d_raw") / SEQUENCE


@pytest.mark.parametrize(
    "edit, file_part, message",
    [
        (lambda r: shutil.rmtree(r / "data_poses" / SEQUENCE), "data_poses", "has no poses"),
        (lambda r: shutil.rmtree(r / SEQ_DIR / "image_01"), "image_01/timestamps.txt", "not found"),
        (lambda r: (r / "calibration" / "perspective.txt").unlink(), "perspective.txt", "not found"),
        (lambda r: shutil.copyfile(r / SEQ_DIR / "image_00/data_rect/0000000000.png", r / SEQ_DIR / "image_00/data_rect/0000000099.png"),
         "image_00/timestamps.txt: frame count", "mismatched frame counts"),
        (lambda r: (r / SEQ_DIR / "image_01/timestamps.txt").write_text(
            "\n".join((r / SEQ_DIR / "image_01/timestamps.txt").read_text().splitlines()[:5]) + "\n"),
         "image_01/timestamps.txt: frame count", "mismatched frame counts"),
        (lambda r: (r / SEQ_DIR / "image_02/data_rgb/0000000004.png").unlink(), "0000000004.png: file_path", "not found"),
        (lambda r: (r / "calibration" / "calib_cam_to_pose.txt").write_text("image_00: 1 0 0 0 0 1 0 0 0 0 1\n"),
         "calib_cam_to_pose.txt: image_00", "expected 12 numbers"),
        (lambda r: (r / "calibration" / "calib_cam_to_velo.txt").write_text("2 0 0 0 0 1 0 0 0 0 1 0\n"),
         "calib_cam_to_velo.txt: cam0 -> velo", "not a rotation"),
        (lambda r: (r / "calibration" / "image_02.yaml").write_text("%YAML:1.0\n---\nmodel_type: MEI\nimage_width: 96\n"),
         "image_02.yaml: mirror_parameters", "missing"),
        (lambda r: (r / "calibration" / "image_02.yaml").write_text(
            (r / "calibration" / "image_02.yaml").read_text().replace("model_type: MEI", "model_type: KANNALA_BRANDT")),
         "image_02.yaml: model_type", "only MEI"),
        (lambda r: (r / SEQ_DIR / "image_00/timestamps.txt").write_text("2013-05-28 08:00:00.000000000\nyesterday\n"),
         "image_00/timestamps.txt: line 2", "timestamp"),
        (lambda r: (r / "data_poses" / SEQUENCE / "cam0_to_world.txt").write_text("0 1 0 0\n"),
         "cam0_to_world.txt: line 1", "expected a frame index and 16 numbers"),
    ],
    ids=["no-poses", "missing-sensor-folder", "missing-calib-file", "more-images-than-stamps", "fewer-stamps-than-frames",
         "missing-frame", "short-calib-line", "velo-not-rigid", "yaml-missing-key", "yaml-other-model", "bad-timestamp",
         "short-pose-line"],
)
def test_bad_input_gets_one_clear_error(sample, tmp_path, edit, file_part, message):
    root = _broken(sample, tmp_path, edit)
    with pytest.raises(Kitti360Error) as err:
        _convert(dict(sample, root=root), tmp_path / "rig")
    text = str(err.value)
    assert "\n" not in text and file_part in text and message in text, text
    assert not (tmp_path / "rig" / "rig.json").exists()


def test_cli_error_is_one_line_and_names_the_file(sample, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "moisst_ns.cli.kitti360_to_rig", str(sample["root"]), SEQUENCE, "--out", str(tmp_path / "o"), "--last-frame", "7"],
        capture_output=True, text=True,
    )
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "image_03/timestamps.txt" in lines[0] and "not found" in lines[0], proc.stderr


def test_mei_yaml_reads_the_published_layout(tmp_path):
    text = (
        "%YAML:1.0\n---\nmodel_type: MEI\ncamera_name: image_02\nimage_width: 1400\nimage_height: 1400\n"
        "mirror_parameters:\n   xi: 2.2134047507854890e+00\ndistortion_parameters:\n   k1: 1.6798235660113681e-02\n"
        "   k2: 1.6548773243373522e+00\n   p1: 4.2223943394772046e-04\n   p2: 4.2462134260997584e-04\n"
        "projection_parameters:\n   gamma1: 1.3363220825849971e+03\n   gamma2: 1.3357883350012958e+03\n"
        "   u0: 7.1694323510126321e+02\n   v0: 7.0576498308221585e+02\n"
    )
    (tmp_path / "image_02.yaml").write_text(text)
    cam = read_mei_yaml(tmp_path / "image_02.yaml")
    assert (cam.width, cam.height) == (1400, 1400)
    assert cam.xi == pytest.approx(2.2134047507854890) and cam.v0 == pytest.approx(705.76498308221585)
