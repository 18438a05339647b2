"""The real-world effects of ``moisst-synth`` (issue 35), as pure numpy / OpenCV functions: pose noise and drift on
the *written* trajectory, auto-exposure, vignetting, OPENCV radial distortion, moving vehicles, motion blur, JPEG,
LiDAR range noise and dropouts, rolling shutter (what each does: ``SynthConfig``'s fields, ``moisst-synth --help``).
Each is off by default (the output is then byte-identical to what it was before these existed); ``--realistic``
turns all but the rolling shutter on at ``REALISTIC``. Units: metres, seconds, radians inside; pixel centres at
``+0.5`` as in ``docs/rig-format.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Bool, Float, Int, UInt8

from moisst_ns.datasets.synth_rig import VehiclePath

BLUR_SAMPLES = 3
"""Renders averaged over the exposure time of ``--motion-blur``."""
MOVER_LATERAL = 2.2
"""Lateral offset of the movers' lanes from the ego path's centre line, metres (oncoming: left; same way: right)."""

REALISTIC: Dict[str, object] = dict(
    pose_noise=(1.0, 0.02), pose_drift=(3.0, 0.05), exposure=0.3, vignetting=0.3, distortion=(-0.12, 0.03), movers=8,
    motion_blur=0.004, jpeg_quality=90, lidar_noise=0.02, lidar_dropout=0.1,
)
"""``--realistic``: the magnitudes of ``../shared/notes/real-data-findings.md`` (the switches' units)."""


@dataclass(frozen=True)
class Effects:
    """The effects of one configuration, resolved (``--realistic`` applied; 0 or None: off)."""

    pose_noise: Tuple[float, float] = (0.0, 0.0)
    """White noise on the written trajectory: centimetres, degrees (standard deviation per axis)."""
    pose_drift: Tuple[float, float] = (0.0, 0.0)
    """Slow drift on the written trajectory: centimetres, degrees (RMS per axis)."""
    exposure: float = 0.0
    """Per-frame auto-exposure amplitude (fraction)."""
    vignetting: float = 0.0
    """Brightness lost at the image corners (fraction)."""
    distortion: Tuple[float, float] = (0.0, 0.0)
    """OPENCV ``k1``, ``k2``."""
    movers: int = 0
    """Moving vehicles."""
    motion_blur: float = 0.0
    """Exposure time, seconds."""
    jpeg_quality: Optional[int] = None
    """JPEG quality, 1-100 (None: PNG; the switch's 0 also means PNG)."""
    lidar_noise: float = 0.0
    """LiDAR range noise, metres (standard deviation)."""
    lidar_dropout: float = 0.0
    """Fraction of LiDAR returns dropped."""
    rolling_shutter: float = 0.0
    """Readout time of every camera, seconds."""

    @property
    def trajectory(self) -> bool:
        return any(self.pose_noise) or any(self.pose_drift)

    @property
    def camera(self) -> bool:
        """Whether images need anything but the plain pinhole render saved as PNG."""
        return bool(self.exposure or self.vignetting or any(self.distortion) or self.movers or self.motion_blur
                    or self.jpeg_quality is not None or self.rolling_shutter)

    def summary(self) -> Dict[str, object]:
        """The effects that are on (for rig.json's metadata)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) not in (0, 0.0, (0.0, 0.0), None)}


def resolve_effects(config) -> Effects:
    """The effects of a ``SynthConfig`` (any object with its fields): a switch left at None takes ``REALISTIC``'s
    value when ``config.realistic``, else stays off; an explicit value always wins."""
    values = {}
    for f in fields(Effects):
        value = getattr(config, f.name)
        if value is None and getattr(config, "realistic", False):
            value = REALISTIC.get(f.name)
        if f.name == "jpeg_quality" and value == 0:
            value = None  # 0: off, i.e. PNG
        if value is not None:
            values[f.name] = tuple(float(v) for v in value) if isinstance(value, (list, tuple)) else value
    return Effects(**values)


def check_effects(fx: Effects, intr: Dict[str, object], period: float) -> List[str]:
    """Problems with the effects' values, one phrase each (the generator joins them into its one-line error)."""
    problems = []
    for name in ("pose_noise", "pose_drift", "distortion", "exposure", "vignetting", "motion_blur", "lidar_noise",
                 "lidar_dropout", "rolling_shutter"):
        if not all(math.isfinite(v) for v in np.atleast_1d(getattr(fx, name))):
            problems.append(f"--{name.replace('_', '-')} must be finite")
    if min(fx.pose_noise + fx.pose_drift) < 0 or fx.movers < 0 or fx.lidar_noise < 0:
        problems.append("--pose-noise, --pose-drift, --movers and --lidar-noise must be >= 0")
    for name in ("exposure", "vignetting", "lidar_dropout"):
        if not 0.0 <= getattr(fx, name) < 1.0:
            problems.append(f"--{name.replace('_', '-')} must be in [0, 1), got {getattr(fx, name)}")
    for name in ("motion_blur", "rolling_shutter"):
        if not 0.0 <= getattr(fx, name) < period:
            problems.append(f"--{name.replace('_', '-')} must be in [0, {period}) seconds, got {getattr(fx, name)}")
    if fx.jpeg_quality is not None and not 1 <= fx.jpeg_quality <= 100:
        problems.append(f"--jpeg-quality must be in 1..100 (0: PNG), got {fx.jpeg_quality}")
    if any(fx.distortion) and all(math.isfinite(v) for v in fx.distortion):
        w, h, f, c = intr["w"], intr["h"], np.array([intr["fl_x"], intr["fl_y"]]), np.array([intr["cx"], intr["cy"]])
        corners = (np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]) - c) / f
        undistorted = undistort_normalised(corners, fx.distortion)
        r2 = np.linspace(0.0, np.nanmax(np.sum(undistorted**2, axis=1)), 256)  # the radii the image spans, squared
        slope = 1.0 + 3.0 * fx.distortion[0] * r2 + 5.0 * fx.distortion[1] * r2**2  # d(r_distorted) / dr
        if not (np.all(slope > 0.0) and np.allclose(distort_normalised(undistorted, fx.distortion), corners, atol=1e-9)):
            problems.append(f"--distortion {fx.distortion[0]} {fx.distortion[1]} cannot be inverted over the image")
    return problems


