"""Settings of the camera-registration stage (``moisst_ns.stages.camera.camera_registration``, which re-exports them).
No nerfstudio import."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class CameraRegistrationConfig:
    """Settings of the camera-registration stage (image sizes and drives enter only through the pyramid rule)."""

    map_voxel: float = 0.05
    """Voxel size of the LiDAR map, metres."""
    min_range: float = 2.0
    """LiDAR points closer than this to their sensor are left out of the map (the vehicle itself), metres."""
    max_depth: float = 40.0
    """Map points farther than this from a camera are not used (a pixel covers too much there), metres."""
    points_per_frame: int = 600
    """Map points sampled per camera frame and outer iteration at full resolution (drawn with probability proportional
    to ``|grad I|`` at their projection); a level ``f`` times smaller samples ``f`` times fewer (it has ``f^2`` times
    fewer pixels)."""
    min_width: int = 40
    """Coarsest pyramid level: halve the images while they stay at least this many pixels wide."""
    outer_iterations: int = 3
    """At most this many outer iterations per coarser pyramid level (visibility, samples and partners re-chosen at the
    current estimate); a level ends earlier once an iteration moves the projections by less than ``stop_px``."""
    max_evaluations: int = 20
    """Residual evaluations per inner least-squares solve."""
    fine_iterations: int = 6
    """At most this many outer iterations at the finest pyramid level: each draws its pairs at the current estimate, and
    along the flat along-track / time-offset valley the estimate creeps towards the minimum over several (measured:
    docs/lab/2026-11-23-camera-registration.md, "The finest level")."""
    stop_px: float = 0.1
    """A level ends once an outer iteration moves the projections by less than this (RMS, that level's pixels)..."""
    fine_stop_px: float = 0.02
    """...the finest level once they move less than this (the creep above moves them 0.02-0.1 px per iteration)."""
    huber: float = 0.5
    """Huber scale of the residuals, in standard deviations of the image's grey level."""
    fine_points_per_frame: int = 5000
    """Map points sampled per camera frame at the finest pyramid level (0: ``points_per_frame``), there and in the
    split halves: the finest level's minimum moves with the sample far more than its formal sigma says (measured:
    docs/lab/2026-11-23-camera-registration.md, "The finest level")."""
    own_baseline: float = 1.5
    """A camera's own partner frame is the first at least this far (driving distance) from the frame, metres."""
    fine_baseline: float = 3.0
    """The same at the finest pyramid level (0: ``own_baseline``): more parallax sharpens the along-track terms
    (measured: docs/lab/2026-11-23-camera-registration.md, "Farther own partners")."""
    shared_view_share: float = 0.5
    """When at least this share of a camera's sampled map points find their reference partner in the reference frame
    nearest in time (the camera shares the reference camera's view at the same instant), a point with a reference
    partner takes no own partner: pairs of one instant do not pass through the reference trajectory, whose noise,
    drift and turn the own pairs (frames metres apart) carry into the estimate (docs/lab/2026-11-27-reference-motion.md,
    2026-11-28). A camera under it (a side camera that sees the reference camera's view only over time) keeps its own
    partners for every point. Above 1: own partners for every point of every camera."""
    held_back_points: int = 300
    """Map points per frame of the held-back check (estimate vs prior), drawn afresh after the fit."""
    max_translation: float = 2.0
    """Bound on the translation correction per axis, metres."""
    max_rotation_deg: float = 30.0
    """Bound on the rotation correction per axis, degrees."""
    max_time_offset: float = 0.3
    """Bound on the time-offset correction, seconds."""
    estimate_extrinsic: bool = True
    """Estimate the extrinsic (else it stays at the prior)."""
    estimate_time_offset: bool = True
    """Estimate the time offset (else it stays at the prior)."""
    min_frames: int = 10
    """A camera with fewer frames keeps its prior here (the NeRF calibrates it): each half of the drive must hold
    enough frames for the split-half test (on a 6-frame 48x36 rig the fits ended worse than the priors)."""
    max_cost_ratio: float = 5.0
    """A fit whose final cost is more than this many times the reference camera's own cost (its frames paired with
    each other at their known poses: the scene's and images' own inconsistency) is a wrong minimum and keeps the prior
    (measured ratios: docs/lab/2026-11-23-camera-registration.md, "Cameras against the LiDAR map")."""
    max_split_half: float = 2.0
    """A fit whose halves lie apart (half their difference, ``split_half_spread``) by more than this many typical prior
    errors (10 cm, 1 deg, 10 ms) on any parameter is not determined by the data and keeps the prior (measured: docs/lab/2026-11-23-camera-registration.md)."""
    min_significance: float = 1.0
    """A fit whose held-back cost rises by less than this many times three standard errors over the frames when one
    correction is stepped by a typical prior error (10 cm, 1 deg, 10 ms; ``typical_error_significance``) keeps the
    prior, and ``moisst-calibrate`` holds it there (the NeRF sees the same view): that view does not determine the
    correction, so wherever the fit ended along it is not the data's answer (measured: docs/lab/2026-11-23-camera-registration.md,
    "The typical-error test"). 0 switches the test off."""
    feature_start: bool = True
    """Start each camera from its pose fitted to SIFT features matched to the reference camera's map-anchored
    keypoints (``feature_start``) where that fit holds, else from its prior (a side camera the reference never
    overlaps); the photometric basin is about a pixel at the coarsest level, the features' is the whole image."""
    own_motion: bool = True
    """A camera that keeps its prior against a LiDAR map (a side camera: its own pairs hardly see its lever arm) is
    placed by its own motion instead: its own matches, triangulated from the trajectory's poses, against the map's
    surfaces (``own_motion``), guarded by the held-back loss and the split halves. Off: it keeps its prior."""
    split_half: bool = True
    """Also solve the two halves of the drive and report sigma as at least their spread (``split_half_spread``; two
    more solves at full resolution)."""
    trajectory_draws: int = 6
    """Where rig.json states the trajectory's errors (``trajectory_accuracy``), each accepted camera is fitted again at
    the finest level from its estimate on this many draws of them, the map rebuilt on each (``camera_registration.trajectory_part``),
    and its sigma is at least their RMS effect (0: off). The map and the camera's partners are placed by the same noisy
    trajectory, which none of the other parts sees."""
    seed: int = 0
    """Seed of the point samples."""
    estimate_readout: bool = False
    """Also estimate each camera's rolling-shutter readout time (an 8th correction, bounded to ``[0, frame period)``,
    starting from rig.json's ``readout_time``, fitted at the two finest pyramid levels); reported in
    ``CameraResult.readout_estimate`` and ``readout_sigma``. Without it the readout is rig.json's (0: a global
    shutter), and every projection uses it either way."""
    max_readout_sigma: float = 0.003
    """An estimated readout time whose sigma exceeds this (seconds) is not determined by the drive: the camera keeps
    rig.json's readout and is registered again with it (``CameraResult.readout_note`` says so)."""
