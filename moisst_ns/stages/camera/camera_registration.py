"""Cameras against the calibrated LiDAR map: each camera's extrinsic and time offset from photometric consistency
over LiDAR-measured, metric geometry (no NeRF): grey levels of map points in a camera's frames against the reference
camera's and its own frames some metres away, robust (Huber) least squares on the 7 corrections of eq. 12, coarse to
fine over an image pyramid, occlusions by a z-buffer, rolling-shutter rows included (``photometric``), each fit
guarded before it replaces the prior (``camera_fit``, ``camera_guards``); a camera the fit leaves at its prior
against a LiDAR map placed by its own motion instead (``own_motion``), one that shares no view with the reference camera
of a rig without a LiDAR by its own tracks on the reference trajectory (``own_tracks``); then a LiDAR whose scans' motion left parameters undetermined
against the cameras at the same instants (``lidar_instant``). docs/method.md, "Cameras against the map" and "Guards", has the
formulation and the measurements. Nothing here imports nerfstudio.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trajectory_noise import trajectory_spread
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.feature_start import FeatureStartConfig, feature_start
from moisst_ns.stages.camera.lidar_map import CameraStageError, NoMapError, NoOverlapError, lidar_map, map_source, pyramid_factors
from moisst_ns.stages.camera.camera_guards import bounds, reference_cost
from moisst_ns.stages.camera.camera_fit import UNDETERMINED, _descend, register_camera
from moisst_ns.stages.camera.camera_result import CameraResult, CameraStageResult, corrected as _corrected, prior_kept as _prior_kept
from moisst_ns.stages.camera.own_motion import OWN, MapSurface, OwnMatches, fit_own_motion, own_matches, own_motion_result
from moisst_ns.stages.camera.own_tracks import TRACKS, fit_own_tracks, weak_by_motion
from moisst_ns.stages.camera.photometric import CameraFrames, Registration
from moisst_ns.stages.lidar.lidar_placement import place_again, place_lidars, trajectory_turn
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, PARAMETERS, UNITS

START = FeatureStartConfig()  # the feature start's settings


def _world(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, source: str, log: Callable[[str], None]) -> Float[np.ndarray, "num 3"]:
    """The map the cameras are registered against (``map_source``): the LiDARs' scans at ``calibration``, or the
    reference camera's features triangulated from its poses; world frame, metres."""
    if source == "lidar":
        return lidar_map(rig, calibration, config.map_voxel, config.min_range, log)
    return feature_map(rig, calibration, FeatureMapConfig(voxel=config.map_voxel), log)


def _fit_again(rig: Rig, world: Optional[np.ndarray], calibration: Calibration, config: CameraRegistrationConfig, source: str,
               problems: Dict[str, Registration], results: Dict[str, CameraResult], reference: Optional[CameraFrames],
               own: Dict[str, OwnMatches]) -> Dict[str, Optional[Tuple[np.ndarray, float]]]:
    """Every camera of ``problems`` fitted again from its estimate on ``rig`` and ``world`` (None: the map ``source``
    rebuilt on ``rig``): at the finest level, as ``_descend`` does there, or by its own motion where it was placed so
    (``own_motion.fit_own_motion`` at the fine radius, ``own_tracks.fit_own_tracks``'s track solves); None where it
    cannot be."""
    thetas = {n: r.correction if n not in own else  # PARAMETERS order -> the solver's
              np.asarray(parameter_difference(r.prior, r.prior_offset, r.estimate, r.time_offset))[list(JACOBIAN_ORDER)] for n, r in results.items()}
    try:
        world = _world(rig, calibration, config, source, lambda _: None) if world is None else world
    except NoMapError:
        return {n: None for n in problems}
    traj, poses = ReferenceTrajectory.of(rig), {}
    surface = MapSurface.of(world, OWN.normal_radius) if own and source == "lidar" else None
    for name, problem in problems.items():
        if name in own:  # refitted by its own motion, from its estimate
            prior = (results[name].prior, results[name].prior_offset)
            again = (fit_own_motion(traj, own[name], surface, *prior, OWN, lambda _: None, name, thetas[name]) if surface is not None else
                     fit_own_tracks(traj, own[name], float(rig.sensors[name].intrinsics["fl_x"]), *prior, TRACKS, lambda _: None, name, thetas[name]))
            poses[name] = None if again is None else _corrected(results[name].prior, results[name].prior_offset, again.theta)
            continue
        settings = replace(config, estimate_readout=len(thetas[name]) > 7)  # as the result was fitted (readout refit: without)
        again = Registration(traj, world, problem.camera, reference, calibration, settings)
        try:
            theta = _descend(again, settings, lambda _: None, thetas[name], [min(problem.camera.levels)])[0]
        except NoOverlapError:
            poses[name] = None
            continue
        poses[name] = _corrected(problem.model.prior.numpy(), problem.model.prior_offset, theta)
    return poses