# ----------------------------------------------------------------------------------------------------------------
# Camera timing and lens


def row_time_offsets(height: int, readout: float, supersample: int = 1) -> Float[np.ndarray, "rows"]:
    """Seconds from the frame stamp at which each (sub-)row of an image is exposed (rolling shutter).

    Row ``r`` (pixel centre at ``v = r + 0.5``) at ``readout (r - (H-1)/2) / (H-1)``, i.e. a point at continuous row
    coordinate ``v`` at ``readout (v - H/2) / (H-1)``; supersampled sub-rows at their own ``v``. All 0 for readout 0.
    """
    v = (np.arange(height * supersample) + 0.5) / supersample
    return readout * (v - height / 2.0) / max(height - 1, 1)


def exposure_offsets(exposure: float, samples: int = BLUR_SAMPLES) -> Float[np.ndarray, "samples"]:
    """Sub-frame times of a blurred render, seconds from each row's time: ``samples`` evenly spread over the exposure
    (centred on the row's time); ``[0]`` without blur."""
    if exposure <= 0.0:
        return np.zeros(1)
    return exposure * ((np.arange(samples) + 0.5) / samples - 0.5)


def distort_normalised(xy: Float[np.ndarray, "num 2"], k: Sequence[float]) -> Float[np.ndarray, "num 2"]:
    """OPENCV radial distortion (``k1``, ``k2``; no tangential terms) of normalised coordinates ``X/Z, Y/Z``."""
    r2 = np.sum(xy**2, axis=-1, keepdims=True)
    return xy * (1.0 + r2 * (k[0] + r2 * k[1]))


def undistort_normalised(xy: Float[np.ndarray, "num 2"], k: Sequence[float]) -> Float[np.ndarray, "num 2"]:
    """Inverse of ``distort_normalised`` (``cv2.undistortPointsIter``, iterated to 1e-12)."""
    import cv2

    pts = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    out = cv2.undistortPointsIter(pts, np.eye(3), np.array([k[0], k[1], 0.0, 0.0]), None, None, criteria)
    return out.reshape(-1, 2)


def pixel_directions(intr: Dict[str, object], supersample: int = 1,
                     distortion: Sequence[float] = (0.0, 0.0)) -> Float[np.ndarray, "rows cols 3"]:
    """Camera-frame ray directions (OpenCV axes, ``z = 1``, not unit) of every (sub-)pixel centre.

    Without distortion the plain pinhole rays; with ``k1``, ``k2`` the rays whose OPENCV
    projection lands on the pixel centre.
    """
    w, h, ss = int(intr["w"]), int(intr["h"]), int(supersample)
    uu, vv = np.meshgrid((np.arange(w * ss) + 0.5) / ss, (np.arange(h * ss) + 0.5) / ss)
    x, y = (uu - intr["cx"]) / intr["fl_x"], (vv - intr["cy"]) / intr["fl_y"]
    if any(distortion):
        x, y = undistort_normalised(np.stack([x, y], axis=-1).reshape(-1, 2), distortion).reshape(h * ss, w * ss, 2).transpose(2, 0, 1)
    return np.stack([x, y, np.ones_like(uu)], axis=-1)


