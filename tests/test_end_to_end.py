"""End to end on a tiny synthetic rig (96x72 pixels, 20 frames per sensor, 3 cameras + LiDAR, 600 steps).

From the paper's perturbation (86.6 cm, 8.7 deg, 100 ms) the forward-right camera must come back to within
2.5 deg (about 3 pixels at this size), 60 ms and 80 cm. These bounds are what the current moisst-lite schedule
reaches in ~4.5 minutes on 2 cores (measured, deterministic for this seed: 71.5 cm, 1.94 deg, 40.6 ms, still
falling when the run ends); they are a regression guard
that a broken calibration (no gradient to the rig, wrong ray convention, wrong sign of delta) fails, NOT the
issue's accuracy target (1 cm / 0.05 deg / 0.5 ms), which this schedule does not reach. The side camera and the
LiDAR are not asserted: they do not converge yet (see docs/method.md, Known limits).
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


E2E_STEPS = 600
BOUNDS = {
    # sensor: (translation cm, rotation deg, time ms)
    "cam_front_right": (80.0, 2.5, 60.0),
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
