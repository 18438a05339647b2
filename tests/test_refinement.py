"""The NeRF's joint refinement of registered cameras (``--camera-refinement``, issue 36) is judged on frames that no
training ray came from: a refinement that does not render them significantly better, or leaves the stage's 3 sigma,
goes back to the stage's estimate.

A small rig (128x96, 20 frames per sensor, seed 1, paper perturbation), 80 steps: the camera registration places
cam_front_right, the NeRF refines it with every fifth of its frames held back.
"""

import json

import numpy as np
import pytest
import roma
import torch

from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
from moisst_ns.data.datamanager import held_back_frames
from moisst_ns.datasets.synth import SynthConfig, make_rig
from moisst_ns.rig.format import load_calibration


@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    root = tmp_path_factory.mktemp("refine")
    rig = make_rig(SynthConfig(out=root / "rig", width=128, height=96, frames=20, seed=1, perturb="paper"))
    config_path = run_calibration(CalibrateConfig(dataset=rig, output_dir=root / "out", max_num_iterations=80, seed=0,
                                                  threads=1, camera_refinement=True, report=False))
    return rig, root / "out", config_path


def test_held_back_frames_are_every_fifth_frame_of_the_named_cameras_from_the_third():
    names = ["ref", "side", "lidar"]
    frame_sensor = [0, 1] * 12
    held = held_back_frames(names, frame_sensor, ("side",))
    side_frames = np.flatnonzero(np.asarray(frame_sensor) == 1)
    assert np.flatnonzero(held.numpy()).tolist() == side_frames[[2, 7]].tolist()
    assert not held_back_frames(names, frame_sensor, ()).any()
    with pytest.raises(ValueError, match="held_back_sensors"):
        held_back_frames(names, frame_sensor, ("rear",))


@pytest.mark.parametrize("step", [5, 40, 79])  # reference-only warm-up, registration, joint
def test_no_training_ray_comes_from_a_held_back_frame(refined, step):
    from nerfstudio.utils.eval_utils import eval_setup

    _, out, config_path = refined
    config, _, _, _ = eval_setup(config_path, test_mode="inference")
    dm_config = config.pipeline.datamanager
    stage = json.loads((out / "camera_registration" / "camera_registration.json").read_text())["sensors"]
    accepted = tuple(n for n, e in stage.items() if not e["kept_prior"])  # the cameras the stage registered are refined
    assert "cam_front_right" in accepted and dm_config.held_back_sensors == accepted
    torch.manual_seed(0)
    datamanager = dm_config.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)
    held = datamanager.held_back
    assert int(held.sum()) == 4 * len(accepted)  # frames 2, 7, 12, 17 of each one's 20
    drawn = torch.cat([datamanager.next_train(step)[1]["indices"][:, 0] for _ in range(20)])
    assert not held[drawn].any()
    if step >= 40:  # past the reference-only warm-up, the camera's other frames are drawn
        sensor = torch.as_tensor(datamanager.rig.frame_sensor_index)[drawn]
        assert (sensor == datamanager.rig.sensor_names.index("cam_front_right")).any()


def test_the_run_keeps_a_refinement_only_where_the_held_back_frames_say_so(refined):
    from nerfstudio.utils.eval_utils import eval_setup

    rig, out, config_path = refined
    check = json.loads((out / "summary.json").read_text())["refinement"]["cam_front_right"]
    assert check["frames"] == 4
    assert check["kept"] == (check["p_value"] < 0.05 and check["loss_refined"] < check["loss_stage"]
                             and not check["beyond_3_sigma"] and not check["still_moving"])
    written = load_calibration(out / "calibration.json")
    stage = load_calibration(out / "camera_registration" / "calibration.json")
    _, pipeline, _, _ = eval_setup(config_path, test_mode="inference")
    loaded = pipeline.model.camera_optimizer.rig.estimate()
    kept_by_the_run = loaded if check["kept"] else stage  # a refinement set back is saved back into the checkpoint
    assert np.allclose(written.T_ref_sensor["cam_front_right"], kept_by_the_run.T_ref_sensor["cam_front_right"], atol=1e-9)
    assert written.time_offset["cam_front_right"] == pytest.approx(kept_by_the_run.time_offset["cam_front_right"], abs=1e-9)
    assert np.allclose(loaded.T_ref_sensor["cam_front_right"], written.T_ref_sensor["cam_front_right"], atol=1e-6)


def test_refinement_check_refuses_a_worse_estimate_and_accepts_a_better_one(refined):
    from nerfstudio.utils.eval_utils import eval_setup

    from moisst_ns.uncertainty import refinement_check

    _, _, config_path = refined
    _, pipeline, _, _ = eval_setup(config_path, test_mode="inference")
    rig = pipeline.model.camera_optimizer.rig
    i = rig.data.sensor_names.index("cam_front_right")
    turn = torch.tensor([0.0, np.deg2rad(6.0), 0.0])  # what 4 frames of an 80-step 128x96 scene tell apart
    with torch.no_grad():
        rig.translation[i], rig.rotvec[i], rig.time_offset[i], rig.trainable[i] = 0.0, 0.0, 0.0, True
        stage_pose = rig.extrinsics()[i].clone()
        rig.rotvec[i] = turn  # "refined" 6 deg from the stage's estimate the scene was trained with
    worse = refinement_check(pipeline, ["cam_front_right"], seed=0)["cam_front_right"]
    assert not worse["kept"] and worse["loss_refined"] > worse["loss_stage"]
    with torch.no_grad():  # now the start (the prior) is that pose and the correction brings it back
        rig.prior_extrinsics[i, :3, :3] = stage_pose[:3, :3] @ roma.rotvec_to_rotmat(turn.double())
        rig.rotvec[i] = -turn
        assert torch.allclose(rig.extrinsics()[i], stage_pose, atol=1e-6)
    better = refinement_check(pipeline, ["cam_front_right"], seed=0)["cam_front_right"]
    assert better["kept"] and better["p_value"] < 0.05
    assert (better["loss_refined"], better["loss_stage"]) == pytest.approx((worse["loss_stage"], worse["loss_refined"]), rel=1e-4)