# ----------------------------------------------------------------------------------------------------------------
# Photometry and files


def photometric_params(rng: np.random.Generator, cameras: int, frames: int, amplitude: float) -> Float[np.ndarray, "cameras frames 5"]:
    """Per-frame auto-exposure of each camera: gain in ``1 +- A``, gamma in ``1 +- A/2``, tint (r, g, b) in ``1 +- A/4``."""
    spread = amplitude * np.array([1.0, 0.5, 0.25, 0.25, 0.25])
    return 1.0 + rng.uniform(-1.0, 1.0, (cameras, frames, 5)) * spread


def vignetting_factor(intr: Dict[str, object], strength: float) -> Float[np.ndarray, "h w"]:
    """Brightness factor of every pixel: ``1 - strength (r / r_corner)^2``, ``r`` the distance of the pixel centre
    from the principal point, ``r_corner`` that of the farthest image corner (pixels)."""
    w, h = int(intr["w"]), int(intr["h"])
    uu, vv = np.meshgrid(np.arange(w) + 0.5 - intr["cx"], np.arange(h) + 0.5 - intr["cy"])
    corner2 = max((x - intr["cx"]) ** 2 + (y - intr["cy"]) ** 2 for x in (0.0, w) for y in (0.0, h))
    return 1.0 - strength * (uu**2 + vv**2) / corner2


def apply_photometric(rgb: Float[np.ndarray, "h w 3"], params: Optional[Float[np.ndarray, "5"]],
                      vignette: Optional[Float[np.ndarray, "h w"]]) -> Float[np.ndarray, "h w 3"]:
    """Camera response on colours in [0, 1]: ``clip(gain * tint * vignette * rgb, 0, 1) ** gamma``."""
    out = rgb.astype(np.float64)
    if vignette is not None:
        out = out * vignette[..., None]
    if params is not None:
        out = np.clip(out * params[0] * params[2:5], 0.0, 1.0) ** params[1]
    return np.clip(out, 0.0, 1.0)


