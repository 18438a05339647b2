"""A LiDAR placed against what two cameras triangulate at the same instant (``stages/lidar/lidar_instant``): on the real
KITTI raw drive 0048 (skipped without ../shared/data), and the sigma a LiDAR's record then carries."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from moisst_ns.datasets.kitti_raw import KittiRawConfig, convert
from moisst_ns.rig.format import Calibration, load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar.lidar_instant import place_lidar, shift_sigmas
from moisst_ns.stages.lidar.lidar_placement import place_lidars, trajectory_turn
from moisst_ns.stages.lidar.lidar_report import stage_sigma
from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig, load_scans

from helpers import KITTI_DRIVE, KITTI_RAW, needs_kitti_raw


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The whole drive, the stereo pairs image_00/01 and image_00/03 and the Velodyne, images halved, paper priors;
    the cameras at the factory calibration, the Velodyne at the prior's rotation and lever arm with the factory's time
    offset (which the shared instant cannot tell from its along-track lever arm on this drive)."""
    config = KittiRawConfig(root=KITTI_RAW, drive=KITTI_DRIVE, out=tmp_path_factory.mktemp("raw") / "rig", cameras=("image_01", "image_03"),
                            downscale=2, points_per_scan=60000, perturb="paper", seed=0)
    rig = load_rig(convert(config))
    truth = load_calibration(rig.root / "ground_truth.json")
    start = Calibration(truth.reference_sensor, dict(truth.T_ref_sensor), dict(truth.time_offset))
    start.T_ref_sensor["velodyne"] = rig.sensors["velodyne"].T_ref_sensor
    scans = load_scans(rig, "velodyne", ReferenceTrajectory.of(rig), LidarFirstConfig(), log=lambda line: None)
    return rig, truth, start, scans


@needs_kitti_raw
def test_the_stereo_cameras_place_the_velodyne_the_drive_cannot(drive):
    """From 50 cm and 5 deg off on every axis (86.6 cm / 8.8 deg), the Velodyne ends within 6 cm per axis and 0.2 deg
    per angle of the factory calibration (itself good to a few centimetres): the lever arm and the roll that this
    almost straight drive's motion leaves undetermined, and the pitch and yaw without the OXTS trajectory's 0.67 / 0.45
    deg turn from image_00 that the motion inherits."""
    rig, truth, start, scans = drive
    placed = place_lidar(rig, start, "velodyne", scans, ["image_01", "image_03"], log=lambda line: None)
    error = np.abs(parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, placed.estimate.matrix(), 0.0))
    assert np.all(error[:3] < 0.06), error[:3]
    assert np.all(np.rad2deg(error[3:6]) < 0.2), np.rad2deg(error[3:6])
    assert {"x", "y", "roll", "pitch", "yaw"} <= set(placed.placed)
    assert placed.cameras == ["image_01", "image_03"] and np.all(np.abs(placed.shifts) < 0.015), placed.shifts
    print("error", error, "shifts", placed.shifts)


@needs_kitti_raw
def test_a_stereo_camera_off_along_the_drive_does_not_tilt_the_velodyne(drive):
    """Both stereo cameras 2 cm behind their factory position at the same instant (what the camera stage's along-track
    lever arm and time offset trade leaves: its depth error grows across the image and tilts the road by ~0.3 deg): the
    pairs' shifts take it back (each within 0.8 cm of +2 cm along image_00's axis), and the Velodyne's roll stays
    within 0.15 deg of the factory calibration."""
    rig, truth, start, scans = drive
    moved = Calibration(start.reference_sensor, dict(start.T_ref_sensor), dict(start.time_offset))
    for camera in ("image_01", "image_03"):
        T = np.array(moved.T_ref_sensor[camera], dtype=np.float64)
        T[2, 3] -= 0.02
        moved.T_ref_sensor[camera] = T
    placed = place_lidar(rig, moved, "velodyne", scans, ["image_01", "image_03"], log=lambda line: None)
    error = parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, placed.estimate.matrix(), 0.0)
    shifts = np.asarray(placed.shifts)
    print("error", error, "shifts", shifts)
    assert abs(np.rad2deg(error[3])) < 0.15, np.rad2deg(error[3])
    assert np.all(np.abs(shifts[:, 1] - 0.02) < 0.008), shifts


