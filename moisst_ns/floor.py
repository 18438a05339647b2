"""The accuracy floor of a dataset at a training budget (``moisst-floor``, and the ``floor`` cases of ``moisst-bench``).

A calibration can only be as good as the scene it registers against. ``run_floor`` measures the floor of the pre-NeRF
stages (``FloorConfig.stages``), then trains the scene with every sensor held at its *true* calibration (the same
field, rays, losses and step count as the method), freezes it, releases every sensor's calibration *at the truth* and
lets the calibration losses move it for ``register_steps`` steps. Where the sensors settle is the floor: a minimum of
the losses that is not the truth, so no schedule of the joint optimisation can be expected to end closer than this
with that scene budget. It also measures the scene's depth errors (``camera_depth_errors``, and LiDAR rays against
their ranges). Nothing is written into the dataset.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from moisst_ns.calibrate import SceneRunConfig, rig_trainer_config
from moisst_ns.stage_run import fixed_calibration_scene, map_range_settings, set_up_trainer
from moisst_ns.runs import ERROR_KEYS, RunError
from moisst_ns.runs.folder import check_output_dir
from moisst_ns.runs.history import format_error_table

CALIBRATION_GROUPS = ("calibration_rotation", "calibration_translation", "calibration_time")


class FloorError(ValueError):
    """The floor cannot be measured on this input: ``<file>: <field>: <problem>`` or a one-line reason."""


@dataclass
class FloorConfig(SceneRunConfig):
    """Measure how close to the truth a scene of this budget lets the calibration settle."""

    dataset: Path
    """Dataset folder holding rig.json and ground_truth.json."""
    output_dir: Path = Path("outputs/floor")
    """Where floor.json, floor_history.csv and the nerfstudio run of the scene go."""
    scene_steps: Optional[int] = None
    """Steps to train the scene at the true calibration (the method's default run length when omitted)."""
    register_steps: int = 300
    """Steps of calibration-only optimisation against the frozen scene, starting at the truth."""
    log_every: int = 25
    """Log every sensor's errors every this many registration steps."""
    average_last: int = 4
    """The floor is the mean error over this many last logged estimates."""
    map_range_mult: float = 0.0
    """Supervise every camera's rays with the LiDAR map's range, this weight per m^2 (the scene trains at the truth, so
    every pose is known; ``moisst-calibrate --map-range-mult`` does it for the cameras the stages hold); 0: off."""
    depth_check_rays: int = 8192
    """Camera rays whose rendered depth is compared with the true surface (0: skip the depth check)."""
    nerf: bool = True
    """Train the NeRF scene at the truth and measure its floor (``--no-nerf``: the stages' floor alone, minutes)."""
    stages: bool = True
    """Also measure the floor of the pre-NeRF stages that calibrate a rig with a LiDAR today: LiDAR first and the camera
    registration started at the truth (the fits' last estimates, guards ignored), and the LiDAR map's depth errors
    where the cameras' fits look (``moisst_ns.stages.stage_floor``)."""


def floor_errors(rows: List[Dict[str, float]], average_last: int) -> Dict[str, Dict[str, float]]:
    """Per sensor, the mean of the last ``average_last`` logged errors.

    Args:
        rows: ``{"step", "sensor", "translation_cm", "rotation_deg", "time_ms"}`` per logged estimate, in step order.
        average_last: How many of each sensor's last rows to average.

    Returns:
        ``{sensor: {"translation_cm", "rotation_deg", "time_ms"}}``.
    """
    out: Dict[str, Dict[str, float]] = {}
    for name in dict.fromkeys(r["sensor"] for r in rows):
        tail = [r for r in rows if r["sensor"] == name][-average_last:]
        out[name] = {k: sum(r[k] for r in tail) / len(tail) for k in ERROR_KEYS}
    return out


def camera_depth_errors(
    rendered_m: np.ndarray, true_m: np.ndarray, in_field: np.ndarray
) -> Dict[str, float]:
    """Depth errors of camera rays against the true surface.

    Args:
        rendered_m: (N,) expected depth rendered by the scene, metres along the unit ray.
        true_m: (N,) distance to the true surface along the same ray, metres (inf on a miss).
        in_field: (N,) whether the LiDAR can see that surface.

    Returns:
        ``{"camera_rays", "median_abs_m", "p90_abs_m"}`` over the rays that hit a surface in the LiDAR's field
        (NaN figures when there are none).
    """
    from moisst_ns.stages.stage_floor import depth_error_stats

    keep = np.isfinite(true_m) & in_field
    return depth_error_stats(np.abs(rendered_m[keep] - true_m[keep]))


def synthetic_scene(rig_root: Path):
    """The ray-castable scene of a ``moisst-synth`` rig (its rig.json ``metadata`` names it), else None."""
    from moisst_ns.datasets.synth import build_scene, config_of_rig

    synth = config_of_rig(json.loads((rig_root / "rig.json").read_text()).get("metadata", {}))
    return build_scene(synth) if synth is not None else None


def scene_depth_check(pipeline, rig_root: Path, num_rays: int) -> Dict[str, float]:
    """Median depth errors of the trained scene (at the true calibration): camera rays against the exact synthetic
    scene (``moisst-synth`` rigs only) and LiDAR rays against their measured range.

    Args:
        pipeline: The trained nerfstudio pipeline (its calibration at the truth).
        rig_root: Dataset folder (its rig.json ``metadata`` names the synthetic scene).
        num_rays: At least this many camera rays are checked.

    Returns:
        ``{"camera_rays", "median_abs_m", "p90_abs_m", "lidar_rays", "lidar_median_abs_m"}``; the camera figures
        are absent when the scene is not known.
    """
    import torch

    from moisst_ns.datasets.synth import in_lidar_field

    scene = synthetic_scene(Path(rig_root))
    model, datamanager = pipeline.model, pipeline.datamanager
    optimizer = model.camera_optimizer
    rig = optimizer.rig
    world, scale = optimizer.world, float(optimizer.world_scale)
    lidars = [i for i, kind in enumerate(rig.data.sensor_types) if kind == "lidar"]
    extrinsics = rig.extrinsics().detach().double().cpu().numpy()
    rendered, truth, in_field, lidar_err = [], [], [], []
    checked, step = 0, 10**6
    with torch.no_grad():
        while checked < num_rays:
            ray_bundle, batch = datamanager.next_train(step)
            step += 1
            outputs = model(ray_bundle)  # training mode: the rays are re-posed at the (true) calibration
            layout = batch["ray_layout"]
            depth = outputs["expected_depth"][:, 0].double().cpu().numpy() / scale
            if layout.lidar is not None and "lidar_range" in batch:
                lidar_err.append(np.abs(depth[layout.lidar] - batch["lidar_range"].double().cpu().numpy() / scale))
            cam = layout.camera
            checked += cam.stop - cam.start
            if scene is None:
                continue
            origins = ray_bundle.origins[cam].double().cpu().numpy() / scale + np.asarray(world.center)
            dirs = ray_bundle.directions[cam].double().cpu().numpy()
            dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
            hit = scene.cast(origins, dirs)["t_hit"].astype(np.float64)
            points = origins + dirs * np.where(np.isfinite(hit), hit, 0.0)[:, None]
            frames = ray_bundle.camera_indices[cam].reshape(-1).long()
            c2w = world.camera_to_world(optimizer.frame_c2w(frames).detach().cpu().numpy())
            sensor = optimizer.frame_sensor[frames.to(optimizer.frame_sensor.device)].cpu().numpy()
            seen = np.zeros(len(points), dtype=bool)
            for lidar in lidars:
                world_T_lidar = c2w @ np.linalg.inv(extrinsics[sensor]) @ extrinsics[lidar]
                local = np.einsum("nji,nj->ni", world_T_lidar[:, :3, :3], points - world_T_lidar[:, :3, 3])
                seen |= in_lidar_field(local)
            rendered.append(depth[cam])
            truth.append(hit)
            in_field.append(seen)
    result: Dict[str, float] = {}
    if scene is not None:
        result.update(camera_depth_errors(np.concatenate(rendered), np.concatenate(truth), np.concatenate(in_field)))
    if lidar_err:
        joined = np.concatenate(lidar_err)
        result.update(lidar_rays=int(joined.size), lidar_median_abs_m=float(np.median(joined)))
    return result


def run_floor(cfg: FloorConfig) -> dict:
    """Train the scene at the truth, register from the truth against it, check its depths (``--nerf``); run the
    pre-NeRF stages from the truth and check the LiDAR map's depths (``--stages``); write ``floor.json``.

    Args:
        cfg: What to measure and where to write it.

    Returns:
        The content of ``floor.json``: ``{"floor": {sensor: errors}, "depth": {...}, wall times, settings}`` for the
        NeRF and ``{"stages": {"floor", "unfitted", "map_depth", "lidar_s", "camera_s"}}`` for the stages.

    Raises:
        FloorError: the dataset has no ground truth, a setting is out of range, or the output folder is refused.
        RigFormatError: rig.json is malformed.
    """
    import torch

    from moisst_ns.rig.format import load_calibration, load_rig

    rig = load_rig(cfg.dataset)
    if not (rig.root / "ground_truth.json").is_file():
        raise FloorError(f"{rig.root / 'ground_truth.json'}: not found: the floor is measured against the true calibration")
    if cfg.register_steps < 1 or cfg.log_every < 1 or cfg.average_last < 1:
        raise FloorError("--register-steps, --log-every and --average-last must be >= 1")
    if not (cfg.nerf or cfg.stages):
        raise FloorError("--no-nerf and --no-stages together leave nothing to measure")
    out = Path(cfg.output_dir)
    try:
        check_output_dir(out, rig.root, create=True)
    except RunError as err:
        raise FloorError(str(err)) from None
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    result: dict = {"method": cfg.method}
    if cfg.stages:
        result["stages"] = stages_floor(rig, load_calibration(rig.root / "ground_truth.json"))
    if cfg.nerf:
        result.update(nerf_floor(cfg, rig, out))
    (out / "floor.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def stages_floor(rig, truth) -> dict:
    """``stage_floor.stage_floor`` (LiDAR first and the camera registration started at the truth) and, on
    ``moisst-synth`` rigs with a LiDAR, ``stage_floor.map_depth_errors`` (the LiDAR map against the true scene)."""
    from moisst_ns.stages.stage_floor import map_depth_errors, stage_floor

    measured = stage_floor(rig, truth, log=lambda line: None)
    scene = synthetic_scene(rig.root) if any(s.type == "lidar" for s in rig.sensors.values()) else None
    if scene is not None:
        measured["map_depth"] = map_depth_errors(rig, truth, lambda o, d: scene.cast(o, d)["t_hit"].astype(np.float64))
    return measured


def nerf_floor(cfg: FloorConfig, rig, out: Path) -> dict:
    """The NeRF floor: the scene trained at the truth, the calibration released at the truth against it."""
    import torch
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    config = rig_trainer_config(cfg.method, cfg.scene_steps, rig.root, out, "scene", cfg.seed)
    config.vis = "tensorboard"
    model, datamanager = config.pipeline.model, config.pipeline.datamanager
    config.pipeline = VanillaPipelineConfig(datamanager=datamanager, model=model)  # the scene alone: no stages, no calibration.json
    if cfg.map_range_mult > 0 and any(s.type == "lidar" for s in rig.sensors.values()):
        datamanager.dataparser.prior_calibration = rig.root / "ground_truth.json"  # the map and the frames at the truth
        map_range_settings(config.pipeline, cfg.map_range_mult, [n for n, s in rig.sensors.items() if s.type == "camera"])
    # The scene is built at the true calibration, so the phases that protect it from miscalibrated sensors
    # (reference-only warm-up, detached registration, coarse-to-fine) are switched off: the best scene of this budget.
    fixed_calibration_scene(config.pipeline)
    config.save_config()

    trainer = set_up_trainer(config, cfg.seed)
    pipeline = trainer.pipeline
    optimizer = pipeline.model.camera_optimizer
    optimizer.set_trainable(False)  # held while the scene trains (released for the registration below)
    optimizer.rig.set_corrections_to(optimizer.rig.data.ground_truth)  # the scene trains at the truth
    start = time.time()
    trainer.train()
    scene_wall = time.time() - start

    for param in pipeline.model.parameters():
        param.requires_grad_(False)
    pipeline.model.train()
    depth = scene_depth_check(pipeline, rig.root, cfg.depth_check_rays) if cfg.depth_check_rays > 0 else {}

    # Register: the scene frozen, every sensor released at its truth. A camera whose pose is estimated has no map
    # range in a real run (moisst-calibrate gives it only to cameras the stages hold), so that term ends with the scene.
    scene_map_range_mult = float(pipeline.model.config.map_range_mult)
    pipeline.model.config.map_range_mult = 0.0
    rig_params = optimizer.rig
    groups = dict(zip(CALIBRATION_GROUPS, (rig_params.rotvec, rig_params.translation, rig_params.time_offset)))
    steppers = []
    for key, param in groups.items():
        param.requires_grad_(True)
        settings = config.optimizers[key]
        opt = settings["optimizer"].setup(params=[param])
        scheduler = ExponentialDecaySchedulerConfig(lr_final=settings["scheduler"].lr_final, max_steps=cfg.register_steps).setup()
        steppers.append((opt, scheduler.get_scheduler(optimizer=opt, lr_init=settings["optimizer"].lr)))
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
    return {
        "scene_steps": config.max_num_iterations,
        "register_steps": cfg.register_steps,
        "average_last": cfg.average_last,
        "map_range_mult": scene_map_range_mult,
        "scene_wall_time_s": scene_wall,
        "register_wall_time_s": register_wall,
        "floor": floor_errors([r for r in rows if r["step"] > 0], cfg.average_last),
        "depth": depth,
    }


def floor_summary(result: dict) -> str:
    """The floor tables and the depth figures as printed by ``moisst-floor``."""
    lines = []
    stages = result.get("stages")
    if stages:
        lines.append(format_error_table(f"floor of the pre-NeRF stages (LiDAR first {stages['lidar_s']:.0f} s, camera registration "
                                        f"{stages['camera_s']:.0f} s, both started at the truth):", stages["floor"]))
        lines += [f"  not fitted: {reason}" for reason in stages["unfitted"]]
        depth = stages.get("map_depth", {})
        if depth.get("camera_rays"):
            lines.append(f"LiDAR-map depth error where the cameras' fits look: median {depth['median_abs_m'] * 1000:.3g} mm, "
                         f"90th percentile {depth['p90_abs_m'] * 1000:.3g} mm ({depth['camera_rays']} rays, {depth['map_points']} map points)")
    if "floor" in result:
        lines.append(format_error_table(f"NeRF floor ({result['scene_steps']} scene steps at the truth, then {result['register_steps']} "
                                        "calibration steps from the truth against the frozen scene):", result["floor"]))
    depth = result.get("depth", {})
    if "median_abs_m" in depth:
        lines.append(f"camera-ray depth error in the LiDAR's field: median {depth['median_abs_m'] * 100:.1f} cm, "
                     f"90th percentile {depth['p90_abs_m'] * 100:.1f} cm ({depth['camera_rays']} rays)")
    if "lidar_median_abs_m" in depth:
        lines.append(f"LiDAR-ray depth error: median {depth['lidar_median_abs_m'] * 100:.1f} cm ({depth['lidar_rays']} rays)")
    return "\n".join(lines)
