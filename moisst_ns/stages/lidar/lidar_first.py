"""LiDAR first: calibrate each LiDAR against the reference trajectory from its own scans (no image, no NeRF).

Every scan point is placed by paper eq. 1-2 at its own firing time (``lidar_geometry``); point-to-plane residuals
between scans over growing baselines (``lidar_scans``) are solved coarse to fine for the 7 parameters of eq. 12 (robust
trust-region Gauss-Newton, analytic Jacobian), then checked (split-half spread, release check) and, where the drive's
halves hold parameters, placed by the shared view (``lidar_view``); the trajectory's stated errors, drawn again, widen
the sigma (``trajectory_spread``). docs/lidar-first.md has the formulation, the rules and the measurements. No nerfstudio.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float, Int
from scipy.optimize import least_squares

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trajectory_noise import trajectory_spread
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, prior_residuals
from moisst_ns.stages.camera.lidar_map import CameraStageError
from moisst_ns.stages.lidar.lidar_scans import (  # noqa: F401 (Correspondences, ScanSet, load_scans, scan_pairs: the stage's data, imported from here too)
    Correspondences, LidarFirstConfig, LidarFirstError, ScanSet, consistency_residuals, find_correspondences, load_scans, scan_pairs)
from moisst_ns.stages.lidar.lidar_view import SharedView, ViewSearch, search_held
from moisst_ns.stages.trust.observability import (JACOBIAN_ORDER, PARAMETERS, TEST_STEPS, TYPICAL_ERROR, UNITS, Observability, analyse_observability,
                                            huber_weights)


@dataclass
class LidarResult:
    """The LiDAR-first estimate of one LiDAR."""

    sensor: str
    prior: Extrinsic
    estimate: Extrinsic
    history: List[Dict[str, float]]
    """Per outer iteration: radius, baseline, pairs, correspondences, robust cost, inlier RMS, change, wall time and
    the estimate after it (``T_ref_sensor``, ``time_offset``)."""
    observability: Observability
    num_scans: int
    deskewed: bool
    dropped: List[str]
    wall_s: float
    held_check: Optional[Dict[str, object]] = None
    """With a parameter held at its prior: ``release_check`` (which held parameters disagree with the scans, and the
    free parameters' spread when they are released) and ``sigma_held`` (``held_sigma``), else None."""
    sigma_split: Optional[List[float]] = None
    """``split_half_spread`` in ``observability.PARAMETERS`` order (m, rad, s; NaN where a half cannot be fitted: not
    measured), or None when ``split_half`` is off."""
    view_search: Optional[Dict[str, object]] = None
    """``view_search``: the columns searched, those placed, their sigma and the notes (``lidar_view.ViewSearch``)."""
    sigma_trajectory: Optional[List[float]] = None
    """``trajectory_spread`` in ``PARAMETERS`` order (m, rad, s), or None when rig.json states no trajectory errors."""

    def undetermined(self) -> List[str]:
        """The parameters (``PARAMETERS`` names) this stage did not determine: held at the prior because the drive's
        halves disagree and not placed by the shared view, or with a split-half (or placed) sigma above a typical prior
        error (``TEST_STEPS``). A parameter the user holds (``estimate_extrinsic``/``estimate_time_offset`` off) is given,
        not undetermined."""
        spread, placed = self.sigma_split or [0.0] * 7, [PARAMETERS[JACOBIAN_ORDER.index(j)] for j in (self.view_search or {}).get("accepted", [])]
        return [p for p in self.motion_undetermined() if p not in placed or spread[PARAMETERS.index(p)] > TEST_STEPS[PARAMETERS.index(p)]]

    def motion_undetermined(self) -> List[str]:
        """The parameters the scans' motion did not determine: ``undetermined`` and those the shared view placed (what
        the camera stage checks at the shared instants, ``lidar_map.map_source``: the view's depth edges placed
        KITTI raw 0048's Velodyne 33 cm off in x under a sigma of 3 cm from the converter's ``--seed 1`` prior)."""
        held = (self.held_check or {}).get("held_apart", [])
        spread = self.sigma_split or [0.0] * 7
        return [p for p, v, typical in zip(PARAMETERS, spread, TEST_STEPS) if p in held or v > typical]


def _fit(traj: ReferenceTrajectory, scans: ScanSet, pairs: np.ndarray, baselines: np.ndarray, start: Extrinsic, prior: Extrinsic, free: np.ndarray,
         config: LidarFirstConfig, log: Callable[[str], None], where: str) -> Tuple[Extrinsic, List[Dict[str, float]]]:
    """Coarse-to-fine outer iterations of the parameters ``free`` (Jacobian order: rotation, translation, delta) from
    ``start``; ``prior`` anchors the bound on delta, ``where`` (``file: sensors.NAME``) names the sensor in errors.

    Returns:
        The estimate and its per-iteration history (``LidarResult.history``).
    """
    begun = time.perf_counter()
    ext, history = start, []
    longest = float(baselines.max()) if len(baselines) else 0.0
    sensor = where.rsplit(".", 1)[-1]
    sigma = np.repeat(np.array(config.prior_sigma, dtype=np.float64)[[1, 0, 2]], [3, 3, 1])  # prior sigmas, Jacobian order
    anchored, sigma = free[sigma[free] > 0], np.where(sigma > 0, sigma, 1.0)  # the free parameters with a prior row
    for outer in range(config.max_outer):
        radius = max(config.radius_end, config.radius_start * 0.6**outer)
        reach = config.start_baseline * 2.0**outer
        active = pairs[(baselines <= reach) | (pairs[:, 1] - pairs[:, 0] <= 2)]  # neighbours always pair
        corr = find_correspondences(traj, ext, scans, active, radius, config)
        if outer == 0 and len(corr.src) < max(100, 0.02 * corr.candidates):
            raise LidarFirstError(
                f"{where}: the scans do not overlap: {len(corr.src)} of {corr.candidates} "
                f"sampled points found a planar neighbour within {radius:.2f} m in the paired scans (wrong trajectory, "
                "time stamps or a static LiDAR?)")
        at_start = consistency_residuals(traj, ext, scans, corr, np.zeros(7))[0]  # the prior's unit
        spent = ext.time_offset - prior.time_offset
        lower, upper = np.full(7, -np.inf), np.full(7, np.inf)
        lower[6], upper[6] = -config.max_time_offset - spent, config.max_time_offset - spent
        cache: Dict[bytes, Tuple[np.ndarray, np.ndarray]] = {}
        scatter = 1.4826 * float(np.median(np.abs(at_start)))  # the prior rows' unit

        def evaluate(free_inc: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
            key = free_inc.tobytes()
            if key not in cache:
                inc = np.zeros(7)
                inc[free] = free_inc
                residuals, jac = consistency_residuals(traj, ext, scans, corr, inc)
                res_p, jac_p = prior_residuals(ext, prior, inc, sigma)
                cache.clear()
                cache[key] = (np.concatenate([residuals, scatter * res_p[anchored]]),
                              np.concatenate([jac, scatter * jac_p[anchored]])[:, free])
            return cache[key]

        solution = least_squares(lambda x: evaluate(x)[0], np.zeros(len(free)), jac=lambda x: evaluate(x)[1],
                                 bounds=(lower[free], upper[free]), loss="huber", f_scale=config.huber, x_scale="jac",
                                 method="trf", max_nfev=config.max_inner_evaluations)
        inc = np.zeros(7)
        inc[free] = solution.x
        ext = ext.updated(inc)
        residuals = solution.fun[:len(corr.src)]
        inliers = np.abs(residuals) < config.huber
        change = (float(np.linalg.norm(inc[3:6])), float(np.linalg.norm(inc[:3])), abs(float(inc[6])))
        history.append({
            "iteration": outer, "radius_m": radius, "max_baseline_m": min(reach, longest), "pairs": int(len(active)),
            "correspondences": int(len(corr.src)), "cost": float(solution.cost / max(len(residuals), 1)),
            "inlier_rms_m": float(np.sqrt(np.mean(residuals[inliers] ** 2))) if inliers.any() else float("nan"),
            "inlier_fraction": float(inliers.mean()), "change_m": change[0], "change_rad": change[1], "change_s": change[2],
            "elapsed_s": time.perf_counter() - begun, "T_ref_sensor": ext.matrix().tolist(), "time_offset": ext.time_offset,
        })
        h = history[-1]
        log(f"[lidar-first] {sensor} it {outer}: radius {radius:.2f} m, pairs {h['pairs']}, {h['correspondences']} corr., "
            + f"inlier rms {1000 * h['inlier_rms_m']:.1f} mm, step {100 * change[0]:.2f} cm / {np.rad2deg(change[1]):.3f} deg / "
            f"{1000 * change[2]:.2f} ms")
        finest = radius <= config.radius_end and reach >= longest
        if finest and all(c < tol for c, tol in zip(change, config.tolerance)):
            break
    return ext, history


def calibrate_lidar(rig: Rig, sensor: str, config: LidarFirstConfig, log: Callable[[str], None] = print) -> LidarResult:
    """Estimate ``ref_T_L`` and ``delta_L`` of one LiDAR from its scans and the reference trajectory alone.

    Args:
        rig: the loaded dataset (its priors are the starting point).
        sensor: the LiDAR's name.
        config: stage settings.
        log: where progress lines go.

    Returns:
        The estimate, its per-iteration history and the observability of each parameter; with a parameter held
        (``estimate_extrinsic`` or ``estimate_time_offset`` off), the ``release_check`` too.
    """
    start = time.perf_counter()
    spec = rig.sensors[sensor]
    traj = ReferenceTrajectory.of(rig)
    scans = load_scans(rig, sensor, traj, config, log)
    prior = Extrinsic(spec.T_ref_sensor[:3, :3].copy(), spec.T_ref_sensor[:3, 3].copy(), float(spec.time_offset))
    pairs, baselines = scan_pairs(traj, scans, prior.time_offset, config)
    free = np.array([i for i in range(7) if (i < 6 and config.estimate_extrinsic) or (i == 6 and config.estimate_time_offset)])
    if len(free) == 0:
        raise LidarFirstError("estimate_extrinsic and estimate_time_offset are both off: nothing to calibrate")
    where = f"{rig.root / 'rig.json'}: sensors.{sensor}"
    ext, history = _fit(traj, scans, pairs, baselines, prior, prior, free, config, log, where)
    unheld = ext if len(free) == 7 else None  # every parameter free from the prior: the release check's fit, if one is held
    fine = replace(config, radius_start=config.radius_end, start_baseline=float(baselines.max()) if len(baselines) else config.start_baseline)
    held_apart: List[int] = []

    def fine_fit(t: ReferenceTrajectory, p: np.ndarray, b: np.ndarray, at: Extrinsic, params: np.ndarray) -> Optional[Extrinsic]:
        """The finest radius' fit from ``at`` on trajectory ``t`` and scan pairs ``p`` (None: those scans do not overlap)."""
        try:
            return _fit(t, scans, p, b, at, prior, params, fine, lambda line: None, where)[0]
        except LidarFirstError:
            return None

    while True:  # the fit, then (hold_split_half, every parameter estimated) again with what the halves disagree on held
        corr = find_correspondences(traj, ext, scans, pairs, config.radius_end, config)
        residuals, jac = consistency_residuals(traj, ext, scans, corr, np.zeros(7))
        observability = analyse_observability(jac, residuals, huber_weights(residuals, config.huber), traj, scans.stamps + ext.time_offset, ext.rotation)
        split = None
        if config.split_half:
            split = split_half_spread(lambda p, b, at=ext, params=free: fine_fit(traj, p, b, at, params), pairs, baselines, len(scans.stamps)).tolist()
            log(f"[lidar-first] {sensor}: " + ("the halves of the drive cannot be fitted apart (split-half sigma not measured)" if np.isnan(split).any() else
                "halves of the drive apart by " + ", ".join(f"{p} {2 * v * u:.3g} {n}" for p, v, (u, n) in zip(PARAMETERS, split, UNITS))))
        apart = [] if split is None or config.hold_split_half <= 0 or len(free) + len(held_apart) < 7 else \
            [JACOBIAN_ORDER[i] for i in range(7) if split[i] > config.hold_split_half * TEST_STEPS[i] and JACOBIAN_ORDER[i] in free]
        if not apart or len(apart) == len(free):  # nothing (more) to hold, or nothing would be left to fit
            break
        log(f"[lidar-first] {sensor}: the halves of the drive disagree on {', '.join(PARAMETERS[JACOBIAN_ORDER.index(j)] for j in apart)}"
            f" by more than {config.hold_split_half:g}x a typical prior error: fitted again from the prior with them held there")
        held_apart, free = held_apart + apart, np.array([j for j in free if j not in apart])
        ext, again = _fit(traj, scans, pairs, baselines, prior, prior, free, config, log, where)
        history += again
    searched = None
    if config.view_search and any(j < 6 for j in held_apart) and rig.sensors[rig.reference_sensor].type == "camera":
        try:
            view = SharedView.of(rig, traj, scans)
        except CameraStageError as err:
            raise LidarFirstError(str(err)) from None
        ext, searched = _place_by_view(sensor, traj, scans, pairs, baselines, ext, prior, free, held_apart, view, observability, split, fine, log, where)
    held = None
    if len(free) < 7:
        # the first fit already freed every parameter from the prior, where the held ones stay: it is the released fit
        # (KITTI raw 0048: the same to 1e-6, the stage 260 -> 213 s); after the view placed some, fit again
        released = unheld if unheld is not None and searched is None else \
            _fit(traj, scans, pairs, baselines, ext, prior, np.arange(7), config, lambda line: log(line + " (released)"), where)[0]
        held = release_check(ext, released, free, observability, expected=held_apart)
        if searched is not None:  # a motion-only release cannot measure what the view placed
            held["sigma_release"] = [0.0 if j in searched.accepted else v for v, j in zip(held["sigma_release"], JACOBIAN_ORDER)]
        held["sigma_held"] = held_sigma(held_apart, [] if searched is None else searched.accepted, config.prior_sigma)
        if held["note"]:
            log(f"[lidar-first] {sensor}: {held['note']}")
    spread = None
    if config.trajectory_draws > 0 and rig.trajectory_accuracy.stated():
        begun = time.perf_counter()
        def drawn_fit(drawn: Rig) -> Dict[str, Optional[Tuple[np.ndarray, float]]]:
            fitted = fine_fit(ReferenceTrajectory.of(drawn), pairs, baselines, ext, free)
            return {sensor: None if fitted is None else (fitted.matrix(), fitted.time_offset)}

        spread = trajectory_spread(drawn_fit, rig, {sensor: (ext.matrix(), ext.time_offset)}, config.trajectory_draws)[sensor].tolist()
        log(f"[lidar-first] {sensor}: the trajectory's stated errors ({config.trajectory_draws} draws, {time.perf_counter() - begun:.0f} s) move it by "
            + ", ".join(f"{p} {v * u:.3g} {n}" for p, v, (u, n) in zip(PARAMETERS, spread, UNITS)) + " RMS")
    return LidarResult(sensor, prior, ext, history, observability, len(scans.stamps), scans.deskewed, scans.dropped,
                       time.perf_counter() - start, held, split, None if searched is None else searched.to_json(), spread)


def _place_by_view(sensor: str, traj: ReferenceTrajectory, scans: ScanSet, pairs, baselines, ext: Extrinsic, prior: Extrinsic, free, held: List[int],
                   view: SharedView, observability: Observability, split: Optional[List[float]], fine: LidarFirstConfig,
                   log: Callable[[str], None], where: str) -> Tuple[Extrinsic, ViewSearch]:
    """``view_search``: the held rotations and lever-arm components searched on the shared view (``search_held``); the
    placed ones leave the weak list with the search's sigma (into ``split`` too), the free parameters are fitted again."""
    shared = view.at(traj, ext, scans, pairs)
    found = search_held(traj, ext, scans, shared, pairs, sorted(j for j in held if j < 6), fine.hold_split_half, TYPICAL_ERROR)
    names = lambda cols: ", ".join(PARAMETERS[JACOBIAN_ORDER.index(j)] for j in cols) or "none"
    log(f"[lidar-first] {sensor}: the shared view ({len(shared.rows.point)} depth edges, {found.evaluations} evaluations) places "
        f"{names(found.accepted)} of {names(found.columns)}" + (f" ({'; '.join(found.notes)})" if found.notes else ""))
    if not found.accepted:
        return ext, found
    ext = _fit(traj, scans, pairs, baselines, ext.updated(found.increment), prior, free, fine, log, where)[0]
    for j in found.accepted:
        i = JACOBIAN_ORDER.index(j)
        dof = observability.dofs[i]
        dof.weak, dof.reason = False, f"placed by the shared view (sigma {found.sigma[j] * UNITS[i][0]:.3g} {UNITS[i][1]})"
        if split is not None:
            split[i] = float(found.sigma[j])
    return ext, found


def release_check(estimate: Extrinsic, released: Extrinsic, free: np.ndarray, observability: Observability,
                  expected: Sequence[int] = ()) -> Dict[str, object]:
    """Are the held parameters consistent with the scans? Compare the held fit with one that also frees them.

    A held parameter is inconsistent when freeing it moves it by more than three formal sigmas and a tenth of a typical
    prior error (1 cm, 0.1 deg, 1 ms): the scans agree better elsewhere, so the value it was held at is likely wrong
    and the free parameters absorbed that error. How far each parameter moves on release is the data's measure of its
    error: for a free one the error the held values put into it, which its formal sigma (conditional on the held
    values) does not contain; for a held one how far the data put it from where it was held.

    Args:
        estimate: the fit with some parameters held at the prior.
        released: a fit with every parameter free (from ``estimate``, or the stage's first fit from the prior).
        free: the indices (Jacobian order) the held fit estimated.
        observability: of the held fit (its formal sigma per parameter).
        expected: held parameters (Jacobian order) expected to move when released: held because the data hardly
            determine them (``LidarFirstConfig.hold_weak``), so their move is their sigma, not a disagreement.

    Returns:
        ``{"held": [...], "held_apart": [...] (those of ``expected``), "released_change": [7], "inconsistent": [...],
        "sigma_release": [7], "note"}`` in ``observability.PARAMETERS`` order (m, rad, s); ``sigma_release`` is ``|released_change|``; ``note`` says which
        held parameters disagree and by how much (empty when none does).
    """
    change = np.asarray(parameter_difference(estimate.matrix(), estimate.time_offset, released.matrix(), released.time_offset))
    is_free = np.isin(np.asarray(JACOBIAN_ORDER), free)
    sigma = np.array([d.sigma for d in observability.dofs])
    held = [p for p, f in zip(PARAMETERS, is_free) if not f]
    inconsistent = [p for p, f, c, s, step, j in zip(PARAMETERS, is_free, change, sigma, TEST_STEPS, JACOBIAN_ORDER)
                    if not f and abs(c) > max(3.0 * s, 0.1 * step) and j not in expected]
    moves = ", ".join(f"{p} {c * u:+.3g} {unit}" for p, c, (u, unit) in zip(PARAMETERS, change, UNITS) if p in inconsistent)
    note = f"held at its prior, {', '.join(inconsistent)} disagree with the scans (released, they move by {moves})" if inconsistent else ""
    return {"held": held, "held_apart": [p for p, j in zip(PARAMETERS, JACOBIAN_ORDER) if j in expected], "released_change": change.tolist(),
            "inconsistent": inconsistent, "sigma_release": np.abs(change).tolist(), "note": note}


def held_sigma(held: Sequence[int], placed: Sequence[int], prior_sigma: Sequence[float]) -> List[float]:
    """The sigma of the parameters held at the prior because the drive's halves disagree (``hold_split_half``) and not
    placed by the shared view: the prior's own, ``LidarFirstConfig.prior_sigma``. How far such a parameter moves when
    released (``release_check``) is not its error: the data hardly determine it (the realistic plaza rig of seed 1:
    y held 50 cm off, released it moved 14 cm).

    Args:
        held: the held parameters (Jacobian order indices).
        placed: those the shared view placed (their sigma is the view's).
        prior_sigma: (translation m, rotation rad, time offset s).

    Returns:
        Per parameter of ``observability.PARAMETERS`` (m, rad, s): the prior's sigma where held and not placed, else 0.
    """
    per_parameter = np.repeat(np.asarray(prior_sigma, dtype=np.float64), [3, 3, 1])  # x y z, roll pitch yaw, delta
    return [float(s) if j in held and j not in placed else 0.0 for s, j in zip(per_parameter, JACOBIAN_ORDER)]


def split_half_spread(fit: Callable[[np.ndarray, np.ndarray], Optional[Extrinsic]], pairs: Int[np.ndarray, "num 2"],
                      baselines: Float[np.ndarray, "num"], num_scans: int) -> Float[np.ndarray, "7"]:
    """Half the difference between the fits of the first and the second half of the drive (why:
    ``camera_guards.split_half_spread``). The scans are split in time; each half keeps the pairs whose two scans both
    lie in it and is fitted on its own (``fit``, from the whole drive's estimate).

    Args:
        fit: ``fit(pairs, baselines) -> Extrinsic``, the stage's fit restricted to those scan pairs (None: the
            half cannot be fitted, e.g. its scans do not overlap).
        pairs: scan index pairs of the whole drive (scans in time order).
        baselines: driving distance of each pair, metres.
        num_scans: how many scans the drive has.

    Returns:
        Per parameter of ``observability.PARAMETERS`` (m, rad, s); NaN everywhere (not measured, not "undetermined":
        the whole drive may still determine them) when a half has no pair or cannot be fitted.
    """
    middle = num_scans // 2
    halves = [(pairs[:, 1] < middle), (pairs[:, 0] >= middle)]
    if not all(h.any() for h in halves):
        return np.full(7, np.nan)
    first, second = (fit(pairs[h], baselines[h]) for h in halves)
    if first is None or second is None:
        return np.full(7, np.nan)
    return np.abs(np.asarray(parameter_difference(first.matrix(), first.time_offset, second.matrix(), second.time_offset))) / 2


@dataclass
class LidarFirstResult:
    """Every LiDAR's estimate, and the full calibration (LiDARs estimated, every other sensor at its prior)."""
    calibration: Calibration
    lidars: Dict[str, LidarResult]


def lidar_sensors(rig: Rig) -> List[str]:
    """The rig's non-reference LiDARs (the ones this stage calibrates)."""
    return [n for n, s in rig.sensors.items() if s.type == "lidar" and n != rig.reference_sensor]


def calibrate_lidars(rig: Rig, config: LidarFirstConfig, sensors: Optional[Sequence[str]] = None,
                     log: Callable[[str], None] = print) -> LidarFirstResult:
    """Run the stage on ``sensors`` (default: every non-reference LiDAR of the rig).

    Raises:
        LidarFirstError: a named sensor is not a non-reference LiDAR, or its scans cannot be used.
    """
    available = lidar_sensors(rig)
    names = list(sensors or available)
    for name in names:
        if name not in available:
            raise LidarFirstError(f"{rig.root / 'rig.json'}: sensors.{name}: not a non-reference LiDAR of this rig (LiDARs: {available or 'none'})")
    if not names:
        raise LidarFirstError(f"{rig.root / 'rig.json'}: sensors: the rig has no LiDAR other than the reference sensor")
    calibration = Calibration.from_rig(rig)  # its own dicts: the rig's priors stay
    results = {name: calibrate_lidar(rig, name, config, log) for name in names}
    for name, result in results.items():
        calibration.T_ref_sensor[name], calibration.time_offset[name] = result.estimate.matrix(), result.estimate.time_offset
    return LidarFirstResult(calibration, results)