@needs_kitti_raw
def test_only_what_the_motion_left_undetermined_is_taken_without_its_sigma(drive):
    """Without the LiDAR-first stage's sigma, a LiDAR takes from the shared instants only the parameters that stage
    left undetermined: the lever arm and the roll move, the pitch and the yaw stay exactly."""
    rig, truth, start, scans = drive
    calibration = Calibration(start.reference_sensor, dict(start.T_ref_sensor), dict(start.time_offset))
    out = place_lidars(rig, calibration, ["image_01", "image_03"], {"velodyne": ["x", "y", "z", "roll"]}, {}, log=lambda line: None,
                      scans={"velodyne": scans})
    moved = np.abs(parameter_difference(start.T_ref_sensor["velodyne"], 0.0, calibration.T_ref_sensor["velodyne"], 0.0))
    assert out["velodyne"].taken == ["x", "y", "z", "roll"]
    assert np.all(moved[:3] > 0.2) and np.rad2deg(moved[3]) > 3.0  # the prior was 50 cm and 5.2 deg off on these
    assert np.all(moved[4:6] < 1e-9)
    assert calibration.time_offset["velodyne"] == start.time_offset["velodyne"]


@needs_kitti_raw
def test_a_motion_estimate_many_sigma_away_hands_over_every_placed_parameter(drive):
    """Where a parameter the motion determined lies more than 3 combined sigma from the shared instants' (here the
    prior's pitch and yaw, 5 deg off, given a motion sigma of 0.01 deg), the two are in different frames: the LiDAR takes
    every parameter the shared instants placed, pitch and yaw included, and ends within 0.3 deg of the factory's."""
    rig, truth, start, scans = drive
    calibration = Calibration(start.reference_sensor, dict(start.T_ref_sensor), dict(start.time_offset))
    tight = [0.001] * 3 + [np.deg2rad(0.01)] * 3 + [0.001]
    out = place_lidars(rig, calibration, ["image_01", "image_03"], {"velodyne": ["x", "y", "z", "roll"]}, {"velodyne": tight}, log=lambda line: None,
                      scans={"velodyne": scans})
    assert out["velodyne"].taken == out["velodyne"].placed and {"pitch", "yaw"} <= set(out["velodyne"].taken)
    error = np.abs(parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, calibration.T_ref_sensor["velodyne"], 0.0))
    assert np.all(np.rad2deg(error[3:6]) < 0.3), np.rad2deg(error[3:6])


@needs_kitti_raw
def test_a_motion_estimate_in_a_turned_frame_gives_the_trajectorys_turn(drive):
    """A motion estimate made in a trajectory frame turned by W from image_00 (``R_motion = W R_factory``; W 1.0 and
    -0.8 deg about image_00's x and y) with a tight motion sigma on pitch and yaw: the placement recovers W about the
    axes both determine within 0.3 deg (the placement's own error), nothing about the LiDAR's roll axis, which the motion
    left undetermined; ``trajectory_turn`` returns it as a rotation."""
    rig, truth, start, scans = drive
    turn = np.deg2rad([1.0, -0.8, 0.0])
    motion = np.array(truth.T_ref_sensor["velodyne"], dtype=np.float64)
    motion[:3, :3] = Rotation.from_rotvec(turn).as_matrix() @ motion[:3, :3]
    motion[:3, 3] = start.T_ref_sensor["velodyne"][:3, 3]
    calibration = Calibration(start.reference_sensor, {**start.T_ref_sensor, "velodyne": motion}, dict(start.time_offset))
    tight = [0.001] * 3 + [np.deg2rad(0.01)] * 3 + [0.001]
    out = place_lidars(rig, calibration, ["image_01", "image_03"], {"velodyne": ["x", "y", "z", "roll"]}, {"velodyne": tight}, log=lambda line: None,
                      scans={"velodyne": scans})
    found = np.array(out["velodyne"].turn)
    assert np.all(np.abs(np.rad2deg(found - turn)) < 0.3), np.rad2deg(found)
    assert abs(found @ motion[:3, 0]) < 1e-9  # nothing about the LiDAR's x (its roll axis), radians
    T = trajectory_turn(out, log=lambda line: None)
    np.testing.assert_allclose(T[:3, :3], Rotation.from_rotvec(found).as_matrix(), atol=1e-12)
    assert trajectory_turn({}, log=lambda line: None) is None


