"""The drive of ``moisst-synth``: the vehicle's smooth analytic path (``VehiclePath``) and the rotations about the
coordinate axes it and the rig are built from (numpy, float64)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Tuple

import numpy as np


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
        poses[:, :3, 3] = np.stack([np.interp(t, self.grid, self.xy[:, 0]), np.interp(t, self.grid, self.xy[:, 1]), bounce], axis=-1)
        return poses

    def at_arclength(self, s: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Centre-line points (N, 2) and headings (N,) at arc lengths ``s`` (metres from the start position)."""
        s = np.asarray(s, dtype=np.float64)
        t = np.interp(s, self.arclength, self.grid)
        xy = np.stack([np.interp(t, self.grid, self.xy[:, 0]), np.interp(t, self.grid, self.xy[:, 1])], axis=-1)
        return xy, self.heading(t)

    def s_at(self, t: float) -> float:
        return float(np.interp(t, self.grid, self.arclength))
