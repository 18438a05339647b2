"""The calibration pipeline behind ``moisst-calibrate``: LiDAR first, then the NeRF; writes ``OUT/calibration.json``.

Runs the LiDAR-first stage (``moisst_ns.stages.lidar_first``) when the rig has a LiDAR, then nerfstudio training of ``moisst`` or ``moisst-lite`` in-process and writes the calibration in the rig
format's ground-truth schema (metres and seconds in the dataset's own frame), plus the nerfstudio run
(config.yml, checkpoint) under ``OUT/<method>/run``. Nothing is written into DATASET. Bad input raises
``CalibrationError`` (one line); ``moisst_ns.cli.calibrate`` turns it into a message and exit status 2.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Sequence

import tyro

from moisst_ns.runs import RunError
from moisst_ns.runs.folder import check_output_dir
from moisst_ns.runs.history import HISTORY_FILE, append_history, format_error_table, stage_history_rows, still_moving
from moisst_ns.runs.verdict import sensor_verdicts, trust_lines


@dataclass
class CalibrateConfig:
    """Calibrate the extrinsics and time offsets of a rig (MOISST)."""

    dataset: tyro.conf.Positional[Path]
    """Dataset folder holding rig.json (moisst-rig/1)."""
    output_dir: Path = Path("outputs/calibration")
    """Where calibration.json and the nerfstudio run go (created; must not be a file)."""
    method: Literal["moisst", "moisst-lite"] = "moisst-lite"
    """``moisst`` (paper settings, for a GPU) or ``moisst-lite`` (2 CPU cores)."""
    max_num_iterations: Optional[int] = None
    """Training steps (schedules scale with it); the method's default when omitted."""
    seed: int = 42
    """Random seed (sampling, initialisation)."""
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
    report: bool = True
    """Write diagnostics to OUT/report: LiDAR points over the images with prior vs calibrated extrinsics, the
    same over a model render, convergence plots, report.md (same as ``moisst-report``)."""
    max_time_offset: Optional[float] = None
    """Bound (seconds) on how far a sensor's time offset may move from its prior (default 0.3 s); a sensor that
    hits it is a runaway and shows in the still-moving / error report instead of going absurd."""
    resume: bool = False
    """Continue the run in --output-dir from its latest checkpoint (calibration, scene and optimiser state)."""
    save_every: Optional[int] = None
    """Checkpoint every N steps and keep every checkpoint (default: the method's, latest only)."""
    threads: Optional[int] = None
    """torch CPU threads (pin for bit-repeatable runs); torch's default when omitted."""
    depth_loss_per_m2: Optional[float] = None
    """LiDAR depth loss on the depth error in metres with this weight per m^2 (same meaning on every rig); the
    method's normalised-depth loss (the paper's) when omitted."""
    registration_sensors: Optional[Literal["cameras", "all"]] = None
    """Override which sensors register against a detached scene during the registration phase: ``cameras`` (the
    calibrated LiDARs' depth shapes the scene while the cameras register) or ``all`` (the method's default; measured
    better for the forward camera, worse for the side camera: docs/method.md)."""
    line_of_sight_mult: Optional[float] = None
    """Weight of the line-of-sight loss on LiDAR rays (Urban Radiance Fields: the density along each LiDAR ray
    must be empty before the measured range and concentrated at it); the method's default when omitted, 0: off."""
    lidar_far_margin: Optional[float] = None
    """LiDAR-guided sampling: end each LiDAR ray this many metres behind its measured range (samples concentrate
    in front of the surface); the method's default when omitted, 0: off."""
    map_range_mult: float = 0.0
    """After the LiDAR-first stage, supervise the rays of the cameras whose pose is known (the reference camera, the
    cameras the stages hold) with the calibrated LiDAR map's range, this weight per m^2 (``stages.map_range``); 0: off."""
    lidar_scene: bool = False
    """After the LiDAR-first stage, let the calibrated LiDARs' metric depth (``--depth-loss-per-m2``, default 5 per
    m^2) shape the scene from step 0 over their whole scan (an experiment of the metric-scene issue: on the
    50-frame rig it helped the side camera's translation and hurt its rotation; docs/method.md)."""
    uncertainty: bool = True
    """After training, measure every camera's 7 standard deviations and its held-back loss against the prior
    (``moisst_ns.uncertainty``; a few seconds per camera): into calibration.json with a verdict per sensor.
    --no-uncertainty: verdicts from the history and the drive only, no sigma for the NeRF's cameras."""
    verbose: bool = False
    """Show every third-party warning and banner (by default the known-harmless ones are hidden:
    ``moisst_ns.quiet``)."""
    camera_registration: bool = True
    """After the LiDAR-first stage, register every camera against the calibrated LiDAR map (photometric consistency
    of the map's points between the cameras' frames; no NeRF; into OUT/camera_registration; without a LiDAR the map
    is the reference camera's triangulated features). The NeRF then holds the registered cameras there and trains the
    scene; a camera the stage could not trust keeps its prior and is calibrated by the NeRF.
    --no-camera-registration: the NeRF calibrates every camera."""
    scene_steps: Optional[int] = None
    """Training steps of the NeRF when the pre-NeRF stages hold every sensor (it then calibrates nothing and only
    builds the scene for the viewer, the report and the uncertainty pass): --max-num-iterations when given, else a
    third of the method's default (500 for ``moisst-lite``)."""
    camera_refinement: bool = False
    """Let the NeRF move the registered cameras further (the paper's joint refinement) instead of holding them."""
    lidar_first: bool = True
    """Calibrate every LiDAR from its own scans before the NeRF (``moisst-lidar-calibrate``, into OUT/lidar_first);
    the NeRF starts from that estimate, holds the LiDARs there and lets their depth shape the scene.
    --no-lidar-first: the paper's pure joint schedule (for the ablation tables)."""


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch as ``ns-train`` does (its train loop, which we bypass, would)."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


