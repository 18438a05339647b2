"""LiDAR first: calibrate each LiDAR against the reference trajectory from its own scans (no image, no NeRF).

Every scan point ``p`` (LiDAR frame) fired at own-clock time ``t`` is placed in the world by paper eq. 1-2,
``x = T_r(t + delta_L) @ ref_T_L @ p``, per point, so raw sweeps are de-skewed by the same interpolated trajectory
(KITTI-360-style motion-compensated scans have no per-point times and are placed at their stamp). The scans of a
static world agree with each other only at the true ``ref_T_L`` and ``delta_L``: a rotation error smears the map in
proportion to the distance driven, a time error in proportion to speed changes, a lever-arm error in proportion to
heading changes (map "crispness": Maddern et al. ICRA 2012, Sheehan et al. IJRR 2012, ethz-asl/lidar_align).

Formulation (ICP-like, ``scan_consistency_residuals``): point-to-plane residuals ``n_b . (x_a - y_b)`` between
sampled points of scan ``a`` and their nearest neighbours in scan ``b``, for scan pairs spread over baselines of
0.5 m to ``max_baseline`` of driving; normals and planarity from each scan's own full-density neighbourhoods (open3d
covariances). Outer iterations re-place every scan, recompute correspondences within a radius that shrinks
coarse-to-fine and admit longer baselines as the estimate improves; each inner problem is a robust (Huber)
Gauss-Newton/trust-region solve of the 7 parameters (``scipy.optimize.least_squares`` with the analytic Jacobian
of ``placement_jacobian``). Unknowns: ``R = R_c Exp(w)`` (rotation about the LiDAR's own axes), ``t = t_c + v``
(reference frame, metres), ``delta = delta_c + d`` (seconds), the same parameterisation as paper eq. 12.

Nothing here imports nerfstudio.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import open3d as o3d
from jaxtyping import Float, Int
from scipy.optimize import least_squares

from moisst_ns.rig.format import Calibration, Rig, RigFormatError, load_lidar_scan
from moisst_ns.stages.lidar_checks import release_check, split_half_spread
from moisst_ns.stages.lidar_geometry import Extrinsic, PointTimes, Trajectory, place_points, placement_jacobian, prior_residuals, trajectory_at
from moisst_ns.stages.lidar_map import CameraStageError
from moisst_ns.stages.lidar_view import SharedView, view_residuals
from moisst_ns.stages.observability import JACOBIAN_ORDER, PARAMETERS, TEST_STEPS, UNITS, Observability, analyse_observability, huber_weights


class LidarFirstError(ValueError):
    """The LiDAR-first stage cannot run on this input; the message is one line naming the file/sensor and field."""


@dataclass
class LidarFirstConfig:
    """Settings of the LiDAR-first stage (defaults measured on the synthetic street and plaza drives)."""

    points_per_scan: int = 3000
    """Points sampled (after a ``voxel_size`` voxel grid) from each scan as correspondence sources."""
    voxel_size: float = 0.2
    """Voxel grid for the source samples, metres (spreads them evenly instead of crowding them near the sensor)."""
    min_range: float = 2.0
    """Points closer than this are dropped (returns from the vehicle itself move with it), metres."""
    normal_radius: float = 1.0
    """Neighbourhood radius of the normals and planarity, metres (within a scan, full density)."""
    normal_max_nn: int = 30
    """At most this many neighbours per normal."""
    min_planarity: float = 0.3
    """A target point is used only when its neighbourhood is planar: ``(l2 - l1) / l3 >=`` this (eigenvalues
    ``l1 <= l2 <= l3`` of its covariance); edges, poles and ring-only neighbourhoods are dropped."""
    normal_agreement: float = 0.9
    """A correspondence is kept only when the source's and the target's normals agree: ``|n_a . n_b| >=`` this (a
    ground point matched to the foot of a wall is not a point-to-plane pair)."""
    plane_noise: float = 0.01
    """Expected point noise, metres: each residual is weighted by ``plane_noise / sqrt(plane_noise^2 + s^2)``, ``s``
    the target neighbourhood's thickness (RMS distance to its own plane), so curved or rough targets count less."""
    min_baseline: float = 0.5
    """Shortest driving distance between the two scans of a pair, metres (consecutive scans always pair)."""
    max_baseline: float = 30.0
    """Longest driving distance between the two scans of a pair, metres (their views must still overlap)."""
    start_baseline: float = 4.0
    """Coarse to fine: the first outer iteration pairs scans up to this far apart; it doubles every iteration."""
    radius_start: float = 1.0
    """Coarse to fine: correspondence radius of the first outer iteration, metres."""
    radius_end: float = 0.15
    """Correspondence radius reached at the end (x0.6 per outer iteration), metres."""
    huber: float = 0.05
    """Huber scale of the point-to-plane residuals, metres (residuals beyond it count linearly: moving objects)."""
    max_outer: int = 20
    """At most this many outer iterations (re-placement + correspondences + solve)."""
    max_inner_evaluations: int = 30
    """At most this many residual evaluations per inner solve."""
    tolerance: Tuple[float, float, float] = (1e-4, 1e-5, 1e-5)
    """Converged when an outer iteration moves the estimate less than (metres, radians, seconds) at the finest
    radius and baseline."""
    max_time_offset: float = 0.3
    """Bound on the change of delta from its prior, seconds."""
    prior_sigma: Tuple[float, float, float] = (1.0, 0.17, 0.1)
    """Gaussian prior at rig.json's values (m, rad, s; ``lidar_geometry.prior_residuals``, one robust residual scatter
    per sigma): what the scans do not determine stays at the prior (a straight drive's along-track lever arm ran 16 m off
    without it); 0: none."""
    max_extrapolation: float = 0.2
    """Scans with points more than this far (seconds) outside the reference trajectory's time span are dropped
    (placing them would extrapolate the trajectory's end segment too far); fewer than 3 left is an error."""
    seed: int = 0
    """Seed of the source-point sampling."""
    estimate_extrinsic: bool = True
    """Estimate ``ref_T_L`` (off: held at the prior, as in the paper's temporal-only Table II)."""
    estimate_time_offset: bool = True
    """Estimate ``delta_L`` (off: held at the prior, as in the paper's spatial-only Table I)."""
    release_check: bool = True
    """With a parameter held: fit once more with every parameter free and report which held values the scans disagree
    with (``release_check``; street rig, delta held 100 ms off: the extrinsic absorbed it, 101 cm off, sigma 371x small)."""
    split_half: bool = True
    """Fit the two halves of the drive apart, from the estimate, and report every parameter's sigma as at least half their
    difference (``lidar_checks.split_half_spread``; 12 s on the 320x240 street rig beside 35 s): on a 6-scan drive the
    estimate was 24-48 cm off per axis at formal sigmas of 1-4 cm; the halves differed by metres."""
    hold_split_half: float = 2.0
    """Parameters whose split-half spread exceeds this many typical prior errors (10 cm, 1 deg, 10 ms; the camera stage's
    rule) are not determined by the drive: fitted again from the prior with them held there, their sigma is how far the
    release fit moves them; 0 never holds. KITTI raw 0048, free: 134 cm / 5.3 deg off, the halves 44-145 cm apart."""
    shared_view: bool = False
    """Fit the LiDAR depth edges to the reference camera's image edges too (``lidar_view``), each kind in units of its own
    scatter. Off: it did not place KITTI raw 0048's Velodyne (docs/lab/2026-11-25-kitti-shared-view.md)."""


