"""Schedules keep their shape when the run length changes, also under ``ns-train ... --max-num-iterations N``."""


import pytest

from moisst_ns.method_configs import moisst_trainer_config
from moisst_ns.schedules import DATAMANAGER_SCHEDULE_FIELDS, MODEL_SCHEDULE_FIELDS, rescale_schedules
from moisst_ns.datasets.synth import SynthConfig, make_rig


def schedule(config) -> dict:
    model, datamanager = config.pipeline.model, config.pipeline.datamanager
    out = {f"model.{n}": getattr(model, n) for n in MODEL_SCHEDULE_FIELDS}
    out.update({f"model.coarse_to_fine.{i}": v for i, v in enumerate(model.coarse_to_fine)})
    out.update({f"datamanager.{n}": getattr(datamanager, n) for n in DATAMANAGER_SCHEDULE_FIELDS})
    out.update({f"{k}.max_steps": v["scheduler"].max_steps for k, v in config.optimizers.items()})
    return out


@pytest.mark.parametrize("method", ["moisst-lite", "moisst"])
@pytest.mark.parametrize("steps", [40, 300, 777, 4000])
def test_rescale_matches_building_for_that_length(method, steps):
    config = moisst_trainer_config(method)
    built_for = config.max_num_iterations
    rescale_schedules(config, built_for, steps)
    direct = moisst_trainer_config(method, steps)
    assert schedule(config) == schedule(direct)  # one rounding: ns-train --max-num-iterations N == moisst-calibrate's
    assert config.pipeline.model.schedule_steps == direct.pipeline.model.schedule_steps == steps
    if method == "moisst-lite":  # the phases are really there (not all zero)
        want = schedule(direct)
        assert want["model.registration_steps"] == round(0.7 * steps) and want["datamanager.reference_only_steps"] == round(0.2 * steps)


def test_ns_train_length_override_rescales_at_setup(tmp_path):
    """As ``ns-train moisst-lite --max-num-iterations 40`` does: the config built for 1500 steps runs 40."""
    rig = tmp_path / "rig"
    make_rig(SynthConfig(out=rig, width=48, height=36, frames=6, perturb="paper", lidar=False))
    config = moisst_trainer_config("moisst-lite")
    assert config.max_num_iterations == 1500 and config.pipeline.model.registration_steps == 1050
    config.max_num_iterations = 40
    config.pipeline.datamanager.data = rig
    config.pipeline.datamanager.dataparser.data = rig
    config.output_dir, config.experiment_name, config.timestamp, config.vis = tmp_path / "out", ".", "run", "tensorboard"
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    assert model.config.registration_steps == 28 and model.config.calibration_warmup_steps == 8
    assert model.config.coarse_to_fine == (8, 28)
    assert trainer.pipeline.datamanager.config.reference_only_steps == 8
    # every rate reaches its final 1 % at step 40, not at step 1500
    scheduler = trainer.optimizers.schedulers["calibration_translation"]
    assert scheduler.lr_lambdas[0](40) == pytest.approx(1e-2)
    assert scheduler.lr_lambdas[0](20) == pytest.approx(1e-1)
