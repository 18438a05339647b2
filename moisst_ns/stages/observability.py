"""Which calibration parameters a drive constrains, from the Jacobian of a calibration's residuals.

For each of a sensor's 7 parameters (lever arm x, y, z in the reference frame; rotation about the sensor's own x,
y, z axes, called roll, pitch, yaw; time offset) the *marginal sensitivity* is the RMS change of the residuals per
unit change of that parameter when the 6 others re-fit to absorb it (the Schur complement of the Gauss-Newton
information ``J^T W J``, normalised per residual). A parameter is *weakly observable* when moving it by a typical
prior error (``TEST_STEPS``: 10 cm, 1 deg, 10 ms) changes the residuals by less than ``MIN_EFFECT`` (2 mm RMS, a
fraction of a LiDAR's range noise): the drive cannot tell that error apart, whatever the solver does. The reason
given comes from the trajectory itself: a lever arm shows only through rotations about the other axes (a flat
drive leaves the vertical weak), a rotation only through distance driven, a time offset only through velocity
changes (at constant speed on a straight line it is collinear with the lever arm along the direction of travel;
see Yang et al., "Degenerate motion analysis for aided INS", RSS 2019).

Nothing here imports nerfstudio.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List

import numpy as np
import roma
import torch
from jaxtyping import Float

PARAMETERS = ("x", "y", "z", "roll", "pitch", "yaw", "time_offset")
"""Parameter names in report order: lever arm along the reference frame's axes; rotation about the sensor's own
x, y, z axes; time offset."""
JACOBIAN_ORDER = (3, 4, 5, 0, 1, 2, 6)
"""Column of each of ``PARAMETERS`` in a Jacobian ordered (rotation vector, translation, time offset)."""
TEST_STEPS = (0.10, 0.10, 0.10, np.deg2rad(1.0), np.deg2rad(1.0), np.deg2rad(1.0), 0.010)
"""A typical prior error per parameter: 10 cm, 1 degree, 10 ms."""
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


def drive_excitation(traj, times: Float[np.ndarray, "num"], sensor_rotation: Float[np.ndarray, "3 3"]) -> dict:
    """What the reference trajectory does over ``times``: rotation about each reference axis (peak to peak of the
    rotation vector relative to the first pose, degrees), the largest turn (degrees), distance driven (m), the mean
    direction of travel in the sensor's frame and the velocity change (m/s)."""
    rot, pos, _, vel = traj.pose_and_rates(np.sort(times))
    rel = roma.rotmat_to_rotvec(torch.from_numpy(np.einsum("ji,njk->nik", rot[0], rot))).numpy()
    steps = np.diff(pos, axis=0)
    local = np.einsum("nji,nj->ni", rot[:-1] @ sensor_rotation, steps)  # each step in the sensor's frame
    travel = local.sum(axis=0)
    return {
        "rotation_deg": np.rad2deg(np.ptp(rel, axis=0)),
        "turn_deg": float(np.rad2deg(np.linalg.norm(rel, axis=1).max())),
        "distance_m": float(np.sum(np.linalg.norm(steps, axis=1))),
        "travel_direction": travel / max(float(np.linalg.norm(travel)), 1e-12),
        "velocity_change_mps": float(np.max(np.linalg.norm(vel[:, None] - vel[None, :], axis=-1))),
    }


def _reason(name: str, excitation: dict) -> str:
    rot = excitation["rotation_deg"]
    if name in ("x", "y", "z"):
        axis = "xyz".index(name)
        others = float(np.hypot(*np.delete(rot, axis)))
        return (f"the reference frame turns only {others:.1f} deg about its axes other than {name} over the drive; a lever "
                f"arm along {name} shows only through such turns (a flat drive leaves the vertical weak)")
    if name == "time_offset":
        return (f"the velocity changes by only {excitation['velocity_change_mps']:.2f} m/s over the drive; a time offset "
                "trades against the lever arm along the direction of travel (a straight constant-speed drive cannot "
                "separate them)")
    direction = ", ".join(f"{v:.2f}" for v in excitation["travel_direction"])
    return (f"the drive covers {excitation['distance_m']:.1f} m along the sensor's ({direction}) direction and turns only "
            f"{excitation['turn_deg']:.1f} deg; a rotation error shows in proportion to the distance driven across its "
            "axis, so a rotation about the direction of travel shows only through turns")


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
        traj: the reference trajectory (``Trajectory``), for the reasons.
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
    excitation = drive_excitation(traj, times, sensor_rotation)
    dofs = []
    for name, info, step in zip(PARAMETERS, marginal, TEST_STEPS):
        sensitivity = float(np.sqrt(info))
        effect = float(sensitivity * step)
        sigma = scatter / np.sqrt(info * total) if info > 0 else float("inf")
        weak = bool(effect < MIN_EFFECT)
        dofs.append(DofObservability(name, sensitivity, effect, float(sigma), weak, _reason(name, excitation) if weak else ""))
    return Observability(dofs)
