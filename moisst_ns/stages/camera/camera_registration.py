"""Cameras against the calibrated LiDAR map: each camera's extrinsic and time offset from photometric consistency
over LiDAR-measured, metric geometry (no NeRF): grey levels of map points in a camera's frames against the reference
camera's and its own frames some metres away, robust (Huber) least squares on the 7 corrections of eq. 12, coarse to
fine over an image pyramid, occlusions by a z-buffer, rolling-shutter rows included (``photometric``), each fit
guarded before it replaces the prior (``camera_guards``); then a LiDAR whose scans' motion left parameters undetermined
against the cameras at the same instants (``lidar_instant``). docs/method.md, "Cameras against the map" and "Guards", has the
formulation and the measurements. Nothing here imports nerfstudio.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float
from scipy.spatial.transform import Rotation

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic
from moisst_ns.rig.trajectory_noise import trajectory_spread
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.feature_start import FeatureStart, FeatureStartConfig, feature_start
from moisst_ns.stages.camera.lidar_map import CameraStageError, NoMapError, NoOverlapError, lidar_map, map_source, pyramid_factors
from moisst_ns.stages.camera.camera_guards import (PARAMETERS, TYPICAL_ERROR, bounds, convergence_tail, held_back_check, points_per_frame, reference_cost,
                                            resolution_spread, solve, split_half_spread, typical_error_significance)
from moisst_ns.stages.camera.own_motion import MapSurface, OwnMotionConfig, fit_own_motion, own_matches
from moisst_ns.stages.camera.photometric import CameraFrames, PairSet, Registration, robust_cost
from moisst_ns.stages.lidar.lidar_instant import InstantPlacement
from moisst_ns.stages.lidar.lidar_placement import place_again, place_lidars, trajectory_turn
from moisst_ns.stages.trust.observability import PARAMETERS as TRUST_ORDER, JACOBIAN_ORDER, UNITS, huber_weights
from moisst_ns.stages.trust.uncertainty_math import least_squares_sigma

START = FeatureStartConfig()  # the feature start's settings


@dataclass
class CameraResult:
    """One camera's registration."""

    sensor: str
    prior: Float[np.ndarray, "4 4"]
    prior_offset: float
    estimate: Float[np.ndarray, "4 4"]
    """``ref_T_c`` (the prior again when ``kept_prior``)."""
    time_offset: float
    sigma: List[float]
    """Standard deviations of the 7 corrections (rad, rad, rad, m, m, m, s): the largest of the formal one (max of
    classical and frame-clustered, ``uncertainty_math.least_squares_sigma``, from the finest level's last solve; inf
    where unconstrained), the split-half spread (``split_half_spread``), the resolution spread
    (``resolution_spread``), the convergence tail (``convergence_tail``) and, where rig.json states the trajectory's
    errors, the trajectory part (``trajectory_part``)."""
    cost_prior: float
    """Held-back mean Huber cost at the prior (fresh samples at the finest level: ``held_back_check``)."""
    cost_estimate: float
    """The same pairs at the estimate."""
    kept_prior: bool
    """The prior is kept: the held-back cost was not significantly lower at the estimate, or ``note`` says why."""
    history: List[Dict[str, object]] = field(default_factory=list)
    wall_s: float = 0.0
    note: str = ""
    """Why the camera kept its prior other than the held-back check (it does not see the map, the fit ran into a
    bound, the halves of the drive disagree, or its cost stayed far above the reference camera's own), else empty."""
    sigma_formal: List[float] = field(default_factory=list)
    """The formal part of ``sigma`` (same order and units)."""
    cost_ratio: float = 0.0
    """Final cost over the reference camera's own (``reference_cost``); 0 when the reference is not a camera."""
    sigma_split: List[float] = field(default_factory=list)
    """The split-half part of ``sigma``: the farther half's distance from the whole (``split_half_spread``; zeros when
    ``split_half`` is off)."""
    start: str = "prior"
    """Where the photometric solve started: ``prior``, ``features`` (``feature_start``) or ``features from 1/F`` (that
    start descended from the second-finest level alone), with the reason."""
    significance: List[float] = field(default_factory=list)
    """``typical_error_significance`` at the estimate (solver order; empty when not measured)."""
    blind: List[str] = field(default_factory=list)
    """The corrections whose significance is under ``min_significance`` (the camera then keeps its prior)."""
    sigma_resolution: List[float] = field(default_factory=list)
    """The resolution part of ``sigma`` (``camera_guards.resolution_spread``)."""
    sigma_convergence: List[float] = field(default_factory=list)
    """The convergence part of ``sigma`` (``camera_guards.convergence_tail``)."""
    held_there: bool = False
    """The prior is kept and ``moisst-calibrate`` holds it there through the NeRF too (``note`` says why): a ``blind``
    camera, or one that shares no view with the reference camera of a rig without a LiDAR."""
    readout_prior: float = 0.0
    """rig.json's readout time, seconds."""
    readout_time: float = 0.0
    """The readout time the calibration uses: the estimate with ``estimate_readout`` when it is determined (sigma at most
    ``max_readout_sigma``) and the camera leaves its prior, else ``readout_prior``."""
    readout_estimate: Optional[float] = None
    """The fit's readout time with ``estimate_readout`` (None without), seconds."""
    readout_sigma: Optional[float] = None
    """Its sigma (the largest of the four parts, as ``sigma``), seconds."""
    readout_note: str = ""
    """Why ``readout_time`` is not the estimate: the drive does not determine it (the camera is then registered again
    with rig.json's readout: the result is that fit's), or the camera kept its prior."""
    sigma_trajectory: List[float] = field(default_factory=list)
    """The trajectory part of ``sigma`` (``trajectory_part``; empty where rig.json states no trajectory errors or the
    camera kept its prior)."""


