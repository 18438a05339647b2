"""Step-valued schedules of a MOISST run: which fields are steps, and rescaling them to another run length.

``method_configs.moisst_trainer_config`` builds every schedule as a fraction of the run; ``ns-train moisst-lite
--max-num-iterations N`` and ``moisst-calibrate --max-num-iterations N`` keep that shape through
``rescale_schedules``. No nerfstudio import (works on the trainer config's attributes).
"""

from __future__ import annotations

MODEL_SCHEDULE_FIELDS = ("calibration_warmup_steps", "registration_steps", "depth_loss_start", "depth_loss_ramp_steps", "hash_weight_decay_steps")
"""Step-valued fields of ``MoisstModelConfig``."""
DATAMANAGER_SCHEDULE_FIELDS = ("reference_only_steps", "registration_steps", "lidar_start_step")
"""Step-valued fields of ``MoisstDataManagerConfig``."""


def rescale_schedules(trainer_config, built_for: int, steps: int) -> None:
    """Rescale, in place, every step-valued schedule of a moisst trainer config built for ``built_for`` steps to a
    run of ``steps``: the model's phases, the datamanager's phases and the optimisers' decay lengths.

    The model, datamanager and schedulers read these config objects at every step, so this works after set-up.
    ``moisst_trainer_config(method, steps)`` gives the same values (to rounding) directly.
    """
    ratio = steps / built_for

    def scaled(value: int) -> int:
        return int(round(value * ratio))

    model = trainer_config.pipeline.model
    datamanager = trainer_config.pipeline.datamanager
    for name in MODEL_SCHEDULE_FIELDS:
        setattr(model, name, scaled(getattr(model, name)))
    model.coarse_to_fine = tuple(scaled(v) for v in model.coarse_to_fine)
    for name in DATAMANAGER_SCHEDULE_FIELDS:
        setattr(datamanager, name, scaled(getattr(datamanager, name)))
    for settings in trainer_config.optimizers.values():
        scheduler = settings.get("scheduler")
        if scheduler is not None and hasattr(scheduler, "max_steps"):
            scheduler.max_steps = scaled(scheduler.max_steps)
            if getattr(scheduler, "warmup_steps", 0):
                scheduler.warmup_steps = scaled(scheduler.warmup_steps)
    model.schedule_steps = steps