def _with_part(results: Dict[str, CameraResult], moved: Dict[str, np.ndarray], field: str, what: str, log: Callable[[str], None]) -> Dict[str, CameraResult]:
    """``results`` with ``moved`` (per camera, ``PARAMETERS`` order) as their sigma's part ``field`` (solver order):
    ``sigma`` at least it, per parameter."""
    out = {}
    for name, r in results.items():
        part = np.zeros(7)
        part[list(JACOBIAN_ORDER)] = moved[name]  # PARAMETERS order -> the solver's
        log(f"[camera-registration] {name}: {what} move it by " + ", ".join(f"{p} {v * u:.3g} {n}" for p, v, (u, n) in zip(PARAMETERS, moved[name], UNITS)))
        out[name] = replace(r, sigma=np.fmax(np.asarray(r.sigma, dtype=np.float64), part).tolist(), **{field: part.tolist()})
    return out


def trajectory_part(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, source: str, problems: Dict[str, Registration],
                    results: Dict[str, CameraResult], reference: Optional[CameraFrames], log: Callable[[str], None],
                    own: Optional[Dict[str, OwnMatches]] = None) -> Dict[str, CameraResult]:
    """``results`` with the trajectory part of their sigma: what the errors rig.json states of the trajectory put into
    each camera (``trajectory_noise.trajectory_spread``: ``config.trajectory_draws`` draws; on each the map is rebuilt and
    every camera fitted again from its estimate, ``_fit_again``). The estimates do not change. The map (LiDAR scans or
    triangulated features) and a camera's own partners are both placed by the trajectory,
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
        own: the matches of the cameras placed by their own motion (``own_motion.own_matches``), refitted so.

    Returns:
        The results with ``sigma`` at least the part, per parameter, and ``sigma_trajectory`` (solver order).
    """
    begun = time.perf_counter()
    fit = lambda drawn: _fit_again(drawn, None, calibration, config, source, problems, results, reference, own or {})
    spread = trajectory_spread(fit, rig, {n: (r.estimate, r.time_offset) for n, r in results.items()}, config.trajectory_draws)
    return _with_part(results, spread, "sigma_trajectory", f"the trajectory's stated errors ({config.trajectory_draws} draws, "
                      f"{time.perf_counter() - begun:.0f} s, RMS)", log)


def map_part(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, problems: Dict[str, Registration],
             results: Dict[str, CameraResult], reference: Optional[CameraFrames], log: Callable[[str], None]) -> Dict[str, CameraResult]:
    """``results`` with the map part of their sigma where the map is the reference camera's features: each camera
    fitted again from its estimate (``_fit_again``) on the features a third frame confirms (``FeatureMapConfig.confirmed``).
    A car driving beside the reference camera triangulates in its pairs of frames at a wrong depth and pulls the cameras
    registered on it; the points it leaves the map with are the ones a third frame does not see where their pair put
    them. The estimates do not change (the confirmed map holds fewer static points too: docs/uncertainty.md).

    Returns:
        The results with ``sigma`` at least the part, per parameter, and ``sigma_map`` (solver order).
    """
    begun = time.perf_counter()
    try:
        world = feature_map(rig, calibration, FeatureMapConfig(voxel=config.map_voxel, confirmed=True), lambda _: None)
    except NoMapError as err:
        log(f"[camera-registration] the confirmed features: {err}; no map part")
        return results
    fitted = _fit_again(rig, world, calibration, config, "features", problems, results, reference, {})
    moved = {n: np.full(7, np.nan) if fitted[n] is None else np.abs(parameter_difference(r.estimate, r.time_offset, *fitted[n]))
             for n, r in results.items()}
    return _with_part(results, moved, "sigma_map", f"the map of confirmed features ({time.perf_counter() - begun:.0f} s)", log)


def camera_sensors(rig: Rig) -> List[str]:
    """The rig's non-reference cameras (the ones this stage registers)."""
    return [n for n, s in rig.sensors.items() if s.type == "camera" and n != rig.reference_sensor]


