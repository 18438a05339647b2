"""Per-vehicle consensus of many drives' calibrations, deviations in σ units, and sensors that moved. Pure numpy.
The seven components (``COMPONENTS``), σ (a drive's own uncertainty or the fleet's robust spread), the weighted-median
consensus and the moved-sensor rule: ``docs/fleet.md`` ("Consensus, σ and the moved-sensor flag").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

COMPONENTS = ("x", "y", "z", "rot_x", "rot_y", "rot_z", "time_offset")
"""The seven components of a deviation: metres (x, y, z), degrees (rot_*), seconds (time_offset)."""
UNITS = ("m", "m", "m", "deg", "deg", "deg", "s")
GROUPS = (slice(0, 3), slice(3, 6), slice(6, 7))
"""Components pooled together for the spread: translation, rotation, time."""
SIGMA_FLOOR = np.array([0.002, 0.002, 0.002, 0.02, 0.02, 0.02, 0.0002])
"""Smallest σ used (2 mm, 0.02°, 0.2 ms): below this, drives agreeing exactly would flag numerical noise."""
MAD_TO_SIGMA = 1.4826


@dataclass
class SensorEstimate:
    """One sensor's calibration from one drive."""

    T_ref_sensor: np.ndarray
    """4x4 extrinsic in the reference sensor's frame."""
    time_offset: float
    """Seconds."""
    sigma: Optional[np.ndarray] = None
    """The drive's own 1-σ uncertainty of the seven ``COMPONENTS``, or None (the fleet's spread is used)."""


@dataclass
class DriveEstimate:
    """A finished drive's calibration."""

    drive: str
    """Drive id."""
    sensors: Dict[str, SensorEstimate]
    """Per sensor (the reference sensor included or not: it is skipped)."""


@dataclass
class Move:
    """A sensor whose estimate stepped between two consecutive drives and stayed there."""

    sensor: str
    """Sensor name."""
    before: str
    """Last drive with the old mount."""
    after: str
    """First drive with the new mount."""
    component: str
    """The component that moved most, in σ units (one of ``COMPONENTS``)."""
    change: float
    """Its change (after minus before), in the component's unit (m, deg, s)."""
    z: float
    """The change in σ units (absolute)."""

    def line(self) -> str:
        """E.g. ``cam_left moved between drive d3 and drive d4 (rot_y +0.98°, 12.1 σ)``."""
        unit = UNITS[COMPONENTS.index(self.component)]
        value = {"m": f"{100 * self.change:+.1f} cm", "deg": f"{self.change:+.2f}°", "s": f"{1000 * self.change:+.1f} ms"}[unit]
        return f"{self.sensor} moved between drive {self.before} and drive {self.after} ({self.component} {value}, {self.z:.1f} σ)"


@dataclass
class SensorConsensus:
    """A vehicle's consensus for one sensor and how each drive deviates from it."""

    T_ref_sensor: np.ndarray
    """Consensus extrinsic (4x4)."""
    time_offset: float
    """Consensus time offset, seconds."""
    used: List[str]
    """Drives the consensus was taken over (those after the last move, if one was flagged)."""
    spread: np.ndarray
    """Robust spread (1.4826 MAD) of the used drives' seven components around the consensus (0 for one drive)."""
    deviation: Dict[str, np.ndarray] = field(default_factory=dict)
    """Per drive: its seven components minus the consensus's (m, deg, s)."""
    z: Dict[str, np.ndarray] = field(default_factory=dict)
    """Per drive: the deviation in σ units."""
    verdict: Dict[str, str] = field(default_factory=dict)
    """Per drive: ``ok``, ``deviates`` (some |z| > flag_sigma) or ``old mount`` (before a flagged move)."""
    move: Optional[Move] = None
    """The move flagged for this sensor, if any."""


