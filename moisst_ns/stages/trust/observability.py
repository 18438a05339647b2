"""Which calibration parameters the data constrain, from the Jacobian of a calibration's residuals
(``analyse_observability``: LiDAR scans registered to each other) or of a sensor's frame poses
``Traj(t + delta) . T_ref_i`` (rig format eq. 2) in its 7 parameters, from the drive alone (``analyse_drive``).

Per parameter, the marginal sensitivity (Schur complement of ``J^T W J``: the other 6 re-fitted) and the RMS effect of
a typical prior error (``TEST_STEPS``); weak below ``MIN_EFFECT``, with the reason taken from the trajectory
(``_reason``). The drive's models: ``absolute`` (world poses: cameras) or ``relative`` (poses between frames: LiDARs,
hand-eye), weak parameters from the eigen-directions scaled by ``TEST_STEPS`` (``weak_parameters``).
docs/lidar-first.md, "Observability", and docs/uncertainty.md, section 1, explain and measure them. Nothing here
imports nerfstudio.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Dict, List, Literal, Optional, Sequence

import numpy as np
import roma
import torch
from jaxtyping import Float

from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.rig.trust import PARAMETERS  # the one parameter order (re-exported)

JACOBIAN_ORDER = (3, 4, 5, 0, 1, 2, 6)
"""Column of each of ``PARAMETERS`` in a Jacobian ordered (rotation vector, translation, time offset)."""
TEST_STEPS = (0.10, 0.10, 0.10, np.deg2rad(1.0), np.deg2rad(1.0), np.deg2rad(1.0), 0.010)
"""A typical prior error per parameter: 10 cm, 1 degree, 10 ms."""
TYPICAL_ERROR = np.asarray(TEST_STEPS)[list(JACOBIAN_ORDER)]
"""``TEST_STEPS`` in Jacobian (solver) order, rad, m, s (the order is its own inverse)."""
SOLVER_NAMES = tuple(PARAMETERS[i] for i in JACOBIAN_ORDER)
"""``PARAMETERS`` in Jacobian (solver) order: roll, pitch, yaw, x, y, z, time_offset; the camera stage's corrections
(with ``estimate_readout`` an 8th, the readout time's, seconds)."""
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
    ``absolute`` / ``relative`` (``analyse_drive``), with the ``partners`` a parameter trades against and the
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


FD_STEPS = (1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-4)
"""Central finite-difference steps per parameter: metres, radians, seconds."""
SCENE_DEPTH_M = 10.0
"""Distance (m) at which an orientation change is measured as a displacement (a camera sees its rotation through points
at scene depth; 1 deg there is 17 cm)."""
MAX_LAG_S = 2.0
"""``relative`` model: frame pairs up to this far apart (a scan-to-map window), seconds."""
MIN_SEPARABILITY = 0.1
"""A parameter is weak when re-fitting the others leaves less than this fraction of its own effect (with
``MIN_EFFECT``: weak when its test step changes the residuals by less than that RMS, metres)."""


@dataclass
class DriveDof:
    """How well the drive constrains one parameter of one sensor."""

    name: str
    """One of ``PARAMETERS``."""
    effect_m: float
    """RMS residual change (metres) of the parameter's test step, the other 6 re-fitted."""
    separability: float
    """``sqrt(marginal / own information)`` in [0, 1]: 1 = independent of the others, 0 = fully absorbed."""
    partners: List[str]
    """The parameters that absorb it most (largest share of the re-fit), strongest first."""
    weak: bool
    reason: str
    """One line, empty when not weak."""


@dataclass
class DriveObservability:
    """Observability of one sensor's parameters from the drive."""

    sensor: str
    model: str
    """``absolute`` or ``relative``."""
    dofs: List[DriveDof] = field(default_factory=list)

    @property
    def weak(self) -> List[str]:
        return [d.name for d in self.dofs if d.weak]


def pose_residuals(
    traj: ReferenceTrajectory, times: Float[np.ndarray, "num"], extrinsic: Float[np.ndarray, "4 4"],
    params: Float[np.ndarray, "7"], model: Literal["absolute", "relative"], pairs: np.ndarray, scene_depth_m: float,
) -> Float[np.ndarray, "num_residuals"]:
    """How the sensor's poses change when its calibration moves by ``params`` from ``extrinsic`` / ``times``.

    Args:
        traj: the reference trajectory.
        times: the frames' reference-clock times with the prior offset (stamp + delta - t0), seconds.
        extrinsic: prior ``T_ref_sensor``.
        params: change of (x, y, z) in the reference frame (m), rotation vector about the sensor's axes (rad) and
            time offset (s), in ``PARAMETERS`` order.
        model: ``absolute`` (world poses) or ``relative`` (poses of frame ``pairs[:, 1]`` seen from ``pairs[:, 0]``).
        pairs: (P, 2) frame index pairs (``relative`` only).
        scene_depth_m: metres per radian of orientation change.

    Returns:
        Flattened (N, 6) residuals, metres: translation change in the sensor's frame, ``scene_depth_m`` times the
        rotation vector of the orientation change.
    """
    t = torch.as_tensor(times, dtype=torch.float64)
    prior = torch.as_tensor(extrinsic, dtype=torch.float64)
    p = torch.as_tensor(params, dtype=torch.float64)
    moved = calibrated_extrinsic(prior, p[3:6], p[0:3])
    before, after = traj(t) @ prior, traj(t + p[6]) @ moved
    if model == "relative":
        idx = torch.as_tensor(pairs, dtype=torch.long)
        before = torch.linalg.inv(before[idx[:, 0]]) @ before[idx[:, 1]]
        after = torch.linalg.inv(after[idx[:, 0]]) @ after[idx[:, 1]]
    change = torch.linalg.inv(before) @ after
    rot = roma.rotmat_to_rotvec(change[:, :3, :3]) * scene_depth_m
    return torch.cat([change[:, :3, 3], rot], dim=1).numpy().reshape(-1)


def frame_pairs(times: Float[np.ndarray, "num"], max_lag_s: float) -> np.ndarray:
    """Index pairs ``(j, k)``, ``j < k``, of frames at most ``max_lag_s`` apart (at least consecutive frames).

    Args:
        times: frame times, seconds.
        max_lag_s: largest time difference, seconds.

    Returns:
        (P, 2) int array.
    """
    order = np.argsort(times)
    out = []
    for a in range(len(order)):
        for b in range(a + 1, len(order)):
            if b > a + 1 and abs(times[order[b]] - times[order[a]]) > max_lag_s:
                break
            out.append((order[a], order[b]))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def pose_jacobian(traj: ReferenceTrajectory, times, extrinsic, model: str, pairs, scene_depth_m: float) -> Float[np.ndarray, "num_residuals 7"]:
    """Central finite-difference Jacobian of ``pose_residuals`` at zero change (metres per m / rad / s)."""
    return np.stack([(pose_residuals(traj, times, extrinsic, step, model, pairs, scene_depth_m)
                      - pose_residuals(traj, times, extrinsic, -step, model, pairs, scene_depth_m)) / (2 * h)
                     for step, h in zip(np.diag(FD_STEPS), FD_STEPS)], axis=1)


def _partners(information: Float[np.ndarray, "7 7"], i: int) -> List[str]:
    """The parameters whose re-fit absorbs most of parameter ``i``: largest ``|H_ij| / sqrt(H_ii H_jj)``."""
    diag = np.sqrt(np.maximum(np.diag(information), 1e-30))
    corr = np.abs(information[i]) / (diag[i] * diag)
    corr[i] = 0.0
    return [PARAMETERS[j] for j in np.argsort(-corr) if corr[j] > 0.5][:2]


SHARE = 0.3
"""A parameter takes part in a weak combination when its share of the (test-step scaled, unit) direction exceeds this."""


def weak_parameters(information: Float[np.ndarray, "7 7"]) -> set:
    """Indices of the parameters that take a material part (``SHARE``) in a weak combination.

    The information is scaled by ``TEST_STEPS`` (``D H D``: a unit vector is a combination of typical prior errors);
    an eigen-direction is weak when a test-sized error along it changes the poses by less than ``MIN_EFFECT`` RMS
    or by less than ``MIN_SEPARABILITY`` times the effect of its largest member alone. Marginal information alone
    would also flag a parameter that plays a tiny part in a degenerate combination (a camera's vertical lever arm
    when the velocity has a small vertical component in its frame).

    Args:
        information: per-pose ``J^T J`` in ``PARAMETERS`` order (metres^2 per unit^2).

    Returns:
        Set of parameter indices.
    """
    scale = np.asarray(TEST_STEPS)
    scaled = information * np.outer(scale, scale)
    values, vectors = np.linalg.eigh(scaled)
    own = np.sqrt(np.maximum(np.diag(scaled), 0.0))
    out = set()
    for value, vector in zip(values, vectors.T):
        effect = np.sqrt(max(value, 0.0))
        members = np.nonzero(np.abs(vector) > SHARE)[0]
        if len(members) and (effect < MIN_EFFECT or effect < MIN_SEPARABILITY * own[members].max()):
            out.update(int(i) for i in members)
    out.update(int(i) for i in np.nonzero(own < MIN_EFFECT)[0])
    return out


def analyse_drive(
    traj: ReferenceTrajectory, times: Float[np.ndarray, "num"], extrinsic: Float[np.ndarray, "4 4"], sensor: str,
    model: Literal["absolute", "relative"],
) -> DriveObservability:
    """Observability of one sensor's 7 parameters from the drive alone.

    Args:
        traj: the reference trajectory.
        times: the sensor's frames, reference-clock times (own stamp + prior delta - ``t0``), seconds; at least 2.
        extrinsic: prior ``T_ref_sensor``.
        sensor: its name (for the report).
        model: ``absolute`` or ``relative`` (module docstring).

    Returns:
        One ``DriveDof`` per parameter, in ``PARAMETERS`` order.
    """
    times = np.asarray(times, dtype=np.float64)
    pairs = frame_pairs(times, MAX_LAG_S) if model == "relative" else np.zeros((0, 2), dtype=np.int64)
    jac = pose_jacobian(traj, times, extrinsic, model, pairs, SCENE_DEPTH_M)
    information = jac.T @ jac / max(len(jac) // 6, 1)  # per pose: RMS over poses
    marginal = marginal_information(information)
    exc = excitation(*traj.pose_and_rates(np.sort(times)))  # what the drive does over the frames (the reasons)
    out = DriveObservability(sensor, model)
    weak_set = weak_parameters(information)
    for i, (name, step) in enumerate(zip(PARAMETERS, TEST_STEPS)):
        own = float(information[i, i])
        effect = float(np.sqrt(marginal[i]) * step)
        separability = float(np.sqrt(marginal[i] / own)) if own > 0 else 0.0
        partners = _partners(information, i)
        weak = i in weak_set
        out.dofs.append(DriveDof(name, effect, separability, partners, weak,
                                 _reason(name, exc, model, partners, effect) if weak else ""))
    return out


def analyse_rig_drive(rig, lidar_first: bool = True) -> List[DriveObservability]:
    """``analyse_drive`` for every non-reference sensor of a loaded rig, at its priors.

    Args:
        rig: a ``moisst_ns.rig.format.Rig``.
        lidar_first: LiDARs are calibrated by the LiDAR-first stage (``relative`` model); else like cameras.

    Returns:
        One result per non-reference sensor, in rig order.
    """
    traj = ReferenceTrajectory.of(rig)
    out = []
    for name, spec in rig.sensors.items():
        if name == rig.reference_sensor:
            continue
        stamps = np.array([f.timestamp for f in rig.frames_of(name)], dtype=np.float64)
        times = stamps + spec.time_offset - traj.t0
        if len(times) < 2:
            times = np.concatenate([times, times + 0.1])
        model = "relative" if (spec.type == "lidar" and lidar_first) else "absolute"
        out.append(analyse_drive(traj, times, spec.T_ref_sensor, name, model))
    return out


def drive_table(results: List[DriveObservability]) -> List[str]:
    """The printed table (effect of a test step in mm, separability) and one WARNING line per weak parameter.

    Args:
        results: ``analyse_rig_drive`` output.

    Returns:
        Lines to print.
    """
    head = f"{'sensor':<12} {'model':<9} " + " ".join(f"{p:>14}" for p in PARAMETERS)
    lines = ["observability from the drive (RMS pose effect of 10 cm / 1 deg / 10 ms, mm; separability; * = weak):", head]
    for r in results:
        cells = [f"{1000 * d.effect_m:7.1f} {d.separability:4.2f}{'*' if d.weak else ' '}" for d in r.dofs]
        lines.append(f"{r.sensor:<12} {r.model:<9} " + " ".join(f"{c:>14}" for c in cells))
    return lines + [f"WARNING: {r.sensor}: {d.name} weakly observable from this drive: {d.reason}" for r in results for d in r.dofs if d.weak]


def drive_json(results: List[DriveObservability]) -> Dict[str, dict]:
    """JSON-ready ``{sensor: {"model", "weak", "dofs": [...]}}``."""
    return {r.sensor: {"model": r.model, "weak": r.weak, "dofs": [asdict(d) for d in r.dofs]} for r in results}
