"""``moisst-synth``: synthetic multi-sensor rigs with exact ground truth, in the ``moisst-rig/1`` format.

A vehicle drives a turning path at varying speed through a textured box world (``street`` or ``plaza``), carrying
three pinhole cameras and a spinning LiDAR at 10 Hz, triggered at different phases and with true clock offsets of
20-60 ms. The data are exactly consistent with ``moisst_ns.rig.geometry``: the reference trajectory is written to
``reference_poses.txt`` first and read back, and a frame of sensor ``i`` stamped ``t`` (its own clock) is rendered
at ``T_r(t + delta_i) @ ref_T_i`` (paper eq. 1-2); a LiDAR point fired ``tau`` after the stamp at
``T_r(t + delta_L + tau) @ ref_T_L``. Everything is seeded (same configuration, byte-identical files). The scene is
``synth_scene``, the vehicle and the rig ``synth_rig``, the frames ``synth_render``, the real-world effects (off by
default) ``synth_effects``; ``config_of_rig`` reads a generated rig's configuration back. Axes: world z up; vehicle
x forward, y left, z up; cameras OpenCV; LiDAR x forward, y left, z up.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from functools import partial
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Tuple

import numpy as np
import tyro

from moisst_ns.datasets.rig_writer import prepare_out, unit_quats, write_rig
from moisst_ns.datasets.synth_effects import Effects, check_effects, make_movers, photometric_params, resolve_effects
from moisst_ns.datasets.synth_render import LIDAR_MAX_RANGE, LIDAR_MIN_RANGE, PERIOD, write_camera_frames, write_lidar_frames
from moisst_ns.datasets.synth_rig import MOUNTS, REFERENCE, SensorTruth, _streams, knock_mount, make_priors, make_truth, vehicle_T_sensor
from moisst_ns.datasets.synth_scene import Scene, VehiclePath, _ground, _plaza_objects, _street_objects
from moisst_ns.rig.trajectory_noise import TrajectoryAccuracy, perturb_trajectory

T0 = 1000.0
"""Absolute time of the first reference frame, seconds (keeps stamps away from zero, like real clocks)."""


class SynthError(ValueError):
    """A configuration or output folder moisst-synth refuses; the message is one line."""


@dataclass
class SynthConfig:
    """Generate a synthetic rig dataset (moisst-rig/1) with exact ground truth."""

    out: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]
    """Output dataset folder (created; must be absent or empty unless --overwrite)."""
    seed: int = 0
    """Seed of everything random: true extrinsics and offsets, scene layout, path turn direction, prior perturbation."""
    frames: int = 50
    """Frames per sensor (10 Hz, so the sequence lasts about frames / 10 seconds)."""
    width: int = 320
    """Image width of every camera, pixels."""
    height: int = 240
    """Image height of every camera, pixels."""
    perturb: Literal["none", "paper"] = "paper"
    """Priors in rig.json: 'none' = the truth; 'paper' = truth perturbed as in the MOISST paper (section IV):
    +-translation on every axis, rotation by +-rotation about every axis, +-time on the offset (random signs)."""
    lidar: bool = True
    """Include the spinning LiDAR."""
    layout: Literal["street", "plaza"] = "street"
    """Scene: 'street' (facades on both sides of a curving road, end walls) or 'plaza' (open square with scattered
    blocks and columns, surrounded by buildings)."""
    perturb_translation: float = 0.5
    """Translation perturbation of --perturb paper, metres per axis (reference frame)."""
    perturb_rotation: float = 5.0
    """Rotation perturbation of --perturb paper, degrees about each axis (R_prior = R_true Rx Ry Rz)."""
    perturb_time: float = 0.1
    """Time offset perturbation of --perturb paper, seconds."""
    supersample: int = 1
    """Rays per pixel along each image axis (2 = 2x2 supersampling, 4x the rendering time)."""
    lidar_beams: int = 32
    """Number of LiDAR beams, evenly spread over -25..+10 degrees of elevation."""
    lidar_azimuth_steps: int = 1024
    """LiDAR firings per revolution (one revolution per frame period)."""
    lidar_max_points: int = 16384
    """Keep at most this many points per scan (a seeded random subset, kept in firing order)."""
    lidar_scans: Literal["raw", "compensated"] = "raw"
    """'raw': each point in the LiDAR frame at its own firing time, with per-point times (``.npz`` points + times);
    'compensated': motion-compensated like KITTI-360's scans, every point in the LiDAR frame at the frame stamp and
    no times (``.npz`` points only)."""
    lidar_noise: Annotated[Optional[float], tyro.conf.arg(metavar="METRES")] = None
    """Standard deviation of Gaussian range noise on every LiDAR point, metres (None or 0: exact ranges).
    --realistic: 0.02."""
    drive: Literal["curve", "straight", "weave"] = "curve"
    """Vehicle path: 'curve' (one turn and back, speed 4-9 m/s, small pitch/roll/bounce), 'straight' (constant 6.5
    m/s on a flat straight line: delta and the along-track lever arm cannot be separated) or 'weave' (heading
    swinging every 4 s at the curve's varying speed)."""
    overwrite: bool = False
    """Replace the generator's outputs in a non-empty OUT (other files there are left alone)."""
    rig_seed: Optional[int] = None
    """Seed of the true extrinsics, time offsets and prior perturbation (default: --seed). Two drives of one vehicle
    share it and differ in --seed (path, scene), e.g. for ``moisst-fleet``."""
    knock: Optional[Tuple[str, float]] = None
    """SENSOR DEG: turn that sensor's true mount by DEG degrees about the vehicle's vertical axis (a mount knocked in
    the workshop); its prior in rig.json stays the unknocked one."""
    realistic: bool = False
    """Turn on every real-world effect (all the switches below and --lidar-noise, not --rolling-shutter) at the
    magnitudes of a real drive, given after '--realistic:' in each. A switch left at None is off without
    --realistic; one given explicitly always wins (0: that effect off)."""
    pose_noise: Annotated[Optional[Tuple[float, float]], tyro.conf.arg(metavar="CM DEG")] = None
    """White noise on the written reference trajectory only (images and scans stay at the true poses): standard
    deviation per axis of the position, centimetres, and of the rotation about the camera's axes, degrees.
    --realistic: 1 0.02."""
    pose_drift: Annotated[Optional[Tuple[float, float]], tyro.conf.arg(metavar="CM DEG")] = None
    """Slow drift added to the written reference trajectory: RMS per axis over the drive, centimetres and degrees
    (three sinusoids per axis with periods of 3-12 s). --realistic: 3 0.05."""
    exposure: Annotated[Optional[float], tyro.conf.arg(metavar="FRACTION")] = None
    """Per-frame auto-exposure of every camera, amplitude A: gain in 1 +- A, gamma in 1 +- A/2, tint per channel in
    1 +- A/4, drawn per frame. --realistic: 0.3."""
    vignetting: Annotated[Optional[float], tyro.conf.arg(metavar="FRACTION")] = None
    """Brightness lost at the image corners (falling off with the squared distance from the principal point).
    --realistic: 0.3."""
    distortion: Annotated[Optional[Tuple[float, float]], tyro.conf.arg(metavar="K1 K2")] = None
    """OPENCV radial distortion of every camera (images rendered through it; rig.json: camera_model OPENCV, k1, k2,
    p1 = p2 = 0). --realistic: -0.12 0.03."""
    movers: Annotated[Optional[int], tyro.conf.arg(metavar="N")] = None
    """Moving vehicles: car-size boxes driving along the road both ways at 4-10 m/s, seen by the cameras and the
    LiDAR where they are at each ray's own time. --realistic: 8."""
    motion_blur: Annotated[Optional[float], tyro.conf.arg(metavar="SECONDS")] = None
    """Exposure time of every camera, seconds: each image is the mean of 3 renders spread over it, centred on each
    row's time. --realistic: 0.004."""
    jpeg_quality: Annotated[Optional[int], tyro.conf.arg(metavar="QUALITY")] = None
    """Write the images as JPEG (.jpg) at this quality, 1-100, instead of PNG (0: PNG). --realistic: 90."""
    lidar_dropout: Annotated[Optional[float], tyro.conf.arg(metavar="FRACTION")] = None
    """Fraction of the LiDAR returns dropped at random. --realistic: 0.1."""
    rolling_shutter: Annotated[float, tyro.conf.arg(metavar="READOUT_S")] = 0.0
    """Rolling-shutter readout time of every camera, seconds: row r (0 = top) of an H-row image stamped t is exposed
    at t + READOUT_S (r - (H-1)/2) / (H-1) (the stamp is the middle row's time); written as each camera's
    readout_time in rig.json. 0: global shutter. Not part of --realistic."""


# ----------------------------------------------------------------------------------------------------------------
# Vehicle path


def make_path(config: SynthConfig) -> VehiclePath:
    """The vehicle path of a configuration (seeded turn direction and oscillation phases)."""
    rng = np.random.default_rng(_streams(config.seed)["path"])
    turn = np.deg2rad(rng.uniform(38.0, 50.0)) * rng.choice([-1.0, 1.0])
    duration = (config.frames - 1) * PERIOD
    return VehiclePath(turn=float(turn), phases=rng.uniform(0, 2 * np.pi, 3), t_min=-10.0, t_max=duration + 14.0,
                       drive=config.drive)


# ----------------------------------------------------------------------------------------------------------------
# Scene


def build_scene(config: SynthConfig, path: Optional[VehiclePath] = None) -> Scene:
    """The scene of a configuration (depends on seed, layout and frames only): deterministic."""
    path = make_path(config) if path is None else path
    rng = np.random.default_rng(_streams(config.seed)["scene"])
    s_start = path.s_at(0.0) - 20.0
    s_end = path.s_at((config.frames - 1) * PERIOD) + 38.0
    objs = {"street": _street_objects, "plaza": _plaza_objects}[config.layout](path, s_start, s_end, rng)
    verts = np.concatenate([o.vertices for o in objs])
    center = 0.5 * (verts[:, :2].min(axis=0) + verts[:, :2].max(axis=0))
    extent = float(np.max(verts[:, :2].max(axis=0) - verts[:, :2].min(axis=0))) + 150.0
    return Scene([_ground(center, extent, rng)] + objs)


# ----------------------------------------------------------------------------------------------------------------
# Rig


def intrinsics(config: SynthConfig) -> Dict[str, object]:
    """PINHOLE intrinsics shared by every camera: fl = 0.8 W (horizontal FOV ~64 deg), centred principal point."""
    fl = 0.8 * config.width
    return {"camera_model": "PINHOLE", "w": config.width, "h": config.height, "fl_x": fl, "fl_y": fl,
            "cx": config.width / 2.0, "cy": config.height / 2.0}


def frame_stamps(sensor: SensorTruth, frames: int) -> List[float]:
    """Own-clock timestamps of a sensor's frames (rounded to the nanosecond)."""
    return [round(T0 + k * PERIOD + sensor.phase, 9) for k in range(frames)]


def reference_trajectory_samples(config: SynthConfig, path: VehiclePath, truth: Dict[str, SensorTruth]):
    """TUM columns of ``world_T_ref`` at the reference camera's frame times: (stamps, positions, quats xyzw)."""
    stamps = np.array(frame_stamps(truth[REFERENCE], config.frames))
    poses = path.world_T_vehicle(stamps - T0) @ vehicle_T_sensor(REFERENCE)
    return stamps, poses[:, :3, 3], unit_quats(poses[:, :3, :3])


def _check_config(config: SynthConfig) -> None:
    problems = []
    if config.frames < 2:
        problems.append(f"--frames must be >= 2, got {config.frames}")
    if config.width < 8 or config.height < 8:
        problems.append(f"--width and --height must be >= 8, got {config.width}x{config.height}")
    if config.supersample < 1:
        problems.append(f"--supersample must be >= 1, got {config.supersample}")
    if config.lidar_beams < 1 or config.lidar_azimuth_steps < 1 or config.lidar_max_points < 1:
        problems.append("--lidar-beams, --lidar-azimuth-steps and --lidar-max-points must be >= 1")
    problems += check_effects(resolve_effects(config), intrinsics(config), PERIOD)
    if config.knock is not None and (config.knock[0] == REFERENCE or config.knock[0] not in MOUNTS):
        problems.append(f"--knock: sensor must be one of {', '.join(n for n in MOUNTS if n != REFERENCE)}, got {config.knock[0]!r}")
    if problems:
        raise SynthError("; ".join(problems))


def _camera_entry(intr: Dict[str, object], fx: Effects) -> Dict[str, object]:
    """rig.json intrinsics of every camera: ``intr``, with the lens distortion and readout time when on."""
    if any(fx.distortion):
        intr = {**intr, "camera_model": "OPENCV", "k1": fx.distortion[0], "k2": fx.distortion[1], "p1": 0.0, "p2": 0.0}
    return {**intr, "readout_time": fx.rolling_shutter} if fx.rolling_shutter else intr


def make_rig(config: SynthConfig) -> Path:
    """Generate the dataset described by ``config`` into ``config.out``; returns that folder."""
    import torch

    from moisst_ns.rig.format import Calibration, load_tum, write_tum
    from moisst_ns.rig.geometry import ReferenceTrajectory

    _check_config(config)
    fx = resolve_effects(config)
    out = prepare_out(Path(config.out), [], config.overwrite, lambda out, _, problem: SynthError(f"{out} {problem}"), "")
    path = make_path(config)
    truth = make_truth(config)
    priors = make_priors(config, truth)
    truth = knock_mount(config, truth)  # after the priors: they keep the mount as it was
    scene = build_scene(config, path)
    streams = _streams(config.seed)

    # 1. The reference trajectory, written first and read back: rendering uses exactly what consumers will read,
    # unless --pose-noise / --pose-drift replace the file by a noisy version (the frames stay at the true poses).
    header = "moisst-synth reference trajectory world_T_cam_front: timestamp tx ty tz qx qy qz qw"
    samples = reference_trajectory_samples(config, path, truth)
    write_tum(out / "reference_poses.txt", *samples, header=header)
    traj = ReferenceTrajectory.from_tum(*load_tum(out / "reference_poses.txt"))
    accuracy = TrajectoryAccuracy(fx.pose_noise[0] / 100, fx.pose_noise[1], fx.pose_drift[0] / 100, fx.pose_drift[1])  # stated as written
    if fx.trajectory:
        noisy = perturb_trajectory(*samples, fx.pose_noise, fx.pose_drift, streams["pose_noise"])
        write_tum(out / "reference_poses.txt", samples[0], *noisy, header=header + " (with pose noise / drift)")

    def world_T(sensor: SensorTruth, stamps: np.ndarray) -> np.ndarray:
        t_rel = torch.as_tensor(np.asarray(stamps, dtype=np.float64) + sensor.time_offset) - traj.t0
        ref = traj(t_rel).numpy()
        return ref @ sensor.T_ref_sensor

    intr = intrinsics(config)
    movers = make_movers(path, fx.movers, (config.frames - 1) * PERIOD, len(scene.atlas.names), np.random.default_rng(streams["movers"])) if fx.movers else None
    cameras = [n for n in MOUNTS if n.startswith("cam")]
    photometric = photometric_params(np.random.default_rng(streams["exposure"]), len(cameras), config.frames, fx.exposure) if fx.exposure else None
    lidar_rngs = tuple(np.random.default_rng(streams[k]) for k in ("lidar", "lidar_noise", "lidar_dropout"))
    frames = []
    for name, sensor in truth.items():
        stamps = frame_stamps(sensor, config.frames)
        folder = ("images" if sensor.type == "camera" else "lidar") + f"/{name}"
        (out / folder).mkdir(parents=True, exist_ok=True)
        pose_at, to_path_time = partial(world_T, sensor), sensor.time_offset - traj.t0  # own clock -> scene clock
        if sensor.type == "camera":
            exposure = None if photometric is None else photometric[cameras.index(name)]
            frames += write_camera_frames(out, folder, name, stamps, scene, intr, pose_at, to_path_time, fx, movers, exposure, config.supersample)
        else:
            frames += write_lidar_frames(out, folder, name, stamps, scene, config, pose_at, to_path_time, fx, movers, lidar_rngs)
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items() if k not in ("out", "overwrite")}
    switches = [f.name for f in fields(Effects) if f.name != "rolling_shutter"]  # None: off unless --realistic
    unused = {"lidar_scans": "raw", "drive": "curve", "rig_seed": None, "knock": None, "realistic": False, "rolling_shutter": 0.0,
              **{name: None for name in switches}}
    for key, default in unused.items():  # recorded when used (older rigs stay byte-identical); an explicit 0 is off
        if meta[key] == default or (key in switches and not config.realistic and not np.any(meta[key])):
            del meta[key]
    if fx.summary():
        meta["effects"] = fx.summary()  # what the switches resolved to (not read back by config_of_rig)
    meta["generator"] = "moisst-synth"
    meta["note"] = "priors per --perturb; true values in ground_truth.json"
    write_rig(out, REFERENCE, list(truth), ["lidar"], {n: _camera_entry(intr, fx) for n in cameras}, frames, priors, meta, accuracy=accuracy)
    Calibration(
        REFERENCE, {n: s.T_ref_sensor for n, s in truth.items()}, {n: s.time_offset for n, s in truth.items()}
    ).write(out / "ground_truth.json")
    return out


