"""What a user would otherwise try: plain nerfacto on the same rig, with the same field settings as a MOISST
preset, and nerfacto's own per-frame pose optimiser (``SO3xR3``) or none. Used by ``moisst-bench``.

The cameras start at the priors (the ``moisst-rig`` dataparser poses them with eq. 2 and the prior calibration);
nerfacto then corrects every frame independently. Its per-frame poses, mapped back to metres, are compared with the
true per-frame poses (paper Table VI style).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Literal, Type

import numpy as np
import torch

from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.configs.base_config import LoggingConfig, MachineConfig, ViewerConfig
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

from moisst_ns.data.dataparser import MoisstRigDataParserConfig
from moisst_ns.method_configs import _adam_decay, moisst_trainer_config
from moisst_ns.compat import without_lpips


@dataclass
class OfflineNerfactoModelConfig(NerfactoModelConfig):
    """Stock nerfacto, minus LPIPS (its weights would be downloaded)."""

    _target: Type = field(default_factory=lambda: OfflineNerfactoModel)


class OfflineNerfactoModel(NerfactoModel):
    """Stock nerfacto, minus LPIPS."""

    def populate_modules(self):
        with without_lpips():
            super().populate_modules()


def nerfacto_trainer_config(preset: Literal["moisst", "moisst-lite"], steps: int, pose_optimizer: Literal["off", "SO3xR3"],
                            rays: int | None = None) -> TrainerConfig:
    """nerfacto with exactly the field, sampling and ray settings of a MOISST preset.

    Args:
        preset: the MOISST preset whose field settings to copy.
        steps: training steps.
        pose_optimizer: nerfacto's per-frame pose optimiser (``SO3xR3``, its default) or ``off``.
        rays: camera rays per step (the preset's when None).
    """
    moisst = moisst_trainer_config(preset, steps)
    src = moisst.pipeline.model
    shared = {f.name: getattr(src, f.name) for f in fields(NerfactoModelConfig) if f.name not in ("_target", "camera_optimizer")}
    model = OfflineNerfactoModelConfig(**shared)
    model.camera_optimizer = CameraOptimizerConfig(mode=pose_optimizer)
    num_rays = rays or moisst.pipeline.datamanager.train_num_rays_per_batch
    datamanager = VanillaDataManagerConfig(dataparser=MoisstRigDataParserConfig(), train_num_rays_per_batch=num_rays,
                                           eval_num_rays_per_batch=num_rays)
    optimizers = {
        "proposal_networks": _adam_decay(1e-2, steps, weight_decay=1e-6),
        "fields": _adam_decay(1e-2, steps, weight_decay=1e-6),
        # nerfacto's own camera_opt schedule (lr 1e-3 decaying to 1e-4), stretched over the run
        "camera_opt": _adam_decay(1e-3, steps, final_factor=0.1),
    }
    return TrainerConfig(
        method_name=f"nerfacto-{'lite' if preset == 'moisst-lite' else 'full'}",
        steps_per_eval_batch=10**9, steps_per_eval_image=10**9, steps_per_eval_all_images=10**9,
        steps_per_save=10**9, max_num_iterations=steps, mixed_precision=False, use_grad_scaler=False,
        save_only_latest_checkpoint=True, machine=MachineConfig(device_type=moisst.machine.device_type),
        logging=LoggingConfig(steps_per_log=moisst.logging.steps_per_log),
        pipeline=VanillaPipelineConfig(datamanager=datamanager, model=model),
        optimizers=optimizers, viewer=ViewerConfig(quit_on_train_completion=True), vis="tensorboard",
    )


@dataclass
class NerfactoResult:
    """A finished nerfacto run: per-frame poses (metres, OpenCV axes, dataset world), and its timing."""

    poses: np.ndarray
    """(N, 4, 4) ``world_T_camera`` of every training frame."""
    frame_sensor_index: np.ndarray
    """(N,) sensor index of each frame (``RigData.sensor_names``)."""
    frame_stamps: np.ndarray
    """(N,) own-clock stamps relative to the rig's t0."""
    seconds_per_step: float
    """Training wall time / steps."""


def run_nerfacto(dataset: Path, out: Path, preset: Literal["moisst", "moisst-lite"], steps: int,
                 pose_optimizer: Literal["off", "SO3xR3"], rays: int | None = None) -> NerfactoResult:
    """Train nerfacto (seed 0) on a ``moisst-rig/1`` dataset and return its per-frame camera poses in metres."""
    from moisst_ns.calibrate import place_run
    from moisst_ns.stage_run import set_up_trainer

    config = place_run(nerfacto_trainer_config(preset, steps, pose_optimizer, rays), Path(dataset), Path(out), "run", 0)
    trainer = set_up_trainer(config, 0)
    start = time.perf_counter()
    trainer.train()
    per_step = (time.perf_counter() - start) / steps
    pipeline = trainer.pipeline
    dataset_ = pipeline.datamanager.train_dataset
    rig = dataset_.metadata["moisst_rig"]
    cameras = dataset_.cameras
    with torch.no_grad():
        c2w = cameras.camera_to_worlds.to(torch.float64).clone()
        n = c2w.shape[0]
        if pose_optimizer != "off":
            adj = pipeline.model.camera_optimizer(torch.arange(n, device=pipeline.model.camera_optimizer.device)).to("cpu", torch.float64)
            # as CameraOptimizer.apply_to_raybundle: directions rotated by adj's rotation, origins shifted by its translation
            c2w[:, :3, :3] = adj[:, :3, :3] @ c2w[:, :3, :3]
            c2w[:, :3, 3] = c2w[:, :3, 3] + adj[:, :3, 3]
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :4] = c2w.numpy()
    return NerfactoResult(rig.world.camera_to_world(poses), np.asarray(rig.frame_sensor_index), np.asarray(rig.frame_stamps), per_step)
