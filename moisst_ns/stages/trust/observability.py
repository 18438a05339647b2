"""Which calibration parameters a drive constrains, from the Jacobian of a calibration's residuals.

Per parameter, the marginal sensitivity (Schur complement of ``J^T W J``: the other 6 re-fitted) and the RMS effect of
a typical prior error (``TEST_STEPS``); weak below ``MIN_EFFECT``, with the reason taken from the trajectory
(``_reason``). The parameter order, test steps, marginal information, ``excitation`` and ``_reason`` are shared with
``drive_observability``. docs/lidar-first.md, "Observability", and docs/uncertainty.md explain and measure it.
Nothing here imports nerfstudio.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
import roma
import torch
from jaxtyping import Float

from moisst_ns.rig.trust import PARAMETERS  # noqa: F401 (the one parameter order, re-exported)

JACOBIAN_ORDER = (3, 4, 5, 0, 1, 2, 6)
"""Column of each of ``PARAMETERS`` in a Jacobian ordered (rotation vector, translation, time offset)."""
TEST_STEPS = (0.10, 0.10, 0.10, np.deg2rad(1.0), np.deg2rad(1.0), np.deg2rad(1.0), 0.010)
"""A typical prior error per parameter: 10 cm, 1 degree, 10 ms."""
TYPICAL_ERROR = np.asarray(TEST_STEPS)[list(JACOBIAN_ORDER)]
"""``TEST_STEPS`` in Jacobian (solver) order, rad, m, s (the order is its own inverse)."""
UNITS = ((100.0, "cm"),) * 3 + ((float(np.rad2deg(1.0)), "deg"),) * 3 + ((1000.0, "ms"),)
"""Display scale and unit of each of ``PARAMETERS`` (from m, rad, s)."""
MIN_EFFECT = 0.002
"""A parameter is weak when its test step changes the RMS residual by less than this, metres."""


@dataclass
class DofObservability:
    """How well one parameter is constrained."""

    name: str
    sensitivity: float
    """RMS residual change per unit of the parameter (metres per metre / radian / second), the others re-fitted."""
    effect_m: float
    """RMS residual change (metres) caused by the parameter's ``TEST_STEPS`` error."""
    sigma: float
    """Formal standard deviation (metres / radians / seconds) from the residual scatter and ``J^T W J``, treating
    correspondences as independent: a lower bound, not a calibrated uncertainty."""
    weak: bool
    reason: str


@dataclass
class Observability:
    """Per-parameter observability of one sensor's calibration."""

    dofs: List[DofObservability]

    @property
    def weak(self) -> List[str]:
        return [d.name for d in self.dofs if d.weak]


