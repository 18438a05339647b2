"""The optional per-sensor trust fields of ``calibration.json`` (docs/rig-format.md): uncertainty and verdict.

``"uncertainty": {"translation_m": [sx, sy, sz], "rotation_deg": [s1, s2, s3], "time_offset_s": sd}`` (one standard
deviation each: translation along the reference frame's axes; rotation as the small-angle rotation vector of
``R_estimate^T R_true`` about the sensor's own axes), ``"verdict"`` (one of ``VERDICTS``), ``"weak"`` (names from
``PARAMETERS``) and ``"reason"`` (one line). A file without them (every file older than them) loads unchanged.

Pure Python/numpy; ``parse_trust`` raises ``TrustFieldError`` naming the field, which ``rig.format`` turns into its
one-line ``RigFormatError``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional

PARAMETERS = ("x", "y", "z", "roll", "pitch", "yaw", "time_offset")
"""The parameter order of reports, trust fields and observability: lever arm along the reference frame's axes;
rotation about the sensor's own x, y, z axes (small-angle rotation-vector components, named roll, pitch, yaw in files;
not Euler angles); time offset. Jacobians order them (rotation vector, translation, time offset):
``stages.trust.observability.JACOBIAN_ORDER``."""
VERDICTS = ("converged", "not converged", "weakly observable")
"""``not converged``: still moving, or the held-back loss at the estimate no better than at the prior;
``weakly observable``: converged but some parameters (``weak``) are not constrained by the data."""
UNCONSTRAINED = 100.0
"""A sigma beyond this many typical prior errors (10 m, 100 deg, 1 s) means the data do not determine the parameter."""
TRUST_KEYS = ("uncertainty", "verdict", "weak", "reason")


class TrustFieldError(ValueError):
    """A trust field with a bad value: ``field`` (relative to the sensor entry) and ``problem``."""

    def __init__(self, fieldname: str, problem: str):
        self.field, self.problem = fieldname, problem
        super().__init__(f"{fieldname}: {problem}")


@dataclass
class SensorTrust:
    """How far one sensor's calibration can be trusted."""

    translation_m: Optional[List[float]] = None
    """sigma of x, y, z (reference frame), metres; None when not computed."""
    rotation_deg: Optional[List[float]] = None
    """sigma of the rotation about the sensor's x, y, z axes, degrees."""
    time_offset_s: Optional[float] = None
    """sigma of the time offset, seconds."""
    verdict: Optional[str] = None
    """One of ``VERDICTS``, or None."""
    weak: List[str] = field(default_factory=list)
    """Weakly observable parameters (``PARAMETERS`` names)."""
    reason: str = ""
    """One line explaining the verdict."""

    def sigmas(self) -> Optional[List[float]]:
        """The 7 sigmas in ``PARAMETERS`` order (m, m, m, deg, deg, deg, s), or None when not all known."""
        if self.translation_m is None or self.rotation_deg is None or self.time_offset_s is None:
            return None
        return list(self.translation_m) + list(self.rotation_deg) + [self.time_offset_s]

    def to_json(self) -> dict:
        out: dict = {}
        if self.sigmas() is not None:
            out["uncertainty"] = {"translation_m": [finite_or_none(v) for v in self.translation_m],
                                  "rotation_deg": [finite_or_none(v) for v in self.rotation_deg], "time_offset_s": finite_or_none(self.time_offset_s)}
        if self.verdict is not None:
            out["verdict"] = self.verdict
            out["weak"] = list(self.weak)
            out["reason"] = self.reason.replace("\r", " ").replace("\n", " ")
        return out


def finite_or_none(value: float) -> Optional[float]:
    """A number for JSON: ``null`` for an infinite or NaN one (an unconstrained or unmeasured sigma)."""
    return float(value) if math.isfinite(value) else None


def _sigma(value, fieldname: str) -> float:
    if value is None:
        return math.inf  # null: not constrained by the data
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise TrustFieldError(fieldname, f"must be a finite number >= 0 (or null: unconstrained), got {value!r}")
    return float(value)


def _triple(value, fieldname: str) -> List[float]:
    if not isinstance(value, list) or len(value) != 3:
        raise TrustFieldError(fieldname, f"must be a list of 3 numbers, got {value!r}")
    return [_sigma(v, f"{fieldname}[{i}]") for i, v in enumerate(value)]


def parse_trust(entry: dict) -> Optional[SensorTrust]:
    """The trust fields of one sensor entry of calibration.json, validated; None when it has none.

    Args:
        entry: the sensor's JSON object.

    Returns:
        ``SensorTrust`` or None.

    Raises:
        TrustFieldError: a present field with a bad value (field name relative to the entry).
    """
    if not any(k in entry for k in TRUST_KEYS):
        return None
    trust = SensorTrust()
    if "uncertainty" in entry:
        unc = entry["uncertainty"]
        if not isinstance(unc, dict):
            raise TrustFieldError("uncertainty", "must be an object")
        for key in ("translation_m", "rotation_deg", "time_offset_s"):
            if key not in unc:
                raise TrustFieldError(f"uncertainty.{key}", "missing")
        trust.translation_m = _triple(unc["translation_m"], "uncertainty.translation_m")
        trust.rotation_deg = _triple(unc["rotation_deg"], "uncertainty.rotation_deg")
        trust.time_offset_s = _sigma(unc["time_offset_s"], "uncertainty.time_offset_s")
    if "verdict" in entry:
        if entry["verdict"] not in VERDICTS:
            raise TrustFieldError("verdict", f"must be one of {', '.join(VERDICTS)}; got {entry['verdict']!r}")
        trust.verdict = entry["verdict"]
    weak = entry.get("weak", [])
    if not isinstance(weak, list) or any(w not in PARAMETERS for w in weak):
        raise TrustFieldError("weak", f"must be a list of names from {', '.join(PARAMETERS)}; got {weak!r}")
    trust.weak = list(weak)
    reason = entry.get("reason", "")
    if not isinstance(reason, str) or "\n" in reason or "\r" in reason:
        raise TrustFieldError("reason", "must be a one-line string")
    trust.reason = reason
    return trust


