"""The LiDAR-first stage's settings (``LidarFirstConfig``) and data: each scan read, filtered and analysed (normals, planarity, thickness; open3d), the scan
pairs over driving baselines, and the point-to-plane correspondences and residuals between paired scans (eq. 1-2's
placement, ``lidar_geometry``). The fit that uses them is ``lidar_first``. No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import count, product, takewhile
from typing import Callable, List, Tuple

import numpy as np
import open3d as o3d
from jaxtyping import Float, Int

from moisst_ns.rig.format import Rig, RigFormatError, load_lidar_scan
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, PointTimes, place_points, placement_jacobian, trajectory_at

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
    split_half: bool = True
    """Fit the two halves of the drive apart, from the estimate, and report every parameter's sigma as at least half their
    difference (``lidar_first.split_half_spread``; 12 s on the 320x240 street rig beside 35 s): on a 6-scan drive the
    estimate was 24-48 cm off per axis at formal sigmas of 1-4 cm; the halves differed by metres."""
    trajectory_draws: int = 6
    """Where rig.json states the trajectory's errors (``trajectory_accuracy``), fit again from the estimate on this many
    draws of them and report every parameter's sigma as at least their RMS effect (``trajectory_noise.trajectory_spread``;
    0: off). The halves cannot show a drift: it biases both alike."""
    hold_split_half: float = 2.0
    """Parameters whose split-half spread exceeds this many typical prior errors (10 cm, 1 deg, 10 ms; the camera stage's
    rule) are not determined by the drive: fitted again from the prior with them held there, their sigma is how far the
    release fit moves them; 0 never holds. KITTI raw 0048, free: 134 cm / 5.3 deg off, the halves 44-145 cm apart."""
    view_search: bool = True
    """Where the halves hold rotations or lever-arm components at the prior and the reference sensor is a camera: place
    them by the reference camera's view of the LiDAR's depth edges (``lidar_view.search_held``), then fit the free
    parameters again around them. ``moisst-calibrate`` and ``ns-train`` turn it off where a camera may place the LiDAR
    at the same instants (``lidar_instant.pairs_with_reference``), which replaces the view."""



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


def load_scans(rig: Rig, sensor: str, traj: ReferenceTrajectory, config: LidarFirstConfig, log: Callable[[str], None] = print) -> ScanSet:
    """Read, filter and analyse every scan of ``sensor``; one-line ``LidarFirstError`` for unusable input."""
    frames = sorted(rig.frames_of(sensor), key=lambda f: f.timestamp)
    t0, prior = float(rig.trajectory_stamps[0]), rig.sensors[sensor].time_offset
    start, end = float(traj.times[0]) - config.max_extrapolation, float(traj.times[-1]) + config.max_extrapolation
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


MOVER_SPEED = 1.5
"""A point whose surface moves faster than this (metres per second, walking pace) between scans is on a mover."""
MOVER_RADIUS = 1.5
"""How far a point's surface may lie in the neighbouring scan to be judged, metres (farther: not judged, kept): a car
15 m/s faster or slower than the rig moves this much between two scans 0.1 s apart."""


def moving_points(traj: ReferenceTrajectory, ext: Extrinsic, scans: ScanSet) -> np.ndarray:
    """The points that do not stay put: a point of scan ``k`` lies off the surface the scans before and after it see
    there (the nearest point within ``MOVER_RADIUS``, planar and facing as the point's own surface, point to plane, all
    placed with ``ext``) by more than ``MOVER_SPEED`` times the time between the two scans, in every neighbouring scan
    that sees such a surface there. A moving car's front and back move by their speed along their normal (0.4-1 m in
    0.1 s at 4-10 m/s); a static surface stays within its noise plus what an extrinsic error does over one scan's
    motion (a 5 deg rotation error over 0.8 m of travel: 7 cm).

    Args:
        traj: the reference trajectory.
        ext: the LiDAR's calibration (a prior's error moves static points by centimetres here, not decimetres).
        scans: the LiDAR's scans, in time order.

    Returns:
        (num,) bool over ``scans.points``: True on a mover.
    """
    world, normals = np.zeros_like(scans.points), np.zeros_like(scans.normals)
    for k in range(len(scans.stamps)):  # one scan at a time: a rotation per point for all of them would be the peak memory
        part = scans.scan(k)
        world[part] = place_points(traj, ext, scans.points[part], scans.times[part])
        rot = trajectory_at(traj, scans.times[part], ext.time_offset)[0]
        normals[part] = np.einsum("nij,nj->ni", rot, scans.normals[part] @ ext.rotation.T)
    moving = np.zeros(len(world), dtype=bool)
    for k in range(len(scans.stamps)):
        here = scans.scan(k)
        judged, off = np.zeros(here.stop - here.start, dtype=bool), np.ones(here.stop - here.start, dtype=bool)
        for j in (k - 1, k + 1):
            if not 0 <= j < len(scans.stamps):
                continue
            there = scans.scan(j)
            index = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(world[there]))
            index.knn_index()
            found, dist2 = index.knn_search(o3d.core.Tensor(world[here]), 1)
            near = found.numpy()[:, 0].astype(np.int64) + there.start
            facing = np.abs(np.einsum("ni,ni->n", normals[near], normals[here])) >= 0.9  # the same surface (not the road under a car)
            seen = (dist2.numpy()[:, 0] < MOVER_RADIUS**2) & scans.planar[near] & scans.planar[here] & facing
            apart = np.abs(np.einsum("ni,ni->n", normals[near], world[here] - world[near]))
            judged |= seen
            off &= ~seen | (apart > MOVER_SPEED * abs(scans.stamps[j] - scans.stamps[k]))
        moving[here] = judged & off
    return moving


def scan_pairs(traj: ReferenceTrajectory, scans: ScanSet, prior_offset: float, config: LidarFirstConfig) -> Tuple[np.ndarray, np.ndarray]:
    """Scan pairs ``(a, b)``, ``a < b``, at driving distances of 0.5, 1, 2, 4... m up to ``max_baseline``, and
    each pair's baseline (metres of the reference trajectory between the two scans' stamps)."""
    _, pos, _, _ = traj.pose_and_rates(scans.stamps + prior_offset)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    targets = list(takewhile(lambda dist: dist <= config.max_baseline, (config.min_baseline * 2**k for k in count())))
    num = len(scans.stamps)
    pairs = {(a, a + gap) for a in range(num) for gap in (1, 2) if a + gap < num}
    for a, dist in product(range(num), targets):
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


def find_correspondences(traj: ReferenceTrajectory, ext: Extrinsic, scans: ScanSet, pairs: np.ndarray, radius: float,
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
    traj: ReferenceTrajectory, ext: Extrinsic, scans: ScanSet, corr: Correspondences, increment: np.ndarray
) -> Tuple[Float[np.ndarray, "num"], Float[np.ndarray, "num 7"]]:
    """Weighted point-to-plane residuals ``w n . (x_src - y_tgt)`` (metres) at ``ext.updated(increment)`` and their
    Jacobian."""
    ra, ja = placement_jacobian(traj, ext, increment, scans.points[corr.src], scans.times[corr.src], corr.normals)
    rb, jb = placement_jacobian(traj, ext, increment, scans.points[corr.tgt], scans.times[corr.tgt], corr.normals)
    return corr.weights * (ra - rb), corr.weights[:, None] * (ja - jb)