def test_a_parameter_placed_at_the_shared_instants_carries_their_sigma_and_the_time_offsets_along_the_drive():
    """``stage_sigma``: a taken lever-arm component is the placement's sigma with the time offset's sigma times the
    drive's velocity along it (a time offset error moves the placed lever arm along the drive); a taken angle is the
    placement's; what was not taken keeps the LiDAR-first sigma (the held prior's where it was held), at least the
    whole difference to the placement where that placed it (two estimates that disagree)."""
    entry = {"observability": [{"sigma": s} for s in (0.01, 0.02, 0.03, 0.001, 0.002, 0.003, 0.004)],
             "held_check": {"sigma_release": [0.0] * 7, "sigma_held": [0.5, 0.5, 0.5, 0.087, 0.0, 0.0, 0.0]},
             "shared_instant": {"taken": ["x", "z", "roll"], "sigma": [0.011, 0.012, 0.013, 0.0014, 0.0015, 0.0016, None],
                                "along_track": [0.1, 0.0, 7.8]}}
    sigma, source = stage_sigma(entry)
    np.testing.assert_allclose(sigma, [np.hypot(0.011, 0.1 * 0.004), 0.5, np.hypot(0.013, 7.8 * 0.004), 0.0014, 0.002, 0.003, 0.004])
    assert source.endswith("and the shared instants")
    # pitch placed there 0.6 deg from the motion's but kept at the motion's (not taken): at least their whole difference
    pitched = np.eye(4)
    pitched[:3, :3] = Rotation.from_rotvec([0.0, np.deg2rad(0.6), 0.0]).as_matrix()
    entry["T_ref_sensor"] = np.eye(4).tolist()
    entry["shared_instant"].update(placed=["x", "z", "roll", "pitch"], T_ref_sensor=pitched.tolist())
    sigma, _ = stage_sigma(entry)
    assert sigma[4] == pytest.approx(np.deg2rad(0.6), rel=1e-9) and sigma[5] == 0.003 and sigma[3] == 0.0014


def test_an_undetermined_parameter_is_taken_where_the_shared_instants_beat_the_motions_sigma(tmp_path, monkeypatch):
    """A parameter the motion left undetermined is taken from the shared instants when they place it (sigma below a
    typical prior error) or, less sharply, with a sigma below the motion's (the held prior's: KITTI raw 0048's
    along-track lever arm, 10 cm against 1 m); not when the motion's is the smaller, and not without the motion's
    sigma. Exact moves: the taken components change by the placement's, the others not at all."""
    from moisst_ns.datasets.synth import SynthConfig, make_rig
    from moisst_ns.stages.lidar import lidar_placement, lidar_scans
    from moisst_ns.stages.lidar.lidar_geometry import Extrinsic
    from moisst_ns.stages.lidar.lidar_instant import InstantPlacement

    rig = load_rig(make_rig(SynthConfig(out=tmp_path / "rig", seed=1, width=32, height=24, frames=2)))
    start = Calibration.from_rig(rig)
    T = np.asarray(start.T_ref_sensor["lidar"], dtype=np.float64)
    placement = InstantPlacement(Extrinsic(T[:3, :3], T[:3, 3] + [0.03, 0.04, 0.05], 0.0),
                                 [0.01, 0.02, 0.15] + [np.deg2rad(0.1)] * 3 + [float("nan")], ["x", "y", "roll", "pitch", "yaw"], 500, ["cam"])
    monkeypatch.setattr(lidar_placement, "place_lidar", lambda *args: replace(placement, taken=[]))
    monkeypatch.setattr(lidar_scans, "load_scans", lambda *args: None)
    held = [1.0, 1.0, 1.0, 0.17, np.deg2rad(0.01), np.deg2rad(0.01), 0.1]  # x, y, z, roll held at the prior
    for motion, taken in (({"lidar": held}, ["x", "y", "z", "roll"]), ({"lidar": held[:2] + [0.05] + held[3:]}, ["x", "y", "roll"]), ({}, ["x", "y", "roll"])):
        calibration = Calibration(start.reference_sensor, dict(start.T_ref_sensor), dict(start.time_offset))
        out = place_lidars(rig, calibration, ["cam"], {"lidar": ["x", "y", "z", "roll"]}, motion, log=lambda line: None)
        assert out["lidar"].taken == taken
        moved = np.asarray(calibration.T_ref_sensor["lidar"])[:3, 3] - T[:3, 3]
        np.testing.assert_allclose(moved, [0.03, 0.04, 0.05 if "z" in taken else 0.0], atol=1e-12)


def test_a_pairs_shifts_take_the_cameras_sigma_and_are_free_where_it_is_not_finite():
    """``shift_sigmas``: a camera 50 cm right of the reference camera, driving along its z at 8 m/s: the shift along
    the baseline takes x's sigma, the other z's and the time offset's (8 m/s x 1 ms) in quadrature, exactly; free (inf)
    without a sigma or where the lever arm's or the offset's is NaN or inf (on a straight drive a NaN there made the
    placement's solve fail: numpy's SVD did not converge)."""
    along, baseline = np.array([0.0, 0.0, 8.0]), np.array([0.5, 0.0, 0.0])
    sigma = [0.001, 0.002, 0.003, 0.02, 0.03, 0.04, 0.001]  # rad x3, m x3, s
    np.testing.assert_allclose(shift_sigmas(sigma, along, baseline), [0.02, np.hypot(0.04, 0.008)], rtol=1e-12)
    for k, bad in ((5, float("nan")), (6, float("inf")), (3, float("nan"))):
        assert np.all(np.isinf(shift_sigmas(sigma[:k] + [bad] + sigma[k + 1:], along, baseline)))
    assert np.all(np.isinf(shift_sigmas(None, along, baseline)))
    assert np.all(np.isfinite(shift_sigmas(sigma[:0] + [float("nan")] + sigma[1:], along, baseline)))  # a rotation's: not used


