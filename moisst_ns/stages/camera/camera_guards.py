"""One camera's robust least-squares solve and the tests its fit must pass before the camera leaves its prior.

``solve`` is the inner trust-region solve of ``camera_registration`` (Huber, bounded corrections). The tests:
``held_back_check`` (is the estimate better than the prior on pairs the fit did not use?),
``typical_error_significance`` (can the data tell the estimate from a typical prior error, per correction?),
``split_half_spread`` (do the two halves of the drive agree?), ``resolution_spread`` (how much did the finest
resolution move the estimate?), ``convergence_tail`` (how far was the descent still going?) and ``reference_cost``
(what the reference camera's own frames get down to: the wrong-minimum test's yardstick). ``config`` is always the stage's
``camera_registration.CameraRegistrationConfig``. Nothing here imports nerfstudio.
"""

from __future__ import annotations

from typing import Dict, Tuple

import numpy as np
from jaxtyping import Float
from scipy.optimize import least_squares

from moisst_ns.rig.format import Calibration
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.trust.observability import TYPICAL_ERROR
from moisst_ns.stages.camera.photometric import CameraFrames, PairSet, Registration, huber_costs, robust_cost

SCALE = np.r_[[np.deg2rad(0.5)] * 3, [0.05] * 3, 0.005, 0.005]
"""The solver's ``x_scale`` per correction (rad, m, s, and s for the readout)."""


def held_back_check(problem: Registration, theta: np.ndarray, factor: int, config) -> Tuple[float, float, bool]:
    """Is the estimate better than the prior on pairs the fit did not use?

    Fresh pairs are drawn at the estimate and at the prior alike (each draw favours the pose it was drawn at: the
    samples sit where that pose sees texture), both evaluated at both poses. The estimate is better when the
    per-frame mean of ``cost(prior) - cost(estimate)`` is positive at three standard errors over the frames.

    Returns:
        (mean Huber cost at the prior, at the estimate, whether the estimate is significantly better).
    """
    draws = [problem.pairs(t, factor, config.held_back_points) for t in (theta, np.zeros_like(theta))]
    check = PairSet(*(np.concatenate([getattr(d, f) for d in draws]) for f in ("points", "frame_a", "own", "frame_b", "value_b")))
    r_est, _, ok_est = problem.residuals(theta, check, factor, jacobian=False)
    r_pri, _, ok_pri = problem.residuals(np.zeros_like(theta), check, factor, jacobian=False)
    both = ok_est & ok_pri
    if not both.any():
        return float("nan"), float("nan"), False
    gain = huber_costs(r_pri[both], config.huber) - huber_costs(r_est[both], config.huber)
    frames = check.frame_a[both]
    per_frame = np.array([gain[frames == f].mean() for f in np.unique(frames)])
    significant = len(per_frame) >= 2 and per_frame.mean() > 3.0 * per_frame.std(ddof=1) / np.sqrt(len(per_frame))
    return robust_cost(r_pri[both], config.huber), robust_cost(r_est[both], config.huber), bool(significant)


def typical_error_significance(problem: Registration, theta: np.ndarray, active: np.ndarray, factor: int,
                                config) -> Float[np.ndarray, "7"]:
    """Can the data tell the estimate from a typical prior error, parameter by parameter?

    Fresh pairs are drawn at ``theta``; each active correction is stepped by a typical prior error
    (``TYPICAL_ERROR``: 10 cm, 1 deg, 10 ms) both ways, and the mean Huber cost increase per frame (the two directions
    averaged, which cancels the profile's slope) is divided by three standard errors of that mean over the frames (as
    ``held_back_check`` judges estimate against prior). Below 1 the frames do not tell a typical error apart: the
    parameter is weakly observable from this camera's view, whatever the drive. A camera that shares little view with
    the reference camera pairs mostly with itself, and two of its own frames see a façade alike whatever its
    along-track lever arm, offset or roll (docs/method.md).

    Returns:
        Per correction (solver order, the first 7 only): mean increase / (3 standard errors); inf for inactive ones, 0
        where fewer than two frames have pairs.
    """
    pairs = problem.pairs(theta, factor, config.held_back_points)
    r0, _, ok0 = problem.residuals(theta, pairs, factor, jacobian=False)
    cost0 = huber_costs(r0, config.huber)
    significance = np.full(7, np.inf)
    for i in np.flatnonzero(active[:7]):
        gain, valid = np.zeros(len(r0)), ok0.copy()
        for sign in (1.0, -1.0):
            step = theta.copy()
            step[i] += sign * TYPICAL_ERROR[i]
            r, _, ok = problem.residuals(step, pairs, factor, jacobian=False)
            gain += 0.5 * (huber_costs(r, config.huber) - cost0)
            valid &= ok
        per_frame = np.array([gain[valid & (pairs.frame_a == f)].mean() for f in np.unique(pairs.frame_a[valid])])
        if len(per_frame) < 2:
            significance[i] = 0.0
            continue
        se = per_frame.std(ddof=1) / np.sqrt(len(per_frame))
        significance[i] = per_frame.mean() / (3.0 * se) if se > 0 else np.inf
    return significance


