"""``moisst-calibrate``'s code path: ``ns-train moisst*`` in-process with the command line's switches.

``MoisstPipeline`` writes ``OUT/calibration.json`` (the ground-truth schema: metres and seconds in the dataset's frame),
``OUT/summary.json``, ``OUT/report``; the nerfstudio run is ``OUT/<method>/run``. Nothing is written into DATASET. Bad
input raises ``CalibrationError`` (one line): ``moisst_ns.cli.calibrate`` turns it into a message and exit status 2.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal, Optional

import tyro

from moisst_ns.runs import RunError
from moisst_ns.runs.folder import check_output_dir
from moisst_ns.stage_run import CalibrationError, CalibrationSwitches, set_up_trainer


@dataclass(kw_only=True)
class SceneRunConfig:
    """Settings shared by ``moisst-calibrate`` and ``moisst-floor``."""

    method: Literal["moisst", "moisst-lite"] = "moisst-lite"
    """``moisst`` (paper settings, for a GPU) or ``moisst-lite`` (2 CPU cores)."""
    seed: int = 42
    """Random seed (sampling, initialisation)."""
    threads: Optional[int] = None
    """torch CPU threads (pin for bit-repeatable runs); torch's default when omitted."""
    verbose: bool = False
    """Show every third-party warning and banner (by default the known-harmless ones are hidden:
    ``moisst_ns.quiet``)."""


@dataclass
class CalibrateConfig(CalibrationSwitches, SceneRunConfig):
    """Calibrate the extrinsics and time offsets of a rig (MOISST)."""

    dataset: tyro.conf.Positional[Path]
    """Dataset folder holding rig.json (moisst-rig/1)."""
    output_dir: Path = Path("outputs/calibration")
    """Where calibration.json and the nerfstudio run go (created; must not be a file)."""
    max_num_iterations: Optional[int] = None
    """Training steps (schedules scale with it); the method's default when omitted."""
    viewer: bool = False
    """Also serve nerfstudio's viewer during training (on 127.0.0.1 unless --viewer-host)."""
    viewer_host: str = "127.0.0.1"
    """Host the viewer listens on; reach it remotely through an ssh port forward rather than 0.0.0.0."""
    depth_loss: bool = True
    """LiDAR depth loss L_D (paper eq. 7); --no-depth-loss for the Table VII ablation."""
    dssim_loss: bool = True
    """DSSIM patch loss (eq. 13; active with --patch-size > 1)."""
    depth_smoothness_loss: bool = True
    """Depth smoothness patch loss (eq. 13; active with --patch-size > 1)."""
    patch_size: Optional[int] = None
    """Sample camera pixels as P x P patches (needed by the patch losses); the method's default when omitted."""
    lidar_rays: Optional[int] = None
    """LiDAR points per step (0: cameras only); the method's default when omitted."""
    rays: Optional[int] = None
    """Camera pixels per step; the method's default when omitted."""
    extrinsics: bool = True
    """Optimise the extrinsics; --no-extrinsics keeps them at the priors (paper Tables II and V: temporal only)."""
    time_offsets: bool = True
    """Optimise the time offsets; --no-time-offsets keeps them at the priors (paper Tables I and V: spatial only)."""
    max_time_offset: Optional[float] = None
    """Bound (seconds) on how far a sensor's time offset may move from its prior (default 0.3 s); a sensor that
    hits it is a runaway and shows in the still-moving / error report instead of going absurd."""
    resume: bool = False
    """Continue the run in --output-dir from its latest checkpoint (calibration, scene and optimiser state)."""
    save_every: Optional[int] = None
    """Checkpoint every N steps and keep every checkpoint (default: the method's, latest only)."""


def place_run(config, root: Path, out: Path, timestamp: str, seed: int):
    """``config`` (a ``TrainerConfig``, changed in place and returned) trained on the dataset ``root`` with
    nerfstudio's machine ``seed``, writing its run to ``out/<method>/<timestamp>``."""
    config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = root
    config.output_dir, config.experiment_name, config.timestamp = out, ".", timestamp
    config.machine.seed = seed
    return config


