"""One camera's photometric registration against the map: coarse to fine over the image pyramid from one or more
starts (``register_camera``), one finest descent per basin, and the guards and sigma of the result (``_guarded``);
``camera_registration`` runs it for every camera of a rig. The formulation is in that module's docstring. No
nerfstudio import."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_guards import (bounds, convergence_tail, held_back_check, points_per_frame, resolution_spread, solve,
                                                   split_half_spread, typical_error_significance)
from moisst_ns.stages.camera.camera_result import CameraResult, corrected as _corrected
from moisst_ns.stages.camera.feature_start import FeatureStart
from moisst_ns.stages.camera.lidar_map import NoOverlapError
from moisst_ns.stages.camera.photometric import PairSet, Registration, robust_cost
from moisst_ns.stages.trust.observability import SOLVER_NAMES, TYPICAL_ERROR, huber_weights
from moisst_ns.stages.trust.uncertainty_math import least_squares_sigma


def _pixel_motion(problem: Registration, theta: np.ndarray, step: np.ndarray, active: np.ndarray, pairs: PairSet, factor: int) -> float:
    """RMS motion (this level's pixels) of a sample of the pairs' projections caused by the last ``step``."""
    if not len(step):
        return 0.0
    sample = slice(0, len(pairs.points), max(1, len(pairs.points) // 2000))
    before = theta.copy()
    before[active] -= step
    model = problem.camera.levels[factor].model
    a, _ = problem.model.pixels(theta, model, pairs.points[sample], pairs.frame_a[sample], False)
    b, _ = problem.model.pixels(before, model, pairs.points[sample], pairs.frame_a[sample], False)
    return float(np.sqrt(np.nanmean(np.sum((a - b) ** 2, axis=1))))


def _descend(problem: Registration, config: CameraRegistrationConfig, log: Callable[[str], None], theta: np.ndarray,
             factors: Optional[Sequence[int]] = None, so_far: Optional[tuple] = None) -> tuple:
    """Coarse to fine from ``theta`` over the pyramid levels ``factors`` (None: all): ``(theta, history, (residuals,
    Jacobian, valid, pairs) of the last solve, {level factor: the corrections at the end of that level})``; ``so_far``:
    such a tuple of the coarser levels, which this call continues."""
    name = problem.camera.sensor
    theta = np.where(_active(config), np.r_[theta, np.zeros(len(_active(config)) - len(theta))], 0.0)
    history, last, level_end = ([], None, {}) if so_far is None else (list(so_far[1]), so_far[2], dict(so_far[3]))
    start = time.perf_counter() - (history[-1]["elapsed_s"] if history else 0.0)
    for factor in sorted(problem.camera.levels, reverse=True) if factors is None else factors:
        finest = factor == min(problem.camera.levels)
        active = _active(config, factor in sorted(problem.camera.levels)[:READOUT_LEVELS])
        for outer in range(config.fine_iterations if finest else config.outer_iterations):
            pairs = problem.pairs(theta, factor, points_per_frame(config, factor, finest))
            if len(pairs.points) < 50:
                raise NoOverlapError(f"sensors.{name}: only {len(pairs.points)} observation pairs with the map at 1/{factor} resolution; "
                                     "the camera does not see the mapped scene")
            previous = theta
            theta, evaluations, (res, jac, ok) = solve(problem, theta, active, pairs, factor, config)
            last = (res, jac, ok, pairs)
            pose, offset = _corrected(problem.model.prior.numpy(), problem.model.prior_offset, theta)
            history.append({"level": factor, "iteration": outer, "pairs": int(ok.sum()), "cost": robust_cost(res[ok], config.huber),
                            "T_ref_sensor": pose.tolist(), "time_offset": offset, "correction": theta.tolist(),
                            "elapsed_s": time.perf_counter() - start})
            if len(theta) > 7:
                history[-1]["readout_time"] = problem.model.readout + float(theta[7])
            log(f"[camera-registration] {name}: 1/{factor} resolution, iteration {outer}: {int(ok.sum())} pairs, "
                f"cost {history[-1]['cost']:.4f}, {evaluations} evaluations, {pairs.shared:.0%} with a reference partner at once" + (f", readout {history[-1]['readout_time'] * 1000:.2f} ms" if len(theta) > 7 else ""))
            if _pixel_motion(problem, theta, (theta - previous)[active], active, pairs, factor) < (config.fine_stop_px if finest else config.stop_px):
                break
        level_end[factor] = theta.copy()
    return theta, history, last, level_end


def _guarded(problem: Registration, config: CameraRegistrationConfig, floor_cost: Optional[float], descent: tuple, begun: str,
             wall_s: float) -> CameraResult:
    """The guards and sigma of one descent (``_descend``): the result, the prior where a guard says so."""
    start = time.perf_counter()
    theta, history, (res, jac, ok, pairs), level_end = descent
    active = _active(config)
    finest = min(problem.camera.levels)
    formal = np.zeros(len(active))
    if active.any():
        weights = np.sqrt(huber_weights(res[ok], config.huber))
        formal[active] = least_squares_sigma(jac[ok][:, active] * weights[:, None], res[ok] * weights, pairs.frame_a[ok]).sigma
    apart, spread = split_half_spread(problem, theta, active, finest, config) if config.split_half and active.any() else (np.zeros(len(active)),) * 2
    resolution = resolution_spread(level_end)
    tail = convergence_tail([h["correction"] for h in history])
    if config.estimate_readout:  # the readout's tail from the levels that fit it
        tail[7] = convergence_tail([h["correction"] for h in history if h["level"] in sorted(problem.camera.levels)[:READOUT_LEVELS]])[7]
    cost_pri, cost_est, better = held_back_check(problem, theta, finest, config)
    at_bound = [SOLVER_NAMES[i] for i in np.flatnonzero(active[:7] & (np.abs(theta[:7]) >= 0.999 * bounds(config)))]
    ratio = history[-1]["cost"] / floor_cost if floor_cost else 0.0
    undetermined = [SOLVER_NAMES[i] for i in np.flatnonzero(active[:7] & (apart[:7] > config.max_split_half * TYPICAL_ERROR))]
    significance = typical_error_significance(problem, theta, active, finest, config) if config.min_significance > 0 else np.full(7, np.inf)
    blind = [SOLVER_NAMES[i] for i in np.flatnonzero(active[:7] & (significance < config.min_significance))]
    kept = not better or bool(at_bound) or ratio > config.max_cost_ratio or bool(undetermined) or bool(blind)
    prior = problem.model.prior.numpy()
    pose, offset = (prior, problem.model.prior_offset) if kept else _corrected(prior, problem.model.prior_offset, theta)
    reasons = []  # every guard that keeps the prior, the strongest first
    if ratio > config.max_cost_ratio:
        reasons.append(f"its photometric cost at the estimate is {ratio:.1f}x the reference camera's own (a wrong minimum)")
    if undetermined:
        reasons.append(f"the two halves of the drive disagree on {', '.join(undetermined)} by more than {config.max_split_half:g}x a typical prior error")
    if at_bound:
        reasons.append(f"ran into its bound on {', '.join(at_bound)} (a runaway)")
    if blind:
        reasons.append(f"its view does not tell a typical prior error apart on {', '.join(blind)} (held-back cost increase under "
                       f"{config.min_significance:g}x three standard errors over the frames)")
    note = "; ".join(reasons)
    sigma = np.fmax.reduce([formal, spread, resolution, tail])
    result = CameraResult(problem.camera.sensor, prior, problem.model.prior_offset, pose, offset, sigma[:7].tolist(), cost_pri,
                          cost_est, kept, history, wall_s + time.perf_counter() - start, note, formal[:7].tolist(), ratio, spread[:7].tolist(), begun,
                          significance.tolist() if config.min_significance > 0 else [], blind, resolution[:7].tolist(),
                          tail[:7].tolist(), held_there=bool(blind), readout_prior=problem.model.readout, readout_time=problem.model.readout)
    return _with_readout(result, theta, sigma, config) if config.estimate_readout else result


UNDETERMINED = "the drive does not determine the readout time"
"""How ``CameraResult.readout_note`` begins when the readout's sigma exceeds ``max_readout_sigma``."""
READOUT_LEVELS = 2
"""With ``estimate_readout`` the readout is fitted at this many of the finest pyramid levels (coarser, a readout error
moves the projections by a fraction of their pixel: it stays at rig.json's there), so the resolution spread sees it."""


def _active(config: CameraRegistrationConfig, readout: bool = True) -> np.ndarray:
    """Which corrections the fit moves: rotation, translation, time offset, and with ``estimate_readout`` the readout
    (``readout``: at this level)."""
    return np.array([config.estimate_extrinsic] * 6 + [config.estimate_time_offset] + [readout] * config.estimate_readout)


def _with_readout(result: CameraResult, theta: np.ndarray, sigma: np.ndarray, config: CameraRegistrationConfig) -> CameraResult:
    """``result`` with the fitted readout time (``theta[7]``, sigma ``sigma[7]``) and whether the calibration takes it."""
    estimate, spread = result.readout_prior + float(theta[7]), float(sigma[7])
    note = ""
    if not spread <= config.max_readout_sigma:
        note = (f"{UNDETERMINED}: {estimate * 1000:.1f} ms, sigma {spread * 1000:.1f} ms "
                f"(over {config.max_readout_sigma * 1000:g} ms); rig.json's {result.readout_prior * 1000:g} ms is kept")
    elif result.kept_prior:
        note = f"the camera keeps its prior, and rig.json's readout time {result.readout_prior * 1000:g} ms with it"
    return replace(result, readout_estimate=estimate, readout_sigma=spread, readout_note=note,
                   readout_time=result.readout_prior if note else estimate)


def _basins(problem: Registration, config: CameraRegistrationConfig, coarse: Sequence[Tuple[tuple, str]], factor: int,
            log: Callable[[str], None]) -> List[Tuple[tuple, str]]:
    """One descent per basin: the starts' descents (``(_descend over the coarse levels, start)``) in the order of their
    last cost at level ``factor``, each dropped when it ended within ``stop_px`` of the projections of one kept before it
    (the descent's own convergence test, on that one's pairs): the finest level, the stage's most costly, then runs once
    per basin, from the lower-cost descent of each."""
    active, kept = _active(config), []
    for descent, begun in sorted(coarse, key=lambda c: c[0][1][-1]["cost"]):
        theta = descent[0]
        apart = [_pixel_motion(problem, other[0], (other[0] - theta)[active], active, other[2][3], factor) for other, _ in kept]
        for (other, other_begun), px in zip(kept, apart):
            log(f"[camera-registration] {problem.camera.sensor}: the {begun.split(' (')[0]} and {other_begun.split(' (')[0]} starts end {px:.3f} px apart "
                f"at 1/{factor} resolution{': one basin' if px < config.stop_px else ''}")
        if all(px >= config.stop_px for px in apart):
            kept.append((descent, begun))
    if len(kept) == 1:
        log(f"[camera-registration] {problem.camera.sensor}: one basin, the finest level runs once")
    return kept


def _started(initial: Optional[FeatureStart]) -> str:
    return "prior" if initial is None else (f"prior ({initial.note})" if initial.theta is None else
                                            f"features ({initial.frames} frames, {initial.matches} matches, RMS {initial.rms_px:.2f} px)")


def register_camera(problem: Registration, config: CameraRegistrationConfig, log: Callable[[str], None] = print,
                    floor_cost: Optional[float] = None, initial: Optional[FeatureStart] = None,
                    warm: Optional[np.ndarray] = None) -> CameraResult:
    """Coarse-to-fine photometric registration of one camera against the map (see the module docstring), then its
    guards; ``floor_cost``: ``reference_cost`` of the rig (None: no wrong-minimum test). With a feature start
    (``initial.theta``) the coarse levels descend from it and from the prior (either can end in a wrong minimum, measured
    on 96x72 rigs), and with three levels or more the feature start also from the second-finest level alone; the finest
    level finishes one descent per basin (``_basins``), and the one with the lower final cost is guarded first, the
    others only if the guards keep the prior for it. ``warm``: corrections already in the finest levels' basin (a
    registration on a slightly turned trajectory): the two finest levels descend from them alone."""
    start = time.perf_counter()
    if warm is not None:
        levels = sorted(problem.camera.levels, reverse=True)[-2:]
        return _guarded(problem, config, floor_cost, _descend(problem, config, log, warm, levels), "first registration (before the trajectory was carried)",
                        time.perf_counter() - start)
    if initial is None or initial.theta is None:
        return _guarded(problem, config, floor_cost, _descend(problem, config, log, np.zeros(len(_active(config)))), _started(initial),
                        time.perf_counter() - start)
    factors = sorted(problem.camera.levels, reverse=True)
    starts = [(initial.theta, factors[:-1], _started(initial)), (np.zeros(len(_active(config))), factors[:-1], "prior")]
    if len(factors) > 2:  # the feature start is about a pixel from its fit at full resolution, inside the finer levels'
        # basin, where the coarsest levels' minima may lie apart from theirs (realistic plaza seed 2: 1/8 and 1/4 put
        # cam_front_right 24-25 cm off, and from there the finer levels stay in a minimum of 1.6x the cost at 1.1 cm)
        starts.append((initial.theta, factors[-2:-1], _started(initial).replace("features", f"features from 1/{factors[-2]}", 1)))
    coarse = [(_descend(problem, config, log, theta, levels), begun) for theta, levels, begun in starts]
    if len(factors) > 1:
        coarse = _basins(problem, config, coarse, factors[-2], log)
    descents = [(_descend(problem, config, log, c[0], factors[-1:], c), begun) for c, begun in coarse]
    if len(descents) == 1:
        return _guarded(problem, config, floor_cost, descents[0][0], descents[0][1], time.perf_counter() - start)
    costs = [d[1][-1]["cost"] for d, _ in descents]
    log(f"[camera-registration] {problem.camera.sensor}: final cost " + ", ".join(f"{c:.4f} from the {b.split(' (')[0]}" for c, (_, b) in zip(costs, descents)))
    for k in np.argsort(costs, kind="stable"):
        result = _guarded(problem, config, floor_cost, descents[k][0], descents[k][1], time.perf_counter() - start)
        if not result.kept_prior:
            break
    log(f"[camera-registration] {problem.camera.sensor}: the {result.start.split(' (')[0]} start {'is kept' if not result.kept_prior else 'fails the guards too'}")
    return result