def _corrected(prior: np.ndarray, prior_offset: float, theta: np.ndarray) -> Tuple[np.ndarray, float]:
    pose = calibrated_extrinsic(torch.from_numpy(prior), torch.from_numpy(theta[:3]), torch.from_numpy(theta[3:6]))
    return pose.numpy(), prior_offset + float(theta[6])


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
    at_bound = [PARAMETERS[i] for i in np.flatnonzero(active[:7] & (np.abs(theta[:7]) >= 0.999 * bounds(config)))]
    ratio = history[-1]["cost"] / floor_cost if floor_cost else 0.0
    undetermined = [PARAMETERS[i] for i in np.flatnonzero(active[:7] & (apart[:7] > config.max_split_half * TYPICAL_ERROR))]
    significance = typical_error_significance(problem, theta, active, finest, config) if config.min_significance > 0 else np.full(7, np.inf)
    blind = [PARAMETERS[i] for i in np.flatnonzero(active[:7] & (significance < config.min_significance))]
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
                    floor_cost: Optional[float] = None, initial: Optional[FeatureStart] = None) -> CameraResult:
    """Coarse-to-fine photometric registration of one camera against the map (see the module docstring), then its
    guards; ``floor_cost``: ``reference_cost`` of the rig (None: no wrong-minimum test). With a feature start
    (``initial.theta``) the coarse levels descend from it and from the prior (either can end in a wrong minimum, measured
    on 96x72 rigs), and with three levels or more the feature start also from the second-finest level alone; the finest
    level finishes one descent per basin (``_basins``), and the one with the lower final cost is guarded first, the
    others only if the guards keep the prior for it."""
    start = time.perf_counter()
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


@dataclass
class CameraStageResult:
    """Every registered camera, and the full calibration (cameras registered, every other sensor as given)."""

    calibration: Calibration
    cameras: Dict[str, CameraResult]
    map_points: int
    map_source: str = "lidar"
    """What the map is: ``"lidar"`` (the LiDARs' scans), ``"features"`` (the reference camera's triangulated features)
    or ``"none"`` (no camera had enough frames to fit)."""
    map_note: str = ""
    """Why the map is the features on a rig with a LiDAR (``map_source``), else empty."""
    lidars: Dict[str, InstantPlacement] = field(default_factory=dict)
    """The LiDARs placed against the registered cameras at the same instants (``lidar_placement.place_lidars``)."""


