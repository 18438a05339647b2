"""Rendering of ``moisst-synth``'s frames: camera images and LiDAR scans from the ray-casting ``Scene``, with the
real-world effects of ``synth_effects`` (moving vehicles, rolling shutter, motion blur, lens distortion, photometry,
JPEG, LiDAR noise and dropouts), and the files they are written to. With every effect off, exactly the renders and
bytes the generator always wrote.

Poses come from a callable ``world_T_at(stamps)`` (own-clock stamps, seconds -> ``(N, 4, 4)`` sensor poses);
``to_path_time`` turns an own-clock stamp into the scene's clock (seconds since the first reference frame), on which
the moving vehicles move.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Bool, Float

from moisst_ns.datasets.synth_effects import (
    Effects,
    Movers,
    apply_photometric,
    encode_jpeg,
    exposure_offsets,
    lidar_dropout_mask,
    lidar_range_noise,
    pixel_directions,
    row_time_offsets,
    to_uint8,
    vignetting_factor,
)
from moisst_ns.datasets.synth_scene import SUN, Scene, TextureAtlas

PERIOD = 0.1
"""Frame period of every sensor and the LiDAR revolution time, seconds (10 Hz)."""
LIDAR_MIN_RANGE = 0.5
LIDAR_MAX_RANGE = 60.0

PoseFn = Callable[[np.ndarray], np.ndarray]


def shade_movers(atlas: TextureAtlas, movers: Movers, hits: Dict[str, np.ndarray], directions: Float[np.ndarray, "num 3"],
                 pixel_angle: float) -> Float[np.ndarray, "num 3"]:
    """Colours in [0, 1] of rays that hit a moving vehicle (``hits``: ``Movers.intersect``'s arrays, those rays only):
    the box-projected texture and Lambert shading of the static scene's objects."""
    m, local, axis, psi = hits["mover"], hits["local"], hits["axis"], hits["heading"]
    rows = np.arange(len(m))
    normal_local = np.zeros_like(local)
    normal_local[rows, axis] = np.sign(local[rows, axis])
    cos, sin = np.cos(psi), np.sin(psi)
    normal = np.stack([cos * normal_local[:, 0] - sin * normal_local[:, 1], sin * normal_local[:, 0] + cos * normal_local[:, 1],
                       normal_local[:, 2]], axis=-1)
    u = np.where(axis == 0, local[:, 1], local[:, 0])
    v = -np.where(axis == 2, local[:, 1], local[:, 2])
    foot = hits["t_hit"] * pixel_angle / np.sqrt(np.maximum(np.abs(np.sum(normal * directions, axis=1)), 0.05))
    scale, off = movers.scale[m], movers.uv_offset[m]
    base = atlas.sample(movers.texture[m], u / scale + off[:, 0], v / scale + off[:, 1], foot / scale)
    light = 0.58 + 0.42 * np.maximum(normal @ SUN, 0.0)
    return np.clip(base * movers.tint[m].astype(np.float32) * light[:, None].astype(np.float32), 0.0, 1.0)


def colour_rays(scene: Scene, origins: np.ndarray, directions: Float[np.ndarray, "num 3"], pixel_angle: float,
                movers: Optional[Movers] = None, times: Optional[Float[np.ndarray, "num"]] = None) -> Tuple[np.ndarray, np.ndarray]:
    """``Scene.colour`` with the moving vehicles where they are at each ray's scene time ``times`` (seconds)."""
    if movers is None:
        return scene.colour(origins, directions, pixel_angle)
    origins = np.broadcast_to(origins, directions.shape)
    hits = movers.intersect(origins, directions, times)
    front = np.isfinite(hits["t_hit"])
    front[front] = hits["t_hit"][front] < scene.cast(origins[front], directions[front])["t_hit"]
    rgb, hit = np.empty(directions.shape, dtype=np.float32), np.ones(len(directions), dtype=bool)
    rgb[~front], hit[~front] = scene.colour(origins[~front], directions[~front], pixel_angle)
    if front.any():
        rgb[front] = shade_movers(scene.atlas, movers, {k: a[front] for k, a in hits.items()}, directions[front], pixel_angle)
    return rgb, hit


def render_frame(scene: Scene, intr: Dict[str, object], world_T_at: PoseFn, stamp: float, to_path_time: float = 0.0,
                 readout: float = 0.0, exposure: float = 0.0, supersample: int = 1, distortion: Sequence[float] = (0.0, 0.0),
                 movers: Optional[Movers] = None, rays: Optional[np.ndarray] = None) -> Tuple[Float[np.ndarray, "h w 3"], Float[np.ndarray, "h w"]]:
    """A camera frame stamped ``stamp`` (own clock, seconds) with rolling shutter, motion blur, distortion, movers.

    Each (sub-)row is cast from the pose at its own time (``row_time_offsets``), each blur sample at its offset
    (``exposure_offsets``); the samples are averaged. With every effect off, a plain pinhole render.
    ``rays``: ``pixel_directions(intr, supersample, distortion)`` when already computed (it is the same every frame).

    Returns:
        (colours in [0, 1] (h, w, 3) before quantisation, fraction of rays that hit geometry (h, w)).
    """
    w, h, ss = int(intr["w"]), int(intr["h"]), int(supersample)
    cam = pixel_directions(intr, ss, distortion) if rays is None else rays
    rows = row_time_offsets(h, readout, ss)
    offsets = exposure_offsets(exposure)
    rgb_sum, hit_sum = 0.0, 0.0
    for offset in offsets:
        if readout == 0.0:
            pose = world_T_at(np.array([stamp + offset]))[0]
            dirs, origins = cam.reshape(-1, 3) @ pose[:3, :3].T, pose[:3, 3]
            times = np.full(len(dirs), stamp + offset)
        else:
            poses = world_T_at(stamp + offset + rows)
            dirs = np.einsum("rij,rcj->rci", poses[:, :3, :3], cam).reshape(-1, 3)
            origins, times = np.repeat(poses[:, :3, 3], w * ss, axis=0), np.repeat(stamp + offset + rows, w * ss)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        rgb, hit = colour_rays(scene, origins, dirs, 1.0 / (float(intr["fl_x"]) * ss), movers, times + to_path_time)
        rgb_sum = rgb_sum + rgb.reshape(h, ss, w, ss, 3).mean(axis=(1, 3))
        hit_sum = hit_sum + hit.reshape(h, ss, w, ss).mean(axis=(1, 3))
    return rgb_sum / len(offsets), hit_sum / len(offsets)


def write_camera_frames(out: Path, folder: str, name: str, stamps: List[float], scene: Scene, intr: Dict[str, object],
                        world_T_at: PoseFn, to_path_time: float, fx: Effects, movers: Optional[Movers],
                        photometric: Optional[np.ndarray], supersample: int) -> List[dict]:
    """Render and write one camera's frames; returns their rig.json frame entries.

    Args:
        photometric: (frames, 5) per-frame gain, gamma, tint (``photometric_params``), or None.
    """
    from PIL import Image

    frames = []
    poses = None if fx.camera else world_T_at(np.array(stamps))  # all frames' poses at once, as always without effects
    vignette = vignetting_factor(intr, fx.vignetting) if fx.vignetting else None
    rays = pixel_directions(intr, supersample, fx.distortion)
    for k, stamp in enumerate(stamps):
        pose_at = world_T_at if poses is None else (lambda _, k=k: poses[k][None])
        rgb, _ = render_frame(scene, intr, pose_at, stamp, to_path_time, fx.rolling_shutter, fx.motion_blur, supersample,
                              fx.distortion, movers, rays)
        if vignette is not None or photometric is not None:
            rgb = apply_photometric(rgb, None if photometric is None else photometric[k], vignette)
        rgb = to_uint8(rgb)
        rel = f"{folder}/{k:06d}.{'png' if fx.jpeg_quality is None else 'jpg'}"
        if fx.jpeg_quality is None:
            Image.fromarray(rgb).save(out / rel, format="PNG", compress_level=3)
        else:
            (out / rel).write_bytes(encode_jpeg(rgb, fx.jpeg_quality))
        frames.append({"sensor": name, "timestamp": stamp, "file_path": rel})
    return frames


def lidar_beam_directions(config) -> Tuple[np.ndarray, np.ndarray]:
    """Unit directions (beams, steps, 3) in the LiDAR frame, and the firing time of each step (steps,).

    The head spins clockwise seen from above (like a Velodyne), starting pointing backwards; all beams of a step fire
    together at ``step * PERIOD / steps`` seconds after the frame stamp. ``config``: a ``SynthConfig``.
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


def render_lidar(scene: Scene, config, world_T_lidar_steps: np.ndarray, rng: np.random.Generator,
                 movers: Optional[Movers] = None, step_path_times: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """One motion-distorted scan.

    Args:
        config: a ``SynthConfig`` (beams, steps, ``lidar_max_points``).
        world_T_lidar_steps: (steps, 4, 4) LiDAR pose at each firing step.
        rng: for the subset kept when there are more than ``lidar_max_points`` hits.
        movers, step_path_times: moving vehicles, hit where they are at each step's scene time (steps,) seconds.

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
    rng_, hit = res["t_hit"], res["hit"]
    if movers is not None:
        ray_times = np.repeat(step_path_times, config.lidar_beams)
        rng_ = np.minimum(rng_, movers.intersect(origins.reshape(-1, 3), dirs.reshape(-1, 3), ray_times)["t_hit"])
        hit = np.isfinite(rng_)
    keep = np.flatnonzero(hit & (rng_ >= LIDAR_MIN_RANGE) & (rng_ <= LIDAR_MAX_RANGE))
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


def write_lidar_frames(out: Path, folder: str, name: str, stamps: List[float], scene: Scene, config, world_T_at: PoseFn,
                       to_path_time: float, fx: Effects, movers: Optional[Movers],
                       rngs: Tuple[np.random.Generator, np.random.Generator, np.random.Generator]) -> List[dict]:
    """Render and write one LiDAR's scans (``config.lidar_scans``: raw with per-point times, or compensated).

    Args:
        rngs: the generators of the kept subset, the range noise and the dropouts.
    """
    subset_rng, noise_rng, dropout_rng = rngs
    frames = []
    _, step_times = lidar_beam_directions(config)
    for k, stamp in enumerate(stamps):
        poses = world_T_at(stamp + step_times)
        points, times = render_lidar(scene, config, poses, subset_rng, movers, stamp + step_times + to_path_time)
        if fx.lidar_noise > 0:
            points = lidar_range_noise(points, fx.lidar_noise, noise_rng)
        if fx.lidar_dropout > 0:
            keep: Bool[np.ndarray, "num"] = lidar_dropout_mask(len(points), fx.lidar_dropout, dropout_rng)
            points, times = points[keep], times[keep]
        rel = f"{folder}/{k:06d}.npz"
        if config.lidar_scans == "compensated":
            step = np.rint(times / (PERIOD / config.lidar_azimuth_steps)).astype(np.int64)
            world = np.einsum("nij,nj->ni", poses[step, :3, :3], points) + poses[step, :3, 3]
            points = ((world - poses[0, :3, 3]) @ poses[0, :3, :3]).astype(np.float32)
            write_npz(out / rel, points=points)
        else:
            write_npz(out / rel, points=points, times=times)
        frames.append({"sensor": name, "timestamp": stamp, "file_path": rel})
    return frames
