"""Camera ray sampling: a share of the rays in P x P patches (for the eq. 13 patch losses), the rest single pixels."""

import pytest
import torch

from moisst_ns.method_configs import moisst_trainer_config
from moisst_ns.datasets.synth import SynthConfig, make_rig


@pytest.fixture(scope="module")
def datamanager(tmp_path_factory):
    root = make_rig(SynthConfig(out=tmp_path_factory.mktemp("dm") / "rig", width=48, height=36, frames=6, seed=2))
    config = moisst_trainer_config("moisst-lite", 100)
    dm_config = config.pipeline.datamanager
    dm_config.patch_size = 4  # moisst-lite's default is 1 (no patch losses); moisst's is 8
    dm_config.train_num_rays_per_batch = 512  # nerfstudio's patch sampler alone would round this to 0
    dm_config.data = root
    dm_config.dataparser.data = root
    torch.manual_seed(0)
    return dm_config.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)


@pytest.mark.parametrize("step", [10, 50, 90])  # reference-only warm-up, registration, joint
def test_quarter_of_the_camera_rays_are_patches(datamanager, step):
    _, batch = datamanager.next_train(step)
    patch = datamanager.config.patch_size
    assert datamanager.config.patch_fraction == 0.25
    total = datamanager.config.train_num_rays_per_batch
    layout = batch["ray_layout"]
    n_patch = layout.num_patch
    assert n_patch == total // 4 and layout.num_camera == total and batch["image"].shape[0] == total
    assert layout.patch_size == patch and layout.has_patches
    patches = batch["indices"][:n_patch].view(-1, patch, patch, 3)
    # one image per patch, rows and columns consecutive
    assert (patches[..., 0] == patches[:, :1, :1, 0]).all()
    assert (patches[:, 1:, :, 1] - patches[:, :-1, :, 1] == 1).all()
    assert (patches[:, :, 1:, 2] - patches[:, :, :-1, 2] == 1).all()
    # the single pixels are spread: far more distinct locations than patches
    pixels = batch["indices"][n_patch:]
    assert len({tuple(p) for p in pixels.tolist()}) > 0.9 * len(pixels)
    reference = datamanager.frame_is_reference[batch["indices"][:, 0].long()]
    if step < datamanager.config.reference_only_steps:
        assert reference.all()
    elif step < datamanager.config.registration_steps:
        assert reference[:n_patch].float().mean() == pytest.approx(0.5, abs=1 / 16)
        assert reference[n_patch:].float().mean() == pytest.approx(0.5, abs=0.01)