def bounds(config) -> Float[np.ndarray, "7"]:
    """The bound on each correction, solver order (rad, m, s)."""
    return np.r_[[np.deg2rad(config.max_rotation_deg)] * 3, [config.max_translation] * 3, config.max_time_offset]


def limits(problem: Registration, config, size: int) -> Tuple[Float[np.ndarray, "p"], Float[np.ndarray, "p"]]:
    """Lower and upper bounds of ``size`` corrections (7, or 8 with the readout's: the readout time stays in
    ``[0, 0.999 frame period)``, the frame period the median interval between the camera's distinct stamps)."""
    bound = bounds(config)
    if size == 7:
        return -bound, bound
    stamps = np.unique(problem.camera.stamps)
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.1
    return np.r_[-bound, -problem.model.readout], np.r_[bound, 0.999 * period - problem.model.readout]


def points_per_frame(config, factor: int, finest: bool) -> int:
    """Map points sampled per camera frame at pyramid level ``factor``: ``fine_points_per_frame`` at the finest level
    (when set), else ``points_per_frame / factor`` (a level ``f`` times smaller has ``f^2`` times fewer pixels), at
    least 200."""
    if finest and config.fine_points_per_frame > 0:
        return int(config.fine_points_per_frame)
    return max(config.points_per_frame // factor, 200)


def solve(problem: Registration, theta: np.ndarray, active: np.ndarray, pairs: PairSet, factor: int, config):
    """One robust (Huber) trust-region solve of the active corrections from ``theta`` on fixed pairs.

    Returns:
        (the new corrections, residual evaluations used, (residuals, Jacobian, valid) at the solution).
    """
    lower, upper = limits(problem, config, len(theta))
    scale = SCALE[:len(theta)][active]
    cache: Dict[Tuple[bytes, bool], tuple] = {}

    def full(x, jacobian=False):
        th = theta.copy()
        th[active] = x
        key = (th.tobytes(), jacobian)
        if key not in cache:  # least_squares asks for the residuals of every trial step, the Jacobian of accepted ones
            cache.clear()
            cache[key] = problem.residuals(th, pairs, factor, jacobian=jacobian)
        return cache[key]

    solution = least_squares(lambda x: full(x)[0], theta[active], jac=lambda x: full(x, True)[1][:, active], method="trf",
                             loss="huber", f_scale=config.huber, x_scale=scale, max_nfev=config.max_evaluations, bounds=(lower[active], upper[active]))
    out = theta.copy()
    out[active] = solution.x
    return out, solution.nfev, full(solution.x, True)


def subset(pairs: PairSet, rows: np.ndarray) -> PairSet:
    return PairSet(pairs.points[rows], pairs.frame_a[rows], pairs.own[rows], pairs.frame_b[rows], pairs.value_b[rows])


def split_half_spread(problem: Registration, theta: np.ndarray, active: np.ndarray, factor: int,
                      config) -> Tuple[Float[np.ndarray, "7"], Float[np.ndarray, "7"]]:
    """How far the estimates from the first and the second half of the drive lie apart, and from the whole's.

    Each half (the camera's frames split in time) is solved from ``theta`` on fresh pairs. Unlike the formal sigma the
    halves also see what changes along the drive or what the drive leaves undetermined (a bias of one stretch of road,
    of one kind of motion; a lever arm a short, nearly straight drive hardly shows). For two independent, equally
    informative halves the whole drive's estimate is their mean, and ``|a - b| / 2``, each half's distance from it,
    estimates its standard deviation. Where one stretch carries the fit the whole is that half's estimate and the other
    half's distance from it, up to ``|a - b|``, is what the drive says (KITTI raw 0048's image_02: a van of the first
    half's frames carries its lateral lever arm, the halves lie 0.00 and 2.83 cm from the whole, the error is 4.52 cm;
    docs/lab/2026-11-29-movers.md). So sigma takes the farther half's distance from the whole (never less than half
    the difference), the "halves disagree" guard half the difference. The LiDAR-first stage's
    ``lidar_first.split_half_spread`` is the same test; its sigma stays half the difference (the realistic street's
    time offset: both halves biased alike by the trajectory's drift, the farther half would not cover it either).

    Returns:
        ``(apart, sigma)`` per correction (rad, rad, rad, m, m, m, s): half the difference of the halves, and the
        farther half's distance from ``theta``; both inf where a half has fewer than 50 pairs, 0 for inactive ones.
    """
    pairs = problem.pairs(theta, factor, points_per_frame(config, factor, factor == min(problem.camera.levels)))
    half = len(problem.camera.stamps) // 2
    estimates = []
    for rows in (pairs.frame_a < half, pairs.frame_a >= half):
        if rows.sum() < 50:
            unknown = np.where(active, np.inf, 0.0)
            return unknown, unknown
        estimates.append(solve(problem, theta, active, subset(pairs, rows), factor, config)[0])
    first, second = estimates
    return np.abs(first - second) / 2, np.maximum(np.abs(first - theta), np.abs(second - theta))


def resolution_spread(level_end: Dict[int, np.ndarray]) -> Float[np.ndarray, "7"]:
    """Half the change of the corrections between the two finest pyramid levels.

    A photometric fit at a resolution is biased by a fraction of that resolution's pixel (aliasing, interpolation,
    sampling at image gradients): a bias that every subset of the frames shares, so neither the formal sigma nor
    the split-half spread sees it. If the bias shrinks in proportion to the pixel, the finest level's bias is about
    the change from the level before it; half that change is taken as one standard deviation (measured: on 96x72 rigs
    the change was 0.9-1.5x the finest level's true error on the parameters the other two sigmas missed, on a 320x240
    rig 1-5x the true error).

    Args:
        level_end: ``{level factor: corrections at the end of that level}`` (``_descend``).

    Returns:
        Per correction (rad, rad, rad, m, m, m, s); zeros with fewer than two levels.
    """
    levels = sorted(level_end)
    if len(levels) < 2:
        return np.zeros(len(next(iter(level_end.values()))))
    return np.abs(level_end[levels[0]] - level_end[levels[1]]) / 2


def convergence_tail(iterates: Float[np.ndarray, "n 7"]) -> Float[np.ndarray, "7"]:
    """How far the descent may still be from where it was heading, from its last three iterates (Aitken's delta^2).

    An iteration converging linearly, each step ``rho`` times the one before (``s2 = rho s1``; an oscillating one has
    ``rho < 0``), has ``s2 rho / (1 - rho) = s2^2 / |s2 - s1|`` still to go after its last step ``s2``: Aitken's
    delta^2 estimate of the remaining distance. Where the steps do not shrink (same sign, ``|s2| >= |s1|``) no limit
    is in sight and the distance of the last two steps, ``|s1| + |s2|``, is taken (a lower bound). Outer iterations
    stop on a step under a tenth of a pixel, which for a weakly observable correction can still be a sizeable step
    (measured, quick benchmark 96x72: a time offset stepping 11.2, 1.4, 1.6 ms ended 12.6 ms from the truth, 5.2x
    its sigma without this term, 4.3x with it).

    Args:
        iterates: the corrections after each outer iteration, in order, across pyramid levels (rad, m, s).

    Returns:
        Per correction, same units; zeros with fewer than three iterates.
    """
    if len(iterates) < 3:
        return np.zeros(len(iterates[0]) if len(iterates) else 7)
    a, b, c = (np.asarray(v, dtype=np.float64) for v in iterates[-3:])
    s1, s2 = b - a, c - b
    growing = (s1 * s2 > 0) & (np.abs(s2) >= np.abs(s1))
    denominator = np.abs(s2 - s1)
    aitken = np.divide(s2 ** 2, denominator, out=np.zeros(len(s2)), where=denominator > 0)
    return np.where(growing, np.abs(s1) + np.abs(s2), aitken)


def reference_cost(traj: ReferenceTrajectory, world: np.ndarray, reference: CameraFrames, calibration: Calibration,
                   config) -> float:
    """The reference camera's own photometric cost: its frames paired with each other at their known poses, full
    resolution. What a correctly registered camera can get down to on this scene and these images."""
    own = Registration(traj, world, reference, None, calibration, config)
    pairs = own.pairs(np.zeros(7), 1, config.points_per_frame)
    res, _, ok = own.residuals(np.zeros(7), pairs, 1, jacobian=False)
    return robust_cost(res[ok], config.huber)
