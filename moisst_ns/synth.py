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
import shutil
import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import tyro

FORMAT = "moisst-rig/1"
T0 = 1000.0
"""Absolute time of the first reference frame, seconds (keeps stamps away from zero, like real clocks)."""
PERIOD = 0.1
"""Frame period of every sensor and the LiDAR revolution time, seconds (10 Hz)."""
REFERENCE = "cam_front"
LIDAR_MIN_RANGE = 0.5
LIDAR_MAX_RANGE = 60.0
TEXTURE_SIZE = 512
SKY_ZENITH = np.array([0.36, 0.52, 0.82])
SKY_HORIZON = np.array([0.82, 0.87, 0.93])
SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])


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
    overwrite: bool = False
    """Replace the generator's outputs in a non-empty OUT (other files there are left alone)."""


# ----------------------------------------------------------------------------------------------------------------
# Small rotation helpers (numpy, float64)


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


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


@dataclass
class VehiclePath:
    """A smooth analytic drive: heading and speed profiles (period 10 s), integrated on a fine grid.

    Time ``t`` is seconds since the first reference frame. Heading ``psi(t) = turn (1 - cos(pi t / 5)) / 2`` (0 to
    ``turn`` over 5 s and back), speed ``v(t) = 6.5 - 2.5 cos(pi t / 5)`` (4 to 9 m/s and back), plus small pitch,
    roll and bounce oscillations so every rotation axis moves a little.
    """

    turn: float
    """Heading change over the first 5 s, radians (sign = turn direction)."""
    phases: np.ndarray
    """Phases of the pitch / roll / bounce oscillations, radians."""
    t_min: float
    t_max: float
    dt: float = 1e-3

    def __post_init__(self):
        self.grid = np.arange(int(round((self.t_max - self.t_min) / self.dt)) + 1) * self.dt + self.t_min
        psi, speed = self.heading(self.grid), self.speed(self.grid)
        vel = np.stack([speed * np.cos(psi), speed * np.sin(psi)], axis=-1)
        steps = 0.5 * (vel[1:] + vel[:-1]) * self.dt
        xy = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
        self.xy = xy - np.array([np.interp(0.0, self.grid, xy[:, 0]), np.interp(0.0, self.grid, xy[:, 1])])
        seg = np.linalg.norm(np.diff(self.xy, axis=0), axis=1)
        self.arclength = np.concatenate([[0.0], np.cumsum(seg)])
        self.arclength -= np.interp(0.0, self.grid, self.arclength)

    def heading(self, t):
        return self.turn * 0.5 * (1.0 - np.cos(np.pi * np.asarray(t) / 5.0))

    def speed(self, t):
        return 6.5 - 2.5 * np.cos(np.pi * np.asarray(t) / 5.0)

    def world_T_vehicle(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) vehicle poses at times ``t`` (N,)."""
        t = np.asarray(t, dtype=np.float64)
        psi = self.heading(t)
        p1, p2, p3 = self.phases
        pitch = np.deg2rad(0.6) * np.sin(2 * np.pi * t / 1.7 + p1) - 0.004 * np.sin(np.pi * t / 5.0)
        roll = np.deg2rad(0.5) * np.sin(2 * np.pi * t / 2.3 + p2)
        bounce = 0.02 * np.sin(2 * np.pi * t / 1.3 + p3)
        poses = np.zeros(t.shape + (4, 4))
        for i in range(t.shape[0]):
            poses[i, :3, :3] = rot_z(psi[i]) @ rot_y(pitch[i]) @ rot_x(roll[i])
        poses[:, 0, 3] = np.interp(t, self.grid, self.xy[:, 0])
        poses[:, 1, 3] = np.interp(t, self.grid, self.xy[:, 1])
        poses[:, 2, 3] = bounce
        poses[:, 3, 3] = 1.0
        return poses

    def at_arclength(self, s: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Centre-line points (N, 2) and headings (N,) at arc lengths ``s`` (metres from the start position)."""
        s = np.asarray(s, dtype=np.float64)
        t = np.interp(s, self.arclength, self.grid)
        xy = np.stack([np.interp(t, self.grid, self.xy[:, 0]), np.interp(t, self.grid, self.xy[:, 1])], axis=-1)
        return xy, self.heading(t)

    def s_at(self, t: float) -> float:
        return float(np.interp(t, self.grid, self.arclength))