# Scans ---------------------------------------------------------------------------------------------------------


@dataclass
class ScanSet:
    """The scans of one LiDAR, concatenated (LiDAR frame), with their neighbourhood geometry."""

    sensor: str
    points: Float[np.ndarray, "num 3"]
    """Points in the LiDAR frame, metres."""
    times: PointTimes
    """Own-clock firing time of each point, seconds since the trajectory's ``t0`` (stamp + per-point offset)."""
    offsets: Int[np.ndarray, "num_scans_plus_one"]
    """Scan ``k`` holds points ``offsets[k]:offsets[k+1]``."""
    stamps: Float[np.ndarray, "num_scans"]
    """Frame stamps, seconds since ``t0``."""
    normals: Float[np.ndarray, "num 3"]
    """Unit normals in the LiDAR frame (from the scan's own neighbourhoods)."""
    planar: np.ndarray
    """(num,) bool: the neighbourhood is planar enough to be a point-to-plane target."""
    thickness: Float[np.ndarray, "num"]
    """RMS distance of each point's neighbourhood to its own best-fit plane, metres."""
    sources: List[Int[np.ndarray, "samples"]]
    """Per scan, the global indices of its sampled source points."""
    files: List[str]
    deskewed: bool
    """Whether the scans carry per-point times (raw sweeps, de-skewed here)."""
    dropped: List[str] = field(default_factory=list)
    """Scans left out, with the reason."""

    def scan(self, k: int) -> slice:
        return slice(int(self.offsets[k]), int(self.offsets[k + 1]))


