"""The LiDAR map's range as a metric depth target for camera rays (``stages.map_range``, ``losses.map_range_loss``,
``MoisstDataManager.map_range_sensors``)."""

import numpy as np
import pytest
import torch

from moisst_ns.datasets.synth import SynthConfig, make_rig
from moisst_ns.floor import synthetic_scene
from moisst_ns.losses import map_range_loss
from moisst_ns.method_configs import moisst_trainer_config
from moisst_ns.stages.camera.map_range import opengl_to_opencv, range_image


def test_a_point_lands_in_its_pixel_with_its_euclidean_range():
    # u = fx x / z + cx = 10 * 1 / 2 + 4 = 9 -> column 9; v = 10 * -0.5 / 2 + 3 = 0.5 -> row 0
    image = range_image(np.array([[1.0, -0.5, 2.0]]), 10.0, 10.0, 4.0, 3.0, 12, 6, window=1)
    assert image.shape == (6, 12) and image.dtype == np.float32
    assert image[0, 9] == pytest.approx(np.sqrt(1 + 0.25 + 4), rel=1e-6)
    assert np.isfinite(image).sum() == 1


def test_a_distorted_camera_puts_the_point_where_its_lens_images_it():
    # x = 0.5, y = -0.25, r = 0.3125; k1 = -0.5: factor 0.84375 -> u = 10 * 0.421875 + 4 = 8.22 (column 8, not the
    # pinhole's 9), v = 10 * -0.2109 + 3 = 0.89 (row 0); k2 = 0.2 adds 0.2 r^2 = 0.0195 to the factor: u = 8.32
    for distortion, column in (((-0.5, 0.0, 0.0, 0.0, 0.0, 0.0), 8), ((-0.5, 0.2, 0.0, 0.0, 0.0, 0.0), 8), ((0.0,) * 6, 9)):
        image = range_image(np.array([[1.0, -0.5, 2.0]]), 10.0, 10.0, 4.0, 3.0, 12, 6, window=1, distortion=distortion)
        assert image[0, column] == pytest.approx(np.sqrt(1 + 0.25 + 4), rel=1e-6) and np.isfinite(image).sum() == 1
    # tangential: p1 = 0.1 moves x by 2 p1 x y = -0.025 (u = 8.75, column 8) and y by p1 (r + 2 y^2) = 0.04375 (v = 0.94)
    image = range_image(np.array([[1.0, -0.5, 2.0]]), 10.0, 10.0, 4.0, 3.0, 12, 6, window=1, distortion=(0.0, 0.0, 0.0, 0.0, 0.1, 0.0))
    assert np.isfinite(image[0, 8]) and np.isfinite(image).sum() == 1


