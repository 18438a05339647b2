"""What a LiDAR takes from its placement at the same instants (``lidar_instant.place_lidar``): the parameters its
scans' motion did not determine or determined less precisely (``place_lidars``), the trajectory's turn from the
reference camera where the two disagree (``trajectory_turn``), and the placement again once the cameras are
registered on the carried trajectory (``place_again``). docs/method.md, "The LiDAR against the cameras at the same
instant" and "The trajectory's frame". No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Dict, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic
from moisst_ns.stages.lidar.lidar_instant import MIN_BASELINE, MIN_ROWS, InstantPlacement, place_lidar
from moisst_ns.stages.lidar.lidar_scans import ScanSet
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER


def place_lidars(rig: Rig, calibration: Calibration, cameras: Sequence[str], undetermined: Dict[str, Sequence[str]],
                 motion_sigma: Dict[str, Sequence[float]], log: Callable[[str], None] = print,
                 camera_sigma: Optional[Dict[str, Sequence[float]]] = None, scans: Optional[Dict[str, ScanSet]] = None) -> Dict[str, InstantPlacement]:
    """Every LiDAR whose scans' motion left parameters undetermined, against the registered ``cameras`` at the same
    instants; ``calibration`` takes, per LiDAR, the parameters its scans' motion did not determine, placed here or with
    a sigma below that stage's (its prior's where it held them: KITTI raw 0048's along-track lever arm, 10 cm against
    1 m; the depth edges' view of the LiDAR-first stage may have placed them: the two cameras' triangulation at one
    instant replaces that view, which is biased by its edges and, with few of them, can fall in a wrong minimum), those
    it determined less precisely (``motion_sigma``, ``PARAMETERS`` order), and every one placed here when one of them lies more than 3
    combined sigma from the motion's: the motion calibrates a LiDAR in the frame the trajectory is given in, the shared
    instant in the reference camera's, which defines the rig's, and such a difference says the two frames differ (KITTI
    raw 0048: the OXTS trajectory turned 0.67 / 0.45 deg from image_00); the placement then records that turn
    (``InstantPlacement.turn``), which the camera stage carries the trajectory by. Changes ``calibration`` in place.

    Args:
        rig: the dataset (its reference sensor a camera).
        calibration: the cameras registered, the LiDARs at the LiDAR-first estimate.
        cameras: the cameras registered (not kept at their priors).
        undetermined: per LiDAR, what its scans' motion did not determine (``LidarResult.motion_undetermined``).
        motion_sigma: per LiDAR, the LiDAR-first stage's sigma (an empty dict: only the undetermined are taken).
        log: where progress lines go.
        camera_sigma: per camera, its registration's sigma (``place_lidar``).
        scans: per LiDAR, its scans once read (filled here; ``place_again`` reads them from it too).

    Returns:
        Per LiDAR placed, the placement with ``taken`` set.
    """
    scans = {} if scans is None else scans
    out = {}
    for lidar, unknown in undetermined.items():
        if not unknown or not cameras:
            continue
        found = place_lidar(rig, calibration, lidar, _scans(rig, lidar, scans, log), cameras, log, camera_sigma)
        if found is None:
            log(f"[camera-registration] {lidar}: no pair of cameras {MIN_BASELINE} m apart puts {MIN_ROWS} points on its scans at the same "
                "instants: nothing placed")
            continue
        T = np.asarray(calibration.T_ref_sensor[lidar], dtype=np.float64)
        moved = np.asarray(parameter_difference(T, 0.0, found.estimate.matrix(), 0.0)[:6])
        motion, why = motion_sigma.get(lidar), {}
        apart = {p: abs(moved[i]) / np.hypot(found.sigma[i], motion[i]) for i, p in enumerate(PARAMETERS[:6])
                 if motion is not None and p in found.placed and p not in unknown}
        other_frame = max(apart.values(), default=0.0) > 3  # the trajectory's frame is not the reference camera's
        for i, p in enumerate(PARAMETERS[:6]):
            unit = 100.0 if i < 3 else float(np.rad2deg(1.0))
            if p in unknown and (p in found.placed or (motion is not None and found.sigma[i] < motion[i])):
                why[p] = "not determined by the motion" + ("" if p in found.placed else f": sigma {found.sigma[i] * unit:.3g} against its {motion[i] * unit:.3g}")
            elif p in apart and (other_frame or found.sigma[i] < motion[i]):
                why[p] = f"sigma {found.sigma[i] * unit:.3g} against the motion's {motion[i] * unit:.3g}, {apart[p]:.1f} sigma apart"
        found.taken = list(why)
        if other_frame:  # R_motion = turn @ R_placed, about each axis where the difference exceeds its sigma (applied, its
            # expected squared error, sigma^2, is then below the difference's, which leaving it makes)
            both = np.array([apart.get(p, 0.0) > 1 for p in PARAMETERS[3:6]], dtype=np.float64)
            found.turn = [float(v) for v in -T[:3, :3] @ (moved[3:6] * both)]
        _take(calibration, lidar, found)
        log(f"[camera-registration] {lidar}: takes from the shared instants {'; '.join(f'{p} ({w})' for p, w in why.items()) or 'nothing'} (cm, deg)")
        out[lidar] = found
    return out


def _scans(rig: Rig, lidar: str, read: Dict[str, ScanSet], log: Callable[[str], None]) -> ScanSet:
    """``lidar``'s scans (``lidar_scans.load_scans``), read once into ``read`` (they depend on the trajectory only
    through its time span, which carrying it does not change)."""
    from moisst_ns.stages.lidar.lidar_scans import LidarFirstConfig, load_scans

    if lidar not in read:
        read[lidar] = load_scans(rig, lidar, ReferenceTrajectory.of(rig), LidarFirstConfig(), log)
    return read[lidar]


def _take(calibration: Calibration, lidar: str, found: InstantPlacement) -> None:
    """``calibration``'s ``lidar`` takes the parameters ``found.taken`` from the placement (in place)."""
    T = np.asarray(calibration.T_ref_sensor[lidar], dtype=np.float64)
    moved = np.asarray(parameter_difference(T, 0.0, found.estimate.matrix(), 0.0)[:6])
    increment = np.zeros(7)
    for p in found.taken:
        i = PARAMETERS.index(p)
        increment[JACOBIAN_ORDER[i]] = moved[i]
    calibration.T_ref_sensor[lidar] = Extrinsic(T[:3, :3], T[:3, 3], float(calibration.time_offset[lidar])).updated(increment).matrix()