def _neighbourhood_geometry(points: np.ndarray, config: LidarFirstConfig) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals, planarity test and thickness of every point's neighbourhood (open3d covariances)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=config.normal_radius, max_nn=config.normal_max_nn))
    evals, evecs = np.linalg.eigh(np.asarray(cloud.covariances))
    planarity = (evals[:, 1] - evals[:, 0]) / np.maximum(evals[:, 2], 1e-12)
    return evecs[:, :, 0], planarity >= config.min_planarity, np.sqrt(np.maximum(evals[:, 0], 0.0))


def load_scans(rig: Rig, sensor: str, traj: Trajectory, config: LidarFirstConfig, log: Callable[[str], None] = print) -> ScanSet:
    """Read, filter and analyse every scan of ``sensor``; one-line ``LidarFirstError`` for unusable input."""
    frames = sorted(rig.frames_of(sensor), key=lambda f: f.timestamp)
    t0, prior = float(rig.trajectory_stamps[0]), rig.sensors[sensor].time_offset
    start, end = traj.times[0] - config.max_extrapolation, traj.times[-1] + config.max_extrapolation
    rng = np.random.default_rng(config.seed)
    pts, tms, offsets, stamps, normals, planar, thickness, sources, files, dropped = [], [], [0], [], [], [], [], [], [], []
    deskewed = False
    for frame in frames:
        path = rig.root / frame.file_path
        try:
            points, offsets_s, _ = load_lidar_scan(path, min_range=config.min_range)
        except RigFormatError as err:
            raise LidarFirstError(str(err)) from None
        stamp = frame.timestamp - t0
        times = stamp + (offsets_s if offsets_s is not None else np.zeros(len(points)))
        deskewed |= offsets_s is not None
        if times.min() + prior < start or times.max() + prior > end:
            dropped.append(f"{frame.file_path}: outside the reference trajectory's time span by more than {config.max_extrapolation} s")
            continue
        if len(points) < 100:
            dropped.append(f"{frame.file_path}: only {len(points)} points beyond {config.min_range} m")
            continue
        points = points.astype(np.float64)
        n, ok, thick = _neighbourhood_geometry(points, config)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        _, _, traced = cloud.voxel_down_sample_and_trace(config.voxel_size, cloud.get_min_bound() - 1, cloud.get_max_bound() + 1)
        reps = np.array([v[0] for v in traced], dtype=np.int64)
        reps = reps[ok[reps]]
        if len(reps) > config.points_per_scan:
            reps = np.sort(rng.choice(reps, config.points_per_scan, replace=False))
        sources.append(reps + offsets[-1])
        pts.append(points), tms.append(times), normals.append(n), planar.append(ok), thickness.append(thick)
        offsets.append(offsets[-1] + len(points)), stamps.append(stamp), files.append(frame.file_path)
    where = f"{rig.root / 'rig.json'}: sensors.{sensor}"
    if len(pts) < 3:
        reasons = f" ({'; '.join(dropped[:2])})" if dropped else ""
        raise LidarFirstError(f"{where}: needs at least 3 usable scans, got {len(pts)} of {len(frames)}{reasons}")
    for note in dropped:
        log(f"[lidar-first] {sensor}: dropped {note}")
    return ScanSet(sensor, np.concatenate(pts), PointTimes.of(np.concatenate(tms)), np.asarray(offsets), np.asarray(stamps),
                   np.concatenate(normals), np.concatenate(planar), np.concatenate(thickness), sources, files, deskewed, dropped)


