"""CalibrationOptimizer: identity at zero correction, exact ray regeneration, gradients to extrinsic and delta."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from moisst_ns.calibration_optimizer import CalibrationOptimizer, CalibrationOptimizerConfig
from moisst_ns.data.dataparser import MoisstRigDataParserConfig
from moisst_ns.rig.format import load_calibration
from moisst_ns.datasets.synth import SynthConfig, build_scene, make_rig


@pytest.fixture(scope="module")
def rig_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("rig") / "rig"
    make_rig(SynthConfig(out=out, width=64, height=48, frames=8, perturb="paper", lidar=False))
    return out


def setup(rig_dir, data_dir=None):
    outputs = MoisstRigDataParserConfig(data=data_dir or rig_dir).setup().get_dataparser_outputs("train")
    opt = CalibrationOptimizer(
        CalibrationOptimizerConfig(), num_cameras=len(outputs.cameras), device="cpu", rig=outputs.metadata["moisst_rig"]
    )
    return outputs, opt


def test_zero_correction_is_identity(rig_dir):
    outputs, opt = setup(rig_dir)
    idx = torch.arange(len(outputs.cameras))
    assert torch.allclose(opt(idx), torch.eye(4)[:3, :4].expand(len(idx), 3, 4), atol=1e-6)
    bundle = outputs.cameras.generate_rays(camera_indices=torch.tensor([[3]]), keep_shape=False)
    before_o, before_d = bundle.origins.clone(), bundle.directions.clone()
    opt.apply_to_raybundle(bundle)
    assert torch.allclose(bundle.origins, before_o, atol=1e-6) and torch.allclose(bundle.directions, before_d, atol=1e-6)


def test_regenerated_rays_hit_what_the_synthetic_camera_saw(rig_dir):
    """With the calibration set to the truth, a regenerated ray reaches the surface point the renderer hit."""
    outputs, opt = setup(rig_dir)
    truth = load_calibration(rig_dir / "ground_truth.json")
    meta = json.loads((rig_dir / "rig.json").read_text())["metadata"]
    scene = build_scene(SynthConfig(out=rig_dir, **{k: meta[k] for k in ("seed", "frames", "width", "height", "layout") if k in meta}))
    opt.rig.set_corrections_to(truth)
    data = outputs.metadata["moisst_rig"]
    scale, center = data.world.scale, data.world.center
    for cam_idx in range(0, len(outputs.cameras), 5):
        bundle = outputs.cameras.generate_rays(camera_indices=torch.tensor([[cam_idx]]), keep_shape=False)
        opt.apply_to_raybundle(bundle)
        origins = bundle.origins.detach().double().numpy() / scale + center
        directions = bundle.directions.detach().double().numpy()
        # the same pixel rays straight from eq. 2 with the true calibration, in metres (OpenCV camera)
        sensor = int(data.frame_sensor_index[cam_idx])
        name = data.sensor_names[sensor]
        pose = opt.rig.reference_pose(torch.tensor(data.frame_stamps[cam_idx] + truth.time_offset[name], dtype=torch.float64))
        world_T_cam = (pose @ torch.as_tensor(truth.T_ref_sensor[name])).numpy()
        assert np.allclose(origins, world_T_cam[:3, 3], atol=1e-4)
        k = outputs.cameras[cam_idx]
        rgb, _ = scene.colour(origins, directions, 1.0 / float(k.fx))
        rendered = np.clip(rgb, 0, 1) * 255.0
        stored = np.asarray(Image.open(outputs.image_filenames[cam_idx]).convert("RGB"), dtype=np.float64).reshape(-1, 3)
        assert np.abs(rendered - stored).mean() < 1.0, name
        # and with the (perturbed) priors the same rays see something else
        prior_origins = outputs.cameras.generate_rays(camera_indices=torch.tensor([[cam_idx]]), keep_shape=False)
        if sensor != data.reference_index:
            rgb_prior, _ = scene.colour(prior_origins.origins.double().numpy() / scale + center, prior_origins.directions.double().numpy(), 1.0 / float(k.fx))
            assert np.abs(np.clip(rgb_prior, 0, 1) * 255.0 - stored).mean() > 5.0


def test_gradients_reach_extrinsic_and_time_offset(rig_dir):
    """d(origin)/d(translation) = scale * world_R_ref and d(origin)/d(delta) = scale * sensor velocity (finite differences)."""
    outputs, opt = setup(rig_dir)
    data = outputs.metadata["moisst_rig"]
    scale = data.world.scale
    cam_idx = int(np.nonzero(data.frame_sensor_index != data.reference_index)[0][2])
    sensor = int(data.frame_sensor_index[cam_idx])
    bundle = outputs.cameras.generate_rays(camera_indices=torch.tensor([[cam_idx]]), keep_shape=False)[:4]
    opt.apply_to_raybundle(bundle)
    origin = bundle.origins[0]
    jac_t = torch.stack([torch.autograd.grad(origin[k], opt.rig.translation, retain_graph=True)[0][sensor] for k in range(3)])
    # the translation correction lives in the reference frame: d(origin)/d(t) = scale * world_R_ref(t + delta)
    stamp = torch.tensor(data.frame_stamps[cam_idx], dtype=torch.float64)
    world_R_ref = opt.rig.reference_pose(stamp + opt.rig.time_offsets()[sensor])[:3, :3].detach().float()
    assert torch.allclose(jac_t, scale * world_R_ref, atol=1e-5)
    grad_delta = torch.stack([torch.autograd.grad(origin[k], opt.rig.time_offset, retain_graph=True)[0][sensor] for k in range(3)])
    eps = 1e-4
    with torch.no_grad():
        c2w = lambda: opt.frame_c2w(torch.tensor([cam_idx]))[0, :3, 3]
        opt.rig.time_offset[sensor] += eps
        plus = c2w()
        opt.rig.time_offset[sensor] -= 2 * eps
        minus = c2w()
        opt.rig.time_offset[sensor] += eps
    assert torch.allclose(grad_delta.double(), (plus - minus) / (2 * eps), rtol=1e-3, atol=1e-5)
    assert grad_delta.norm() > 0.5 * scale  # the rig moves at metres per second: delta is observable
    # a rotation correction turns the rays: their directions depend on rotvec
    (grad_rot,) = torch.autograd.grad(bundle.directions.sum(), opt.rig.rotvec, retain_graph=True)
    assert grad_rot[sensor].abs().sum() > 0 and grad_rot[data.reference_index].abs().sum() == 0


def test_reference_sensor_is_never_moved(rig_dir):
    outputs, opt = setup(rig_dir)
    ref = opt.rig.data.reference_index
    with torch.no_grad():
        opt.rig.translation.fill_(0.3)
        opt.rig.rotvec.fill_(0.1)
        opt.rig.time_offset.fill_(0.05)
    ext = opt.rig.extrinsics()
    assert torch.equal(ext[ref], torch.eye(4, dtype=torch.float64))
    assert float(opt.rig.time_offsets()[ref]) == 0.0


def test_bounds_project_runaway_parameters(rig_dir):
    outputs, opt = setup(rig_dir)
    with torch.no_grad():
        opt.rig.time_offset.fill_(5.0)
        opt.rig.translation.fill_(-9.0)
        opt.rig.rotvec.fill_(3.0)
    opt.project()
    cfg = opt.config
    assert float(opt.rig.time_offset.max()) == pytest.approx(cfg.max_time_offset)
    assert float(opt.rig.translation.min()) == pytest.approx(-cfg.max_translation)
    assert float(opt.rig.rotvec.norm(dim=-1).max()) == pytest.approx(np.deg2rad(cfg.max_rotation_deg), rel=1e-5)


def test_apply_to_camera_gives_calibrated_pose(rig_dir):
    outputs, opt = setup(rig_dir)
    with torch.no_grad():
        opt.rig.translation[1] = torch.tensor([0.1, -0.2, 0.05])
    for idx in range(len(outputs.cameras)):
        camera = outputs.cameras[idx : idx + 1]
        camera.metadata["cam_idx"] = idx
        got = opt.apply_to_camera(camera)
        expected = (outputs.cameras.camera_to_worlds[idx].double() @ torch.cat([opt(torch.tensor([idx]))[0].double(), torch.tensor([[0, 0, 0, 1.0]], dtype=torch.float64)]))
        assert torch.allclose(got[0].double(), expected, atol=1e-5)