def test_a_point_far_outside_the_image_does_not_fold_back_into_it_through_the_lens():
    # x = 1.55 (56 deg off axis), k1 = -0.5: factor 1 - 0.5 * 1.55^2 = -0.20, so the polynomial puts it at u = 0.88
    # (column 0) although the pinhole puts it at u = 19.5, beyond the image's 50 % margin: no range there
    point = np.array([[3.1, 0.0, 2.0]])
    image = range_image(point, 10.0, 10.0, 4.0, 3.0, 12, 6, window=1, distortion=(-0.5, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert not np.isfinite(image).any()
    # a point inside the image still goes through the lens: x = 0.5, factor 0.875, u = 8.38 (column 8, row 3)
    near = range_image(np.array([[1.0, 0.0, 2.0]]), 10.0, 10.0, 4.0, 3.0, 12, 6, window=1, distortion=(-0.5, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert np.isfinite(near[3, 8])


def test_the_nearest_point_of_a_pixel_wins_and_points_behind_or_outside_are_dropped():
    points = np.array([[0.0, 0.0, 4.0], [0.0, 0.0, 3.0], [0.0, 0.0, -3.0], [100.0, 0.0, 1.0]])
    image = range_image(points, 10.0, 10.0, 2.5, 2.5, 5, 5, window=1)
    assert image[2, 2] == pytest.approx(3.0)
    assert np.isfinite(image).sum() == 1


def test_a_far_surface_does_not_show_through_the_gaps_of_a_near_one():
    near = np.array([[x, y, 10.0] for x in np.arange(-4.0, 4.01, 2.0) for y in np.arange(-4.0, 4.01, 2.0)])  # every 10th pixel
    far = np.array([[x, y, 40.0] for x in np.arange(-16.0, 16.0, 0.2) for y in np.arange(-16.0, 16.0, 0.2)])  # every pixel
    unfiltered = range_image(np.r_[near, far], 50.0, 50.0, 25.0, 25.0, 50, 50, window=1)
    filtered = range_image(np.r_[near, far], 50.0, 50.0, 25.0, 25.0, 50, 50, window=11)
    # the near wall's points land on pixels 5, 15, ..., 45 of both axes, at ranges 10 to sqrt(4^2 + 4^2 + 10^2) = 11.49
    assert np.nanmax(unfiltered[5:46, 5:46]) > 39.0  # the far wall fills the near wall's gaps
    inner = filtered[5:46, 5:46]
    assert np.nanmax(inner) < 11.5 and np.isfinite(inner).sum() == 25  # only the near wall's own points remain


def test_opengl_pose_to_opencv_points():
    c2w = np.array([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]])  # looks along world -z
    cam = opengl_to_opencv(c2w, np.array([[1.5, 2.0, 1.0]]))  # 2 in front, 0.5 to the right
    np.testing.assert_allclose(cam, [[0.5, 0.0, 2.0]])


def test_map_range_loss_is_huber_in_metres_over_the_rays_with_a_range():
    depth = torch.tensor([2.0, 2.0, 2.0, 2.0])
    target = torch.tensor([2.05, 3.0, float("nan"), 2.0])  # model units, 2 units per metre
    # errors in metres: -0.025 (quadratic: 0.5 e^2), -0.5 (linear: 0.2 (0.5 - 0.1)), none, 0
    expected = (0.5 * 0.025**2 + 0.2 * (0.5 - 0.1) + 0.0) / 3
    assert float(map_range_loss(depth, target, units_per_metre=2.0)) == pytest.approx(expected, rel=1e-6)
    none = map_range_loss(depth.requires_grad_(), torch.full((4,), float("nan")), 2.0)
    assert float(none) == 0.0 and none.requires_grad


@pytest.fixture(scope="module")
def rig_and_datamanager(tmp_path_factory):
    root = make_rig(SynthConfig(out=tmp_path_factory.mktemp("mr") / "rig", width=64, height=48, frames=8, seed=1, perturb="none"))
    config = moisst_trainer_config("moisst-lite", 100)
    dm = config.pipeline.datamanager
    dm.data = dm.dataparser.data = root
    dm.map_range_sensors = ("cam_front",)
    dm.train_num_rays_per_batch = 4096
    torch.manual_seed(0)
    return root, dm.setup(device="cpu", test_mode="val", world_size=1, local_rank=0)


def test_map_ranges_are_the_true_surface_along_the_training_rays(rig_and_datamanager):
    root, datamanager = rig_and_datamanager
    ray_bundle, batch = datamanager.next_train(10**6)  # past every warm-up: all cameras sampled
    camera = batch["ray_layout"].camera
    frame_sensor = [datamanager.rig.sensor_names[i] for i in datamanager.rig.frame_sensor_index[batch["indices"][:, 0].long().numpy()]]
    is_reference = np.array([s == "cam_front" for s in frame_sensor])
    target = batch["map_range"].numpy()
    assert is_reference.any() and (~is_reference).any()
    assert np.isnan(target[~is_reference]).all()  # only the listed camera gets targets
    has = is_reference & np.isfinite(target)
    assert has.sum() > 0.3 * is_reference.sum()
    world = datamanager.rig.world
    origins = ray_bundle.origins[camera].double().numpy() / world.scale + np.asarray(world.center)
    dirs = ray_bundle.directions[camera].double().numpy()
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    scene = synthetic_scene(root)
    hit = scene.cast(origins[has], dirs[has])["t_hit"].astype(np.float64)
    error = np.abs(target[has] / world.scale - hit)
    assert np.median(error) < 0.05 and np.percentile(error, 75) < 0.15  # metres, 5 cm map voxels on 64x48 pixels


def test_the_map_range_loss_starts_with_the_depth_loss_and_trains_the_scene(tmp_path):
    rig = make_rig(SynthConfig(out=tmp_path / "rig", width=48, height=36, frames=6, seed=1, perturb="none"))
    config = moisst_trainer_config("moisst-lite", 100)
    config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = rig
    config.pipeline.datamanager.map_range_sensors = ("cam_front",)
    config.pipeline.model.map_range_mult = 1.0
    config.pipeline.lidar_first = config.pipeline.camera_registration = False  # the LiDAR prior is the truth here
    config.output_dir, config.experiment_name, config.timestamp, config.vis = tmp_path / "out", ".", "run", "tensorboard"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline, model = trainer.pipeline, trainer.pipeline.model
    start = model.config.depth_loss_start
    assert start > 0
    model._update_schedule(start - 1)
    _, before, _ = pipeline.get_train_loss_dict(step=start - 1)
    assert "map_range_loss" not in before
    late = start + model.config.depth_loss_ramp_steps + 1
    model._update_schedule(late)
    _, after, _ = pipeline.get_train_loss_dict(step=late)
    assert "map_range_loss" in after and float(after["map_range_loss"]) > 0.0
    field = [p for p in model.field.parameters() if p.requires_grad]
    grads = torch.autograd.grad(after["map_range_loss"], field, allow_unused=True)
    assert any(g is not None and float(g.abs().sum()) > 0 for g in grads)