def _world(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, source: str, log: Callable[[str], None]) -> Float[np.ndarray, "num 3"]:
    """The map the cameras are registered against (``map_source``): the LiDARs' scans at ``calibration``, or the
    reference camera's features triangulated from its poses; world frame, metres."""
    if source == "lidar":
        return lidar_map(rig, calibration, config.map_voxel, config.min_range, log)
    return feature_map(rig, calibration, FeatureMapConfig(voxel=config.map_voxel), log)


def trajectory_part(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, source: str, problems: Dict[str, Registration],
                    results: Dict[str, CameraResult], reference: Optional[CameraFrames], log: Callable[[str], None]) -> Dict[str, CameraResult]:
    """``results`` with the trajectory part of their sigma: what the errors rig.json states of the trajectory put into
    each camera (``trajectory_noise.trajectory_spread``: ``config.trajectory_draws`` draws; on each the map is rebuilt and
    every camera fitted again from its estimate: at the finest level, as ``_descend`` does there, or by its own motion
    where it was placed so, ``own_motion.fit_own_motion`` at the fine radius). The estimates do not
    change. The map (LiDAR scans or triangulated features) and a camera's own partners are both placed by the trajectory,
    so a noisy one moves the estimate by more than any part measured on the given trajectory can see (realistic rigs
    without a LiDAR, cam_front_right: plaza seed 2's x 2.6 sigma and street seed 3's pitch 3.0 sigma off without this
    part, within 1.4 sigma with it: docs/uncertainty.md).

    Args:
        rig: the dataset; its ``trajectory_accuracy`` is stated.
        calibration: the stage's start (the map's LiDAR extrinsics, the cameras' priors).
        config: settings.
        source: the map's source (``map_source``).
        problems: each accepted camera's registration problem (its frames).
        results: their results.
        reference: the reference camera's frames (None: the reference is not a camera).
        log: where progress lines go.

    Returns:
        The results with ``sigma`` at least the part, per parameter, and ``sigma_trajectory`` (solver order).
    """
    begun = time.perf_counter()
    finest = {n: min(p.camera.levels) for n, p in problems.items()}
    own = {n: own_matches(rig, n, OWN) for n, r in results.items() if r.start.startswith("own motion")}  # placed by their own motion
    thetas = {n: np.asarray(r.history[-1]["correction"], dtype=np.float64) if n not in own else
              np.r_[Rotation.from_matrix(r.prior[:3, :3].T @ r.estimate[:3, :3]).as_rotvec(), r.estimate[:3, 3] - r.prior[:3, 3], r.time_offset - r.prior_offset]
              for n, r in results.items()}

    def fit(drawn: Rig) -> Dict[str, Optional[Tuple[np.ndarray, float]]]:
        try:
            world = _world(drawn, calibration, config, source, lambda _: None)
        except NoMapError:
            return {n: None for n in problems}
        traj, poses = ReferenceTrajectory.of(drawn), {}
        surface = MapSurface.of(world, OWN.normal_radius) if own else None
        for name, problem in problems.items():
            if name in own:  # refitted by its own motion, from its estimate
                again = fit_own_motion(traj, own[name], surface, results[name].prior, results[name].prior_offset, OWN, lambda _: None, name, thetas[name])
                poses[name] = None if again is None else _corrected(results[name].prior, results[name].prior_offset, again.theta)
                continue
            settings = replace(config, estimate_readout=len(thetas[name]) > 7)  # as the result was fitted (readout refit: without)
            again = Registration(traj, world, problem.camera, reference, calibration, settings)
            try:
                theta = _descend(again, settings, lambda _: None, thetas[name], [finest[name]])[0]
            except NoOverlapError:
                poses[name] = None
                continue
            poses[name] = _corrected(problem.model.prior.numpy(), problem.model.prior_offset, theta)
        return poses

    spread = trajectory_spread(fit, rig, {n: (r.estimate, r.time_offset) for n, r in results.items()}, config.trajectory_draws)
    out = {}
    for name, r in results.items():
        part = np.zeros(7)
        part[list(JACOBIAN_ORDER)] = spread[name]  # PARAMETERS order -> the solver's
        sigma = np.fmax(np.asarray(r.sigma, dtype=np.float64), part)
        log(f"[camera-registration] {name}: the trajectory's stated errors ({config.trajectory_draws} draws, {time.perf_counter() - begun:.0f} s) move it by "
            + ", ".join(f"{p} {v * u:.3g} {n}" for p, v, (u, n) in zip(TRUST_ORDER, spread[name], UNITS)) + " RMS")
        out[name] = replace(r, sigma=sigma.tolist(), sigma_trajectory=part.tolist())
    return out