def make_path(config: SynthConfig) -> VehiclePath:
    """The vehicle path of a configuration (seeded turn direction and oscillation phases)."""
    rng = np.random.default_rng(_streams(config.seed)["path"])
    turn = np.deg2rad(rng.uniform(38.0, 50.0)) * rng.choice([-1.0, 1.0])
    duration = (config.frames - 1) * PERIOD
    return VehiclePath(turn=float(turn), phases=rng.uniform(0, 2 * np.pi, 3), t_min=-10.0, t_max=duration + 14.0)


def _streams(seed: int) -> Dict[str, np.random.SeedSequence]:
    names = ("path", "rig", "scene", "perturb", "lidar", "lidar_noise")
    return dict(zip(names, np.random.SeedSequence(seed).spawn(len(names))))


# ----------------------------------------------------------------------------------------------------------------
# Textures


COLOUR_TEXTURES = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "stereo_motorcycle")
GRAY_TEXTURES = ("brick", "camera", "cell", "coins", "gravel", "grass", "clock", "text")


def _load_skimage(name: str) -> np.ndarray:
    import skimage.data

    image = getattr(skimage.data, name)()
    if isinstance(image, tuple):
        image = image[0]
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0, 1) * 255).astype(np.uint8) if image.dtype.kind == "f" else image.astype(np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    return image[..., :3]


@dataclass
class TextureAtlas:
    """Square power-of-two textures with mip pyramids, packed in one flat float32 array for vectorised lookups."""

    names: List[str]
    data: np.ndarray
    """(total_texels, 3) float32 in [0, 1]."""
    gray: np.ndarray
    """(total_texels, 1) float32: the mean of the three channels (for the detail modulation)."""
    offsets: np.ndarray
    """(num_textures, num_levels) start of each level in ``data``."""
    size: int
    num_levels: int

    @classmethod
    def build(cls, names: Sequence[str], size: int = TEXTURE_SIZE) -> "TextureAtlas":
        from PIL import Image

        levels = int(np.log2(size)) + 1
        chunks, offsets, cursor = [], np.zeros((len(names), levels), dtype=np.int64), 0
        for i, name in enumerate(names):
            img = Image.fromarray(_load_skimage(name)).resize((size, size), Image.BICUBIC)
            level = np.asarray(img, dtype=np.float32) / 255.0
            lo, hi = np.percentile(level, [1.0, 99.0])  # equal contrast for every texture
            level = np.clip((level - lo) / max(hi - lo, 1e-3) * 0.9 + 0.05, 0.0, 1.0)
            for lvl in range(levels):
                offsets[i, lvl] = cursor
                chunks.append(level.reshape(-1, 3))
                cursor += level.shape[0] * level.shape[1]
                if level.shape[0] > 1:
                    level = 0.25 * (level[0::2, 0::2] + level[1::2, 0::2] + level[0::2, 1::2] + level[1::2, 1::2])
        data = np.concatenate(chunks).astype(np.float32)
        return cls(list(names), data, data.mean(axis=1, keepdims=True), offsets, size, levels)

    def _bilinear(self, d: np.ndarray, tex: np.ndarray, level: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        n = self.size >> level
        x = u * n - 0.5
        y = v * n - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[:, None].astype(np.float32), (y - y0)[:, None].astype(np.float32)
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        mask = n - 1
        base = self.offsets[tex, level]
        xa, xb = x0 & mask, (x0 + 1) & mask
        ya, yb = base + (y0 & mask) * n, base + ((y0 + 1) & mask) * n
        top = d[ya + xa] * (1 - fx) + d[ya + xb] * fx
        bottom = d[yb + xa] * (1 - fx) + d[yb + xb] * fx
        return top * (1 - fy) + bottom * fy

    def sample(self, tex: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: np.ndarray, gray: bool = False) -> np.ndarray:
        """Trilinear lookup with wrap-around tiling.

        Args:
            tex: (N,) texture indices.
            u, v: (N,) coordinates in tiles (1.0 = one texture width; v grows downwards in the image).
            footprint: (N,) size of the pixel footprint, in tiles.
            gray: look up the gray version (one channel).

        Returns:
            (N, 3) float32 colours, or (N, 1) when ``gray``.
        """
        lod = np.clip(np.log2(np.maximum(footprint * self.size, 1e-12)), 0.0, self.num_levels - 1.0)
        l0 = np.floor(lod).astype(np.int64)
        l1 = np.minimum(l0 + 1, self.num_levels - 1)
        frac = (lod - l0)[:, None].astype(np.float32)
        u = u - np.floor(u)
        v = v - np.floor(v)
        d = self.gray if gray else self.data
        return self._bilinear(d, tex, l0, u, v) * (1 - frac) + self._bilinear(d, tex, l1, u, v) * frac


# ----------------------------------------------------------------------------------------------------------------
# Scene


@dataclass
class SceneObject:
    """One textured object: triangles plus a local frame for the planar texture mapping."""

    vertices: np.ndarray
    """(V, 3) world coordinates."""
    triangles: np.ndarray
    """(T, 3) vertex indices."""
    rotation: np.ndarray
    """World rotation of the object's mapping frame (its box axes)."""
    origin: np.ndarray
    """World origin of the mapping frame."""
    texture: str
    scale: float
    """Metres per texture tile."""
    tint: Tuple[float, float, float]
    detail: str
    detail_scale: float
    detail_strength: float
    uv_offset: Tuple[float, float]


def box_object(center, size, yaw: float, texture: str, scale: float, rng: np.random.Generator, tint=(1.0, 1.0, 1.0),
               detail: str = "gravel", detail_scale: float = 0.6, detail_strength: float = 0.25) -> SceneObject:
    """An axis-aligned box of ``size`` (along its x, y, z) rotated by ``yaw`` about z, centred at ``center``."""
    sx, sy, sz = (0.5 * np.asarray(size, dtype=np.float64)).tolist()
    corners = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    rot = rot_z(yaw)
    center = np.asarray(center, dtype=np.float64)
    return SceneObject(
        vertices=corners @ rot.T + center, triangles=tris, rotation=rot, origin=center, texture=texture, scale=scale,
        tint=tuple(float(c) for c in tint), detail=detail, detail_scale=detail_scale, detail_strength=detail_strength,
        uv_offset=tuple(float(c) for c in rng.uniform(0, 1, 2)),
    )


def cylinder_object(center_xy, radius: float, height: float, texture: str, scale: float, rng: np.random.Generator,
                    tint=(1.0, 1.0, 1.0), segments: int = 16) -> SceneObject:
    """A vertical prism with ``segments`` sides standing on the ground (a column)."""
    ang = np.arange(segments) * 2 * np.pi / segments
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], axis=-1)
    verts = np.concatenate([np.c_[ring, np.zeros(segments)], np.c_[ring, np.full(segments, height)], [[0, 0, height]]])
    tris = []
    for i in range(segments):
        j = (i + 1) % segments
        tris += [(i, j, segments + j), (i, segments + j, segments + i), (segments + i, segments + j, 2 * segments)]
    origin = np.array([center_xy[0], center_xy[1], 0.0])
    return SceneObject(
        vertices=verts + origin, triangles=np.array(tris, dtype=np.int64), rotation=np.eye(3), origin=origin,
        texture=texture, scale=scale, tint=tuple(float(c) for c in tint), detail="brick", detail_scale=0.5,
        detail_strength=0.2, uv_offset=tuple(float(c) for c in rng.uniform(0, 1, 2)),
    )


