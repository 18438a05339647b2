"""``moisst-synth``: synthetic multi-sensor rigs with exact ground truth, in the ``moisst-rig/1`` format.

A vehicle drives a smooth path that turns (heading changes by tens of degrees) and changes speed (4 <-> 9 m/s)
through a textured box world (``street`` or ``plaza`` layout), carrying three pinhole cameras and a spinning
LiDAR, all at 10 Hz but triggered at different phases of the cycle and with true clock offsets of 20-60 ms.

The data are exactly consistent with the calibration model of ``moisst_ns.rig.geometry``: the reference
trajectory is written to ``reference_poses.txt`` first, read back, and a frame of sensor ``i`` stamped ``t`` (its
own clock) is rendered at ``world_T_i = T_r(t + delta_i) @ ref_T_i`` (paper eq. 1-2) with ``T_r`` interpolating the
written samples. LiDAR points are motion-distorted like a raw scan: a point fired ``tau`` seconds after the frame
stamp is expressed in the LiDAR frame at ``T_r(t + delta_L + tau) @ ref_T_L``.

Geometry is rendered by ray casting (``open3d.t.geometry.RaycastingScene``); colours come from photographs shipped
inside scikit-image, mapped per object by a planar (box) projection of the hit point, tiled at several metre scales,
sampled trilinearly from a mip pyramid, with view-independent Lambert shading. Everything is seeded: the same
configuration gives byte-identical files.

Axes: world z up; vehicle frame x forward, y left, z up; cameras OpenCV (x right, y down, z forward); LiDAR x forward,
y left, z up.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import tyro

from moisst_ns.datasets.synth_scene import Scene, VehiclePath, _ground, _plaza_objects, _street_objects, rot_x, rot_y, rot_z

T0 = 1000.0
"""Absolute time of the first reference frame, seconds (keeps stamps away from zero, like real clocks)."""
PERIOD = 0.1
"""Frame period of every sensor and the LiDAR revolution time, seconds (10 Hz)."""
REFERENCE = "cam_front"
LIDAR_MIN_RANGE = 0.5
LIDAR_MAX_RANGE = 60.0


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
    lidar_noise: float = 0.0
    """Standard deviation of Gaussian range noise on every LiDAR point, metres (0: exact ranges)."""
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


# ----------------------------------------------------------------------------------------------------------------
# Small rotation helpers (numpy, float64)


def _pose(rotation: np.ndarray, translation) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def _inv(pose: np.ndarray) -> np.ndarray:
    return _pose(pose[:3, :3].T, -pose[:3, :3].T @ pose[:3, 3])


def _orthonormalise(rotation: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(rotation)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


# OpenCV camera axes expressed in the vehicle frame (x forward, y left, z up): cam x = right = -y_V,
# cam y = down = -z_V, cam z = forward = x_V.
V_R_OPENCV = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def perturbation_rotation(signs: Sequence[float], degrees: float) -> np.ndarray:
    """``Rx(sx a) @ Ry(sy a) @ Rz(sz a)``, the rotation part of the paper's prior perturbation."""
    a = np.deg2rad(degrees)
    return rot_x(signs[0] * a) @ rot_y(signs[1] * a) @ rot_z(signs[2] * a)


def paper_perturbation(T_ref_sensor: np.ndarray, time_offset: float, signs: Sequence[float], translation: float,
                       rotation_deg: float, time: float) -> Tuple[np.ndarray, float]:
    """The MOISST paper's prior perturbation (section IV) of one sensor.

    Args:
        T_ref_sensor: true extrinsic (4x4).
        time_offset: true delta, seconds.
        signs: 7 signs (+-1): translation x, y, z; rotation about x, y, z; time.
        translation: metres per axis. rotation_deg: degrees about each axis. time: seconds.

    Returns:
        (prior extrinsic ``[R Rx Ry Rz | t + s * translation]``, prior delta ``time_offset + s * time``).
    """
    prior = T_ref_sensor.copy()
    prior[:3, :3] = T_ref_sensor[:3, :3] @ perturbation_rotation(signs[3:6], rotation_deg)
    prior[:3, 3] = T_ref_sensor[:3, 3] + np.asarray(signs[:3]) * translation
    return prior, float(time_offset + signs[6] * time)


# ----------------------------------------------------------------------------------------------------------------
# Vehicle path