# ----------------------------------------------------------------------------------------------------------------
# What a generated rig's truth is, for measuring a scene against it


def config_of_rig(metadata: dict) -> Optional[SynthConfig]:
    """The ``SynthConfig`` a moisst-synth rig was generated with (rig.json's ``metadata``), or None for other rigs.

    Args:
        metadata: rig.json's ``"metadata"`` object (``{}`` when absent).

    Returns:
        The configuration (``out`` set to ``.``), from which ``build_scene`` rebuilds the exact scene geometry.
    """
    if metadata.get("generator") != "moisst-synth":
        return None
    names = {f for f in SynthConfig.__dataclass_fields__ if f not in ("out", "overwrite")}
    return SynthConfig(out=Path("."), **{k: v for k, v in metadata.items() if k in names})


def in_lidar_field(points: np.ndarray) -> np.ndarray:
    """Which points (LiDAR frame, metres) the synthetic LiDAR can measure: range and beam elevation limits.

    Args:
        points: (N, 3) points in the LiDAR frame, metres.

    Returns:
        (N,) boolean mask.
    """
    ranges = np.linalg.norm(points, axis=-1)
    elevation = np.rad2deg(np.arcsin(np.clip(points[:, 2] / np.maximum(ranges, 1e-9), -1.0, 1.0)))
    return (ranges >= LIDAR_MIN_RANGE) & (ranges <= LIDAR_MAX_RANGE) & (elevation >= -25.0) & (elevation <= 10.0)