@dataclass
class VehicleConsensus:
    """The consensus calibration of one vehicle."""

    reference_sensor: str
    """The reference sensor (identity, not combined)."""
    drives: List[str]
    """The vehicle's finished drives, in order."""
    sensors: Dict[str, SensorConsensus]
    """Per non-reference sensor."""

    def moves(self) -> List[Move]:
        """Every flagged move, by sensor name."""
        return [s.move for _, s in sorted(self.sensors.items()) if s.move is not None]


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The weighted median (the midpoint of the two middle values when the weights split exactly in half)."""
    order = np.argsort(values, kind="stable")
    v, w = np.asarray(values, float)[order], np.asarray(weights, float)[order]
    cum = np.cumsum(w) / w.sum()
    lower = int(np.searchsorted(cum, 0.5 - 1e-12))
    if abs(cum[lower] - 0.5) < 1e-9 and lower + 1 < len(v):
        return 0.5 * (v[lower] + v[lower + 1])
    return float(v[lower])


def components(estimate: SensorEstimate, T_center: np.ndarray, delta_center: float) -> np.ndarray:
    """The seven components of ``estimate`` relative to a centre (m, deg, s; see the module docstring)."""
    T = np.asarray(estimate.T_ref_sensor, float)
    omega = Rotation.from_matrix(T[:3, :3] @ T_center[:3, :3].T).as_rotvec(degrees=True)
    return np.concatenate([T[:3, 3] - T_center[:3, 3], omega, [estimate.time_offset - delta_center]])


def _center(estimates: Sequence[SensorEstimate], sigmas: np.ndarray):
    """Weighted-median centre (4x4, δ) of some estimates, pivoting rotations on their chordal mean."""
    rotations = np.stack([np.asarray(e.T_ref_sensor, float)[:3, :3] for e in estimates])
    u, _, vt = np.linalg.svd(rotations.sum(axis=0))
    pivot = np.eye(4)
    pivot[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rel = np.stack([components(e, pivot, 0.0) for e in estimates])
    weights = 1.0 / np.square(sigmas)
    med = np.array([weighted_median(rel[:, j], weights[:, j]) for j in range(7)])
    center = np.eye(4)
    center[:3, :3] = Rotation.from_rotvec(med[3:6], degrees=True).as_matrix() @ pivot[:3, :3]
    center[:3, 3] = med[:3]
    return center, float(med[6])


def fleet_spread(vehicles: Dict[str, List[DriveEstimate]], reference: Dict[str, str]) -> Dict[str, np.ndarray]:
    """Per sensor name, the fleet's spread-based σ of the seven components (see the module docstring): pooled over
    the vehicles (one rig model: a sensor of that name is as precise on every vehicle), never over sensors (a LiDAR
    calibrates to hundredths of a degree where a camera may wander by degrees); ``SIGMA_FLOOR`` without two drives."""
    residuals: Dict[str, List[List[float]]] = {}
    for vehicle, drives in vehicles.items():
        names = sorted({n for d in drives for n in d.sensors} - {reference[vehicle]})
        for name in names:
            pool = residuals.setdefault(name, [[], [], []])
            ests = [d.sensors[name] for d in drives if name in d.sensors]
            n = len(ests)
            if n < 2:
                continue
            center, delta = _center(ests, np.ones((n, 7)))
            rel = np.abs(np.stack([components(e, center, delta) for e in ests])) * np.sqrt(n / (n - 1))
            for g, group in enumerate(GROUPS):
                pool[g].extend(rel[:, group].ravel())
    out = {}
    for name, pool in residuals.items():
        sigma = SIGMA_FLOOR.copy()
        for g, group in enumerate(GROUPS):
            if pool[g]:
                sigma[group] = np.maximum(SIGMA_FLOOR[group], MAD_TO_SIGMA * float(np.median(pool[g])))
        out[name] = sigma
    return out


def _find_move(name: str, ids: List[str], x: np.ndarray, sig: np.ndarray, flag_sigma: float) -> Optional[Move]:
    """The strongest step between consecutive drives that every drive on both sides supports (or None)."""
    best = None
    w = 1.0 / np.square(sig)
    for k in range(1, len(ids)):
        a = np.array([weighted_median(x[:k, j], w[:k, j]) for j in range(7)])
        b = np.array([weighted_median(x[k:, j], w[k:, j]) for j in range(7)])
        sa, sb = 1.0 / np.sqrt(w[:k].sum(axis=0)), 1.0 / np.sqrt(w[k:].sum(axis=0))
        z = (b - a) / np.sqrt(sa**2 + sb**2)
        for j in np.argsort(-np.abs(z)):
            if abs(z[j]) <= flag_sigma:
                break
            s = np.sign(z[j])
            after_ok = np.all(s * (x[k:, j] - a[j]) / np.sqrt(sa[j] ** 2 + sig[k:, j] ** 2) > flag_sigma)
            before_ok = np.all(s * (b[j] - x[:k, j]) / np.sqrt(sb[j] ** 2 + sig[:k, j] ** 2) > flag_sigma)
            if after_ok and before_ok:
                if best is None or abs(z[j]) > best.z:
                    best = Move(name, ids[k - 1], ids[k], COMPONENTS[j], float(b[j] - a[j]), float(abs(z[j])))
                break
    return best


def vehicle_consensus(drives: List[DriveEstimate], reference: str, spread_sigma: Dict[str, np.ndarray], flag_sigma: float = 5.0) -> VehicleConsensus:
    """Combine one vehicle's drives (in the order driven) sensor by sensor.

    Args:
        drives: the vehicle's finished drives, in order.
        reference: the reference sensor (skipped).
        spread_sigma: per sensor, the fleet's σ of the seven components (``fleet_spread``), used where a drive has
            no own σ (``SIGMA_FLOOR`` for a sensor missing there).
        flag_sigma: threshold, in σ units, of a "deviates" verdict and of a flagged move.

    Returns:
        The consensus, per-drive deviations and verdicts, and flagged moves.
    """
    sensors = {}
    for name in sorted({n for d in drives for n in d.sensors} - {reference}):
        have = [d for d in drives if name in d.sensors]
        ids = [d.drive for d in have]
        ests = [d.sensors[name] for d in have]
        spread = spread_sigma.get(name, SIGMA_FLOOR)
        sig = np.stack([spread if e.sigma is None else np.maximum(np.asarray(e.sigma, float), 1e-12) for e in ests])
        center, delta = _center(ests, sig)
        x = np.stack([components(e, center, delta) for e in ests])
        move = _find_move(name, ids, x, sig, flag_sigma) if len(ests) > 1 else None
        start = ids.index(move.after) if move else 0
        if start:
            center, delta = _center(ests[start:], sig[start:])
        dev = np.stack([components(e, center, delta) for e in ests])
        spread = MAD_TO_SIGMA * np.median(np.abs(dev[start:]), axis=0)
        out = SensorConsensus(center, delta, ids[start:], spread, move=move)
        for i, drive in enumerate(ids):
            out.deviation[drive], out.z[drive] = dev[i], dev[i] / sig[i]
            out.verdict[drive] = "old mount" if i < start else ("deviates" if np.max(np.abs(out.z[drive])) > flag_sigma else "ok")
        sensors[name] = out
    return VehicleConsensus(reference, [d.drive for d in drives], sensors)


def sigma_from_uncertainty(entry: Optional[dict], R_ref_sensor: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """The seven σ of a calibration.json sensor's optional ``uncertainty`` object, or None when absent/incomplete.

    Args:
        entry: the sensor's ``uncertainty`` object (``rotation_deg`` about the sensor's own axes).
        R_ref_sensor: the sensor's rotation (3x3); when given, the rotation σ are turned onto the reference sensor's
            axes as ``COMPONENTS`` has them (``ω_ref = R ω_sensor``: the diagonal of ``R diag(σ²) Rᵀ``).

    Returns:
        ``(σx, σy, σz [m], σ_rot_x, σ_rot_y, σ_rot_z [deg], σδ [s])``, or None.
    """
    if not isinstance(entry, dict):
        return None
    try:
        out = np.array(list(entry["translation_m"]) + list(entry["rotation_deg"]) + [entry["time_offset_s"]], float)
    except (KeyError, TypeError, ValueError):
        return None
    if out.shape != (7,) or not np.all(np.isfinite(out)) or not np.all(out > 0):
        return None
    if R_ref_sensor is not None:
        R = np.asarray(R_ref_sensor, float)[:3, :3]
        out[3:6] = np.sqrt(np.square(R) @ np.square(out[3:6]))
    return out