LIDAR_DEPTH_PER_M2 = 5.0
"""Weight of the metric LiDAR depth loss once the LiDARs are calibrated, per m^2 (docs/method.md: the old default
was 0.018 per m^2 on the 50-frame rig; 500 model units, ~5 per m^2, lowered the floor five-fold on the tiny rig)."""


def lidar_scene_settings(config, depth_per_m2: float) -> None:
    """What calibrated LiDARs change in the NeRF stage: their depth, in metres with ``depth_per_m2``, shapes the
    scene from step 0, over the whole scan (not only the reference camera's view, so the side cameras find
    geometry where they look) and also while the cameras register against the scene.

    Args:
        config: the trainer config (changed in place).
        depth_per_m2: depth loss weight per square metre.
    """
    model, datamanager = config.pipeline.model, config.pipeline.datamanager
    model.registration_sensors = "cameras"
    model.depth_loss_units, model.depth_loss_mult = "metric", depth_per_m2
    model.depth_loss_start = model.depth_loss_ramp_steps = 0
    datamanager.lidar_start_step = 0
    datamanager.lidar_reference_view_only = False


def fixed_calibration_scene(config) -> None:
    """Train the scene as the best scene of the budget when no sensor's calibration moves (every non-reference
    sensor held at a stage's estimate, or ``moisst-floor`` at the truth): the phases that protect the scene from
    miscalibrated sensors (reference-only warm-up, detached registration, coarse-to-fine) are switched off, so every
    sensor's rays, the LiDAR's depth included, shape the scene from the start.

    Args:
        config: the trainer config (changed in place).
    """
    model, datamanager = config.pipeline.model, config.pipeline.datamanager
    model.calibration_warmup_steps, model.reference_only_warmup, model.registration_steps = 0, False, 0
    model.coarse_to_fine = (0, 0)
    datamanager.reference_only_steps = datamanager.registration_steps = 0


def rig_trainer_config(method: str, steps: Optional[int], root: Path, out: Path, timestamp: str, seed: int):
    """The method's trainer config on a rig dataset, writing its nerfstudio run to ``out/<method>/<timestamp>``.

    Args:
        method: ``moisst`` or ``moisst-lite``.
        steps: run length (the method's default when None; schedules scale with it).
        root: dataset folder.
        out: output folder.
        timestamp: the run's folder name under ``out/<method>``.
        seed: nerfstudio's machine seed.

    Returns:
        The ``TrainerConfig`` (nerfstudio imported here, not at module import).
    """
    from moisst_ns.method_configs import moisst_trainer_config

    config = moisst_trainer_config(method, steps)
    config.pipeline.datamanager.data = root
    config.pipeline.datamanager.dataparser.data = root
    config.output_dir, config.experiment_name, config.timestamp = out, ".", timestamp
    config.machine.seed = seed
    return config


