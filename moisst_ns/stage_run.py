"""The calibration stages as a run runs them before the NeRF: their switches, running them into ``OUT/lidar_first`` and
``OUT/camera_registration`` (a resumed run loads them from there), and what their estimate changes in the NeRF's config.
No nerfstudio import: ``MoisstPipeline``, ``moisst-calibrate``'s flags (``moisst_ns.calibrate``) and ``moisst-floor`` share it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence


REFINEMENT_START = 0.5
"""With ``camera_refinement`` and every sensor placed by a stage, the share of the run during which the scene trains
with every sensor held at the stages' estimate before the refined cameras are released (the schedule built to find
cameras from their priors, a reference-only warm-up and a detached registration, ran registered cameras 19-82 cm off)."""


class CalibrationError(ValueError):
    """A calibration that cannot start or had to stop; the message is one line naming file/option and problem."""


@dataclass(kw_only=True)
class CalibrationSwitches:
    """What a calibration run does around the NeRF: ``moisst-calibrate --<name>`` and ``ns-train moisst*
    --pipeline.<name>`` are the same switches."""

    lidar_first: bool = True
    """Calibrate every LiDAR from its own scans before the NeRF (``moisst-lidar-calibrate``, into OUT/lidar_first);
    the NeRF starts from that estimate, holds the LiDARs there and lets their depth shape the scene. Off: the paper's
    pure joint schedule (for the ablation tables)."""
    camera_registration: bool = True
    """After the LiDAR-first stage, register every camera against the calibrated LiDAR map (photometric consistency
    of the map's points between the cameras' frames; no NeRF; into OUT/camera_registration; without a LiDAR the map
    is the reference camera's triangulated features). The NeRF then holds the registered cameras there and trains the
    scene; a camera the stage could not trust keeps its prior and is calibrated by the NeRF. Off: the NeRF calibrates
    every camera."""
    estimate_readout: bool = False
    """The camera-registration stage also estimates each camera's rolling-shutter readout time (``CameraRegistrationConfig
    .estimate_readout``: kept when its sigma is under 3 ms, else rig.json's is kept, as camera_registration.json says);
    the NeRF and calibration.json keep rig.json's readout."""
    camera_refinement: bool = False
    """Let the NeRF move the registered cameras further (the paper's joint refinement, eq. 12) instead of holding
    them; a fifth of each such camera's frames is held back from training, and a camera's refinement is kept only
    where it renders those frames significantly better than the stage's estimate, stays within the stage's 3 sigma and
    has settled (``MoisstPipeline.judge_refinement``), else the camera goes back to the stage's estimate. Off: measured,
    it never helped (docs/lab/2026-11-27-refinement.md)."""
    map_range_mult: float = 10.0
    """After the LiDAR-first stage, supervise the rays of the cameras whose pose is known (the reference camera, the
    cameras the stages hold) with the calibrated LiDAR map's range, this weight per m^2 (``stages.map_range``): the
    scene then agrees with the LiDAR in every camera's view, not only the reference camera's; 0: off."""
    scene_steps: Optional[int] = None
    """Training steps of the NeRF when the stages hold every sensor (it then calibrates nothing and only builds the
    scene for the viewer, the report and the uncertainty pass). ``moisst-calibrate``: --max-num-iterations when given,
    else ``method_configs.SCENE_STEPS`` (2000 for ``moisst-lite``); ``ns-train``: the run's length when omitted."""
    uncertainty: bool = True
    """After training, measure every camera's 7 standard deviations and its held-back loss against the prior
    (``moisst_ns.uncertainty``; a few seconds per camera): into calibration.json with a verdict per sensor.
    Off: verdicts from the history and the drive only, no sigma for the NeRF's cameras."""
    report: bool = True
    """Write diagnostics to OUT/report: LiDAR points over the images with prior vs calibrated extrinsics, the same over
    a model render, convergence plots, report.md (same as ``moisst-report``)."""
    stages_from: Optional[Path] = None
    """A ``moisst-calibrate`` OUT or ``ns-train`` run folder of the same rig whose stages' results this run loads
    instead of running the stages (e.g. the stages on a CPU machine, the NeRF on a GPU one); its sensors must be the
    rig's. Omitted: the stages run (a resumed run loads its own)."""


@dataclass
class StageRun:
    """What the stages leave for the NeRF and the checks after it: the dataset's ``rig``, ``truth`` (or None), ``prior``
    (rig.json's) and drive observability, each stage's summary (or None), the sensors a stage placed (``held``), those
    the NeRF keeps there (``frozen``; ``all_held``: every non-reference sensor), those it refines from there
    (``refined``), and the run's ``out``, seed, resumption."""

    rig: object
    truth: object
    prior: object
    drive: list
    out: Path
    seed: int
    resumed: bool
    lidar: Optional[dict] = None
    cameras: Optional[dict] = None
    held: dict = field(default_factory=dict)
    frozen: tuple = ()
    refined: tuple = ()
    all_held: bool = False


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch as ``ns-train`` does (its ``_set_random_seed``)."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def set_up_trainer(config, seed: int):
    """The set-up trainer of ``config`` (a ``TrainerConfig``), built after ``seed_everything(seed)`` as ``ns-train``
    builds it."""
    seed_everything(seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def fixed_calibration_scene(pipeline) -> None:
    """Train the scene as the best scene of the budget when no sensor's calibration moves (every non-reference
    sensor held at a stage's estimate, or ``moisst-floor`` at the truth): the phases that protect the scene from
    miscalibrated sensors (reference-only warm-up, detached registration, coarse-to-fine) are switched off, so every
    sensor's rays, the LiDAR's depth included, shape the scene from the start (``pipeline``: changed in place)."""
    model, datamanager = pipeline.model, pipeline.datamanager
    model.calibration_warmup_steps, model.reference_only_warmup, model.registration_steps = 0, False, 0
    model.coarse_to_fine = (0, 0)
    datamanager.reference_only_steps = datamanager.registration_steps = 0


def map_range_settings(pipeline, mult: float, cameras: Sequence[str]) -> None:
    """Supervise the rays of ``cameras`` (poses known at the dataparser's prior calibration) with the LiDAR map's
    range, ``mult`` per square metre (``stages.map_range``; ``pipeline``: changed in place)."""
    pipeline.model.map_range_mult = mult
    pipeline.datamanager.map_range_sensors = tuple(cameras)


def prepare_stages(pipeline, out: Path, seed: int, resume_from: Optional[Path]) -> StageRun:
    """Run the stages that the switches of ``pipeline`` (a ``MoisstPipelineConfig``) ask for into ``out`` with ``seed``
    (a run resumed from the run folder ``resume_from`` loads those cached in ``out`` or there), apply their estimate to
    ``pipeline`` (``apply_stage_results``), then seed again: the NeRF starts as if no stage had drawn a number."""
    from moisst_ns.rig.format import Calibration, load_calibration, load_rig
    from moisst_ns.stages.lidar.lidar_instant import pairs_with_reference
    from moisst_ns.stages.trust.observability import analyse_rig_drive, drive_table

    dataparser = pipeline.datamanager.dataparser
    dataparser.data = Path(pipeline.datamanager.data or dataparser.data)  # as the datamanager will
    rig = load_rig(dataparser.setup().rig_folder())
    truth_file = rig.root / "ground_truth.json"
    run = StageRun(rig, load_calibration(truth_file) if truth_file.is_file() else None, Calibration.from_rig(rig),
                   analyse_rig_drive(rig, lidar_first=pipeline.lidar_first), out, seed, resume_from is not None)
    print("\n".join(drive_table(run.drive)))
    opt = pipeline.model.camera_optimizer
    options = dict(max_time_offset=opt.max_time_offset, seed=seed, estimate_extrinsic=opt.optimize_extrinsics,
                   estimate_time_offset=opt.optimize_time_offsets)
    cache = (out, resume_from, resume_from.parent.parent) if resume_from else ()  # ns-train's run folder, moisst-calibrate's OUT
    cache = (pipeline.stages_from,) if pipeline.stages_from else cache
    if pipeline.lidar_first:
        # the cameras' same-instant placement replaces the depth edges' view where a pair can make it (KITTI raw 0048's
        # seed 1: the view put the Velodyne's along-track lever arm 22.5 cm off under a sigma of 6 cm); seed 0's stage 213 -> 141 s
        view = not (pipeline.camera_registration and opt.optimize_extrinsics and pairs_with_reference(rig))
        run.lidar = _cached("lidar_first", cache, rig) or run_lidar_first(rig, run.prior, run.truth, out, dict(options, view_search=view))
        if pipeline.camera_registration:
            camera_options = dict(options, estimate_readout=pipeline.estimate_readout)
            run.cameras = _cached("camera_registration", cache, rig) or run_camera_registration(rig, run.lidar, run.truth, out, camera_options)
    apply_stage_results(pipeline, run)
    seed_everything(seed)
    return run


def _cached(name: str, folders: Sequence[Optional[Path]], rig) -> Optional[dict]:
    """A stage's summary from the first of ``folders`` holding ``<name>/<name>.json`` (its calibration.json beside it,
    as ``"file"``), or None (not cached: the stage runs). Raises ``CalibrationError`` when it names a sensor that
    ``rig`` does not have (another rig's stages)."""
    for folder in folders:
        summary = Path(folder or "") / name / f"{name}.json"
        if folder is not None and summary.is_file():
            print(f"{name}: loaded from {summary.parent} (not run again)")
            loaded = json.loads(summary.read_text())
            unknown = sorted(set(loaded.get("sensors", {})) - set(rig.sensors))
            if unknown:
                raise CalibrationError(f"{summary}: sensors: {', '.join(unknown)} not in {rig.root / 'rig.json'} (another rig's stages)")
            return dict(loaded, file=summary.parent / "calibration.json")
    return None


def apply_stage_results(pipeline, run: StageRun) -> None:
    """The NeRF starts from the stages' estimate (the dataparser's ``prior_calibration``) and holds there the sensors
    they placed (LiDARs; cameras registered or held at their prior), unless ``camera_refinement`` lets the registered
    cameras move (with frames held back to judge it); with every sensor held it only builds the scene
    (``fixed_calibration_scene``, ``scene_steps``). Changes ``pipeline`` in place and sets ``run.held``, ``run.frozen``,
    ``run.refined``, ``run.all_held``."""
    if run.lidar is None and run.cameras is None:
        return
    rig, model = run.rig, pipeline.model
    # a camera the stage holds at its prior (``held_there``: its view does not tell a typical prior error apart, or
    # it shares no view with the reference camera of a rig without a LiDAR) stays there: the NeRF sees the same view
    # (on the 96x72 end-to-end test rig it took a blind camera from its prior to 86 cm / 9.5 deg; on the camera-only
    # plaza rig of seed 1 an unregistered side camera to 13.5 deg from a prior 8.8 deg off)
    cameras = {n: e for n, e in (run.cameras or {}).get("sensors", {}).items() if not e["kept_prior"] or e.get("held_there")}
    run.held = {**(run.lidar or {}).get("sensors", {}), **cameras}
    for name, placed in (run.cameras or {}).get("lidars", {}).items():  # placed against the cameras at the same instants
        run.held[name] = dict(run.held[name], shared_instant=placed)
    run.frozen = tuple(n for n in run.held if not pipeline.camera_refinement or rig.sensors[n].type == "lidar" or run.held[n].get("held_there"))
    run.refined = tuple(n for n in run.held if n not in run.frozen)
    pipeline.datamanager.held_back_sensors = run.refined
    run.all_held = len(run.frozen) == len(rig.sensors) - 1
    if run.all_held:  # nothing left to calibrate in the NeRF: it only builds the scene
        fixed_calibration_scene(pipeline)
    elif run.refined and len(run.held) == len(rig.sensors) - 1:  # refinement only: the scene first, at the stages' estimate
        fixed_calibration_scene(pipeline)
        model.calibration_warmup_steps = int(REFINEMENT_START * model.schedule_steps)
    stage = run.cameras if run.cameras else run.lidar
    file = stage.get("file") or run.out / ("camera_registration" if run.cameras else "lidar_first") / "calibration.json"
    pipeline.datamanager.dataparser.prior_calibration = Path(file).resolve()  # config.yml keeps it: loading the run needs it
    model.camera_optimizer.frozen_sensors = run.frozen
    if pipeline.map_range_mult > 0 and run.lidar is not None and any(s.type == "lidar" for s in rig.sensors.values()):
        map_range_settings(pipeline, pipeline.map_range_mult, [n for n in (rig.reference_sensor, *run.frozen) if rig.sensors[n].type == "camera"])


def run_lidar_first(rig, prior, truth, out: Path, options: dict) -> Optional[dict]:
    """The LiDAR-first stage into ``out/lidar_first`` when the rig has a non-reference LiDAR; its summary, or None."""
    from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, LidarFirstError, calibrate_lidars, lidar_sensors
    from moisst_ns.stages.lidar.lidar_report import write_stage_outputs

    if not lidar_sensors(rig):
        return None
    config = LidarFirstConfig(**options)
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


def run_camera_registration(rig, lidar_stage: Optional[dict], truth, out: Path, options: dict) -> Optional[dict]:
    """The camera-registration stage into ``out/camera_registration`` when the rig has a non-reference camera and a
    map: a LiDAR (calibrated by the LiDAR-first stage, or the reference) or, without one, the reference camera's
    triangulated features; its summary, or None (no map: the NeRF calibrates the cameras)."""
    from moisst_ns.rig.format import Calibration, load_calibration
    from moisst_ns.stages.camera.camera_registration import CameraRegistrationConfig, camera_sensors, register_cameras
    from moisst_ns.stages.camera.camera_report import write_stage_outputs
    from moisst_ns.stages.camera.lidar_map import CameraStageError, NoMapError
    from moisst_ns.stages.lidar.lidar_report import stage_sigma

    has_lidar = any(s.type == "lidar" for s in rig.sensors.values())
    if not camera_sensors(rig) or not (has_lidar or rig.sensors[rig.reference_sensor].type == "camera"):
        return None
    start = load_calibration(lidar_stage.get("file", out / "lidar_first" / "calibration.json")) if lidar_stage is not None else Calibration.from_rig(rig)
    config = CameraRegistrationConfig(**options)
    try:
        lidars = (lidar_stage or {}).get("sensors", {})
        result = register_cameras(rig, start, config, lidar_undetermined={n: e.get("motion_undetermined", e.get("undetermined", [])) for n, e in lidars.items()},
                                  lidar_sigma={n: stage_sigma(e)[0] for n, e in lidars.items()})
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