def _facade_texture(rng: np.random.Generator) -> Tuple[str, Tuple[float, float, float]]:
    if rng.uniform() < 0.55:
        return str(rng.choice(COLOUR_TEXTURES)), tuple(rng.uniform(0.85, 1.1, 3))
    base = rng.uniform(0.45, 1.0, 3)
    return str(rng.choice(GRAY_TEXTURES)), tuple(base / base.max() * rng.uniform(0.8, 1.05))


def _facade(center, size, yaw, rng) -> SceneObject:
    texture, tint = _facade_texture(rng)
    return box_object(center, size, yaw, texture, float(rng.uniform(2.0, 7.0)), rng, tint,
                      detail=str(rng.choice(["brick", "gravel", "grass", "cell"])),
                      detail_scale=float(rng.uniform(0.3, 0.9)), detail_strength=float(rng.uniform(0.15, 0.35)))


def _ground(center_xy, extent: float, rng) -> SceneObject:
    obj = box_object([center_xy[0], center_xy[1], -0.5], [extent, extent, 1.0], 0.0, "gravel", 3.5, rng,
                     tint=(0.78, 0.74, 0.66), detail="grass", detail_scale=0.45, detail_strength=0.3)
    return obj


def _street_objects(path: VehiclePath, s_start: float, s_end: float, rng: np.random.Generator) -> List[SceneObject]:
    objs: List[SceneObject] = []
    for side in (1.0, -1.0):  # +1: left of the road, -1: right
        s = s_start
        while s < s_end:
            length = rng.uniform(6.0, 16.0)
            setback, depth, height = rng.uniform(5.0, 12.0), rng.uniform(5.0, 10.0), rng.uniform(5.0, 18.0)
            (xy,), (psi,) = path.at_arclength([s + 0.5 * length])
            normal = np.array([-np.sin(psi), np.cos(psi)])
            c = xy + side * (setback + 0.5 * depth) * normal
            objs.append(_facade([c[0], c[1], 0.5 * height], [length, depth, height], psi, rng))
            if rng.uniform() < 0.7:  # a taller second row behind, visible through gaps and above
                back = setback + depth + rng.uniform(2.0, 6.0)
                d2, h2 = rng.uniform(6.0, 12.0), rng.uniform(10.0, 26.0)
                c2 = xy + side * (back + 0.5 * d2) * normal
                objs.append(_facade([c2[0], c2[1], 0.5 * h2], [length * rng.uniform(0.8, 1.2), d2, h2], psi, rng))
            s += length + (rng.uniform(0.5, 4.0) if rng.uniform() < 0.5 else 0.0)
        # street furniture: poles, car-size blocks, low boxes
        s = s_start + rng.uniform(0, 6)
        while s < s_end:
            (xy,), (psi,) = path.at_arclength([s])
            normal = np.array([-np.sin(psi), np.cos(psi)])
            kind = rng.uniform()
            if kind < 0.4:
                lat, h = rng.uniform(3.4, 4.4), rng.uniform(3.0, 5.5)
                c = xy + side * lat * normal
                tex, tint = _facade_texture(rng)
                objs.append(box_object([c[0], c[1], 0.5 * h], [0.22, 0.22, h], psi, tex, 1.0, rng, tint))
            elif kind < 0.8:
                lat = rng.uniform(2.9, 3.6)
                c = xy + side * lat * normal
                tex, tint = _facade_texture(rng)
                size = [rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.95), rng.uniform(1.3, 1.7)]
                objs.append(box_object([c[0], c[1], 0.5 * size[2]], size, psi + rng.uniform(-0.05, 0.05), tex,
                                       float(rng.uniform(1.2, 2.5)), rng, tint, detail="coins", detail_scale=0.3))
            else:
                lat = rng.uniform(3.2, 4.5)
                c = xy + side * lat * normal
                tex, tint = _facade_texture(rng)
                size = rng.uniform(0.6, 1.4, 3)
                objs.append(box_object([c[0], c[1], 0.5 * size[2]], size, psi + rng.uniform(-0.5, 0.5), tex,
                                       float(rng.uniform(0.8, 1.6)), rng, tint))
            s += rng.uniform(4.0, 10.0)
    for s_wall, extra in ((s_start - 2.0, -3.0), (s_end + 2.0, 3.0)):  # end walls across the road
        (xy,), (psi,) = path.at_arclength([s_wall])
        c = xy + extra * np.array([np.cos(psi), np.sin(psi)])
        h = rng.uniform(22.0, 30.0)
        objs.append(_facade([c[0], c[1], 0.5 * h], [6.0, 90.0, h], psi, rng))
    return objs