def make_path(config: SynthConfig) -> VehiclePath:
    """The vehicle path of a configuration (seeded turn direction and oscillation phases)."""
    rng = np.random.default_rng(_streams(config.seed)["path"])
    turn = np.deg2rad(rng.uniform(38.0, 50.0)) * rng.choice([-1.0, 1.0])
    duration = (config.frames - 1) * PERIOD
    return VehiclePath(turn=float(turn), phases=rng.uniform(0, 2 * np.pi, 3), t_min=-10.0, t_max=duration + 14.0,
                       drive=config.drive)


def _streams(seed: int) -> Dict[str, np.random.SeedSequence]:
    names = ("path", "rig", "scene", "perturb", "lidar", "lidar_noise")
    return dict(zip(names, np.random.SeedSequence(seed).spawn(len(names))))


# ----------------------------------------------------------------------------------------------------------------
# Textures


# ----------------------------------------------------------------------------------------------------------------
# Scene


def build_scene(config: SynthConfig, path: Optional[VehiclePath] = None) -> Scene:
    """The scene of a configuration (depends on seed, layout and frames only): deterministic."""
    path = make_path(config) if path is None else path
    rng = np.random.default_rng(_streams(config.seed)["scene"])
    s_start = path.s_at(0.0) - 20.0
    s_end = path.s_at((config.frames - 1) * PERIOD) + 38.0
    if config.layout == "street":
        objs = _street_objects(path, s_start, s_end, rng)
    elif config.layout == "plaza":
        objs = _plaza_objects(path, s_start, s_end, rng)
    else:
        raise ValueError(f"unknown layout {config.layout!r}")
    verts = np.concatenate([o.vertices for o in objs])
    center = 0.5 * (verts[:, :2].min(axis=0) + verts[:, :2].max(axis=0))
    extent = float(np.max(verts[:, :2].max(axis=0) - verts[:, :2].min(axis=0))) + 150.0
    return Scene([_ground(center, extent, rng)] + objs)


# ----------------------------------------------------------------------------------------------------------------
# Rig


@dataclass
class SensorTruth:
    """A sensor's true calibration and trigger phase."""

    name: str
    type: str
    T_ref_sensor: np.ndarray
    time_offset: float
    phase: float
    """Its frames are stamped ``T0 + k * PERIOD + phase`` on its own clock."""


# Nominal mounts in the vehicle frame (x forward, y left, z up): position, yaw, pitch-down (degrees).
MOUNTS = {
    "cam_front": ((1.8, 0.0, 1.6), 0.0, 3.0),
    "cam_front_right": ((1.8, -0.55, 1.6), -10.0, 3.0),
    "cam_left": ((1.2, 0.8, 1.5), 85.0, 5.0),
    "lidar": ((1.5, 0.0, 2.0), 0.0, 0.0),
}
PHASES = {"cam_front": 0.0, "cam_front_right": 0.025, "cam_left": 0.05, "lidar": 0.075}


