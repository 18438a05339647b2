"""``ns-train moisst`` (paper settings) and ``ns-train moisst-lite`` (2 CPU cores), plus the ``moisst-rig`` dataparser.

Schedules are fractions of the run, built for the method's default length and rescaled to another
(``schedules.rescale_schedules``): here for ``moisst-calibrate --max-num-iterations N``, by the model at set-up for
``ns-train ... --max-num-iterations N``, with the same rounding. The pipeline is ``MoisstPipeline`` (the stages before
the NeRF, calibration.json after it), trained by ``MoisstTrainer``.
"""

from __future__ import annotations

import torch

from nerfstudio.configs.base_config import LoggingConfig, MachineConfig, ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.plugins.types import MethodSpecification

from moisst_ns.data.datamanager import MoisstDataManagerConfig
from moisst_ns.data.dataparser import MoisstRigDataParserConfig
from moisst_ns.model import MoisstModelConfig
from moisst_ns.pipeline import MoisstPipelineConfig, MoisstTrainer
from moisst_ns.schedules import rescale_schedules

DEFAULT_ITERATIONS = {"moisst": 30000, "moisst-lite": 1500}
SCENE_STEPS = {"moisst": 10000, "moisst-lite": 2000}
"""``moisst-calibrate``'s NeRF steps when the stages hold every sensor (the scene only): at 500 the rendered depth ran
2.2-2.7 m from the LiDAR's at the reference camera; at 2000, with the LiDAR map's range, 0.09-0.27 m on idealised
street and plaza and realistic street rigs, 2.4 m on a realistic plaza whose LiDAR the stage left 71 cm off
(docs/lab/2026-11-23-metric-scene.md)."""


def _adam_decay(lr: float, steps: int, weight_decay: float = 0.0, final_factor: float = 1e-2) -> dict:
    """Adam with an exponential decay to ``final_factor`` of the initial rate over the run (paper IV)."""
    return {
        "optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15, weight_decay=weight_decay),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr * final_factor, max_steps=steps),
    }


def moisst_trainer_config(method: str = "moisst", max_num_iterations: int | None = None) -> TrainerConfig:
    """Build the trainer config of ``moisst`` or ``moisst-lite`` for a given run length.

    ``moisst`` follows paper IV: Adam, network lr 1e-2, exponential decay of every rate to 1e-2 of its start,
    weight decay 1e-6 on the network including the hash grid, the grid's removed after 5 of 50 epochs (10 %).
    The calibration rates are in our metric units (metres, radians, seconds). ``moisst-lite`` is the 2-core CPU
    preset: fewer rays and samples, a smaller grid, a reference-only warm-up and a coarse-to-fine hash release.
    """
    if method not in DEFAULT_ITERATIONS:
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(DEFAULT_ITERATIONS)}")
    steps, default = max_num_iterations or DEFAULT_ITERATIONS[method], DEFAULT_ITERATIONS[method]
    lite = method == "moisst-lite"
    device = "cuda" if torch.cuda.is_available() else "cpu"
    model = MoisstModelConfig(
        eval_num_rays_per_chunk=1 << 12 if lite else 1 << 15,
        average_init_density=0.01,
        hash_weight_decay_steps=int(0.1 * default),
        depth_loss_start=int(0.04 * default),
        depth_loss_ramp_steps=int(0.05 * default),
        schedule_steps=default,
    )
    datamanager = MoisstDataManagerConfig(
        dataparser=MoisstRigDataParserConfig(),
        lidar_rays_per_batch=256 if lite else 1024,
        train_num_rays_per_batch=1024 if lite else 4096,
        # The patch losses of eq. 13 (DSSIM, depth smoothness) use a quarter of the camera rays (``patch_fraction``),
        # sampled as P x P patches. On for `moisst` (the paper's losses); off for `moisst-lite` (--patch-size 4 turns them on),
        # because at its budget they measured worse (docs/method.md, "Schedules", item 6).
        patch_size=1 if lite else 8,
        eval_num_rays_per_batch=1024 if lite else 4096,
    )
    if lite:
        model.num_proposal_samples_per_ray = (64, 32)
        model.num_nerf_samples_per_ray = 24
        model.num_levels = 12
        model.log2_hashmap_size = 15
        model.max_res = 1024
        model.proposal_net_args_list = [
            {"hidden_dim": 16, "log2_hashmap_size": 15, "num_levels": 5, "max_res": 128, "use_linear": False},
            {"hidden_dim": 16, "log2_hashmap_size": 15, "num_levels": 5, "max_res": 256, "use_linear": False},
        ]
        model.calibration_warmup_steps = int(0.2 * default)
        model.depth_loss_start = model.calibration_warmup_steps
        model.registration_steps = int(0.7 * default)
        datamanager.reference_only_steps = model.calibration_warmup_steps
        datamanager.registration_steps = model.registration_steps
        model.reference_only_warmup = True
        model.coarse_to_fine = (int(0.2 * default), int(0.7 * default))
    datamanager.lidar_start_step = model.depth_loss_start
    # Calibration rates (Adam moves a parameter at most ~lr per step): radians, metres, seconds.
    rot_lr, trans_lr, time_lr = (3e-3, 1e-2, 3e-3) if lite else (1e-3, 3e-3, 1e-3)
    # Every rate decays to 1 % over the run, as in the paper (``_adam_decay``). (Decaying the calibration rates only to
    # 10 % helped the tiny test rig but made the 320x240 rig worse: 64 cm / 2.4 deg / 79 ms vs 80-89 cm / 1.3-1.6 deg /
    # 56 ms for the forward-right camera, so the paper's decay is kept.)
    config = TrainerConfig(
        _target=MoisstTrainer,
        method_name=method,
        steps_per_eval_batch=10**9 if lite else 500,
        steps_per_eval_image=10**9 if lite else 500,
        steps_per_eval_all_images=10**9,
        steps_per_save=max(steps // 3, 100) if lite else 2000,
        max_num_iterations=steps,
        machine=MachineConfig(device_type=device),
        logging=LoggingConfig(steps_per_log=25 if lite else 100),
        pipeline=MoisstPipelineConfig(datamanager=datamanager, model=model),
        optimizers={  # one config object per group: ``rescale_schedules`` rescales each
            **{group: _adam_decay(1e-2, default, weight_decay=1e-6) for group in ("proposal_networks", "fields", "hash_grids")},
            **{f"calibration_{part}": _adam_decay(lr, default) for part, lr in zip(("rotation", "translation", "time"), (rot_lr, trans_lr, time_lr))},
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 12 if lite else 1 << 15, websocket_host="127.0.0.1"),
        vis="viewer",
    )
    if steps != default:  # the rounding of ``ns-train ... --max-num-iterations N`` (the model rescales so at set-up)
        rescale_schedules(config, default, steps)
    return config


moisst_method = MethodSpecification(
    config=moisst_trainer_config("moisst"),
    description="MOISST spatiotemporal calibration of camera rigs (paper settings).",
)

moisst_lite_method = MethodSpecification(
    config=moisst_trainer_config("moisst-lite"),
    description="MOISST calibration, lean preset for a few CPU cores.",
)