def scan_pairs(traj: Trajectory, scans: ScanSet, prior_offset: float, config: LidarFirstConfig) -> Tuple[np.ndarray, np.ndarray]:
    """Scan pairs ``(a, b)``, ``a < b``, at driving distances of 0.5, 1, 2, 4... m up to ``max_baseline``, and
    each pair's baseline (metres of the reference trajectory between the two scans' stamps)."""
    _, pos, _, _ = traj.pose_and_rates(scans.stamps + prior_offset)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    targets = []
    b = config.min_baseline
    while b <= config.max_baseline:
        targets.append(b)
        b *= 2
    pairs = set()
    num = len(scans.stamps)
    for a in range(num):
        for gap in (1, 2):
            if a + gap < num:
                pairs.add((a, a + gap))
        for dist in targets:
            b = int(np.searchsorted(arc, arc[a] + dist))
            if b < num and arc[b] - arc[a] <= config.max_baseline:
                pairs.add((a, b))
    pairs_arr = np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)
    return pairs_arr, arc[pairs_arr[:, 1]] - arc[pairs_arr[:, 0]]


# Correspondences and the solve ---------------------------------------------------------------------------------


@dataclass
class Correspondences:
    """Point-to-plane pairs of one outer iteration: source point ``src`` should lie on the plane of ``tgt``."""

    src: Int[np.ndarray, "num"]
    tgt: Int[np.ndarray, "num"]
    normals: Float[np.ndarray, "num 3"]
    """World-frame normal at each target (fixed during the inner solve)."""
    weights: Float[np.ndarray, "num"]
    """Per-residual weight (target thickness against the expected point noise)."""
    candidates: int
    """Source points queried (before the radius and planarity tests)."""


def find_correspondences(traj: Trajectory, ext: Extrinsic, scans: ScanSet, pairs: np.ndarray, radius: float,
                         config: LidarFirstConfig) -> Correspondences:
    """Nearest neighbours (open3d) of each pair's source samples in its target scan, all placed with ``ext``, kept
    within ``radius``, on planar targets and with agreeing normals."""
    world = place_points(traj, ext, scans.points, scans.times)
    src_all, tgt_all, candidates = [], [], 0
    for b in np.unique(pairs[:, 1]):
        sources = np.concatenate([scans.sources[a] for a in pairs[pairs[:, 1] == b, 0]])
        if len(sources) == 0:
            continue
        candidates += len(sources)
        part = scans.scan(int(b))
        index = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(world[part]))
        index.knn_index()
        found, dist2 = index.knn_search(o3d.core.Tensor(world[sources]), 1)
        tgt = found.numpy()[:, 0].astype(np.int64) + part.start
        keep = (dist2.numpy()[:, 0] < radius * radius) & scans.planar[tgt]
        src_all.append(sources[keep]), tgt_all.append(tgt[keep])
    if not src_all:
        empty = np.zeros(0, dtype=np.int64)
        return Correspondences(empty, empty, np.zeros((0, 3)), np.zeros(0), candidates)
    src, tgt = np.concatenate(src_all), np.concatenate(tgt_all)
    rot_b, _, _, _ = trajectory_at(traj, scans.times[tgt], ext.time_offset)
    rot_a, _, _, _ = trajectory_at(traj, scans.times[src], ext.time_offset)
    normals = np.einsum("nij,nj->ni", rot_b, scans.normals[tgt] @ ext.rotation.T)
    agree = np.abs(np.einsum("ni,ni->n", normals, np.einsum("nij,nj->ni", rot_a, scans.normals[src] @ ext.rotation.T)))
    keep = agree >= config.normal_agreement
    weights = config.plane_noise / np.sqrt(config.plane_noise**2 + scans.thickness[tgt[keep]] ** 2)
    return Correspondences(src[keep], tgt[keep], normals[keep], weights, candidates)


