"""A camera placed by its own motion against the reference trajectory alone (hand-eye calibration with a time offset).

A camera that shares no view with the reference camera of a rig without a LiDAR has no map to be placed on. Its own
images still tell its own motion, which eq. 2 ties to the reference trajectory: its poses are ``Traj(t + delta) ref_T_c``
(each row at its own time under a rolling shutter). Two costs of its own SIFT matches (``own_motion.own_matches``) at
those poses, the trajectory giving the scale:
- coarse: the epipolar constraint of every matched pair (Sampson distance, pixels), from a grid over delta. It sees the
  relative rotations and translation directions only (the hand-eye constraint ``A X = X B`` of Heng et al. 2013 and
  Taylor and Nieto 2016), and leaves a valley along which a rotation, delta and the lever arm trade: a start, not an
  estimate;
- fine: the matches chained into tracks over several frames (``tracks``), each triangulated from all its views
  (midpoint of the rays), the angle between each observation and its point (pixels) the residual: a track's views must
  agree on one point, so the lengths of the baselines count too, which is where a lever arm shows in the turns. Tracks
  with a view beyond ``thresholds_px`` at the current estimate are dropped (mismatches that pass a pair's epipolar
  RANSAC chain into tracks no point explains), the thresholds shrinking as the estimate settles.
``scipy.optimize.least_squares`` (soft L1) on the 7 corrections of eq. 12 throughout. A planar drive turns about one
axis, which leaves the lever arm along it undetermined: the drive's own-motion observability names it weak
(``weak_by_motion``), beside the sigma (the formal part, clustered by frame; the split halves of the drive; the short and
the long tracks each fitted alone). Measured: docs/lab/2026-12-02-own-tracks.md. No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple

import numpy as np
from jaxtyping import Float, Int
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_guards import SCALE, resolution_spread
from moisst_ns.stages.camera.own_motion import DeltaGridConfig, OwnMatches, OwnMotionFit, observation_poses
from moisst_ns.stages.trust.observability import analyse_drive
from moisst_ns.stages.trust.uncertainty_math import least_squares_sigma


@dataclass
class OwnTracksConfig(DeltaGridConfig):
    """Settings of a camera's fit against the reference trajectory alone (the coarse starts' solves are epipolar)."""

    thresholds_px: Tuple[float, ...] = (8.0, 4.0, 2.0, 2.0)
    """One track solve per threshold: tracks with a view farther than it from its point are left out, pixels."""
    min_tracks: int = 100
    """Fewer tracks of at least 3 views kept at the last threshold: the camera is not placed."""
    short_span: int = 3
    """The baseline part of sigma: the tracks spanning at most this many frames and the longer ones, each fitted alone;
    the farther of the two from the whole (a bias of the long baselines' far points, which the formal part and the
    halves share: idealised plaza seed 1's roll, 10 -> 1.7 sigma)."""


@dataclass
class Tracks:
    """A camera's observations chained into tracks: each observation's track, frame, normalised coordinates and row."""

    track: Int[np.ndarray, "n"]
    frame: Int[np.ndarray, "n"]
    xy: Float[np.ndarray, "n 2"]
    row: Float[np.ndarray, "n"]
    """Image row, pixels (its time under a rolling shutter)."""
    key: Int[np.ndarray, "n"]
    """The observation's keypoint (``OwnMatches.key_a``)."""
    stamps: Float[np.ndarray, "frames"]
    readout: float
    height: int

    def subset(self, keep: np.ndarray) -> "Tracks":
        """The observations ``keep`` (a mask), their tracks renumbered 0.."""
        return Tracks(np.unique(self.track[keep], return_inverse=True)[1], self.frame[keep], self.xy[keep], self.row[keep], self.key[keep],
                      self.stamps, self.readout, self.height)

    @property
    def count(self) -> int:
        return int(self.track.max()) + 1 if len(self.track) else 0


def tracks(matches: OwnMatches) -> Tracks:
    """``matches`` chained into tracks (connected components of the keypoints they join, ``scipy.sparse.csgraph``),
    dropping tracks that hold two keypoints of one frame."""
    keys = np.r_[matches.key_a, matches.key_b]
    ids, inverse = np.unique(keys, return_inverse=True)
    half = len(matches.key_a)
    graph = coo_matrix((np.ones(half), (inverse[:half], inverse[half:])), shape=(len(ids), len(ids)))
    label = connected_components(graph, directed=False)[1]
    first = np.unique(inverse, return_index=True)[1]  # one observation per keypoint
    frame = np.r_[matches.frame_a, matches.frame_b][first]
    xy, row = np.r_[matches.xy_a, matches.xy_b][first], np.r_[matches.row_a, matches.row_b][first]
    pairs = label * (len(matches.stamps) + 1) + frame
    twice = np.unique(pairs, return_counts=True)
    clash = np.unique(label[np.isin(pairs, twice[0][twice[1] > 1])])
    out = Tracks(label, frame, xy, row, ids, matches.stamps, matches.readout, matches.height)
    return out.subset(~np.isin(label, clash))


def _fitted(matches: OwnMatches, focal: float, config: OwnTracksConfig, args: tuple, log: Callable[[str], None], sensor: str,
            start: Optional[np.ndarray]) -> Optional[Tuple[np.ndarray, Tracks, object, Tracks]]:
    """``fit_own_tracks``' corrections alone: its tracks of 3 views or more, every ``hold_out``-th held back, refined
    from ``start`` (None: the epipolar start over the delta grid). Returns (corrections, the fitted tracks kept, the
    solution, the held-back tracks), or None when fewer than ``config.min_tracks`` are kept."""
    every = tracks(matches)
    views = np.bincount(every.track, minlength=every.count)
    every = every.subset(views[every.track] >= 3)
    held = every.track % config.hold_out == config.hold_out - 1
    fit, back = every.subset(~held), every.subset(held)
    if start is None:
        coarse, best = matches.subset(slice(None, None, max(1, len(matches.frame_a) // config.coarse_matches))), None
        for theta in config.starts():
            solution = _solve(lambda x: sampson_px(x, coarse, focal, *args), theta)
            if best is None or solution.cost < best.cost:
                best = solution
        log(f"[own-tracks] {sensor}: epipolar start at delta {best.x[6] * 1000:+.1f} ms from the prior, median {np.median(np.abs(best.fun)):.3f} px")
        start = _solve(lambda x: sampson_px(x, matches, focal, *args), best.x).x
    theta, kept, solution = _refine(np.asarray(start, dtype=np.float64), fit, focal, config, args)
    if solution is None or kept.count < config.min_tracks:
        log(f"[own-tracks] {sensor}: {kept.count} tracks of 3 views or more agree (the fit needs {config.min_tracks}): not placed")
        return None
    return theta, kept, solution, back


def sampson_px(theta, matches: OwnMatches, focal: float, traj, prior, offset) -> Float[np.ndarray, "n"]:
    """Each match's signed Sampson distance to the epipolar geometry of its two poses at ``theta``, pixels."""
    poses = [observation_poses(theta, f, r, matches.stamps, matches.readout, matches.height, traj, prior, offset)
             for f, r in ((matches.frame_a, matches.row_a), (matches.frame_b, matches.row_b))]
    b_T_a = np.linalg.inv(poses[1]) @ poses[0]
    R, t = b_T_a[:, :3, :3], b_T_a[:, :3, 3] / np.maximum(np.linalg.norm(b_T_a[:, :3, 3], axis=1, keepdims=True), 1e-12)
    xa, xb = np.c_[matches.xy_a, np.ones(len(matches.xy_a))], np.c_[matches.xy_b, np.ones(len(matches.xy_b))]
    line_b = np.cross(t, np.einsum("nij,nj->ni", R, xa))  # E x_a
    line_a = np.einsum("nji,nj->ni", R, np.cross(xb, t))  # E^T x_b
    norm = np.sqrt(line_b[:, 0] ** 2 + line_b[:, 1] ** 2 + line_a[:, 0] ** 2 + line_a[:, 1] ** 2)
    return focal * np.sum(xb * line_b, 1) / np.maximum(norm, 1e-12)


def track_px(theta, obs: Tracks, focal: float, traj, prior, offset) -> Float[np.ndarray, "n2"]:
    """Each observation's angle to its track's point (the midpoint of the track's rays at ``theta``), in pixels at the
    image centre (x and y of the unit-vector difference, times the focal length)."""
    poses = observation_poses(theta, obs.frame, obs.row, obs.stamps, obs.readout, obs.height, traj, prior, offset)
    ray = np.c_[obs.xy, np.ones(len(obs.xy))]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    d = np.einsum("nij,nj->ni", poses[:, :3, :3], ray)
    across = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # the midpoint minimises the distances to the rays
    A, b = np.zeros((obs.count, 3, 3)), np.zeros((obs.count, 3))
    np.add.at(A, obs.track, across)
    np.add.at(b, obs.track, np.einsum("nij,nj->ni", across, poses[:, :3, 3]))
    point = np.linalg.solve(A + 1e-9 * np.eye(3), b[..., None])[..., 0][obs.track]
    seen = np.einsum("nji,nj->ni", poses[:, :3, :3], point - poses[:, :3, 3])
    seen /= np.maximum(np.linalg.norm(seen, axis=1, keepdims=True), 1e-12)
    return (focal * (seen - ray)[:, :2]).ravel()


def _solve(residuals: Callable[[np.ndarray], np.ndarray], theta: np.ndarray):
    return least_squares(residuals, theta, loss="soft_l1", f_scale=1.0, diff_step=1e-7, x_scale=SCALE[:7])


def _refine(theta, obs: Tracks, focal, config: OwnTracksConfig, args, thresholds=None):
    """The track solves from ``theta``, one per threshold: (theta, the tracks kept, the last solution)."""
    solution, kept = None, obs
    for limit in thresholds or config.thresholds_px:
        far = np.abs(track_px(theta, obs, focal, *args)).reshape(-1, 2).max(1) > limit
        kept = obs.subset(~np.isin(obs.track, np.unique(obs.track[far])))
        if kept.count < 7:
            return theta, kept, None
        solution = _solve(lambda x: track_px(x, kept, focal, *args), theta)
        theta = solution.x
    return theta, kept, solution


def _loss(theta, obs: Tracks, focal, cap, args) -> float:
    """Mean of each held-back observation's angle to its point, capped at ``cap``, pixels."""
    return float(np.mean(np.minimum(np.abs(track_px(theta, obs, focal, *args)), cap))) if obs.count else cap


def fit_own_tracks(traj: ReferenceTrajectory, matches: OwnMatches, focal: float, prior: Float[np.ndarray, "4 4"], prior_offset: float,
                   config: OwnTracksConfig, log: Callable[[str], None] = print, sensor: str = "camera",
                   start: Optional[np.ndarray] = None, halved: Optional[OwnMatches] = None) -> Optional[OwnMotionFit]:
    """The camera's 7 corrections from its own matches against the reference trajectory (module docstring).

    Args:
        traj: the reference trajectory.
        matches: ``own_motion.own_matches`` of the camera (with their keypoints).
        focal: its focal length, pixels (the residuals' unit).
        prior: prior ``ref_T_c``; prior_offset: prior delta, seconds.
        config: settings.
        log: where progress lines go; sensor: the camera's name for them.
        start: corrections to refine from by the track solves alone (a drawn trajectory's refit), None: the delta grid.
        halved: the camera's matches on keypoints found at 1/2 resolution (``own_matches(..., downscale=2)``): the
            same fit on them, from its own start, gives the resolution part of sigma; None (or too few tracks there):
            no such part.

    Returns:
        The fit (``points``: tracks of 3 views or more kept; losses in pixels), or None when fewer than
        ``config.min_tracks`` such tracks are kept.
    """
    args = (traj, prior, prior_offset)
    found = _fitted(matches, focal, config, args, log, sensor, start)
    if found is None:
        return None
    theta, kept, solution, back = found
    pixels = solution.fun
    weights = (1 + pixels ** 2) ** -0.25  # the square root of soft L1's IRLS weight (f_scale 1 px)
    formal = least_squares_sigma(solution.jac * weights[:, None], pixels * weights, np.repeat(kept.frame, 2)).sigma
    middle = len(matches.stamps) // 2
    first = np.full(kept.count, len(matches.stamps))
    np.minimum.at(first, kept.track, kept.frame)
    halves = [_refine(theta, kept.subset(h[kept.track]), focal, config, args, config.thresholds_px[-1:])[0] for h in (first < middle, first >= middle)]
    split = np.max([np.abs(h - theta) for h in halves], axis=0)
    last = np.zeros(kept.count, dtype=np.int64)
    np.maximum.at(last, kept.track, kept.frame)
    short = (last - first <= config.short_span)[kept.track]
    spans = [_refine(theta, kept.subset(h), focal, config, args, config.thresholds_px[-1:])[0] for h in (short, ~short)]
    baseline = np.max([np.abs(h - theta) for h in spans], axis=0)
    half = None if halved is None else _fitted(halved, focal, config, args, lambda _: None, sensor, None)
    resolution = np.zeros(7) if half is None else resolution_spread({1: theta, 2: half[0]})
    cap = config.thresholds_px[0]
    result = OwnMotionFit(theta, np.asarray(formal), split, baseline, np.zeros(7), kept.count, _loss(np.zeros(7), back, focal, cap, args),
                          _loss(theta, back, focal, cap, args), resolution)
    log(f"[own-tracks] {sensor}: {kept.count} tracks agree within {config.thresholds_px[-1]:g} px (median {np.median(np.abs(pixels)):.3f} px); "
        f"held-back loss {result.loss_estimate:.3f} px (prior {result.loss_prior:.3f} px)")
    return result


TRACKS = OwnTracksConfig()  # the fit's settings


def weak_by_motion(traj: ReferenceTrajectory, matches: OwnMatches, prior: Float[np.ndarray, "4 4"], prior_offset: float,
                   log: Callable[[str], None] = print, sensor: str = "camera") -> List[str]:
    """The parameters a camera placed by its own tracks cannot have fixed on this drive: those the drive's motion does
    not separate in the relative model of ``observability.analyse_drive`` (its own motion against the
    trajectory's, as these tracks see it: a planar drive leaves the vertical lever arm weak), whatever the fit's sigma.

    Args:
        traj: the reference trajectory.
        matches: the camera's own matches (their frames' ``stamps``).
        prior: prior ``ref_T_c``; prior_offset: prior delta, seconds.
        log: where one line per weak parameter goes; sensor: the camera's name for it.

    Returns:
        Trust names (``PARAMETERS`` order).
    """
    drive = analyse_drive(traj, matches.stamps + prior_offset, prior, sensor, "relative")
    for dof in drive.dofs:
        if dof.weak:
            log(f"[own-tracks] {sensor}: {dof.name} weakly observable from this drive: {dof.reason}")
    return drive.weak