OWN = OwnMotionConfig()  # the own-motion fit's settings


def own_motion_result(rig: Rig, traj: ReferenceTrajectory, surface: MapSurface, kept: CameraResult, config: CameraRegistrationConfig,
                      log: Callable[[str], None]) -> CameraResult:
    """``kept`` (a camera the photometric fit left at its prior against a LiDAR map) placed by its own motion
    (``own_motion.fit_own_motion``), or ``kept`` again, its note extended, where that fit places nothing, its held-back
    loss is no lower than the prior's or the drive's halves disagree by more than ``max_split_half`` typical errors.
    sigma is the largest of the fit's formal, split-half and convergence parts; ``history`` stays the photometric fit's."""
    begun = time.perf_counter()
    fit = fit_own_motion(traj, own_matches(rig, kept.sensor, OWN), surface, kept.prior, kept.prior_offset, OWN, log, kept.sensor)
    apart = [] if fit is None else [PARAMETERS[i] for i in np.flatnonzero(fit.sigma_split > config.max_split_half * TYPICAL_ERROR)]
    why = ("its own matches do not lie on the map" if fit is None else
           f"its own motion's held-back loss {fit.loss_estimate:.4g} m is no lower than the prior's {fit.loss_prior:.4g} m" if not fit.loss_estimate < fit.loss_prior else
           f"the two halves of the drive place it apart on {', '.join(apart)} by more than {config.max_split_half:g}x a typical prior error" if apart else "")
    if why:
        log(f"[camera-registration] {kept.sensor}: {why}; it keeps its prior")
        return replace(kept, note=f"{kept.note}; by its own motion: {why}")
    pose, offset = _corrected(kept.prior, kept.prior_offset, fit.theta)
    sigma = np.fmax.reduce([fit.sigma_formal, fit.sigma_split, fit.sigma_convergence])
    log(f"[camera-registration] {kept.sensor}: the photometric fit kept its prior ({kept.note or 'held-back check'}); placed by its own motion instead")
    return replace(kept, estimate=pose, time_offset=offset, sigma=sigma.tolist(), cost_prior=fit.loss_prior, cost_estimate=fit.loss_estimate,
                   kept_prior=False, note="", sigma_formal=fit.sigma_formal.tolist(), sigma_split=fit.sigma_split.tolist(), blind=[], significance=[],
                   start=f"own motion ({fit.points} of its own matches on the map; the photometric fit: {kept.note or 'held-back check'})",
                   sigma_resolution=[], sigma_convergence=fit.sigma_convergence.tolist(), held_there=False, wall_s=kept.wall_s + time.perf_counter() - begun)


def _prior_kept(name: str, calibration: Calibration, why: str, rig: Optional[Rig] = None) -> CameraResult:
    """The result of a camera the stage does not fit: its prior, sigma inf, ``why`` as the note."""
    prior, offset = np.asarray(calibration.T_ref_sensor[name], dtype=np.float64), float(calibration.time_offset[name])
    readout = float(rig.sensors[name].readout_time) if rig is not None else 0.0
    return CameraResult(name, prior, offset, prior, offset, [float("inf")] * 7, float("nan"), float("nan"), True, note=why,
                        readout_prior=readout, readout_time=readout)