def consistency_residuals(
    traj: Trajectory, ext: Extrinsic, scans: ScanSet, corr: Correspondences, increment: np.ndarray
) -> Tuple[Float[np.ndarray, "num"], Float[np.ndarray, "num 7"]]:
    """Weighted point-to-plane residuals ``w n . (x_src - y_tgt)`` (metres) at ``ext.updated(increment)`` and their
    Jacobian."""
    ra, ja = placement_jacobian(traj, ext, increment, scans.points[corr.src], scans.times[corr.src], corr.normals)
    rb, jb = placement_jacobian(traj, ext, increment, scans.points[corr.tgt], scans.times[corr.tgt], corr.normals)
    return corr.weights * (ra - rb), corr.weights[:, None] * (ja - jb)


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
    free parameters' spread when they are released), else None."""
    sigma_split: Optional[List[float]] = None
    """``split_half_spread`` in ``observability.PARAMETERS`` order (m, rad, s; NaN where a half cannot be fitted: not
    measured), or None when ``split_half`` is off."""


def joint_residuals(traj: Trajectory, ext: Extrinsic, scans: ScanSet, corr: Correspondences, shared: Optional[SharedView],
                    increment: np.ndarray, config: LidarFirstConfig) -> Tuple[Float[np.ndarray, "num"], Float[np.ndarray, "num 7"]]:
    """The point-to-plane residuals (metres) followed by the edge distances times ``shared.scale``, and their Jacobian
    (Jacobian order: rotation vector, translation, time offset)."""
    residuals, jac = consistency_residuals(traj, ext, scans, corr, increment)
    if shared is None or shared.rows is None or len(shared.rows.point) == 0:
        return residuals, jac
    res_v, jac_v = view_residuals(traj, ext, scans, shared.view, shared.rows, increment)
    return np.concatenate([residuals, shared.scale * res_v]), np.concatenate([jac, shared.scale * jac_v])