def decide_verdict(still_moving: Optional[str], loss_estimate: Optional[float], loss_prior: Optional[float],
                   weak: List[str], hit_bounds: List[str], unconstrained: Optional[List[str]] = None,
                   blind: Optional[List[str]] = None, held: Optional[str] = None) -> tuple:
    """The verdict of one sensor and its one-line reason.

    Args:
        still_moving: the spread of its last logged estimates when it is still moving (``runs.history.still_moving``),
            else None.
        loss_estimate: held-back loss at the estimate (None: not measured).
        loss_prior: the same at the prior.
        weak: weakly observable parameters (drive and data).
        hit_bounds: the bounds its estimate ran into.
        unconstrained: parameters the data do not determine at all (sigma infinite or beyond ``UNCONSTRAINED``
            times the typical prior error): the estimate of them is arbitrary.
        blind: parameters a typical prior error of which the sensor's view does not tell apart (camera registration's
            ``typical_error_significance``): the sensor was held at its prior.
        held: why the parameters held at their priors disagree with the data (LiDAR first's ``release_check``), else
            None: the free parameters absorbed that error, by an amount of the held error's size (measured: 101 cm from
            the truth for a LiDAR whose prior was 86.6 cm off, delta held 100 ms off), so the prior is kept.

    Returns:
        ``(verdict, reason)``. Every ``not converged`` sensor keeps its prior (the reason ends ": the prior is kept"):
        calibration.json holds an estimate only where the tool vouches for it, and a calibration never silently ends
        worse than it started. Still moving is among them: the held-back loss cannot say whether a NeRF-calibrated
        sensor improved (the scene was fitted to the estimate), and the measured case did not (camera-only plaza rig
        of seed 1: the side camera the stages could not register ended 13.5 deg off against a prior 8.8 deg off, with
        a lower held-back loss).
    """
    if blind:
        cause = f"its view does not tell a typical prior error (10 cm, 1 deg, 10 ms) apart on {', '.join(blind)}"
    elif unconstrained:
        cause = f"{', '.join(unconstrained)} not determined by the data (sigma beyond {UNCONSTRAINED:g}x a typical prior error)"
    elif loss_estimate is not None and loss_prior is not None and not loss_estimate < loss_prior:
        cause = f"held-back loss {loss_estimate:.5g} at the estimate is no better than {loss_prior:.5g} at the prior"
    elif still_moving:
        cause = f"still moving over its last estimates ({still_moving})"
    elif held:
        cause = held
    elif hit_bounds:
        cause = f"ran into its bound on {', '.join(hit_bounds)}"
    else:
        better = (f"; held-back loss {loss_estimate:.5g} vs {loss_prior:.5g} at the prior"
                  if loss_estimate is not None and loss_prior is not None else "")
        if weak:
            return "weakly observable", f"{', '.join(weak)} weakly observable{better}"
        return "converged", f"settled, every parameter observable{better}"
    return "not converged", f"{cause}: the prior is kept"


def parameter_difference(T_a, delta_a: float, T_b, delta_b: float) -> List[float]:
    """The 7 parameters of ``b`` minus those of ``a``: translation (m, reference frame), the small-angle rotation
    vector of ``R_a^T R_b`` (rad, about the sensor's own axes), time offset (s).

    Args:
        T_a: ``T_ref_sensor`` of ``a``, 4x4.
        delta_a: its time offset, seconds.
        T_b: ``T_ref_sensor`` of ``b``.
        delta_b: its time offset.

    Returns:
        7 numbers in ``PARAMETERS`` order.
    """
    import numpy as np
    import roma
    import torch

    a, b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    rot = roma.rotmat_to_rotvec(torch.from_numpy(a[:3, :3].T @ b[:3, :3])).numpy()
    return [float(v) for v in b[:3, 3] - a[:3, 3]] + [float(v) for v in rot] + [float(delta_b - delta_a)]


def sigma_units(difference: List[float], *trusts: Optional[SensorTrust]) -> List[Optional[float]]:
    """``|difference| / sqrt(sum of the sigma^2)`` per parameter over the trusts that carry sigmas (independent
    estimates: the variances add); None where no sigma is known or it is 0.

    Args:
        difference: ``parameter_difference`` (m, rad, s).
        trusts: the estimates' trust fields (sigmas in m, deg, s).

    Returns:
        7 ratios (or None).
    """
    known = [[math.radians(s) if 3 <= k < 6 else s for k, s in enumerate(t.sigmas())] for t in trusts if t is not None and t.sigmas() is not None]
    if not known:
        return [None] * 7
    variances = [sum(sig[k] * sig[k] for sig in known) for k in range(7)]
    return [abs(d) / math.sqrt(v) if v > 0 and math.isfinite(v) else None for d, v in zip(difference, variances)]
