"""End to end on a tiny synthetic rig: from the paper's perturbation, the calibration must get close to the truth.

The bounds are set from what a short CPU run can resolve at this size (96x72 pixels, 20 frames per sensor):
one pixel is ~0.75 deg, so rotation must come back from the 8.7 deg perturbation to about a pixel; time from 100 ms
to a few ms (the rig moves ~6 m/s, so 1 ms is 6 mm). They are well below the perturbation, so a calibration that
does not work fails them.
"""

import json

import pytest

from moisst_ns.cli.calibrate import CalibrateConfig, run_calibration
from moisst_ns.synth import SynthConfig, make_rig

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
    "cam_front_right": (30.0, 1.0, 10.0),
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