def apply_scene_switches(model, depth_loss_per_m2: Optional[float], line_of_sight_mult: Optional[float],
                         lidar_far_margin: Optional[float]) -> None:
    """The LiDAR-scene switches shared by ``moisst-calibrate`` and ``moisst-floor`` (None: the method's default).

    Args:
        model: the model config (changed in place).
        depth_loss_per_m2: metric depth loss weight per m^2.
        line_of_sight_mult: weight of the line-of-sight loss.
        lidar_far_margin: LiDAR-guided sampling margin, metres.
    """
    if depth_loss_per_m2 is not None:
        model.depth_loss_units, model.depth_loss_mult = "metric", depth_loss_per_m2
    if line_of_sight_mult is not None:
        model.line_of_sight_mult = line_of_sight_mult
    if lidar_far_margin is not None:
        model.lidar_far_margin_m = lidar_far_margin


def map_range_settings(config, mult: float, cameras: Sequence[str]) -> None:
    """Supervise the rays of ``cameras`` (poses known) with the LiDAR map's range (``stages.map_range``).

    Args:
        config: the trainer config (changed in place).
        mult: weight per square metre (``model.map_range_mult``).
        cameras: cameras whose pose is known at the dataparser's prior calibration.
    """
    config.pipeline.model.map_range_mult = mult
    config.pipeline.datamanager.map_range_sensors = tuple(cameras)


class CalibrationError(ValueError):
    """A calibration that cannot start or had to stop; the message is one line naming file/option and problem."""


def calibrate_trainer_config(cfg: CalibrateConfig, root: Path, out: Path, steps: Optional[int]):
    """``moisst-calibrate``'s trainer config: the method's at ``steps`` with the command line's switches applied.

    Args:
        cfg: the command line.
        root: dataset folder.
        out: output folder.
        steps: run length (the method's default when None).

    Returns:
        The ``TrainerConfig``.

    Raises:
        CalibrationError: options that leave nothing to calibrate.
    """
    config = rig_trainer_config(cfg.method, steps, root, out, "run", cfg.seed)
    model = config.pipeline.model
    apply_scene_switches(model, cfg.depth_loss_per_m2, cfg.line_of_sight_mult, cfg.lidar_far_margin)
    if not cfg.depth_loss:
        model.depth_loss_mult = model.line_of_sight_mult = 0.0
    if not cfg.dssim_loss:
        model.dssim_loss_mult = 0.0
    if not cfg.depth_smoothness_loss:
        model.depth_smoothness_mult = 0.0
    if cfg.max_time_offset is not None:
        model.camera_optimizer.max_time_offset = cfg.max_time_offset
    if cfg.patch_size is not None:
        config.pipeline.datamanager.patch_size = cfg.patch_size
    if cfg.lidar_rays is not None:
        config.pipeline.datamanager.lidar_rays_per_batch = cfg.lidar_rays
    if cfg.rays is not None:
        config.pipeline.datamanager.train_num_rays_per_batch = cfg.rays
        config.pipeline.datamanager.eval_num_rays_per_batch = cfg.rays
    if not cfg.extrinsics and not cfg.time_offsets:
        raise CalibrationError("--no-extrinsics and --no-time-offsets together leave nothing to calibrate")
    model.camera_optimizer.optimize_extrinsics = cfg.extrinsics
    model.camera_optimizer.optimize_time_offsets = cfg.time_offsets
    config.viewer.quit_on_train_completion = True
    config.viewer.websocket_host = cfg.viewer_host
    config.vis = "viewer+tensorboard" if cfg.viewer else "tensorboard"
    if cfg.save_every:
        config.steps_per_save = cfg.save_every
        config.save_only_latest_checkpoint = False
    return config