def rig_trainer_config(method: str, steps: Optional[int], root: Path, out: Path, timestamp: str, seed: int):
    """The ``TrainerConfig`` of ``method`` (``moisst`` / ``moisst-lite``) for ``steps`` (its default when None),
    placed by ``place_run``."""
    from moisst_ns.method_configs import moisst_trainer_config

    return place_run(moisst_trainer_config(method, steps), root, out, timestamp, seed)


def calibrate_trainer_config(cfg: CalibrateConfig, root: Path, out: Path, steps: Optional[int]):
    """``moisst-calibrate``'s trainer config: the method's for ``steps`` (its default when None) on the dataset
    ``root``, writing to ``out``, with the command line ``cfg``'s switches; ``CalibrationError`` when they leave
    nothing to calibrate."""
    config = rig_trainer_config(cfg.method, steps, root, out, "run", cfg.seed)
    pipeline = config.pipeline
    model, datamanager = pipeline.model, pipeline.datamanager
    for switch, weight in (("depth_loss", "depth_loss_mult"), ("dssim_loss", "dssim_loss_mult"), ("depth_smoothness_loss", "depth_smoothness_mult")):
        if not getattr(cfg, switch):
            setattr(model, weight, 0.0)  # the loss off
    if cfg.max_time_offset is not None:
        model.camera_optimizer.max_time_offset = cfg.max_time_offset
    if cfg.patch_size is not None:
        datamanager.patch_size = cfg.patch_size
    if cfg.lidar_rays is not None:
        datamanager.lidar_rays_per_batch = cfg.lidar_rays
    if cfg.rays is not None:
        datamanager.train_num_rays_per_batch = datamanager.eval_num_rays_per_batch = cfg.rays
    if not cfg.extrinsics and not cfg.time_offsets:
        raise CalibrationError("--no-extrinsics and --no-time-offsets together leave nothing to calibrate")
    model.camera_optimizer.optimize_extrinsics = cfg.extrinsics
    model.camera_optimizer.optimize_time_offsets = cfg.time_offsets
    for switch in fields(CalibrationSwitches):
        setattr(pipeline, switch.name, getattr(cfg, switch.name))
    pipeline.scene_steps, pipeline.output_dir = scene_only_steps(cfg), out
    config.viewer.quit_on_train_completion = True
    config.viewer.websocket_host = cfg.viewer_host
    config.vis = "viewer+tensorboard" if cfg.viewer else "tensorboard"
    if cfg.save_every:
        config.steps_per_save = cfg.save_every
        config.save_only_latest_checkpoint = False
    return config


def scene_only_steps(cfg: CalibrateConfig) -> int:
    """The NeRF's run length when the stages hold every sensor: ``--scene-steps``, else ``--max-num-iterations``, else
    the method's ``SCENE_STEPS``."""
    from moisst_ns.method_configs import SCENE_STEPS

    return cfg.scene_steps or cfg.max_num_iterations or SCENE_STEPS[cfg.method]


def run_calibration(cfg: CalibrateConfig) -> Path:
    """Calibrate ``cfg.dataset`` into ``cfg.output_dir`` (``MoisstPipeline``: stages, NeRF, checks, report); returns
    the run's config.yml path."""
    import torch

    from moisst_ns.rig.format import RigFormatError, load_rig

    try:
        rig = load_rig(cfg.dataset)
        check_output_dir(cfg.output_dir, rig.root, create=True)
    except (RigFormatError, RunError) as err:
        raise CalibrationError(str(err)) from None
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    config = calibrate_trainer_config(cfg, rig.root, cfg.output_dir, cfg.max_num_iterations)
    if cfg.resume:
        checkpoints = config.get_checkpoint_dir()
        if not checkpoints.is_dir() or not any(checkpoints.glob("step-*.ckpt")):
            raise CalibrationError(f"{checkpoints}: --resume: no checkpoint to resume from")
        config.load_dir = checkpoints
    config.save_config()
    try:
        set_up_trainer(config, cfg.seed).train()
    except FloatingPointError as err:
        raise CalibrationError(str(err)) from None
    return config.get_base_dir() / "config.yml"