def _plaza_objects(path: VehiclePath, s_start: float, s_end: float, rng: np.random.Generator) -> List[SceneObject]:
    objs: List[SceneObject] = []
    xy_path, _ = path.at_arclength(np.arange(s_start - 5.0, s_end + 5.0, 0.5))
    lo, hi = xy_path.min(axis=0) - 22.0, xy_path.max(axis=0) + 22.0

    def clear(p, margin):
        return np.min(np.linalg.norm(xy_path - p, axis=1)) > margin

    # Surrounding buildings along the four sides of the square.
    for axis in (0, 1):
        for side, edge in ((-1.0, lo), (1.0, hi)):
            other = 1 - axis
            pos = lo[other] - 20.0
            while pos < hi[other] + 20.0:
                length, depth, height = rng.uniform(8.0, 18.0), rng.uniform(6.0, 12.0), rng.uniform(8.0, 25.0)
                c = np.zeros(2)
                c[other] = pos + 0.5 * length
                c[axis] = edge[axis] + side * (rng.uniform(0.0, 4.0) + 0.5 * depth)
                size = [length, depth, height] if axis == 1 else [depth, length, height]
                objs.append(_facade([c[0], c[1], 0.5 * height], size, 0.0, rng))
                pos += length
    # Scattered blocks and columns at various distances, clear of the vehicle's corridor.
    area = float(np.prod(hi - lo))
    count = int(area / 70.0)
    for _ in range(count * 4):
        if count <= 0:
            break
        p = rng.uniform(lo + 2.0, hi - 2.0)
        kind = rng.uniform()
        if kind < 0.3:
            radius, height = rng.uniform(0.25, 0.6), rng.uniform(3.0, 9.0)
            if not clear(p, 3.0 + radius):
                continue
            tex, tint = _facade_texture(rng)
            objs.append(cylinder_object(p, radius, height, tex, float(rng.uniform(1.0, 3.0)), rng, tint))
        elif kind < 0.85:
            size = np.r_[rng.uniform(0.8, 4.0, 2), rng.uniform(0.8, 5.0)]
            if not clear(p, 3.0 + 0.72 * max(size[0], size[1])):
                continue
            objs.append(_facade([p[0], p[1], 0.5 * size[2]], size, rng.uniform(0, np.pi), rng))
        else:
            size = np.r_[rng.uniform(4.0, 9.0, 2), rng.uniform(5.0, 12.0)]
            if not clear(p, 3.5 + 0.72 * max(size[0], size[1])):
                continue
            objs.append(_facade([p[0], p[1], 0.5 * size[2]], size, rng.uniform(0, np.pi), rng))
        count -= 1
    return objs