def to_uint8(rgb: Float[np.ndarray, "h w 3"]) -> UInt8[np.ndarray, "h w 3"]:
    """Colours in [0, 1] to 8 bits, rounded."""
    return (np.clip(rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8)


def encode_jpeg(rgb: UInt8[np.ndarray, "h w 3"], quality: int) -> bytes:
    """JPEG file bytes of an RGB image (OpenCV's encoder, deterministic)."""
    import cv2

    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return data.tobytes()


# ----------------------------------------------------------------------------------------------------------------
# LiDAR


def lidar_range_noise(points: Float[np.ndarray, "num 3"], sigma: float, rng: np.random.Generator) -> Float[np.ndarray, "num 3"]:
    """Gaussian noise of standard deviation ``sigma`` (metres) on each point's range, along its ray; float32."""
    ranges = np.linalg.norm(points, axis=1, keepdims=True)
    return (points * (1.0 + rng.normal(0.0, sigma, ranges.shape) / ranges)).astype(np.float32)


def lidar_dropout_mask(count: int, fraction: float, rng: np.random.Generator) -> Bool[np.ndarray, "num"]:
    """Which of ``count`` returns survive random dropouts of probability ``fraction``."""
    return rng.uniform(size=count) >= fraction


# ----------------------------------------------------------------------------------------------------------------
# Moving vehicles


@dataclass
class Movers:
    """Car-size boxes driving along the ego path's road, on the ground, at constant speed along the centre line.

    Time ``t``: seconds since the first reference frame (the ``VehiclePath`` clock).
    """

    path: VehiclePath
    size: Float[np.ndarray, "movers 3"]
    """Length, width, height, metres."""
    s0: Float[np.ndarray, "movers"]
    """Arc length along the centre line at ``t = 0``, metres."""
    speed: Float[np.ndarray, "movers"]
    """Metres per second along the centre line (negative: oncoming)."""
    lateral: Float[np.ndarray, "movers"]
    """Offset from the centre line, metres, left positive."""
    texture: Int[np.ndarray, "movers"]
    """Index into the scene's texture atlas."""
    tint: Float[np.ndarray, "movers 3"]
    scale: Float[np.ndarray, "movers"]
    """Metres per texture tile."""
    uv_offset: Float[np.ndarray, "movers 2"]

    def poses(self, t: Float[np.ndarray, "times"]) -> Tuple[Float[np.ndarray, "times movers 3"], Float[np.ndarray, "times movers"]]:
        """Box centres (metres, world) and headings (radians about z) at times ``t``."""
        s = self.s0[None, :] + self.speed[None, :] * np.asarray(t, dtype=np.float64)[:, None]
        xy, psi = self.path.at_arclength(s.ravel())
        xy, psi = xy.reshape(s.shape + (2,)), psi.reshape(s.shape)
        normal = np.stack([-np.sin(psi), np.cos(psi)], axis=-1)
        centre = xy + self.lateral[None, :, None] * normal
        z = np.broadcast_to(0.5 * self.size[None, :, 2], s.shape)
        return np.concatenate([centre, z[..., None]], axis=-1), psi

    def intersect(self, origins: Float[np.ndarray, "num 3"], directions: Float[np.ndarray, "num 3"],
                  times: Float[np.ndarray, "num"]) -> Dict[str, np.ndarray]:
        """Cast rays (unit directions, metres) against the boxes where they are at each ray's time.

        Returns:
            ``t_hit`` (num,) metres (inf on a miss), ``mover`` (num,) index (-1 on a miss), ``local`` (num, 3) hit point
            in the box's frame (x along its heading, metres), ``axis`` (num,) the box axis of the face hit, ``heading``
            (num,) the box's heading, radians.
        """
        n = len(directions)
        out = {"t_hit": np.full(n, np.inf), "mover": np.full(n, -1), "local": np.zeros((n, 3)), "axis": np.zeros(n, dtype=np.int64),
               "heading": np.zeros(n)}
        unique, inverse = np.unique(np.asarray(times, dtype=np.float64), return_inverse=True)
        centres, headings = self.poses(unique)
        origins = np.broadcast_to(origins, directions.shape)
        for m in range(len(self.s0)):
            rel = origins - centres[inverse, m]
            b = np.einsum("ni,ni->n", rel, directions)  # bounding sphere first: the box test on its rays only
            disc = b * b - np.einsum("ni,ni->n", rel, rel) + 0.25 * float(self.size[m] @ self.size[m])
            rays = np.flatnonzero((disc >= 0.0) & (np.sqrt(np.maximum(disc, 0.0)) > b))
            if len(rays) == 0:
                continue
            psi, rel, dw = headings[inverse[rays], m], rel[rays], directions[rays]
            cos, sin = np.cos(psi), np.sin(psi)
            o = np.stack([cos * rel[:, 0] + sin * rel[:, 1], -sin * rel[:, 0] + cos * rel[:, 1], rel[:, 2]], axis=-1)
            d = np.stack([cos * dw[:, 0] + sin * dw[:, 1], -sin * dw[:, 0] + cos * dw[:, 1], dw[:, 2]], axis=-1)
            d = np.where(np.abs(d) < 1e-12, np.where(d < 0, -1e-12, 1e-12), d)
            half = 0.5 * self.size[m]
            t1, t2 = (-half - o) / d, (half - o) / d
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            enter, leave = near.max(axis=1), far.min(axis=1)
            better = (enter <= leave) & (enter > 0.0) & (enter < out["t_hit"][rays])
            hit = rays[better]
            out["t_hit"][hit], out["mover"][hit] = enter[better], m
            out["local"][hit] = o[better] + enter[better, None] * d[better]
            out["axis"][hit], out["heading"][hit] = near[better].argmax(axis=1), psi[better]
        return out


def make_movers(path: VehiclePath, count: int, duration: float, textures: int, rng: np.random.Generator) -> Movers:
    """``count`` vehicles that pass the ego vehicle during ``[0, duration]`` seconds: each is ``gap`` metres ahead of
    it along the road at a random time of the drive (3-30 m for oncoming ones, -12..25 m for those going its way),
    drives at 4-10 m/s, in the left lane (oncoming) or the right lane (same way), ``MOVER_LATERAL`` from the centre."""
    oncoming = rng.uniform(size=count) < 0.5
    speed = rng.uniform(4.0, 10.0, count) * np.where(oncoming, -1.0, 1.0)
    meet = rng.uniform(0.0, duration, count)
    gap = np.where(oncoming, rng.uniform(3.0, 30.0, count), rng.uniform(-12.0, 25.0, count))
    s0 = np.array([path.s_at(float(t)) for t in meet]) + gap - speed * meet
    lateral = np.where(oncoming, MOVER_LATERAL, -MOVER_LATERAL) + rng.uniform(-0.15, 0.15, count)
    size = np.stack([rng.uniform(3.8, 4.8, count), rng.uniform(1.7, 1.95, count), rng.uniform(1.3, 1.7, count)], axis=-1)
    return Movers(path, size, s0, speed, lateral, rng.integers(0, textures, count), rng.uniform(0.55, 1.1, (count, 3)),
                  rng.uniform(1.2, 2.5, count), rng.uniform(0.0, 1.0, (count, 2)))
