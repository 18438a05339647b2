"""End to end on a tiny synthetic rig (96x72 pixels, 20 frames per sensor, 3 cameras + LiDAR, 100 steps).

``moisst-calibrate``'s default path: the LiDAR-first stage, the cameras registered against the LiDAR map, then the
NeRF holding them (its steps train only the scene and move no parameter: a short run tests the same path). From the
paper's perturbation (86.6 cm, 8.7 deg, 100 ms) the forward-right camera must come back to within 10 cm / 0.3 deg / 10
ms (measured 5.3-5.6 cm / 0.11 deg / 3.3-5.5 ms: at 96x72 a pixel is 0.8 deg; the 320x240 rig reaches 0.2 cm / 0.015
deg / 0.12 ms, docs/method.md), the LiDAR to 1 cm / 0.01 deg / 0.1 ms. The side camera's view at this size does not
tell a typical prior error apart on its lever arm across the track and its roll (camera registration's typical-error
test): it must keep its prior exactly, held through the NeRF, and say so (``not converged``). Before that test it was
accepted 13-40 cm off, and a NeRF left free took it to 86 cm / 9.5 deg / 159 ms. A regression guard that a broken
stage (wrong sign of delta, wrong pixel convention, no held camera) fails, not the issue's accuracy target.
"""

import json

import pytest

from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
from moisst_ns.datasets.synth import SynthConfig, make_rig

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    make_rig(SynthConfig(out=root / "rig", width=96, height=72, frames=20, seed=1, perturb="paper"))
    run_calibration(CalibrateConfig(dataset=root / "rig", output_dir=root / "out", max_num_iterations=E2E_STEPS, seed=0, threads=2))
    return json.loads((root / "out" / "summary.json").read_text())


E2E_STEPS = 100
BOUNDS = {
    # sensor: (translation cm, rotation deg, time ms)
    "cam_front_right": (10.0, 0.3, 10.0),
    "lidar": (1.0, 0.01, 0.1),
}


def test_priors_start_at_the_paper_perturbation(calibrated):
    for name, err in calibrated["errors_before"].items():
        assert err["translation_cm"] == pytest.approx(86.6, abs=0.1)
        assert err["time_ms"] == pytest.approx(100.0, abs=0.01)


@pytest.mark.parametrize("sensor", sorted(BOUNDS))
def test_errors_shrink_below_bounds(calibrated, sensor):
    after = calibrated["errors_after"][sensor]
    trans, rot, time_ms = BOUNDS[sensor]
    assert after["rotation_deg"] < rot, after
    assert after["time_ms"] < time_ms, after
    assert after["translation_cm"] < trans, after


def test_the_blind_side_camera_keeps_its_prior_and_says_so(calibrated):
    assert calibrated["errors_final"]["cam_left"] == calibrated["errors_before"]["cam_left"]
    verdict = calibrated["verdicts"]["cam_left"]
    assert verdict["verdict"] == "not converged" and not verdict["trust"]
    assert verdict["reason"].startswith("its view does not tell a typical prior error") and "the prior is kept" in verdict["reason"]
    assert calibrated["trust"]["sensors"]["cam_left"]["kept_prior"]