def scene_only_steps(cfg: CalibrateConfig) -> int:
    """The NeRF's run length when the pre-NeRF stages hold every sensor (``--scene-steps``).

    Args:
        cfg: the command line.

    Returns:
        ``--scene-steps``, else ``--max-num-iterations``, else a third of the method's default.
    """
    from moisst_ns.method_configs import DEFAULT_ITERATIONS

    return cfg.scene_steps or cfg.max_num_iterations or DEFAULT_ITERATIONS[cfg.method] // 3


def run_calibration(cfg: CalibrateConfig) -> Path:
    """Train, then write ``calibration.json``; returns the run's config.yml path."""
    import torch

    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import Calibration, RigFormatError, load_calibration, load_rig

    try:
        rig = load_rig(cfg.dataset)
        out = cfg.output_dir
        check_output_dir(out, rig.root, create=True)
    except (RigFormatError, RunError) as err:
        raise CalibrationError(str(err)) from None
    if cfg.threads:
        torch.set_num_threads(cfg.threads)

    config = calibrate_trainer_config(cfg, rig.root, out, cfg.max_num_iterations)
    model = config.pipeline.model
    checkpoints = config.get_checkpoint_dir()
    if cfg.resume:
        if not checkpoints.is_dir() or not any(checkpoints.glob("step-*.ckpt")):
            raise CalibrationError(f"{checkpoints}: --resume: no checkpoint to resume from")
        config.load_dir = checkpoints
    config.save_config()

    from moisst_ns.stages.drive_observability import analyse_rig_drive, drive_json, drive_table

    drive = analyse_rig_drive(rig, lidar_first=cfg.lidar_first)
    print("\n".join(drive_table(drive)))

    truth_file = rig.root / "ground_truth.json"
    truth = load_calibration(truth_file) if truth_file.is_file() else None
    prior = Calibration.from_rig(rig)
    stage = run_lidar_first(cfg, rig, prior, truth, out) if cfg.lidar_first else None
    cameras = run_camera_registration(cfg, rig, stage, truth, out) if cfg.lidar_first and cfg.camera_registration else None
    held: dict = {}
    if stage is not None or cameras is not None:
        # a camera the stage holds at its prior (``held_there``: its view does not tell a typical prior error apart, or
        # it shares no view with the reference camera of a rig without a LiDAR) stays there: the NeRF sees the same view
        # (on the 96x72 end-to-end test rig it took a blind camera from its prior to 86 cm / 9.5 deg; on the camera-only
        # plaza rig of seed 1 an unregistered side camera to 13.5 deg from a prior 8.8 deg off)
        held = {**(stage or {}).get("sensors", {}), **{n: e for n, e in (cameras or {}).get("sensors", {}).items() if not e["kept_prior"] or e.get("held_there")}}
        frozen = tuple(n for n in held if not cfg.camera_refinement or rig.sensors[n].type == "lidar" or held[n].get("held_there"))
        if len(frozen) == len(rig.sensors) - 1:  # nothing left to calibrate in the NeRF: it only builds the scene
            config = calibrate_trainer_config(cfg, rig.root, out, scene_only_steps(cfg))
            config.load_dir, model = (checkpoints if cfg.resume else None), config.pipeline.model
            fixed_calibration_scene(config)
        config.pipeline.datamanager.dataparser.prior_calibration = out / ("camera_registration" if cameras else "lidar_first") / "calibration.json"
        model.camera_optimizer.frozen_sensors = frozen
        if cfg.registration_sensors is not None:
            model.registration_sensors = cfg.registration_sensors
        if cfg.map_range_mult > 0 and stage is not None and any(s.type == "lidar" for s in rig.sensors.values()):
            known = [n for n in (rig.reference_sensor, *frozen) if rig.sensors[n].type == "camera"]
            map_range_settings(config, cfg.map_range_mult, known)
        if cfg.lidar_scene:
            lidar_scene_settings(config, cfg.depth_loss_per_m2 if cfg.depth_loss_per_m2 is not None else LIDAR_DEPTH_PER_M2)
            if not cfg.depth_loss:
                model.depth_loss_mult = 0.0
        config.save_config()
        if not cfg.resume:
            history = config.get_base_dir() / HISTORY_FILE
            history.unlink(missing_ok=True)
            for step, rows in stage_history_rows({"sensors": held}, truth):
                append_history(history, step, rows)

    seed_everything(cfg.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    start = time.time()
    try:
        trainer.train()
    except FloatingPointError as err:
        raise CalibrationError(str(err)) from None
    wall = time.time() - start

    optimizer = trainer.pipeline.model.camera_optimizer
    estimate = optimizer.rig.estimate()
    estimate.write(out / "calibration.json")
    summary = {"method": cfg.method, "iterations": config.max_num_iterations, "wall_time_s": wall, "seed": cfg.seed}
    if stage is not None:
        summary["lidar_first"] = {n: {k: e[k] for k in ("wall_s", "weak", "change_from_prior") + (("errors_after",) if truth else ())}
                                  for n, e in stage["sensors"].items()}
    print(f"\nwrote {out / 'calibration.json'}  ({config.max_num_iterations} steps, {wall:.0f} s)")
    if truth is not None:
        before = calibration_report_errors(prior, truth)
        after = calibration_report_errors(estimate, truth)
        skip = {truth.reference_sensor}
        before = {k: v for k, v in before.items() if k not in skip}
        after = {k: v for k, v in after.items() if k not in skip}
        print(format_error_table("errors of the priors (before):", before))
        print(format_error_table("errors after calibration:", after))
        summary["errors_before"], summary["errors_after"] = before, after
    bounds = optimizer.config
    for i, name in enumerate(optimizer.rig.data.sensor_names):
        hit = []
        if bounds.max_time_offset > 0 and abs(float(optimizer.rig.time_offset[i])) >= 0.999 * bounds.max_time_offset:
            hit.append(f"time offset (±{bounds.max_time_offset * 1000:.0f} ms)")
        if bounds.max_translation > 0 and float(optimizer.rig.translation[i].abs().max()) >= 0.999 * bounds.max_translation:
            hit.append(f"translation (±{bounds.max_translation} m)")
        if hit:
            print(f"WARNING: {name} ran into its bound on {', '.join(hit)}: a runaway, do not trust its estimate")
            summary.setdefault("hit_bounds", {})[name] = hit
    # a sensor the NeRF held never moved in it: its convergence is its stage's (whose iterations open the history)
    moving = {n: s for n, s in still_moving(config.get_base_dir() / HISTORY_FILE).items() if n not in model.camera_optimizer.frozen_sensors}
    for name, spread in moving.items():
        print(f"WARNING: {name} is still moving over its last estimates ({spread}); run longer or check the data")
    summary["still_moving"] = moving
    if cameras is not None:
        summary["camera_registration"] = {n: {k: e[k] for k in ("wall_s", "kept_prior", "loss_prior", "loss_estimate") + (("errors_after",) if truth else ())}
                                          for n, e in cameras["sensors"].items()}
    from moisst_ns.uncertainty import UncertaintyConfig, assess_run

    frozen = set(model.camera_optimizer.frozen_sensors)
    final, summary["trust"], lines = assess_run(trainer.pipeline, estimate, {"sensors": {n: e for n, e in held.items() if n in frozen}} if frozen else None, drive, moving, summary.get("hit_bounds", {}),
                                                UncertaintyConfig(seed=cfg.seed) if cfg.uncertainty else None)
    summary["drive_observability"] = drive_json(drive)
    print("\n".join(lines))
    final.write(out / "calibration.json")
    if truth is not None:
        summary["errors_final"] = {k: v for k, v in calibration_report_errors(final, truth).items() if k != truth.reference_sensor}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    verdicts = None
    if cfg.report:
        from moisst_ns.report import write_report

        report = write_report(config.get_base_dir() / "config.yml", out / "report", pipeline=trainer.pipeline)
        print(f"diagnostics: {report}")
        verdicts = json.loads((report.parent / "report.json").read_text())["verdicts"]
    if verdicts is None:  # --no-report: the same flags, without the depth check of the renders
        names = [n for n in optimizer.rig.data.sensor_names if n != rig.reference_sensor]
        lidars = [n for n in names if rig.sensors[n].type == "lidar"]
        verdicts = sensor_verdicts(names, summary, json.loads((out / "calibration.json").read_text()), (), lidars, rig.reference_sensor)
    summary["verdicts"] = verdicts
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print("\n".join(trust_lines(verdicts)))
    return config.get_base_dir() / "config.yml"


def run_lidar_first(cfg: CalibrateConfig, rig, prior, truth, out: Path) -> Optional[dict]:
    """The LiDAR-first stage into ``out/lidar_first`` when the rig has a non-reference LiDAR; its summary, or None."""
    from moisst_ns.stages.lidar_first import LidarFirstConfig, LidarFirstError, calibrate_lidars, lidar_sensors
    from moisst_ns.stages.lidar_report import write_stage_outputs

    if not lidar_sensors(rig):
        return None
    config = LidarFirstConfig(**_stage_options(cfg))
    try:
        result = calibrate_lidars(rig, config)
    except LidarFirstError as err:
        raise CalibrationError(f"{err} (--no-lidar-first skips the LiDAR-first stage)") from None
    stage = write_stage_outputs(result, config, prior, truth, out / "lidar_first")
    for name, entry in stage["sensors"].items():
        print(_stage_line("LiDAR-first", name, entry, truth) + (f"; weakly observable: {', '.join(entry['weak'])}" if entry["weak"] else ""))
    return stage


def _stage_line(stage: str, name: str, entry: dict, truth) -> str:
    """``<stage>: <sensor> in <s> s[: <errors> from the truth]``: a stage's one line per sensor."""
    line = f"{stage}: {name} in {entry['wall_s']:.1f} s"
    if truth is not None:
        e = entry["errors_after"]
        line += f": {e['translation_cm']:.2f} cm / {e['rotation_deg']:.3f} deg / {e['time_ms']:.2f} ms from the truth"
    return line


def _stage_options(cfg: CalibrateConfig) -> dict:
    """The options every pre-NeRF stage takes from ``moisst-calibrate``'s: the time-offset bound (the stage's own
    default when not given), the seed and which parameters to estimate."""
    bound = {} if cfg.max_time_offset is None else {"max_time_offset": cfg.max_time_offset}
    return dict(bound, seed=cfg.seed, estimate_extrinsic=cfg.extrinsics, estimate_time_offset=cfg.time_offsets)


def run_camera_registration(cfg: CalibrateConfig, rig, lidar_stage: Optional[dict], truth, out: Path) -> Optional[dict]:
    """The camera-registration stage into ``out/camera_registration`` when the rig has a non-reference camera and a
    map: a LiDAR (calibrated by the LiDAR-first stage, or the reference) or, without one, the reference camera's
    triangulated features; its summary, or None (no map: the NeRF calibrates the cameras)."""
    from moisst_ns.rig.format import Calibration, load_calibration
    from moisst_ns.stages.camera_registration import CameraRegistrationConfig, camera_sensors, register_cameras
    from moisst_ns.stages.camera_report import write_stage_outputs
    from moisst_ns.stages.lidar_map import CameraStageError, NoMapError

    has_lidar = any(s.type == "lidar" for s in rig.sensors.values())
    if not camera_sensors(rig) or not (has_lidar or rig.sensors[rig.reference_sensor].type == "camera"):
        return None
    start = load_calibration(out / "lidar_first" / "calibration.json") if lidar_stage is not None else Calibration.from_rig(rig)
    config = CameraRegistrationConfig(**_stage_options(cfg))
    try:
        result = register_cameras(rig, start, config)
    except NoMapError as err:
        print(f"camera registration skipped: {err}; the NeRF calibrates the cameras")
        return None
    except CameraStageError as err:
        raise CalibrationError(f"{err} (--no-camera-registration skips the camera-registration stage)") from None
    stage = write_stage_outputs(result, config, start, truth, out / "camera_registration")
    for name, entry in stage["sensors"].items():
        why = entry["note"] or "held-back cost not significantly lower than at the prior"
        then = "held there" if entry.get("held_there") else "the NeRF calibrates it"
        print(_stage_line("camera registration", name, entry, truth) + (f" ({why}: prior kept, {then})" if entry["kept_prior"] else ""))
    return stage
