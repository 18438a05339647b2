"""The vehicle and rig of ``moisst-synth``: the vehicle's smooth analytic path (``VehiclePath``) and the rotations about
the coordinate axes both are built from (numpy, float64), sensor mounts, true extrinsics and time offsets, the MOISST
paper's prior perturbation, and the generator's seeded random streams. ``config`` arguments are ``synth.SynthConfig``
objects (only their fields are read)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Dict, Sequence, Tuple

import numpy as np

from moisst_ns.datasets.rig_writer import inverse, rigid

REFERENCE = "cam_front"


# ----------------------------------------------------------------------------------------------------------------
# The drive


def _rotation(axis: int, a: float) -> np.ndarray:
    """Rotation by ``a`` radians about the coordinate axis ``axis`` (0, 1, 2: x, y, z)."""
    c, s = np.cos(a), np.sin(a)
    i, j = (axis + 1) % 3, (axis + 2) % 3
    out = np.eye(3)
    out[i, i] = out[j, j] = c
    out[i, j], out[j, i] = -s, s
    return out


rot_x, rot_y, rot_z = (partial(_rotation, axis) for axis in range(3))


@dataclass
class VehiclePath:
    """A smooth analytic drive: heading and speed profiles (period 10 s), integrated on a fine grid.

    Time ``t`` is seconds since the first reference frame. Heading ``psi(t) = turn (1 - cos(pi t / 5)) / 2`` (0 to
    ``turn`` over 5 s and back), speed ``v(t) = 6.5 - 2.5 cos(pi t / 5)`` (4 to 9 m/s and back), plus small pitch,
    roll and bounce oscillations so every rotation axis moves a little (``drive="curve"``, the default).
    ``drive="straight"``: heading 0 and speed 6.5 m/s throughout, no oscillation (flat, constant twist: a time offset
    cannot be told from the lever arm along the direction of travel). ``drive="weave"``: the heading swings by
    ``+-|turn| / 3`` with period 4 s at the curve's varying speed and oscillations (the twist keeps changing).
    """

    turn: float
    """Heading change over the first 5 s, radians (sign = turn direction)."""
    phases: np.ndarray
    """Phases of the pitch / roll / bounce oscillations, radians."""
    t_min: float
    t_max: float
    dt: float = 1e-3
    drive: str = "curve"
    """``curve``, ``straight`` or ``weave`` (see above)."""

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
        if self.drive == "straight":
            return np.zeros_like(np.asarray(t, dtype=np.float64))
        if self.drive == "weave":
            return abs(self.turn) / 3.0 * np.sin(2 * np.pi * np.asarray(t) / 4.0)
        return self.turn * 0.5 * (1.0 - np.cos(np.pi * np.asarray(t) / 5.0))

    def speed(self, t):
        if self.drive == "straight":
            return np.full_like(np.asarray(t, dtype=np.float64), 6.5)
        return 6.5 - 2.5 * np.cos(np.pi * np.asarray(t) / 5.0)

    def world_T_vehicle(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) vehicle poses at times ``t`` (N,)."""
        t = np.asarray(t, dtype=np.float64)
        psi = self.heading(t)
        p1, p2, p3 = self.phases
        pitch = np.deg2rad(0.6) * np.sin(2 * np.pi * t / 1.7 + p1) - 0.004 * np.sin(np.pi * t / 5.0)
        roll = np.deg2rad(0.5) * np.sin(2 * np.pi * t / 2.3 + p2)
        bounce = 0.02 * np.sin(2 * np.pi * t / 1.3 + p3)
        if self.drive == "straight":
            pitch, roll, bounce = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
        poses = np.tile(np.eye(4), (len(t), 1, 1))
        for i in range(len(t)):
            poses[i, :3, :3] = rot_z(psi[i]) @ rot_y(pitch[i]) @ rot_x(roll[i])
        poses[:, :3, 3] = np.stack([np.interp(t, self.grid, self.xy[:, 0]), np.interp(t, self.grid, self.xy[:, 1]), bounce], -1)
        return poses

    def at_arclength(self, s: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Centre-line points (N, 2) and headings (N,) at arc lengths ``s`` (metres from the start position)."""
        s = np.asarray(s, dtype=np.float64)
        t = np.interp(s, self.arclength, self.grid)
        xy = np.stack([np.interp(t, self.grid, self.xy[:, 0]), np.interp(t, self.grid, self.xy[:, 1])], axis=-1)
        return xy, self.heading(t)

    def s_at(self, t: float) -> float:
        return float(np.interp(t, self.grid, self.arclength))


# ----------------------------------------------------------------------------------------------------------------
# Small rotation helpers (numpy, float64)


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


def _streams(seed: int) -> Dict[str, np.random.SeedSequence]:
    names = ("path", "rig", "scene", "perturb", "lidar", "lidar_noise", "pose_noise", "movers", "exposure", "lidar_dropout")
    return dict(zip(names, np.random.SeedSequence(seed).spawn(len(names))))



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
    return rigid(_orthonormalise(rot), np.asarray(pos) + np.asarray(jitter_t))


def _rig_seed(config) -> int:
    return config.seed if config.rig_seed is None else config.rig_seed


def knock_mount(config, truth: Dict[str, SensorTruth]) -> Dict[str, SensorTruth]:
    """The truth with ``--knock SENSOR DEG`` applied: that sensor turned about the vehicle's z axis, in place."""
    if config.knock is None:
        return truth
    name, degrees = config.knock
    v_T_ref = vehicle_T_sensor(REFERENCE)
    sensor = truth[name]
    v_T_s = v_T_ref @ sensor.T_ref_sensor
    v_T_s[:3, :3] = _orthonormalise(rot_z(np.deg2rad(degrees)) @ v_T_s[:3, :3])
    ref_T = inverse(v_T_ref) @ v_T_s
    ref_T[:3, :3] = _orthonormalise(ref_T[:3, :3])
    ref_T[3] = [0.0, 0.0, 0.0, 1.0]
    return {**truth, name: SensorTruth(name, sensor.type, ref_T, sensor.time_offset, sensor.phase)}


def make_truth(config) -> Dict[str, SensorTruth]:
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
        ref_T = inverse(v_T_ref) @ vehicle_T_sensor(name, jt, jr)
        ref_T[:3, :3] = _orthonormalise(ref_T[:3, :3])
        ref_T[3] = [0.0, 0.0, 0.0, 1.0]
        truth[name] = SensorTruth(name, "lidar" if name == "lidar" else "camera", ref_T, delta, PHASES[name])
    return truth


def perturbed_priors(config, names: Sequence[str], truth: Dict[str, Tuple[np.ndarray, float]], rng: np.random.Generator,
                     reference: str) -> Dict[str, Tuple[np.ndarray, float]]:
    """Priors for rig.json of ``truth`` (name -> (T_ref_sensor, time offset)): the truth (``config.perturb`` 'none',
    and always for ``reference``) or ``paper_perturbation`` with ``config.perturb_*``. Seven signs are drawn from
    ``rng`` for every one of ``names`` in order, present in ``truth`` or not (the signs do not depend on which are)."""
    priors = {}
    for name in names:
        signs = rng.choice([-1.0, 1.0], size=7)
        if name not in truth:
            continue
        T, offset = truth[name]
        if name == reference or config.perturb == "none":
            priors[name] = (T.copy(), offset)
        else:
            priors[name] = paper_perturbation(T, offset, signs, config.perturb_translation, config.perturb_rotation, config.perturb_time)
    return priors


def make_priors(config, truth: Dict[str, SensorTruth]) -> Dict[str, Tuple[np.ndarray, float]]:
    """Priors for rig.json: the truth (--perturb none) or the paper's perturbation (--perturb paper)."""
    return perturbed_priors(config, tuple(MOUNTS), {n: (t.T_ref_sensor, t.time_offset) for n, t in truth.items()},
                            np.random.default_rng(_streams(_rig_seed(config))["perturb"]), REFERENCE)
