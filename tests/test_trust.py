"""Trust without ground truth (issue 14): drive observability, sigma of least squares, the calibration.json fields."""

from __future__ import annotations

import json

import numpy as np
import pytest
import roma
import torch

from moisst_ns.rig.format import Calibration, RigFormatError, load_calibration
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import SensorTrust, decide_verdict
from moisst_ns.stages.trust.observability import analyse_drive, drive_table
from moisst_ns.stages.trust.uncertainty_math import inherited_sigma, least_squares_sigma

DT = 0.1


def _trajectory(kind: str):
    """Constructed 10 s drives, 10 Hz, z-up world, the reference frame x forward."""
    t = np.arange(0, 10, DT)
    zero = 0 * t
    pitch = roll = zero
    if kind == "straight":
        x, y, yaw = 6.5 * t, zero, zero
    elif kind == "accelerating":
        x, y, yaw = 2 * t + 0.4 * t**2, zero, zero
    else:  # planar weaving turns, optionally pitching and rolling
        yaw = 0.3 * np.sin(2 * np.pi * t / 4)
        x, y = np.cumsum(6.5 * np.cos(yaw) * DT), np.cumsum(6.5 * np.sin(yaw) * DT)
        if kind == "pitch_roll":
            pitch, roll = 0.05 * np.sin(2 * np.pi * t / 1.7), 0.05 * np.sin(2 * np.pi * t / 2.3)
    rot = lambda a, b, c: roma.rotvec_to_rotmat(torch.tensor(np.stack([a, b, c], 1)))  # noqa: E731
    rotations = rot(zero, zero, yaw) @ rot(zero, pitch, zero) @ rot(roll, zero, zero)
    quats = roma.rotmat_to_unitquat(rotations).numpy()
    return ReferenceTrajectory.from_tum(t, np.stack([x, y, zero], 1), quats), t[:-1] + 0.05


EXTRINSIC = np.eye(4)
EXTRINSIC[:3, 3] = [0.5, -0.3, 0.2]


@pytest.mark.parametrize("kind, model, weak", [
    ("straight", "absolute", {"x", "time_offset"}),          # delta = along-track lever arm under a constant twist
    ("accelerating", "absolute", set()),                     # the speed changes: delta separates
    ("turns", "absolute", set()),
    ("straight", "relative", {"x", "y", "z", "roll", "time_offset"}),  # hand-eye: pure translation shows nothing
    ("accelerating", "relative", {"x", "y", "z", "roll"}),
    ("turns", "relative", {"z"}),                            # a flat drive leaves the vertical lever arm weak
    ("pitch_roll", "relative", set()),
])
def test_drive_observability_on_constructed_drives(kind, model, weak):
    traj, times = _trajectory(kind)
    result = analyse_drive(traj, times, EXTRINSIC, "s", model)
    assert set(result.weak) == weak
    lines = drive_table([result])
    assert sum(line.startswith("WARNING: s: ") for line in lines) == len(weak)
    for d in result.dofs:
        assert bool(d.reason) == d.weak


def test_straight_drive_names_the_partner_and_the_reason():
    traj, times = _trajectory("straight")
    dofs = {d.name: d for d in analyse_drive(traj, times, EXTRINSIC, "s", "absolute").dofs}
    assert "x" in dofs["time_offset"].partners and "time_offset" in dofs["x"].partners
    assert "constant" in dofs["time_offset"].reason and dofs["time_offset"].separability < 0.01


