"""A reference trajectory's own errors, as a GPS/INS or SLAM system makes them: white noise and a slow drift
(``moisst-synth --pose-noise / --pose-drift`` writes them; rig.json's ``trajectory_accuracy`` states them, and the
LiDAR and camera stages draw them again for their sigma, ``trajectory_spread``). Pure numpy / scipy."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float

from moisst_ns.rig.files import RigFormatError
from moisst_ns.rig.trust import parameter_difference


@dataclass(frozen=True)
class TrajectoryAccuracy:
    """rig.json's optional ``trajectory_accuracy``: what the trajectory's source states of its errors, per axis
    (``perturb_trajectory``'s model). All 0 (the default): the trajectory is taken as exact."""

    noise_m: float = 0.0
    """White noise of the positions (world axes), standard deviation, metres."""
    noise_deg: float = 0.0
    """White noise of the orientations (rotation vector about the reference sensor's axes), degrees."""
    drift_m: float = 0.0
    """Slow drift of the positions, RMS over the drive (periods of 3-12 s), metres."""
    drift_deg: float = 0.0
    """Slow drift of the orientations, RMS over the drive, degrees."""

    def stated(self) -> bool:
        return any(asdict(self).values())

    @classmethod
    def parse(cls, raw, file) -> "TrajectoryAccuracy":
        """rig.json's ``trajectory_accuracy`` (absent: None), or a ``RigFormatError`` naming the field."""
        if raw is None:
            return cls()
        if not isinstance(raw, dict):
            raise RigFormatError(file, "trajectory_accuracy", f"must be an object of {[f.name for f in fields(cls)]}, got {raw!r}")
        for key, value in raw.items():
            if key not in {f.name for f in fields(cls)}:
                raise RigFormatError(file, f"trajectory_accuracy.{key}", f"unknown key (known: {', '.join(f.name for f in fields(cls))})")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise RigFormatError(file, f"trajectory_accuracy.{key}", f"must be a finite number >= 0, got {value!r}")
        return cls(**{k: float(v) for k, v in raw.items()})

    def draw(self, stamps: Float[np.ndarray, "num"], positions: Float[np.ndarray, "num 3"], quats_xyzw: Float[np.ndarray, "num 4"],
             seed: int) -> Tuple[Float[np.ndarray, "num 3"], Float[np.ndarray, "num 4"]]:
        """The trajectory with one more draw of its stated errors (``perturb_trajectory``; ``seed`` the draw)."""
        return perturb_trajectory(stamps, positions, quats_xyzw, (100 * self.noise_m, self.noise_deg), (100 * self.drift_m, self.drift_deg),
                                  np.random.SeedSequence(seed))


def drift_signal(times: Float[np.ndarray, "num"], rms: float, rng: np.random.Generator) -> Float[np.ndarray, "num 3"]:
    """A slow drift per axis: three sinusoids with periods drawn in 3-12 s and random phases, scaled so that each
    axis' RMS over ``times`` is exactly ``rms`` (the unit of ``rms``)."""
    period = rng.uniform(3.0, 12.0, (3, 3))  # (axis, component)
    phase = rng.uniform(0.0, 2.0 * np.pi, (3, 3))
    waves = np.sin(2.0 * np.pi * times[:, None, None] / period[None] + phase[None]).sum(axis=2)
    return rms * waves / np.maximum(np.sqrt(np.mean(waves**2, axis=0)), 1e-12)


def perturb_trajectory(
    stamps: Float[np.ndarray, "num"], positions: Float[np.ndarray, "num 3"], quats_xyzw: Float[np.ndarray, "num 4"],
    noise: Sequence[float], drift: Sequence[float], seed: np.random.SeedSequence,
) -> Tuple[Float[np.ndarray, "num 3"], Float[np.ndarray, "num 4"]]:
    """The reference trajectory as a GPS/INS or SLAM system would report it.

    Args:
        stamps: sample times, seconds. positions: ``world_t_ref``, metres. quats_xyzw: ``world_q_ref``.
        noise: white noise (centimetres, degrees): standard deviation per axis of the position (world axes) and of the
            rotation vector ``Log(R_true^T R_written)`` (about the reference sensor's own axes).
        drift: slow drift (centimetres, degrees), RMS per axis over the samples, as ``drift_signal`` (periods 3-12 s).
        seed: the draws; white noise and drift use separate streams (turning one on leaves the other's values alone).

    Returns:
        (positions (metres), unit quaternions x, y, z, w with w >= 0).
    """
    from scipy.spatial.transform import Rotation

    noise_rng, drift_rng = (np.random.default_rng(s) for s in seed.spawn(2))
    t = np.asarray(stamps, dtype=np.float64) - stamps[0]
    d_pos = drift_signal(t, drift[0] / 100.0, drift_rng) + noise_rng.normal(0.0, noise[0] / 100.0, (len(t), 3))
    d_rot = drift_signal(t, np.deg2rad(drift[1]), drift_rng) + noise_rng.normal(0.0, np.deg2rad(noise[1]), (len(t), 3))
    quats = (Rotation.from_quat(quats_xyzw) * Rotation.from_rotvec(d_rot)).as_quat()
    return positions + d_pos, quats * np.where(quats[:, 3:4] < 0, -1.0, 1.0)


Pose = Tuple[Float[np.ndarray, "4 4"], float]
"""A sensor's ``T_ref_sensor`` and time offset (seconds)."""


def trajectory_spread(fit: Callable[[object], Dict[str, Optional[Pose]]], rig, estimates: Dict[str, Pose],
                      draws: int) -> Dict[str, Float[np.ndarray, "7"]]:
    """What the trajectory's own errors put into a stage's estimates: per sensor, the RMS difference from its estimate
    of ``draws`` fits, each on a copy of the rig whose trajectory carries one more draw of the errors rig.json states
    (``TrajectoryAccuracy.draw``, seeds 0 .. draws-1). Where an estimate responds linearly to the trajectory, its error
    from the given trajectory's errors is one draw of that spread. The drive's halves cannot show it: a drift biases
    both alike (realistic street seed 2: the LiDAR's delta 11.5 ms off, its halves within 3.6 ms of the whole).

    Args:
        fit: ``fit(drawn_rig) -> {sensor: (T_ref_sensor, time_offset) or None (it failed)}``, the stage's fit from its
            estimates on that rig (``rig`` with only ``trajectory_positions`` and ``trajectory_quats_xyzw`` replaced).
        rig: the loaded dataset (``rig.format.Rig``: its trajectory and ``trajectory_accuracy``).
        estimates: the stage's estimate per sensor on the given trajectory.
        draws: how many draws.

    Returns:
        Per sensor of ``estimates``, per parameter of ``rig.trust.PARAMETERS`` (m, rad, s); NaN where no draw could be fitted.
    """
    moved: Dict[str, list] = {name: [] for name in estimates}
    for seed in range(draws):
        positions, quats = rig.trajectory_accuracy.draw(rig.trajectory_stamps, rig.trajectory_positions, rig.trajectory_quats_xyzw, seed)
        fitted = fit(replace(rig, trajectory_positions=positions, trajectory_quats_xyzw=quats))
        for name, pose in fitted.items():
            if pose is not None:
                moved[name].append(parameter_difference(*estimates[name], *pose))
    return {name: np.sqrt(np.mean(np.square(m), axis=0)) if m else np.full(7, np.nan) for name, m in moved.items()}