def vehicle_T_sensor(name: str, jitter_t=(0.0, 0.0, 0.0), jitter_r=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Mount of a sensor on the vehicle, with optional jitter (metres; radians about the sensor's own axes)."""
    pos, yaw, pitch = MOUNTS[name]
    body = rot_z(np.deg2rad(yaw)) @ rot_y(np.deg2rad(pitch))
    axes = V_R_OPENCV if name.startswith("cam") else np.eye(3)
    rot = body @ axes @ rot_x(jitter_r[0]) @ rot_y(jitter_r[1]) @ rot_z(jitter_r[2])
    return _pose(_orthonormalise(rot), np.asarray(pos) + np.asarray(jitter_t))


def _rig_seed(config: SynthConfig) -> int:
    return config.seed if config.rig_seed is None else config.rig_seed


def knock_mount(config: SynthConfig, truth: Dict[str, SensorTruth]) -> Dict[str, SensorTruth]:
    """The truth with ``--knock SENSOR DEG`` applied: that sensor turned about the vehicle's z axis, in place."""
    if config.knock is None:
        return truth
    name, degrees = config.knock
    v_T_ref = vehicle_T_sensor(REFERENCE)
    sensor = truth[name]
    v_T_s = v_T_ref @ sensor.T_ref_sensor
    v_T_s[:3, :3] = _orthonormalise(rot_z(np.deg2rad(degrees)) @ v_T_s[:3, :3])
    ref_T = _inv(v_T_ref) @ v_T_s
    ref_T[:3, :3] = _orthonormalise(ref_T[:3, :3])
    ref_T[3] = [0.0, 0.0, 0.0, 1.0]
    return {**truth, name: SensorTruth(name, sensor.type, ref_T, sensor.time_offset, sensor.phase)}


def make_truth(config: SynthConfig) -> Dict[str, SensorTruth]:
    """True extrinsics (in the reference camera's frame) and time offsets; seeded."""
    rng = np.random.default_rng(_streams(_rig_seed(config))["rig"])
    v_T_ref = vehicle_T_sensor(REFERENCE)
    sign = rng.choice([-1.0, 1.0])
    signs = {"cam_front_right": sign, "cam_left": -sign, "lidar": rng.choice([-1.0, 1.0])}
    truth = {REFERENCE: SensorTruth(REFERENCE, "camera", np.eye(4), 0.0, PHASES[REFERENCE])}
    for name in ("cam_front_right", "cam_left", "lidar"):
        jt = rng.uniform(-0.03, 0.03, 3)
        jr = np.deg2rad(rng.uniform(-1.0, 1.0, 3))
        delta = round(float(signs[name] * rng.uniform(0.02, 0.06)), 6)
        if name == "lidar" and not config.lidar:
            continue
        ref_T = _inv(v_T_ref) @ vehicle_T_sensor(name, jt, jr)
        ref_T[:3, :3] = _orthonormalise(ref_T[:3, :3])
        ref_T[3] = [0.0, 0.0, 0.0, 1.0]
        truth[name] = SensorTruth(name, "lidar" if name == "lidar" else "camera", ref_T, delta, PHASES[name])
    return truth


def make_priors(config: SynthConfig, truth: Dict[str, SensorTruth]) -> Dict[str, Tuple[np.ndarray, float]]:
    """Priors for rig.json: the truth (--perturb none) or the paper's perturbation (--perturb paper)."""
    rng = np.random.default_rng(_streams(_rig_seed(config))["perturb"])
    priors = {}
    for name in ("cam_front", "cam_front_right", "cam_left", "lidar"):
        signs = rng.choice([-1.0, 1.0], size=7)  # drawn for every sensor, so signs do not depend on --no-lidar
        if name not in truth:
            continue
        t = truth[name]
        if name == REFERENCE or config.perturb == "none":
            priors[name] = (t.T_ref_sensor.copy(), t.time_offset)
            continue
        priors[name] = paper_perturbation(t.T_ref_sensor, t.time_offset, signs, config.perturb_translation,
                                          config.perturb_rotation, config.perturb_time)
    return priors


def intrinsics(config: SynthConfig) -> Dict[str, object]:
    """PINHOLE intrinsics shared by every camera: fl = 0.8 W (horizontal FOV ~64 deg), centred principal point."""
    fl = 0.8 * config.width
    return {"camera_model": "PINHOLE", "w": config.width, "h": config.height, "fl_x": fl, "fl_y": fl,
            "cx": config.width / 2.0, "cy": config.height / 2.0}


def frame_stamps(sensor: SensorTruth, frames: int) -> List[float]:
    """Own-clock timestamps of a sensor's frames (rounded to the nanosecond)."""
    return [round(T0 + k * PERIOD + sensor.phase, 9) for k in range(frames)]


def render_camera(scene: Scene, intr: Dict[str, object], world_T_cam: np.ndarray, supersample: int = 1) -> Tuple[np.ndarray, np.ndarray]:
    """Render a pinhole camera (OpenCV axes; pixel centres at +0.5).

    Returns:
        (uint8 RGB image (h, w, 3), fraction of each pixel's rays that hit geometry (h, w)).
    """
    w, h, ss = int(intr["w"]), int(intr["h"]), int(supersample)
    u = (np.arange(w * ss) + 0.5) / ss
    v = (np.arange(h * ss) + 0.5) / ss
    uu, vv = np.meshgrid(u, v)
    dirs = np.stack([(uu - intr["cx"]) / intr["fl_x"], (vv - intr["cy"]) / intr["fl_y"], np.ones_like(uu)], axis=-1)
    dirs = dirs.reshape(-1, 3) @ world_T_cam[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rgb, hit = scene.colour(world_T_cam[:3, 3], dirs, 1.0 / (float(intr["fl_x"]) * ss))
    rgb = rgb.reshape(h, ss, w, ss, 3).mean(axis=(1, 3))
    hit = hit.reshape(h, ss, w, ss).mean(axis=(1, 3))
    return (np.clip(rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8), hit


def lidar_beam_directions(config: SynthConfig) -> Tuple[np.ndarray, np.ndarray]:
    """Unit directions (beams, steps, 3) in the LiDAR frame, and the firing time of each step (steps,).

    The head spins clockwise seen from above (like a Velodyne), starting pointing backwards; all beams of a step fire
    together at ``step * PERIOD / steps`` seconds after the frame stamp.
    """
    elev = np.deg2rad(np.linspace(-25.0, 10.0, config.lidar_beams))
    steps = config.lidar_azimuth_steps
    azim = np.pi - 2 * np.pi * np.arange(steps) / steps
    dirs = np.stack([
        np.cos(elev)[:, None] * np.cos(azim)[None, :],
        np.cos(elev)[:, None] * np.sin(azim)[None, :],
        np.broadcast_to(np.sin(elev)[:, None], (config.lidar_beams, steps)),
    ], axis=-1)
    return dirs, np.arange(steps) * (PERIOD / steps)


def render_lidar(scene: Scene, config: SynthConfig, world_T_lidar_steps: np.ndarray, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """One motion-distorted scan.

    Args:
        world_T_lidar_steps: (steps, 4, 4) LiDAR pose at each firing step.
        rng: for the subset kept when there are more than ``lidar_max_points`` hits.

    Returns:
        (points (N, 3) float32 in the LiDAR frame at each point's own firing time, per-point time offsets (N,)).
    """
    local, times = lidar_beam_directions(config)
    local = local.transpose(1, 0, 2)  # (steps, beams, 3): firing order
    rot = world_T_lidar_steps[:, :3, :3]
    dirs = np.einsum("sij,sbj->sbi", rot, local)
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.broadcast_to(world_T_lidar_steps[:, None, :3, 3], dirs.shape)
    res = scene.cast(origins.reshape(-1, 3), dirs.reshape(-1, 3))
    rng_ = res["t_hit"]
    keep = np.flatnonzero(res["hit"] & (rng_ >= LIDAR_MIN_RANGE) & (rng_ <= LIDAR_MAX_RANGE))
    if len(keep) > config.lidar_max_points:
        keep = np.sort(rng.choice(keep, size=config.lidar_max_points, replace=False))
    points = local.reshape(-1, 3)[keep] * rng_[keep, None]
    point_times = np.repeat(times, config.lidar_beams)[keep]
    return points.astype(np.float32), point_times.astype(np.float64)


def write_npz(path: Path, **arrays: np.ndarray) -> None:
    """Like ``np.savez`` but byte-reproducible (fixed zip member dates)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, array in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.ascontiguousarray(array), allow_pickle=False)


def reference_trajectory_samples(config: SynthConfig, path: VehiclePath, truth: Dict[str, SensorTruth]):
    """TUM columns of ``world_T_ref`` at the reference camera's frame times: (stamps, positions, quats xyzw)."""
    import roma
    import torch

    stamps = np.array(frame_stamps(truth[REFERENCE], config.frames))
    poses = path.world_T_vehicle(stamps - T0) @ vehicle_T_sensor(REFERENCE)
    quats = roma.rotmat_to_unitquat(torch.from_numpy(poses[:, :3, :3])).numpy()
    quats = quats * np.where(quats[:, 3:4] < 0, -1.0, 1.0)
    return stamps, poses[:, :3, 3], quats


def _prepare_out(config: SynthConfig) -> Path:
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise SynthError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not config.overwrite:
            raise SynthError(f"{out} exists and is not empty; pass --overwrite to replace its dataset")
        from moisst_ns.datasets.output import clear_generated_dataset

        clear_generated_dataset(out)
    out.mkdir(parents=True, exist_ok=True)
    return out


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
    if not config.lidar_noise >= 0:
        problems.append(f"--lidar-noise must be >= 0, got {config.lidar_noise}")
    if config.knock is not None and (config.knock[0] == REFERENCE or config.knock[0] not in MOUNTS):
        problems.append(f"--knock: sensor must be one of {', '.join(n for n in MOUNTS if n != REFERENCE)}, got {config.knock[0]!r}")
    if problems:
        raise SynthError("; ".join(problems))


def make_rig(config: SynthConfig) -> Path:
    """Generate the dataset described by ``config`` into ``config.out``; returns that folder."""
    import torch
    from PIL import Image

    from moisst_ns.rig.format import Calibration, load_tum, rig_json, write_tum
    from moisst_ns.rig.geometry import ReferenceTrajectory

    _check_config(config)
    out = _prepare_out(config)
    path = make_path(config)
    truth = make_truth(config)
    priors = make_priors(config, truth)
    truth = knock_mount(config, truth)  # after the priors: they keep the mount as it was
    scene = build_scene(config, path)

    # 1. The reference trajectory, written first and read back: rendering uses exactly what consumers will read.
    write_tum(out / "reference_poses.txt", *reference_trajectory_samples(config, path, truth),
              header="moisst-synth reference trajectory world_T_cam_front: timestamp tx ty tz qx qy qz qw")
    traj = ReferenceTrajectory.from_tum(*load_tum(out / "reference_poses.txt"))

    def world_T(sensor: SensorTruth, stamps: np.ndarray) -> np.ndarray:
        t_rel = torch.as_tensor(np.asarray(stamps, dtype=np.float64) + sensor.time_offset) - traj.t0
        ref = traj(t_rel).numpy()
        return ref @ sensor.T_ref_sensor

    intr = intrinsics(config)
    lidar_rng = np.random.default_rng(_streams(config.seed)["lidar"])
    noise_rng = np.random.default_rng(_streams(config.seed)["lidar_noise"])
    frames = []
    for name, sensor in truth.items():
        stamps = frame_stamps(sensor, config.frames)
        folder = ("images" if sensor.type == "camera" else "lidar") + f"/{name}"
        (out / folder).mkdir(parents=True, exist_ok=True)
        if sensor.type == "camera":
            poses = world_T(sensor, np.array(stamps))
            for k, stamp in enumerate(stamps):
                rgb, _ = render_camera(scene, intr, poses[k], config.supersample)
                rel = f"{folder}/{k:06d}.png"
                Image.fromarray(rgb).save(out / rel, format="PNG", compress_level=3)
                frames.append({"sensor": name, "timestamp": stamp, "file_path": rel})
        else:
            _, step_times = lidar_beam_directions(config)
            for k, stamp in enumerate(stamps):
                poses = world_T(sensor, stamp + step_times)
                points, times = render_lidar(scene, config, poses, lidar_rng)
                if config.lidar_noise > 0:
                    ranges = np.linalg.norm(points, axis=1, keepdims=True)
                    points = (points * (1.0 + noise_rng.normal(0.0, config.lidar_noise, ranges.shape) / ranges)).astype(np.float32)
                rel = f"{folder}/{k:06d}.npz"
                if config.lidar_scans == "compensated":
                    step = np.rint(times / (PERIOD / config.lidar_azimuth_steps)).astype(np.int64)
                    world = np.einsum("nij,nj->ni", poses[step, :3, :3], points) + poses[step, :3, 3]
                    points = ((world - poses[0, :3, 3]) @ poses[0, :3, :3]).astype(np.float32)
                    write_npz(out / rel, points=points)
                else:
                    write_npz(out / rel, points=points, times=times)
                frames.append({"sensor": name, "timestamp": stamp, "file_path": rel})
    frames.sort(key=lambda f: (f["timestamp"], f["sensor"]))

    sensors = {name: (sensor.type, priors[name][0], priors[name][1], intr if sensor.type == "camera" else {})
               for name, sensor in truth.items()}
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items() if k not in ("out", "overwrite")}
    for key, default in (("lidar_scans", "raw"), ("lidar_noise", 0.0), ("drive", "curve"), ("rig_seed", None), ("knock", None)):  # recorded when used (older rigs stay byte-identical)
        if meta[key] == default:
            del meta[key]
    meta["generator"] = "moisst-synth"
    meta["note"] = "priors per --perturb; true values in ground_truth.json"
    rig = rig_json(REFERENCE, "reference_poses.txt", sensors, frames, meta)
    (out / "rig.json").write_text(json.dumps(rig, indent=1) + "\n")
    Calibration(
        REFERENCE, {n: s.T_ref_sensor for n, s in truth.items()}, {n: s.time_offset for n, s in truth.items()}
    ).write(out / "ground_truth.json")
    return out