def test_sigma_of_linear_least_squares_matches_the_closed_form():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(400, 3)) * [1.0, 0.1, 5.0]
    noise = 0.05
    exact = noise * np.sqrt(np.diag(np.linalg.inv(a.T @ a)))
    errors, sigmas = [], []
    for _ in range(300):
        y = a @ np.array([1.0, -2.0, 0.5]) + rng.normal(0, noise, 400)
        x = np.linalg.lstsq(a, y, rcond=None)[0]
        fit = least_squares_sigma(a, a @ x - y, np.arange(400) // 10)
        errors.append(x - [1.0, -2.0, 0.5])
        sigmas.append(fit.classical)
    np.testing.assert_allclose(np.mean(sigmas, axis=0), exact, rtol=0.05)
    np.testing.assert_allclose(np.std(errors, axis=0), exact, rtol=0.15)


def test_cluster_robust_sigma_covers_correlated_residuals():
    """40 clusters of 10 residuals sharing one offset each: the classical sigma is far too small, the reported
    (cluster-robust) one covers the spread of the estimates."""
    rng = np.random.default_rng(4)
    groups = np.arange(400) // 10
    a = np.stack([np.ones(400), rng.normal(size=400)], 1)
    a[:, 1] = np.repeat(rng.normal(size=40), 10)  # the regressor is constant within a cluster too
    errors, classical, reported = [], [], []
    for _ in range(300):
        y = a @ [0.0, 0.0] + np.repeat(rng.normal(0, 0.1, 40), 10) + rng.normal(0, 0.01, 400)
        x = np.linalg.lstsq(a, y, rcond=None)[0]
        fit = least_squares_sigma(a, a @ x - y, groups)
        errors.append(x)
        classical.append(fit.classical)
        reported.append(fit.sigma)
    spread = np.std(errors, axis=0)
    assert np.all(np.mean(classical, axis=0) < 0.5 * spread)
    np.testing.assert_allclose(np.mean(reported, axis=0), spread, rtol=0.2)


def test_unconstrained_parameter_gets_infinite_sigma():
    a = np.stack([np.ones(50), np.zeros(50)], 1)
    fit = least_squares_sigma(a, np.random.default_rng(0).normal(size=50), np.arange(50))
    assert np.isfinite(fit.sigma[0]) and np.isinf(fit.sigma[1])


def _pose(rotvec, translation):
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = roma.rotvec_to_rotmat(torch.tensor(rotvec, dtype=torch.float64)).numpy(), translation
    return pose


def test_inherited_sigma_is_the_camera_error_that_follows_a_misplaced_map():
    """One LiDAR parameter off by its sigma moves the map rigidly (ref_T_L' ref_T_L^-1); a camera following it ends
    off by exactly the inherited sigma in each of its parameters (to first order), whatever the two mounts are."""
    rng = np.random.default_rng(3)
    ref_T_lidar, ref_T_cam = _pose(rng.normal(0, 1, 3), rng.normal(0, 1, 3)), _pose(rng.normal(0, 1, 3), rng.normal(0, 1, 3))
    for k, step in enumerate([1e-4] * 3 + [1e-5] * 3):
        sigma = np.zeros(7)
        sigma[k] = step
        moved = ref_T_lidar.copy()
        if k < 3:
            moved[k, 3] += step
        else:
            moved[:3, :3] = ref_T_lidar[:3, :3] @ _pose(np.eye(3)[k - 3] * step, np.zeros(3))[:3, :3]
        followed = moved @ np.linalg.inv(ref_T_lidar) @ ref_T_cam
        error = np.concatenate([followed[:3, 3] - ref_T_cam[:3, 3],
                                roma.rotmat_to_rotvec(torch.from_numpy(ref_T_cam[:3, :3].T @ followed[:3, :3])).numpy(), [0.0]])
        np.testing.assert_allclose(inherited_sigma(ref_T_lidar, ref_T_cam, sigma), np.abs(error), rtol=1e-3, atol=1e-12)
    np.testing.assert_allclose(inherited_sigma(ref_T_lidar, ref_T_cam, [0, 0, 0, 0, 0, 0, 0.004]), [0] * 6 + [0.004])


def test_inherited_sigma_variances_add_and_infinity_reaches_only_what_it_moves():
    ref_T_lidar, ref_T_cam = np.eye(4), _pose([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])  # camera 1 m along the LiDAR's x
    out = inherited_sigma(ref_T_lidar, ref_T_cam, [0.03, 0.0, 0.0, 0.0, 0.0, 0.04, 0.0])
    np.testing.assert_allclose(out, [0.03, 0.04, 0.0, 0.0, 0.0, 0.04, 0.0], atol=1e-15)  # yaw 0.04 rad x 1 m -> y
    out = inherited_sigma(ref_T_lidar, ref_T_cam, [np.inf, 0.0, 0.0, 0.0, 0.0, 0.0, 0.002])
    assert np.isinf(out[0]) and np.all(np.isfinite(out[1:])) and out[6] == 0.002


def test_trust_fields_round_trip(tmp_path):
    calib = Calibration("cam0", {"cam0": np.eye(4), "cam1": np.eye(4)}, {"cam0": 0.0, "cam1": 0.01},
                        {"cam1": SensorTrust([0.01, 0.02, 0.03], [0.1, 0.2, 0.3], 0.001, "weakly observable", ["x", "time_offset"], "straight drive")})
    calib.write(tmp_path / "c.json")
    raw = json.loads((tmp_path / "c.json").read_text())
    assert raw["sensors"]["cam1"]["uncertainty"] == {"translation_m": [0.01, 0.02, 0.03], "rotation_deg": [0.1, 0.2, 0.3], "time_offset_s": 0.001}
    assert "verdict" not in raw["sensors"]["cam0"]
    back = load_calibration(tmp_path / "c.json")
    assert back.trust["cam1"] == calib.trust["cam1"] and "cam0" not in back.trust
    back.write(tmp_path / "d.json")
    assert (tmp_path / "d.json").read_text() == (tmp_path / "c.json").read_text()


def test_unconstrained_sigma_round_trips_as_null(tmp_path):
    calib = Calibration("a", {"a": np.eye(4), "b": np.eye(4)}, {"a": 0.0, "b": 0.0},
                        {"b": SensorTrust([np.inf, 0.1, 0.1], [0.1, 0.1, 0.1], np.inf, "weakly observable", ["x"], "r")})
    calib.write(tmp_path / "c.json")
    raw = json.loads((tmp_path / "c.json").read_text())
    assert raw["sensors"]["b"]["uncertainty"]["translation_m"][0] is None
    assert raw["sensors"]["b"]["uncertainty"]["time_offset_s"] is None
    assert load_calibration(tmp_path / "c.json").trust["b"].sigmas()[0] == np.inf


def test_old_files_load_and_bad_trust_fields_name_the_field(tmp_path):
    old = {"reference_sensor": "a", "sensors": {"a": {"T_ref_sensor": np.eye(4).tolist()}, "b": {"T_ref_sensor": np.eye(4).tolist(), "time_offset": 0.1}}}
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert load_calibration(tmp_path / "old.json").trust == {}
    for key, value, field in (("verdict", "fine", "verdict"), ("weak", ["up"], "weak"),
                              ("uncertainty", {"translation_m": [1, 2], "rotation_deg": [1, 2, 3], "time_offset_s": 0}, "uncertainty.translation_m"),
                              ("uncertainty", {"translation_m": [1, 2, 3], "rotation_deg": [1, 2, -3], "time_offset_s": 0}, "uncertainty.rotation_deg[2]"),
                              ("reason", "two\nlines", "reason")):
        bad = json.loads(json.dumps(old))
        bad["sensors"]["b"][key] = value
        (tmp_path / "bad.json").write_text(json.dumps(bad))
        with pytest.raises(RigFormatError) as err:
            load_calibration(tmp_path / "bad.json")
        assert err.value.field == f"sensors.b.{field}"
        assert "\n" not in str(err.value)


@pytest.mark.parametrize("moving, loss_est, loss_prior, weak, hit, verdict, keep_prior", [
    (None, 0.01, 0.02, [], [], "converged", False),
    (None, 0.01, 0.02, ["z"], [], "weakly observable", False),
    ("2.0 cm", 0.01, 0.02, [], [], "not converged", True),   # still moving: the prior is kept

    (None, 0.02, 0.02, [], [], "not converged", True),     # no better than the prior: keep the prior
    (None, 0.03, 0.02, ["z"], [], "not converged", True),
    (None, 0.01, 0.02, [], ["time offset"], "not converged", True),  # at a bound: the estimate is arbitrary
    (None, None, None, [], [], "converged", False),          # no held-back loss (LiDAR-first sensor)
    (None, None, None, ["x"], [], "not converged", True),     # x unconstrained (sigma inf): the estimate is arbitrary
])
def test_verdict_rules(moving, loss_est, loss_prior, weak, hit, verdict, keep_prior):
    got, reason = decide_verdict(moving, loss_est, loss_prior, weak, hit, weak if keep_prior and loss_est is None else [])
    assert got == verdict
    assert reason.endswith(": the prior is kept") == keep_prior and "\n" not in reason


def test_a_blind_camera_keeps_its_prior_whatever_its_loss():
    """Camera registration's typical-error test said the view does not tell y and roll apart: even a lower held-back
    loss at the estimate does not make it converged; the prior is kept and the reason names the blind parameters."""
    got, reason = decide_verdict(None, 0.01, 0.02, [], [], [], ["y", "roll"])
    assert got == "not converged" and reason.endswith(": the prior is kept")
    assert "y, roll" in reason and "\n" not in reason
    assert decide_verdict(None, 0.01, 0.02, [], [], [], [])[0] == "converged"


def _write(path, dx=0.0, roll_deg=0.0, ddelta=0.0, sigma=None, verdict=None, weak=()):
    import roma as _roma

    pose = np.eye(4)
    pose[:3, :3] = _roma.rotvec_to_rotmat(torch.tensor([np.deg2rad(roll_deg), 0.0, 0.0])).numpy()
    pose[0, 3] = 0.5 + dx
    trust = {}
    if sigma is not None or verdict is not None:
        s = sigma or (None, None, None)
        trust["cam1"] = SensorTrust([s[0]] * 3 if s[0] is not None else None, [s[1]] * 3 if s[1] is not None else None, s[2],
                                    verdict, list(weak), "test")
    Calibration("cam0", {"cam0": np.eye(4), "cam1": pose}, {"cam0": 0.0, "cam1": 0.02 + ddelta}, trust).write(path)
    return path


def test_eval_two_estimates_in_sigma_units(tmp_path):
    from moisst_ns.cli.evaluate import EvaluateConfig, run_evaluate, sigma_table

    a = _write(tmp_path / "a.json", sigma=(0.01, 0.1, 0.001), verdict="converged")
    b = _write(tmp_path / "b.json", dx=0.03, roll_deg=0.3, ddelta=0.005, sigma=(0.01, 0.1, 0.001), verdict="converged")
    rows = sigma_table(a, b)
    assert rows["second_is_estimate"]
    units = rows["sensors"]["cam1"]["sigma_units"]
    np.testing.assert_allclose([units[0], units[3], units[6]], [0.03 / np.sqrt(2e-4), 0.3 / np.sqrt(0.02), 0.005 / np.sqrt(2e-6)], rtol=1e-6)
    assert units[1] == pytest.approx(0.0, abs=1e-9)
    text = run_evaluate(EvaluateConfig(calibration=a, ground_truth=b))
    assert "DISAGREE" in text and "sigma units" in text
    close = _write(tmp_path / "c.json", dx=0.01, sigma=(0.01, 0.1, 0.001), verdict="converged")
    assert "DISAGREE" not in run_evaluate(EvaluateConfig(calibration=a, ground_truth=close))


def test_eval_estimate_against_truth_adds_sigma_units(tmp_path):
    from moisst_ns.cli.evaluate import EvaluateConfig, run_evaluate

    est = _write(tmp_path / "est.json", dx=0.02, sigma=(0.01, 0.1, 0.001), verdict="converged")
    truth = _write(tmp_path / "truth.json")
    text = run_evaluate(EvaluateConfig(calibration=est, ground_truth=truth))
    assert "errors of" in text and "error of" in text and "+2 (2.0)" in text
    plain = _write(tmp_path / "plain.json", dx=0.02)
    assert "sigma units" not in run_evaluate(EvaluateConfig(calibration=plain, ground_truth=truth))


@pytest.mark.parametrize("verdict, code", [("converged", None), ("weakly observable", None), ("not converged", 3)])
def test_calibrate_exit_status_follows_the_verdicts(tmp_path, monkeypatch, verdict, code):
    import sys

    import moisst_ns.cli.calibrate as cli

    def fake_run(cfg):
        cfg.output_dir.mkdir(parents=True, exist_ok=True)
        _write(cfg.output_dir / "calibration.json", verdict=verdict)

    monkeypatch.setattr(cli, "_run_calibration", fake_run)
    monkeypatch.setattr(sys, "argv", ["moisst-calibrate", str(tmp_path / "data"), "--output-dir", str(tmp_path / "out")])
    if code is None:
        cli.main()
    else:
        with pytest.raises(SystemExit) as err:
            cli.main()
        assert err.value.code == code


def test_coverage_counts_errors_within_three_sigma_and_too_wide_sigmas(tmp_path):
    """The benchmark's calibration check of sigma (``bench.coverage``), exact on constructed estimates."""
    from moisst_ns.bench.coverage import coverage_markdown, coverage_summary, sensor_coverage

    truth = _write(tmp_path / "truth.json")
    tight = _write(tmp_path / "tight.json", dx=0.02, roll_deg=0.5, ddelta=0.005, sigma=(0.01, 0.1, 0.001), verdict="converged")
    wide = _write(tmp_path / "wide.json", dx=0.02, roll_deg=0.5, ddelta=0.005, sigma=(1.0, 10.0, 0.1), verdict="converged")
    row = sensor_coverage(tight, truth)["cam1"]
    assert row["error"] == pytest.approx([0.02, 0, 0, np.deg2rad(0.5), 0, 0, 0.005], abs=1e-9)
    assert row["sigma"][3] == pytest.approx(np.deg2rad(0.1))
    assert sensor_coverage(truth, truth) == {}  # no sigmas: nothing to judge
    s = coverage_summary({"tight": {"cam1": row}})
    assert (s["within_3sigma"], s["finite"]) == (1, 3)  # x within; roll and the time offset 5 sigma miss; zero errors: held
    assert sorted((m[2], round(m[3], 6)) for m in s["misses"]) == [("roll", 5.0), ("time_offset", 5.0)]
    assert s["too_wide"] == [] and s["largest_ratio"] == pytest.approx(0.01 / np.sqrt(0.02**2 / 3))
    s = coverage_summary({"wide": sensor_coverage(wide, truth)})
    assert (s["within_3sigma"], s["finite"]) == (3, 3)
    assert [(k, round(u, 2)) for _, _, k, u in s["too_wide"]] == [("translation", 86.6), ("rotation", 34.64), ("time offset", 20.0)]
    assert "3 of 3" in "\n".join(coverage_markdown(s))


def test_coverage_judges_weakly_observable_sensors_on_their_observable_kinds_and_lists_past_5_sigma(tmp_path):
    """Without a converged sensor the 10x rule is still judged on the kinds with no weak parameter of a weakly
    observable sensor, and its parameters beyond 5 sigma are listed; a sensor marked not converged is in neither."""
    from moisst_ns.bench.coverage import coverage_markdown, coverage_summary, sensor_coverage

    truth = _write(tmp_path / "truth.json")
    weak = _write(tmp_path / "weak.json", dx=0.02, roll_deg=0.5, ddelta=0.004, sigma=(0.001, 0.05, 0.001), verdict="weakly observable",
                  weak=("roll",))
    row = sensor_coverage(weak, truth)["cam1"]
    assert row["weak"] == ["roll"]
    s = coverage_summary({"weak": {"cam1": row}})
    assert s["converged_kinds"] == 0 and len(s["observable_ratios"]) == 2  # translation and time offset; rotation has roll
    assert s["observable_ratios"] == pytest.approx([0.001 / np.sqrt(0.02**2 / 3), 0.25])
    assert [(m[2], round(m[3], 6)) for m in s["past_5sigma"]] == [("x", 20.0), ("roll", 10.0)]
    assert "beyond 5 sigma of a sensor not marked not converged: 2" in "\n".join(coverage_markdown(s))
    gone = _write(tmp_path / "gone.json", dx=0.02, roll_deg=0.5, ddelta=0.004, sigma=(0.001, 0.05, 0.001), verdict="not converged")
    s = coverage_summary({"gone": sensor_coverage(gone, truth)})
    assert s["observable_ratios"] == [] and s["past_5sigma"] == [] and len(s["misses"]) == 3


def test_verdict_of_a_fit_whose_held_parameters_disagree():
    """A fit whose held parameters disagree with the data is not converged and gives way to its prior (the free
    parameters absorbed the held error), before the weak and bound checks; without it the same fit is converged."""
    from moisst_ns.rig.trust import decide_verdict

    reason = "held at its prior, time_offset disagree with the scans"
    assert decide_verdict(None, None, None, ["z"], ["x"], held=reason) == ("not converged", f"{reason}: the prior is kept")
    assert decide_verdict(None, None, None, [], [])[0] == "converged"