def place_again(rig: Rig, calibration: Calibration, placements: Dict[str, InstantPlacement], cameras: Sequence[str],
                log: Callable[[str], None] = print, camera_sigma: Optional[Dict[str, Sequence[float]]] = None,
                scans: Optional[Dict[str, ScanSet]] = None) -> Dict[str, InstantPlacement]:
    """The LiDARs of ``place_lidars`` placed once more at the same instants, against the cameras registered again on the
    trajectory carried to the reference camera (the cameras' rotation errors pass into the placement through the stereo
    geometry: KITTI raw 0048's Velodyne yaw -0.29 deg against the first registration's cameras, -0.11 against the
    carried ones); each takes the same parameters as the first time, the turn stays the first's. Changes
    ``calibration`` in place.

    Args:
        rig: the dataset, its trajectory carried (``Rig.carry_trajectory``).
        calibration: the cameras registered again, the LiDARs as the first placement left them.
        placements: ``place_lidars``' result.
        cameras: the cameras registered (not kept at their priors).
        log: where progress lines go.
        camera_sigma: per camera, its registration's sigma (``place_lidar``).
        scans: per LiDAR, its scans as ``place_lidars`` read them (read here where absent).

    Returns:
        Per LiDAR, the new placement (the first where nothing was taken or no pair places it now).
    """
    scans = {} if scans is None else scans
    out = dict(placements)
    for lidar, first in placements.items():
        if not first.taken or not cameras:
            continue
        found = place_lidar(rig, calibration, lidar, _scans(rig, lidar, scans, log), cameras, log, camera_sigma)
        if found is None:
            log(f"[camera-registration] {lidar}: against the cameras registered again, nothing placed: the first placement stands")
            continue
        out[lidar] = replace(found, taken=list(first.taken), turn=list(first.turn))
        _take(calibration, lidar, out[lidar])
        log(f"[camera-registration] {lidar}: takes {', '.join(first.taken)} again, against the cameras registered again")
    return out


def trajectory_turn(placements: Dict[str, InstantPlacement], log: Callable[[str], None] = print) -> Optional[np.ndarray]:
    """The reference sensor's pose in the frame the trajectory is given in, from the LiDARs whose motion and shared
    instants disagree (``InstantPlacement.turn``; their mean), or None when none does.

    Args:
        placements: ``place_lidars``' result.
        log: where the turn is reported.

    Returns:
        ``trajectory_T_reference``, 4x4 (a rotation), or None.
    """
    turns = [p.turn for p in placements.values() if p.turn]
    if not turns:
        return None
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.mean(turns, axis=0)).as_matrix()
    log(f"[camera-registration] the trajectory is turned {np.degrees(np.mean(turns, axis=0)).round(3).tolist()} deg (rotation vector) from the "
        f"reference sensor by {', '.join(n for n, p in placements.items() if p.turn)}'s motion against its shared instants: the cameras again on it carried there")
    return T