def _fit(traj: Trajectory, scans: ScanSet, pairs: np.ndarray, baselines: np.ndarray, start: Extrinsic, prior: Extrinsic, free: np.ndarray,
         config: LidarFirstConfig, log: Callable[[str], None], where: str,
         view: Optional[SharedView] = None) -> Tuple[Extrinsic, List[Dict[str, float]]]:
    """Coarse-to-fine outer iterations of the parameters ``free`` (Jacobian order: rotation, translation, delta) from
    ``start``; ``prior`` anchors the bound on delta, ``where`` (``file: sensors.NAME``) names the sensor in errors,
    ``view`` (the reference camera's frames and the scans' depth edges) adds the shared-view residuals.

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
        at_start = consistency_residuals(traj, ext, scans, corr, np.zeros(7))[0]  # the shared view's rows and the prior's unit
        shared = view.at(traj, ext, scans, active, at_start) if view is not None else None
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
                residuals, jac = joint_residuals(traj, ext, scans, corr, shared, inc, config)
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
        if shared is not None:
            edge_px = np.abs(solution.fun[len(corr.src):len(solution.fun) - len(anchored)]) / max(shared.scale, 1e-12)
            h.update(view_rows=int(len(edge_px)), view_median_px=float(np.median(edge_px)) if len(edge_px) else float("nan"))
        log(f"[lidar-first] {sensor} it {outer}: radius {radius:.2f} m, pairs {h['pairs']}, {h['correspondences']} corr., "
            + (f"{h['view_rows']} edge points at {h['view_median_px']:.2f} px, " if shared is not None else "")
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
    traj = Trajectory.from_rig(rig)
    scans = load_scans(rig, sensor, traj, config, log)
    prior = Extrinsic(spec.T_ref_sensor[:3, :3].copy(), spec.T_ref_sensor[:3, 3].copy(), float(spec.time_offset))
    pairs, baselines = scan_pairs(traj, scans, prior.time_offset, config)
    free = np.array([i for i in range(7) if (i < 6 and config.estimate_extrinsic) or (i == 6 and config.estimate_time_offset)])
    if len(free) == 0:
        raise LidarFirstError("estimate_extrinsic and estimate_time_offset are both off: nothing to calibrate")
    where = f"{rig.root / 'rig.json'}: sensors.{sensor}"
    try:
        view = SharedView.of(rig, traj, scans) if config.shared_view else None
    except CameraStageError as err:
        raise LidarFirstError(str(err)) from None
    ext, history = _fit(traj, scans, pairs, baselines, prior, prior, free, config, log, where, view)
    fine = replace(config, radius_start=config.radius_end, start_baseline=float(baselines.max()) if len(baselines) else config.start_baseline)
    held_apart: List[int] = []
    while True:  # the fit, then (hold_split_half, every parameter estimated) again with what the halves disagree on held
        corr = find_correspondences(traj, ext, scans, pairs, config.radius_end, config)
        shared = view.at(traj, ext, scans, pairs, consistency_residuals(traj, ext, scans, corr, np.zeros(7))[0]) if view is not None else None
        residuals, jac = joint_residuals(traj, ext, scans, corr, shared, np.zeros(7), config)
        observability = analyse_observability(jac, residuals, huber_weights(residuals, config.huber), traj, scans.stamps + ext.time_offset, ext.rotation)
        split = None
        if config.split_half:
            def half(p: np.ndarray, b: np.ndarray, at: Extrinsic = ext, params: np.ndarray = free) -> Optional[Extrinsic]:
                try:
                    return _fit(traj, scans, p, b, at, prior, params, fine, lambda line: None, where, view)[0]
                except LidarFirstError:  # the half's scans do not overlap
                    return None

            split = split_half_spread(half, pairs, baselines, len(scans.stamps)).tolist()
            log(f"[lidar-first] {sensor}: " + ("the halves of the drive cannot be fitted apart (split-half sigma not measured)" if np.isnan(split).any() else
                "halves of the drive apart by " + ", ".join(f"{p} {2 * v * u:.3g} {n}" for p, v, (u, n) in zip(PARAMETERS, split, UNITS))))
        apart = [] if split is None or config.hold_split_half <= 0 or len(free) + len(held_apart) < 7 else \
            [JACOBIAN_ORDER[i] for i in range(7) if split[i] > config.hold_split_half * TEST_STEPS[i] and JACOBIAN_ORDER[i] in free]
        if not apart or len(apart) == len(free):  # nothing (more) to hold, or nothing would be left to fit
            break
        log(f"[lidar-first] {sensor}: the halves of the drive disagree on {', '.join(PARAMETERS[JACOBIAN_ORDER.index(j)] for j in apart)}"
            f" by more than {config.hold_split_half:g}x a typical prior error: fitted again from the prior with them held there")
        held_apart, free = held_apart + apart, np.array([j for j in free if j not in apart])
        ext, again = _fit(traj, scans, pairs, baselines, prior, prior, free, config, log, where, view)
        history += again
    if shared is not None:  # weak now means that neither the motion nor the shared view determines it
        for dof in observability.dofs:
            if dof.weak:
                dof.reason += f"; nor do the {len(shared.rows.point)} LiDAR depth edges seen in the reference camera's frames"
    held = None
    if len(free) < 7 and config.release_check:
        released, _ = _fit(traj, scans, pairs, baselines, ext, prior, np.arange(7), config, lambda line: log(line + " (released)"), where, view)
        held = release_check(ext, released, free, observability, expected=held_apart)
        if held["note"]:
            log(f"[lidar-first] {sensor}: {held['note']}")
    return LidarResult(sensor, prior, ext, history, observability, len(scans.stamps), scans.deskewed, scans.dropped,
                       time.perf_counter() - start, held, split)


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
    calibration = Calibration.from_rig(rig)
    calibration.T_ref_sensor, calibration.time_offset = dict(calibration.T_ref_sensor), dict(calibration.time_offset)
    results = {name: calibrate_lidar(rig, name, config, log) for name in names}
    for name, result in results.items():
        calibration.T_ref_sensor[name], calibration.time_offset[name] = result.estimate.matrix(), result.estimate.time_offset
    return LidarFirstResult(calibration, results)