def test_the_cameras_that_may_pair_with_the_reference_camera(tmp_path):
    """``pairs_with_reference`` (what turns the LiDAR stage's depth-edge view off in the full pipeline): every
    non-reference camera whose prior lies 20 cm or more from the reference camera; one moved to 10 cm drops out; a
    LiDAR reference has none."""
    from moisst_ns.datasets.synth import SynthConfig, make_rig
    from moisst_ns.stages.lidar.lidar_instant import pairs_with_reference

    rig = load_rig(make_rig(SynthConfig(out=tmp_path / "rig", seed=1, width=32, height=24, frames=2)))
    assert pairs_with_reference(rig) == ["cam_front_right", "cam_left"]
    near = np.array(rig.sensors["cam_front_right"].T_ref_sensor, dtype=np.float64)
    near[:3, 3] = [0.1, 0.0, 0.0]
    rig.sensors["cam_front_right"] = replace(rig.sensors["cam_front_right"], T_ref_sensor=near)
    assert pairs_with_reference(rig) == ["cam_left"]
    assert pairs_with_reference(replace(rig, reference_sensor="lidar")) == []


@needs_kitti_raw
def test_placed_again_against_the_cameras_registered_again(drive):
    """``place_again``: the Velodyne placed first against stereo cameras turned 0.1 deg about their vertical axis
    (rotation errors of a first registration pass into the placement through the stereo geometry: 0.36 deg in pitch),
    then again against the factory cameras: it takes the same parameters, each exactly as a placement against the
    factory cameras from there gives it, keeps the first's turn, and ends within 0.15 deg per angle of the factory
    rotation (0.03 / 0.07 / 0.08 measured), from over 0.3 deg."""
    from moisst_ns.stages.lidar.lidar_placement import place_again

    rig, truth, start, scans = drive
    cameras = ["image_01", "image_03"]
    turned = Calibration(start.reference_sensor, dict(start.T_ref_sensor), dict(start.time_offset))
    for camera in cameras:
        T = np.array(turned.T_ref_sensor[camera], dtype=np.float64)
        T[:3, :3] = Rotation.from_rotvec(np.deg2rad([0.0, 0.1, 0.0])).as_matrix() @ T[:3, :3]
        turned.T_ref_sensor[camera] = T
    tight = [0.001] * 3 + [np.deg2rad(0.01)] * 3 + [0.001]
    first = place_lidars(rig, turned, cameras, {"velodyne": ["x", "y", "z", "roll"]}, {"velodyne": tight}, log=lambda line: None,
                      scans={"velodyne": scans})
    before = np.rad2deg(np.abs(parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, turned.T_ref_sensor["velodyne"], 0.0)[3:6]))
    calibration = Calibration(start.reference_sensor, {**start.T_ref_sensor, "velodyne": turned.T_ref_sensor["velodyne"]}, dict(start.time_offset))
    direct = place_lidar(rig, calibration, "velodyne", scans, cameras, log=lambda line: None)
    again = place_again(rig, calibration, first, cameras, log=lambda line: None, scans={"velodyne": scans})["velodyne"]
    assert again.taken == first["velodyne"].taken and again.turn == first["velodyne"].turn
    expected = parameter_difference(turned.T_ref_sensor["velodyne"], 0.0, direct.estimate.matrix(), 0.0)[:6]
    moved = parameter_difference(turned.T_ref_sensor["velodyne"], 0.0, calibration.T_ref_sensor["velodyne"], 0.0)[:6]
    for i, p in enumerate(["x", "y", "z", "roll", "pitch", "yaw"]):
        assert moved[i] == pytest.approx(expected[i] if p in again.taken else 0.0, abs=1e-9), p
    after = np.rad2deg(np.abs(parameter_difference(truth.T_ref_sensor["velodyne"], 0.0, calibration.T_ref_sensor["velodyne"], 0.0)[3:6]))
    print("before", before, "after", after, "taken", again.taken)
    assert before.max() > 0.3 and after.max() < 0.15, (before, after)
