"""What the camera stage returns (``CameraResult`` per camera, ``CameraStageResult``), and the two ways a result is made without a fit:
the corrections applied to a prior (eq. 12) and a prior kept. No nerfstudio import."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import calibrated_extrinsic
from moisst_ns.stages.lidar.lidar_instant import InstantPlacement


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
    (``resolution_spread``), the convergence tail (``convergence_tail``), where rig.json states the trajectory's
    errors the trajectory part (``trajectory_part``) and on the reference camera's features the map part (``map_part``)."""
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
    sigma_map: List[float] = field(default_factory=list)
    """The map part of ``sigma`` (``camera_registration.map_part``; empty where the map is a LiDAR's or the camera was
    placed by its own motion), solver order."""
    weak: List[str] = field(default_factory=list)
    """Parameters (trust names, ``PARAMETERS``) its evidence cannot fix on this drive whatever its sigma says: for a
    camera placed by its own tracks, those the drive's motion does not separate (``own_tracks.weak_by_motion``)."""

    @property
    def correction(self) -> Float[np.ndarray, "p"]:
        """The photometric fit's corrections to the prior at its end (solver order: rad, m, s[, readout s])."""
        return np.asarray(self.history[-1]["correction"], dtype=np.float64)


def corrected(prior: np.ndarray, prior_offset: float, theta: np.ndarray) -> Tuple[np.ndarray, float]:
    """``prior`` and its offset with the corrections ``theta`` (rotation vector rad, lever arm m, delta s: eq. 12)."""
    pose = calibrated_extrinsic(torch.from_numpy(prior), torch.from_numpy(theta[:3]), torch.from_numpy(theta[3:6]))
    return pose.numpy(), prior_offset + float(theta[6])


def prior_kept(name: str, calibration: Calibration, why: str, rig: Optional[Rig] = None) -> CameraResult:
    """The result of a camera the stage does not fit: its prior, sigma inf, ``why`` as the note."""
    prior, offset = np.asarray(calibration.T_ref_sensor[name], dtype=np.float64), float(calibration.time_offset[name])
    readout = float(rig.sensors[name].readout_time) if rig is not None else 0.0
    return CameraResult(name, prior, offset, prior, offset, [float("inf")] * 7, float("nan"), float("nan"), True, note=why,
                        readout_prior=readout, readout_time=readout)


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