def register_cameras(rig: Rig, calibration: Calibration, config: CameraRegistrationConfig, sensors: Optional[Sequence[str]] = None,
                     log: Callable[[str], None] = print, lidar_undetermined: Optional[Dict[str, Sequence[str]]] = None,
                     lidar_sigma: Optional[Dict[str, Sequence[float]]] = None,
                     warm: Optional[Dict[str, Float[np.ndarray, "p"]]] = None) -> CameraStageResult:
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
        warm: per camera, its corrections to the prior (solver order) from a registration on the trajectory before it
            was carried: the finest two levels descend from there alone (no feature start, no other basin).

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
    own: Dict[str, OwnMatches] = {}  # the matches of those fitted so
    if floor is not None:
        log(f"[camera-registration] {reference_name}'s own photometric cost (its frames against each other): {floor:.4f}")
    for name in cameras:
        if name in results:
            continue
        problem = problems[name] = Registration(traj, world, CameraFrames.of(rig, name, factors), reference, calibration, config)
        initial, first = None, (warm or {}).get(name)
        if reference is not None and config.feature_start and first is None:
            initial = feature_start(traj, world, problem.camera, reference, np.asarray(calibration.T_ref_sensor[reference_name], dtype=np.float64),
                                    float(calibration.time_offset[reference_name]), problem.model.prior.numpy(), problem.model.prior_offset,
                                    rig.sensors[name].intrinsics, bounds(config), START, log)
            if initial.theta is None:
                log(f"[camera-registration] {name}: {initial.note}")
        own_motion = config.own_motion and config.estimate_extrinsic and config.estimate_time_offset
        if source == "features" and initial is not None and initial.theta is None:  # no photometric fit can place it
            lost = f"its start on {reference_name}'s features failed" if initial.matches >= START.min_inliers * START.min_frames else f"it shares no view with {reference_name}"
            why = (f"{lost} ({initial.note}) and {why_source or 'the rig has no LiDAR'}: fitted to "
                   f"{reference_name}'s triangulated features alone, it inherits their errors, which none of its sigma parts sees")
            results[name] = replace(_prior_kept(name, calibration, why, rig), held_there=True)
            log(f"[camera-registration] {name}: {why}; " + ("placing it by its own tracks on the trajectory" if own_motion else "it keeps its prior, not fitted"))
            if own_motion:  # against the trajectory alone
                begun, own[name] = time.perf_counter(), own_matches(rig, name, OWN)
                fit = fit_own_tracks(traj, own[name], float(rig.sensors[name].intrinsics["fl_x"]), results[name].prior, results[name].prior_offset, TRACKS, log, name,
                                     halved=own_matches(rig, name, OWN, downscale=2))
                results[name] = own_motion_result(fit, results[name], config, log, begun, source)
                if not results[name].kept_prior:  # what its own motion cannot fix on this drive
                    results[name] = replace(results[name], weak=weak_by_motion(traj, own[name], results[name].prior, results[name].prior_offset, log, name))
        else:
            try:
                results[name] = register_camera(problem, config, log, floor, initial, first)
                if results[name].readout_note.startswith(UNDETERMINED):  # refitted with rig.json's readout, which it keeps
                    log(f"[camera-registration] {name}: {results[name].readout_note}; refitting with it")
                    again = Registration(traj, world, problem.camera, reference, calibration, config)
                    results[name] = replace(register_camera(again, replace(config, estimate_readout=False), log, floor, initial,
                                                            None if first is None else first[:7]),  # without the readout
                                            **{k: getattr(results[name], k) for k in ("readout_estimate", "readout_sigma", "readout_note")})
            except NoOverlapError as err:
                results[name] = _prior_kept(name, calibration, str(err), rig)
                log(f"[camera-registration] {name}: {err}; it keeps its prior here")
            if own_motion and source == "lidar" and results[name].kept_prior:  # on the map
                begun, surface, own[name] = time.perf_counter(), surface or MapSurface.of(world, OWN.normal_radius), own_matches(rig, name, OWN)
                fit = fit_own_motion(traj, own[name], surface, results[name].prior, results[name].prior_offset, OWN, log, name)
                results[name] = own_motion_result(fit, results[name], config, log, begun)
        r = results[name]
        out.T_ref_sensor[name], out.time_offset[name] = r.estimate, r.time_offset
    accepted = {n: p for n, p in problems.items() if not results[n].kept_prior}
    placed = {n: p for n, p in accepted.items() if n not in own}  # on the map
    if source == "features" and placed:
        results.update(map_part(rig, calibration, config, placed, {n: results[n] for n in placed}, reference, log))
    if config.trajectory_draws > 0 and rig.trajectory_accuracy.stated() and accepted:
        results.update(trajectory_part(rig, calibration, config, source, accepted, {n: results[n] for n in accepted}, reference, log,
                                       {n: m for n, m in own.items() if n in accepted}))
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
    first = {n: r.correction for n, r in result.cameras.items() if not r.kept_prior and n not in own and r.history}  # the turn is small: they start in their basin
    try:
        again = register_cameras(carried, start, config, sensors, log, lidar_undetermined, warm=first)
    except NoMapError as err:  # its features no longer triangulate
        log(f"[camera-registration] on the carried trajectory: {err}: the trajectory and the cameras as first registered")
        return result
    again.calibration.trajectory_T_reference = turn
    registered = [n for n in cameras if not again.cameras[n].kept_prior]
    return replace(again, lidars=place_again(carried, again.calibration, lidars, registered, log, {n: again.cameras[n].sigma for n in cameras}, scans))