def huber_weights(residuals: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights of the Huber loss (1 inside ``scale``, ``scale / |r|`` beyond)."""
    return np.minimum(1.0, scale / np.maximum(np.abs(residuals), 1e-12))


def marginal_information(information: Float[np.ndarray, "7 7"]) -> Float[np.ndarray, "7"]:
    """``H_ii - H_ir H_rr^+ H_ri`` for every ``i``: what is left of each parameter's information once the others
    may move (0 for a parameter the others can fully absorb)."""
    out = np.empty(len(information))
    for i in range(len(information)):
        rest = [j for j in range(len(information)) if j != i]
        h_rr = information[np.ix_(rest, rest)]
        h_ri = information[rest, i]
        out[i] = information[i, i] - h_ri @ np.linalg.pinv(h_rr, rcond=1e-12, hermitian=True) @ h_ri
    return np.maximum(out, 0.0)


def excitation(rot: Float[np.ndarray, "num 3 3"], pos: Float[np.ndarray, "num 3"], rate: Float[np.ndarray, "num 3"],
               vel: Float[np.ndarray, "num 3"], sensor_rotation: Optional[Float[np.ndarray, "3 3"]] = None) -> dict:
    """What the reference trajectory does at its sorted sample times, from ``world_R_ref``, ``world_t_ref`` (m), the
    body angular rate (rad/s) and the velocity (m/s) there: distance driven (m), rotation about each reference axis
    (peak to peak of the rotation vector relative to the first pose) and the largest turn (degrees), speed range (m/s),
    spread of the angular rate (deg/s); with ``sensor_rotation`` (``ref_R_sensor``) also the mean direction of travel
    in the sensor's frame and the largest velocity change (m/s)."""
    rel = roma.rotmat_to_rotvec(torch.from_numpy(np.einsum("ji,njk->nik", rot[0], rot))).numpy()
    steps = np.diff(pos, axis=0)
    speed = np.linalg.norm(vel, axis=1)
    out = {"distance_m": float(np.sum(np.linalg.norm(steps, axis=1))), "speed_min": float(speed.min()),
           "speed_max": float(speed.max()), "turn_deg": float(np.rad2deg(np.linalg.norm(rel, axis=1).max())),
           "rotation_deg": np.rad2deg(np.ptp(rel, axis=0)),
           "rate_spread_dps": float(np.rad2deg(np.linalg.norm(rate - rate.mean(0), axis=1).max()))}
    if sensor_rotation is not None:
        travel = np.einsum("nji,nj->ni", rot[:-1] @ sensor_rotation, steps).sum(axis=0)  # each step in the sensor's frame
        out["travel_direction"] = travel / max(float(np.linalg.norm(travel)), 1e-12)
        out["velocity_change_mps"] = float(np.max(np.linalg.norm(vel[:, None] - vel[None, :], axis=-1)))
    return out


def _reason(name: str, exc: dict, model: str = "scans", partners: Sequence[str] = (), effect: float = 0.0) -> str:
    """One line: why ``name`` is weak on this drive (``exc``: its ``excitation``).

    ``model``: ``scans`` (``analyse_observability``: LiDAR scans registered to each other), or the drive analysis's
    ``absolute`` / ``relative`` (``drive_observability``), with the ``partners`` a parameter trades against and the
    RMS effect (metres) of its test step."""
    with_ = f"; it trades against {' and '.join(partners)}" if partners else ""
    if name in ("x", "y", "z") and model != "absolute":
        others = float(np.hypot(*np.delete(exc["rotation_deg"], "xyz".index(name))))
        how = f" over the drive; a lever arm along {name}" if model == "scans" else "; seen through the sensor's own motion a lever arm"
        return (f"the reference frame turns only {others:.1f} deg about its axes other than {name}{how} shows only "
                f"through such turns (a flat drive leaves the vertical weak){with_}")
    if name in ("x", "y", "z"):
        return (f"moving it by 10 cm changes the poses by {1000 * effect:.1f} mm RMS once the others re-fit; the speed "
                f"({exc['speed_min']:.2f}-{exc['speed_max']:.2f} m/s) and turns ({exc['turn_deg']:.1f} deg) do not tell "
                f"it from a time offset{with_}")
    if name == "time_offset" and model == "scans":
        return (f"the velocity changes by only {exc['velocity_change_mps']:.2f} m/s over the drive; a time offset "
                "trades against the lever arm along the direction of travel (a straight constant-speed drive cannot "
                "separate them)")
    if name == "time_offset":
        return (f"speed {exc['speed_min']:.2f}-{exc['speed_max']:.2f} m/s and the turn rate varies by only "
                f"{exc['rate_spread_dps']:.1f} deg/s over the drive: under a constant twist a time offset is a fixed "
                f"extrinsic change (a straight constant-speed drive cannot separate it from the along-track lever arm){with_}")
    if model == "scans":
        direction = ", ".join(f"{v:.2f}" for v in exc["travel_direction"])
        return (f"the drive covers {exc['distance_m']:.1f} m along the sensor's ({direction}) direction and turns only "
                f"{exc['turn_deg']:.1f} deg; a rotation error shows in proportion to the distance driven across its "
                "axis, so a rotation about the direction of travel shows only through turns")
    return (f"the drive covers {exc['distance_m']:.1f} m and turns {exc['turn_deg']:.1f} deg; seen through the sensor's "
            f"own motion a rotation shows only in proportion to the motion across its axis{with_}")


def analyse_observability(
    jacobian: Float[np.ndarray, "num 7"], residuals: Float[np.ndarray, "num"], weights: Float[np.ndarray, "num"],
    traj, times: Float[np.ndarray, "num_scans"], sensor_rotation: Float[np.ndarray, "3 3"],
) -> Observability:
    """Observability of the 7 parameters at a solution.

    Args:
        jacobian: residual Jacobian, columns (rotation vector about the sensor's axes, translation in the reference
            frame, time offset), metres per radian / metre / second.
        residuals: residuals at the solution, metres.
        weights: robust (IRLS) weight of each residual.
        traj: the reference trajectory (``ReferenceTrajectory``), for the reasons.
        times: reference-clock times of the sensor's frames (seconds since ``t0``).
        sensor_rotation: ``ref_R_sensor`` (to say in which direction the sensor travels).

    Returns:
        One ``DofObservability`` per parameter, in ``PARAMETERS`` order.
    """
    total = float(weights.sum())
    jac = jacobian[:, JACOBIAN_ORDER]
    information = (jac * weights[:, None]).T @ jac
    marginal = marginal_information(information / max(total, 1e-12))
    dof_resid = max(total - len(PARAMETERS), 1.0)
    scatter = float(np.sqrt(np.sum(weights * residuals**2) / dof_resid))
    exc = excitation(*traj.pose_and_rates(np.sort(times)), sensor_rotation)
    dofs = []
    for name, info, step in zip(PARAMETERS, marginal, TEST_STEPS):
        sensitivity = float(np.sqrt(info))
        effect = float(sensitivity * step)
        sigma = scatter / np.sqrt(info * total) if info > 0 else float("inf")
        weak = bool(effect < MIN_EFFECT)
        dofs.append(DofObservability(name, sensitivity, effect, float(sigma), weak, _reason(name, exc) if weak else ""))
    return Observability(dofs)
