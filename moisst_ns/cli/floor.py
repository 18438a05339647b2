"""``moisst-floor DATASET --output-dir OUT``: the accuracy floor of a dataset at a training budget.

A calibration can only be as good as the scene it registers against. This tool measures that limit on a rig with
``ground_truth.json``: it trains the scene with every sensor held at its *true* calibration (the same field, rays,
losses and step count as the method), freezes the scene, then releases every sensor's calibration *at the truth*
and lets the calibration losses move it for ``--register-steps`` steps. Where the sensors settle is the floor:
a minimum of the losses that is not the truth, so no schedule of the joint optimisation can be expected to end
closer than this with that scene budget. It separates "the optimisation did not get there" from "the scene
cannot tell". Nothing is written into DATASET.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.pipeline import LIDAR_DEPTH_PER_M2, lidar_scene_settings, seed_everything
from moisst_ns.quiet import quiet_third_party
from moisst_ns.runs import RunError
from moisst_ns.runs.folder import check_output_dir
from moisst_ns.runs.history import format_error_table

CALIBRATION_GROUPS = ("calibration_rotation", "calibration_translation", "calibration_time")


@dataclass
class FloorConfig:
    """Measure how close to the truth a scene of this budget lets the calibration settle."""

    dataset: tyro.conf.Positional[Path]
    """Dataset folder holding rig.json and ground_truth.json."""
    output_dir: Path = Path("outputs/floor")
    """Where floor.json, floor_history.csv and the nerfstudio run of the scene go."""
    method: Literal["moisst", "moisst-lite"] = "moisst-lite"
    """Preset whose field, rays, losses and schedules build the scene."""
    scene_steps: Optional[int] = None
    """Steps to train the scene at the true calibration (the method's default run length when omitted)."""
    register_steps: int = 300
    """Steps of calibration-only optimisation against the frozen scene, starting at the truth."""
    log_every: int = 25
    """Log every sensor's errors every this many registration steps."""
    average_last: int = 4
    """The floor is the mean error over this many last logged estimates."""
    seed: int = 42
    """Random seed (sampling, initialisation)."""
    threads: Optional[int] = None
    """torch CPU threads; torch's default when omitted."""
    depth_loss_per_m2: Optional[float] = None
    """LiDAR depth loss on the depth error in metres with this weight per m^2 (same meaning on every rig); the
    method's normalised-depth loss (the paper's) when omitted."""
    verbose: bool = False
    """Show every third-party warning (known-harmless ones are hidden by default: ``moisst_ns.quiet``)."""
    lidar_scene: bool = False
    """Train the scene as ``moisst-calibrate --lidar-scene`` does (metric LiDAR depth from step 0 over the whole
    scan; ``--depth-loss-per-m2`` or the pipeline's default weight of 5 per m^2)."""


def floor_errors(rows: List[Dict[str, float]], average_last: int) -> Dict[str, Dict[str, float]]:
    """Per sensor, the mean of the last ``average_last`` logged errors (rows: step, sensor and the three errors)."""
    out: Dict[str, Dict[str, float]] = {}
    for name in dict.fromkeys(r["sensor"] for r in rows):
        tail = [r for r in rows if r["sensor"] == name][-average_last:]
        out[name] = {k: sum(r[k] for r in tail) / len(tail) for k in ("translation_cm", "rotation_deg", "time_ms")}
    return out


def run_floor(cfg: FloorConfig) -> Dict[str, Dict[str, float]]:
    """Train the scene at the truth, register from the truth against it, write ``floor.json``; returns the floor."""
    import torch
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    from moisst_ns.method_configs import moisst_trainer_config
    from moisst_ns.rig.format import RigFormatError, load_rig

    try:
        rig = load_rig(cfg.dataset)
    except RigFormatError as err:
        fail("moisst-floor", str(err))
    if not (rig.root / "ground_truth.json").is_file():
        fail("moisst-floor", f"{rig.root / 'ground_truth.json'}: not found: the floor is measured against the true calibration")
    if cfg.register_steps < 1 or cfg.log_every < 1 or cfg.average_last < 1:
        fail("moisst-floor", "--register-steps, --log-every and --average-last must be >= 1")
    out = cfg.output_dir
    try:
        check_output_dir(out, rig.root, create=True)
    except RunError as err:
        fail("moisst-floor", err)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)

    config = moisst_trainer_config(cfg.method, cfg.scene_steps)
    config.pipeline.datamanager.data = rig.root
    config.pipeline.datamanager.dataparser.data = rig.root
    config.output_dir, config.experiment_name, config.timestamp = out, ".", "scene"
    config.machine.seed = cfg.seed
    config.vis = "tensorboard"
    model, datamanager = config.pipeline.model, config.pipeline.datamanager
    if cfg.lidar_scene and any(s.type == "lidar" for s in rig.sensors.values()):
        lidar_scene_settings(config, cfg.depth_loss_per_m2 if cfg.depth_loss_per_m2 is not None else LIDAR_DEPTH_PER_M2)
    elif cfg.depth_loss_per_m2 is not None:
        model.depth_loss_units, model.depth_loss_mult = "metric", cfg.depth_loss_per_m2
    # The scene is built at the true calibration, so the phases that protect it from miscalibrated sensors
    # (reference-only warm-up, detached registration, coarse-to-fine) are switched off: the best scene of this budget.
    model.camera_optimizer.mode = "off"
    model.calibration_warmup_steps, model.reference_only_warmup, model.registration_steps = 0, False, 0
    model.coarse_to_fine = (0, 0)
    datamanager.reference_only_steps = datamanager.registration_steps = 0
    config.save_config()

    seed_everything(cfg.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    pipeline = trainer.pipeline
    optimizer = pipeline.model.camera_optimizer
    optimizer.rig.set_corrections_to(optimizer.rig.data.ground_truth)  # the scene trains at the truth
    start = time.time()
    trainer.train()
    scene_wall = time.time() - start

    # Register: the scene frozen, every sensor released at its truth.
    for param in pipeline.model.parameters():
        param.requires_grad_(False)
    rig_params = optimizer.rig
    groups = dict(zip(CALIBRATION_GROUPS, (rig_params.rotvec, rig_params.translation, rig_params.time_offset)))
    steppers = []
    for key, param in groups.items():
        param.requires_grad_(True)
        settings = config.optimizers[key]
        opt = settings["optimizer"].setup(params=[param])
        lr_final = settings["scheduler"].lr_final
        scheduler = ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=cfg.register_steps).setup()
        steppers.append((opt, scheduler.get_scheduler(optimizer=opt, lr_init=settings["optimizer"].lr)))
    pipeline.model.train()
    names = rig_params.data.sensor_names
    rows: List[Dict[str, float]] = []

    def log(step: int) -> None:
        for name, err in (rig_params.errors() or {}).items():
            if name != names[rig_params.data.reference_index]:
                rows.append({"step": step, "sensor": name, **{k: float(v) for k, v in err.items()}})

    log(0)
    base = config.max_num_iterations
    start = time.time()
    for step in range(1, cfg.register_steps + 1):
        pipeline.model._update_schedule(base + step)
        _, loss_dict, _ = pipeline.get_train_loss_dict(step=base + step)
        loss = torch.stack([v for v in loss_dict.values()]).sum()
        for opt, _ in steppers:
            opt.zero_grad(set_to_none=True)
        loss.backward()
        for opt, scheduler in steppers:
            opt.step()
            scheduler.step()
        optimizer.project()
        if step % cfg.log_every == 0 or step == cfg.register_steps:
            log(step)
    register_wall = time.time() - start

    with (out / "floor_history.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["step", "sensor", "translation_cm", "rotation_deg", "time_ms"])
        writer.writeheader()
        writer.writerows(rows)
    floor = floor_errors([r for r in rows if r["step"] > 0], cfg.average_last)
    result = {
        "method": cfg.method,
        "scene_steps": config.max_num_iterations,
        "register_steps": cfg.register_steps,
        "average_last": cfg.average_last,
        "scene_wall_time_s": scene_wall,
        "register_wall_time_s": register_wall,
        "floor": floor,
    }
    (out / "floor.json").write_text(json.dumps(result, indent=1) + "\n")
    print(format_error_table(f"floor ({config.max_num_iterations} scene steps at the truth, then {cfg.register_steps} "
                             "calibration steps from the truth against the frozen scene):", floor))
    print(f"wrote {out / 'floor.json'}")
    return floor


def main() -> None:
    cfg = tyro.cli(FloorConfig)
    quiet_third_party(cfg.verbose)
    run_floor(cfg)


if __name__ == "__main__":
    main()