def camera_sensors(rig: Rig) -> List[str]:
    """The rig's non-reference cameras (the ones this stage registers)."""
    return [n for n, s in rig.sensors.items() if s.type == "camera" and n != rig.reference_sensor]


def register_cameras(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, sensors: Optional[Sequence[str]] = None,
                     log: Callable[[str], None] = print, lidar_undetermined: Optional[Dict[str, Sequence[str]]] = None,
                     lidar_sigma: Optional[Dict[str, Sequence[float]]] = None) -> CameraStageResult:
    """Register every non-reference camera against the map of the LiDARs at ``calibration``.

    Args:
        rig: the dataset; its reference sensor must be a camera (its images carry the colours) or a LiDAR. With a
            LiDAR the map is the LiDARs' scans (``lidar_map``), without one the reference camera's triangulated
            features (``camera_map.feature_map``); those features too when a LiDAR's calibration is not determined
            (``lidar_undetermined``, ``map_source``).
        calibration: the calibration to start from (the LiDAR-first estimate: LiDARs calibrated, cameras at priors).
        config: settings.
        sensors: the cameras to register (default: every non-reference camera).
        log: where progress lines go.
        lidar_undetermined: per LiDAR, the parameters its scans' motion did not determine in the LiDAR-first stage,
            placed by its depth edges' view or not (``LidarResult.motion_undetermined``; None: all determined).
        lidar_sigma: per LiDAR, that stage's sigma (``PARAMETERS`` order); both feed ``place_lidars`` (None: no LiDAR is
            placed). When the placements say the trajectory is turned (``trajectory_turn``), the cameras are registered
            again on it carried to the reference camera (``trajectory_T_reference``) and the LiDARs placed again against
            them (``place_again``).

    Returns:
        The result; ``calibration`` holds the registered cameras (or their priors where kept).

    Raises:
        CameraStageError: no map (no LiDAR and no camera reference, or no triangulated features), an unreadable image or
            scan, or a camera that does not see the map.
    """
    cameras = camera_sensors(rig)
    if not cameras:
        raise CameraStageError(f"{rig.root / 'rig.json'}: sensors: no camera other than the reference sensor to register")
    for name in sensors or []:
        if name not in cameras:
            raise CameraStageError(f"{rig.root / 'rig.json'}: sensors.{name}: not a non-reference camera of this rig (cameras: {cameras})")
    cameras = list(sensors) if sensors else cameras
    out = Calibration(calibration.reference_sensor, dict(calibration.T_ref_sensor), dict(calibration.time_offset))
    results = {n: _prior_kept(n, calibration, f"only {len(rig.frames_of(n))} frames; the stage needs {config.min_frames}", rig)
               for n in cameras if len(rig.frames_of(n)) < config.min_frames}
    for name, r in results.items():
        log(f"[camera-registration] {name}: {r.note}; it keeps its prior here")
    if len(results) == len(cameras):  # nothing to fit: no map needed
        return CameraStageResult(out, results, 0, "none")
    source, why_source = map_source(rig, lidar_undetermined)
    if source == "features" and why_source:
        log(f"[camera-registration] the map is {rig.reference_sensor}'s triangulated features: {why_source}")
    world = _world(rig, calibration, config, source, log)
    traj = ReferenceTrajectory.of(rig)
    reference_name = rig.reference_sensor if rig.sensors[rig.reference_sensor].type == "camera" else None
    widths = [int(rig.sensors[n].intrinsics["w"]) for n in cameras + ([reference_name] if reference_name else [])]
    factors = pyramid_factors(min(widths), config.min_width)
    reference = CameraFrames.of(rig, reference_name, factors) if reference_name else None
    floor = reference_cost(traj, world, reference, calibration, config) if reference is not None else None
    problems: Dict[str, Registration] = {}
    surface: Optional[MapSurface] = None  # the map's normals, for a camera placed by its own motion
    if floor is not None:
        log(f"[camera-registration] {reference_name}'s own photometric cost (its frames against each other): {floor:.4f}")
    for name in cameras:
        if name in results:
            continue
        problem = problems[name] = Registration(traj, world, CameraFrames.of(rig, name, factors), reference, calibration, config)
        initial = None
        if reference is not None and config.feature_start:
            initial = feature_start(traj, world, problem.camera, reference, np.asarray(calibration.T_ref_sensor[reference_name], dtype=np.float64),
                                    float(calibration.time_offset[reference_name]), problem.model.prior.numpy(), problem.model.prior_offset,
                                    rig.sensors[name].intrinsics, bounds(config), START, log)
            if initial.theta is None:
                log(f"[camera-registration] {name}: {initial.note}")
        if source == "features" and initial is not None and initial.theta is None:  # neither this stage nor the NeRF can place it
            lost = f"its start on {reference_name}'s features failed" if initial.matches >= START.min_inliers * START.min_frames else f"it shares no view with {reference_name}"
            why = (f"{lost} ({initial.note}) and {why_source or 'the rig has no LiDAR'}: fitted to "
                   f"{reference_name}'s triangulated features alone, it inherits their errors, which none of its sigma parts sees")
            results[name] = replace(_prior_kept(name, calibration, why, rig), held_there=True)
            log(f"[camera-registration] {name}: {why}; it keeps its prior, not fitted")
            continue
        try:
            results[name] = register_camera(problem, config, log, floor, initial)
            if results[name].readout_note.startswith(UNDETERMINED):  # refitted with rig.json's readout, which it keeps
                log(f"[camera-registration] {name}: {results[name].readout_note}; refitting with it")
                again = Registration(traj, world, problem.camera, reference, calibration, config)
                results[name] = replace(register_camera(again, replace(config, estimate_readout=False), log, floor, initial),
                                        **{k: getattr(results[name], k) for k in ("readout_estimate", "readout_sigma", "readout_note")})
        except NoOverlapError as err:
            results[name] = _prior_kept(name, calibration, str(err), rig)
            log(f"[camera-registration] {name}: {err}; it keeps its prior here")
        if config.own_motion and source == "lidar" and results[name].kept_prior and config.estimate_extrinsic and config.estimate_time_offset:
            surface = surface or MapSurface.of(world, OWN.normal_radius)
            results[name] = own_motion_result(rig, traj, surface, results[name], config, log)
        r = results[name]
        out.T_ref_sensor[name], out.time_offset[name] = r.estimate, r.time_offset
    accepted = {n: p for n, p in problems.items() if not results[n].kept_prior}
    if config.trajectory_draws > 0 and rig.trajectory_accuracy.stated() and accepted:
        results.update(trajectory_part(rig, calibration, config, source, accepted, {n: results[n] for n in accepted}, reference, log))
    scans = {}  # per LiDAR, read once for both placements
    lidars = (place_lidars(rig, out, [n for n in cameras if not results[n].kept_prior], lidar_undetermined or {}, lidar_sigma, log,
                           {n: results[n].sigma for n in cameras}, scans)
              if why_source and config.estimate_extrinsic and lidar_sigma is not None else {})  # an extrinsic the user holds stays
    result = CameraStageResult(out, {n: results[n] for n in cameras}, len(world), source, why_source, lidars)
    turn = trajectory_turn(lidars, log)
    if turn is None:
        return result
    # the trajectory is not given in the reference camera's frame: the cameras again on it carried there, then the
    # LiDARs placed again against them (taking what they took the first time: the motion's estimate was of the other frame)
    carried, start = replace(rig), replace(calibration, T_ref_sensor={**calibration.T_ref_sensor, **{n: out.T_ref_sensor[n] for n in lidars}})
    carried.carry_trajectory(turn)
    try:
        again = register_cameras(carried, start, config, sensors, log, lidar_undetermined)
    except NoMapError as err:  # its features no longer triangulate
        log(f"[camera-registration] on the carried trajectory: {err}: the trajectory and the cameras as first registered")
        return result
    again.calibration.trajectory_T_reference = turn
    registered = [n for n in cameras if not again.cameras[n].kept_prior]
    return replace(again, lidars=place_again(carried, again.calibration, lidars, registered, log, {n: again.cameras[n].sigma for n in cameras}, scans))
