"""Per-sensor verdicts (``moisst_ns.runs.verdict``): which sensors the run's last lines tell the user to trust."""

from __future__ import annotations

from moisst_ns.runs.verdict import sensor_verdicts, trust_lines

E = lambda t, r, m: {"translation_cm": t, "rotation_deg": r, "time_ms": m}  # noqa: E731
SENSORS = ["cam_right", "cam_left", "lidar"]


def summary(**extra):
    base = {"errors_before": {n: E(86.6, 8.7, 100.0) for n in SENSORS},
            "errors_after": {"cam_right": E(37.8, 0.69, 21.7), "cam_left": E(142.9, 7.65, 36.6), "lidar": E(0.01, 0.003, 0.0)}}
    base.update(extra)
    return base


def render(camera, residual, depth=10.0):
    return {"camera": camera, "median_depth_residual_m": residual, "median_lidar_depth_m": depth}


def test_worse_than_prior_and_still_moving_are_flags():
    v = sensor_verdicts(SENSORS, summary(still_moving={"cam_right": "std 3.00 cm, 0.100 deg, 1.00 ms"}), lidars=["lidar"])
    assert v["cam_left"]["flags"] == ["worse than its prior in translation (142.90 cm / 7.650 deg / 36.60 ms after, "
                                      "86.60 cm / 8.700 deg / 100.00 ms before)"]
    assert v["cam_right"]["flags"] == ["still moving (std 3.00 cm, 0.100 deg, 1.00 ms)"]
    assert v["lidar"]["trust"] and not v["cam_left"]["trust"] and not v["cam_right"]["trust"]
    assert v["lidar"]["errors_before"] == E(86.6, 8.7, 100.0) and v["lidar"]["errors_after"] == E(0.01, 0.003, 0.0)
    lines = trust_lines(v)
    assert lines[-1] == "Trust: lidar." and lines[0].startswith("Do not trust: cam_right (still moving")


def test_depth_mismatch_at_the_reference_blames_a_nerf_lidar_not_a_stage_lidar():
    renders = [render("cam_front", 24.1), render("cam_right", 0.2)]
    nerf = sensor_verdicts(SENSORS, summary(), renders=renders, lidars=["lidar"], reference="cam_front")
    assert nerf["lidar"]["flags"] == ["depth mismatch: median |rendered depth - LiDAR depth| = 24.10 m on cam_front's render (> 1.00 m)"]
    assert any(f.startswith("registered against an unreliable scene") for f in nerf["cam_right"]["flags"])
    staged = sensor_verdicts(SENSORS, summary(lidar_first={"lidar": {"weak": ["z"]}}), renders=renders, lidars=["lidar"], reference="cam_front")
    assert staged["lidar"]["trust"] and staged["lidar"]["weak"] == ["z"]
    assert "weakly observable from this drive: z" in staged["lidar"]["caveats"]


def test_depth_mismatch_at_the_reference_does_not_blame_a_camera_registered_against_the_lidar_map():
    renders = [render("cam_front", 24.1)]
    registration = {"cam_right": {"kept_prior": False}, "cam_left": {"kept_prior": True}}
    v = sensor_verdicts(SENSORS, summary(camera_registration=registration, lidar_first={"lidar": {"weak": []}}), renders=renders,
                        lidars=["lidar"], reference="cam_front")
    assert v["cam_right"]["caveats"] == ["the scene disagrees with the LiDAR (median |rendered depth - LiDAR depth| = 24.10 m on "
                                         "cam_front's render (> 1.00 m)); this camera was registered by the camera stage against its map, not against the scene"]
    assert v["cam_right"]["trust"]
    assert any(f.startswith("registered against an unreliable scene") for f in v["cam_left"]["flags"])  # kept its prior: the NeRF's


def test_depth_mismatch_at_another_camera_flags_that_camera_only():
    renders = [render("cam_front", 0.3), render("cam_right", 0.4), render("cam_left", 5.0, depth=20.0)]
    v = sensor_verdicts(SENSORS, {}, renders=renders, lidars=["lidar"], reference="cam_front")
    assert v["cam_left"]["flags"] == ["depth mismatch: median |rendered depth - LiDAR depth| = 5.00 m on cam_left's render (> 2.00 m)"]
    assert v["cam_right"]["trust"] and v["lidar"]["trust"]
    assert sensor_verdicts(SENSORS, {}, renders=renders, lidars=[], reference="cam_front")["cam_left"]["trust"]  # no LiDAR, no check


def test_optional_fields_of_calibration_json_are_shown_and_tolerated():
    calibration = {"sensors": {"cam_left": {"verdict": "not converged", "reason": "no overlap", "uncertainty": {"translation_cm": 40}},
                               "cam_right": {"verdict": "weakly observable", "weak": ["z"], "reason": "flat drive"},
                               "lidar": {"T_ref_sensor": [[1, 0, 0, 0]] * 4}}}
    v = sensor_verdicts(SENSORS, {}, calibration)
    assert v["cam_left"]["flags"] == ["not converged: no overlap"] and v["cam_left"]["uncertainty"] == {"translation_cm": 40}
    assert v["cam_right"]["trust"] and v["cam_right"]["caveats"] == ["weakly observable from this drive: z (flat drive)"]
    assert v["lidar"]["trust"] and "verdict" not in v["lidar"]
    assert sensor_verdicts(SENSORS, {}, {"sensors": "garbage"})["lidar"]["trust"]
    assert trust_lines(sensor_verdicts(["a"], {}, {"sensors": {"a": {"verdict": "not converged"}}})) == [
        "Do not trust: a (not converged).", "Trust: no sensor of this run."]