class Scene:
    """The textured world: an open3d ray-casting scene plus per-object texture mapping."""

    def __init__(self, objects: Sequence[SceneObject]):
        import open3d as o3d

        self.objects = list(objects)
        names = sorted({o.texture for o in objects} | {o.detail for o in objects})
        self.atlas = TextureAtlas.build(names)
        index = {n: i for i, n in enumerate(names)}
        verts, tris, tri_obj, start = [], [], [], 0
        for i, obj in enumerate(objects):
            verts.append(obj.vertices)
            tris.append(obj.triangles + start)
            tri_obj.append(np.full(len(obj.triangles), i, dtype=np.int64))
            start += len(obj.vertices)
        self.vertices = np.concatenate(verts).astype(np.float32)
        self.triangles = np.concatenate(tris).astype(np.uint32)
        self.triangle_object = np.concatenate(tri_obj)
        self.obj_rotation = np.stack([o.rotation for o in objects])
        self.obj_origin = np.stack([o.origin for o in objects])
        self.obj_texture = np.array([index[o.texture] for o in objects], dtype=np.int64)
        self.obj_scale = np.array([o.scale for o in objects])
        self.obj_tint = np.array([o.tint for o in objects], dtype=np.float32)
        self.obj_detail = np.array([index[o.detail] for o in objects], dtype=np.int64)
        self.obj_detail_scale = np.array([o.detail_scale for o in objects])
        self.obj_detail_strength = np.array([o.detail_strength for o in objects], dtype=np.float32)
        self.obj_offset = np.array([o.uv_offset for o in objects])
        self.raycasting = o3d.t.geometry.RaycastingScene()
        self.raycasting.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Dict[str, np.ndarray]:
        """Cast rays (unit ``directions``); returns ``t_hit`` (inf on a miss), ``hit``, ``triangle``, ``normal``."""
        import open3d as o3d

        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        ans = self.raycasting.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        return {
            "t_hit": t_hit,
            "hit": np.isfinite(t_hit),
            "triangle": ans["primitive_ids"].numpy().astype(np.int64),
            "normal": ans["primitive_normals"].numpy().astype(np.float64),
        }

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance of world points (N, 3) to the nearest surface, metres."""
        import open3d as o3d

        return self.raycasting.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()

    def colour(self, origins: np.ndarray, directions: np.ndarray, pixel_angle: float) -> Tuple[np.ndarray, np.ndarray]:
        """Shaded colours (N, 3) in [0, 1] of rays, and the hit mask; misses get the sky gradient.

        Args:
            origins: (3,) or (N, 3) ray origins.
            directions: (N, 3) unit directions.
            pixel_angle: angular size of a pixel, radians (for the mip level).
        """
        res = self.cast(origins, directions)
        hit = res["hit"]
        out = np.empty(directions.shape, dtype=np.float32)
        elev = np.clip(directions[~hit, 2], 0.0, 1.0)[:, None] ** 0.6
        out[~hit] = ((1 - elev) * SKY_HORIZON + elev * SKY_ZENITH).astype(np.float32)
        if hit.any():
            d = directions[hit]
            org = np.broadcast_to(origins, directions.shape)[hit]
            dist = res["t_hit"][hit]
            points = org + d * dist[:, None]
            normal = res["normal"][hit]
            cos = np.sum(normal * d, axis=1)
            normal = normal * -np.sign(cos + 1e-12)[:, None]  # face the viewer
            cos = np.abs(cos)
            obj = self.triangle_object[res["triangle"][hit]]
            rot = self.obj_rotation[obj]
            local = np.einsum("nji,nj->ni", rot, points - self.obj_origin[obj])
            nloc = np.abs(np.einsum("nji,nj->ni", rot, normal))
            axis = np.argmax(nloc, axis=1)
            u = np.where(axis == 0, local[:, 1], local[:, 0])
            v = -np.where(axis == 2, local[:, 1], local[:, 2])
            foot = dist * pixel_angle / np.sqrt(np.maximum(cos, 0.05))
            scale, dscale = self.obj_scale[obj], self.obj_detail_scale[obj]
            off = self.obj_offset[obj]
            base = self.atlas.sample(self.obj_texture[obj], u / scale + off[:, 0], v / scale + off[:, 1], foot / scale)
            det = self.atlas.sample(self.obj_detail[obj], u / dscale - off[:, 1], v / dscale + off[:, 0], foot / dscale, gray=True)
            strength = self.obj_detail_strength[obj][:, None]
            col = base * self.obj_tint[obj] * (1.0 - strength + 2.0 * strength * det)
            light = 0.58 + 0.42 * np.maximum(normal @ SUN, 0.0)
            out[hit] = np.clip(col * light[:, None].astype(np.float32), 0.0, 1.0)
        return out, hit


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


def make_truth(config: SynthConfig) -> Dict[str, SensorTruth]:
    """True extrinsics (in the reference camera's frame) and time offsets; seeded."""
    rng = np.random.default_rng(_streams(config.seed)["rig"])
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
    rng = np.random.default_rng(_streams(config.seed)["perturb"])
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
        for name in ("rig.json", "reference_poses.txt", "ground_truth.json"):
            (out / name).unlink(missing_ok=True)
        for name in ("images", "lidar"):
            if (out / name).is_dir():
                shutil.rmtree(out / name)
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
    if problems:
        raise SynthError("; ".join(problems))


def make_rig(config: SynthConfig) -> Path:
    """Generate the dataset described by ``config`` into ``config.out``; returns that folder."""
    import torch
    from PIL import Image

    from moisst_ns.rig.format import Calibration, load_tum, write_tum
    from moisst_ns.rig.geometry import ReferenceTrajectory

    _check_config(config)
    out = _prepare_out(config)
    path = make_path(config)
    truth = make_truth(config)
    priors = make_priors(config, truth)
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

    sensors = {}
    for name, sensor in truth.items():
        prior, delta = priors[name]
        entry = {"type": sensor.type, "T_ref_sensor": prior.tolist(), "time_offset": float(delta)}
        if sensor.type == "camera":
            entry.update(intr)
        sensors[name] = entry
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items() if k not in ("out", "overwrite")}
    for key, default in (("lidar_scans", "raw"), ("lidar_noise", 0.0)):  # recorded when used (older rigs stay byte-identical)
        if meta[key] == default:
            del meta[key]
    meta["generator"] = "moisst-synth"
    meta["note"] = "priors per --perturb; true values in ground_truth.json"
    rig = {"format": FORMAT, "reference_sensor": REFERENCE, "trajectory": "reference_poses.txt", "sensors": sensors,
           "frames": frames, "metadata": meta}
    (out / "rig.json").write_text(json.dumps(rig, indent=1) + "\n")
    Calibration(
        REFERENCE, {n: s.T_ref_sensor for n, s in truth.items()}, {n: s.time_offset for n, s in truth.items()}
    ).write(out / "ground_truth.json")
    return out
