"""``moisst-bench --speed``: seconds per training step of each MOISST preset against stock nerfacto.

Each trainer is set up for the preset's full run (1500 steps for ``moisst-lite``, 30000 for ``moisst``), so the
step measured is the one a real run takes (its compile decision, schedules and phases), then trained from
``start_fraction`` of the run (mid-registration for ``moisst-lite``): ``warmup_steps`` untimed (a graph met for the
first time compiles there), then ``timed_steps`` timed. Stock nerfacto (``moisst_ns.bench.baseline``: nerfstudio's
own model and data manager, no pose optimiser) gets the preset's field, sampling and camera rays per step. The
MOISST preset runs cameras only (``lidar_rays_per_batch = 0``), then with the preset's LiDAR rays added.

Set-up times (data loading, and compiling the hash grids) are reported apart from the per-step times.
"""

from __future__ import annotations

import json
import resource
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Literal, Tuple

PRESETS: Tuple[str, ...] = ("moisst-lite", "moisst")


@dataclass(frozen=True)
class SpeedPlan:
    """How many steps each measurement takes (2 cores: ``moisst`` steps are ~20x ``moisst-lite``'s)."""

    warmup_steps: int
    """Untimed steps after set-up."""
    timed_steps: int
    """Timed steps; their mean is the figure."""
    start_fraction: float = 0.3
    """Fraction of the run the measured steps start at (``moisst-lite``: inside the registration phase)."""


PLANS: Dict[str, SpeedPlan] = {"moisst-lite": SpeedPlan(warmup_steps=5, timed_steps=40), "moisst": SpeedPlan(warmup_steps=2, timed_steps=3)}


def speed_rig(out: Path) -> Path:
    """The rig the speed table runs on: ``moisst-synth`` street seed 0, 96x72, 20 frames, 3 cameras + LiDAR,
    the paper's perturbation (rays per step, not image size, set the cost of a step). Generated once.

    Args:
        out: the benchmark's output folder (the rig goes to ``out/rigs/speed``).

    Returns:
        The rig folder.
    """
    from moisst_ns.datasets.synth import SynthConfig, make_rig

    folder = out / "rigs" / "speed"
    if not (folder / "rig.json").is_file():
        shutil.rmtree(folder, ignore_errors=True)
        make_rig(SynthConfig(out=folder, seed=0, layout="street", width=96, height=72, frames=20, perturb="paper"))
    return folder


def _trainer(kind: Literal["moisst", "nerfacto"], preset: str, rig: Path, out: Path, lidar: bool):
    """A set-up nerfstudio trainer of the preset's full run; returns (trainer, steps of the run, set-up seconds)."""
    from moisst_ns.bench.baseline import nerfacto_trainer_config
    from moisst_ns.method_configs import DEFAULT_ITERATIONS
    from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

    from moisst_ns.calibrate import CalibrateConfig, calibrate_trainer_config, place_run
    from moisst_ns.stage_run import set_up_trainer

    steps = DEFAULT_ITERATIONS[preset]
    shutil.rmtree(out, ignore_errors=True)
    if kind == "moisst":
        cfg = CalibrateConfig(dataset=rig, output_dir=out, method=preset, lidar_rays=None if lidar else 0, report=False, seed=0)
        config = calibrate_trainer_config(cfg, rig, out, steps)
        config.pipeline = VanillaPipelineConfig(datamanager=config.pipeline.datamanager, model=config.pipeline.model)  # the NeRF's steps alone
    else:
        config = place_run(nerfacto_trainer_config(preset, steps, "off"), rig, out, "run", 0)
    config.vis = "tensorboard"
    started = time.perf_counter()
    trainer = set_up_trainer(config, 0)
    return trainer, steps, time.perf_counter() - started


def step_seconds(trainer, steps: int, plan: SpeedPlan) -> float:
    """Mean wall seconds of ``plan.timed_steps`` training steps from ``plan.start_fraction`` of the run.

    Args:
        trainer: a set-up nerfstudio trainer.
        steps: the run's length.
        plan: warm-up and timed steps.

    Returns:
        Seconds per step.
    """
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    start = int(plan.start_fraction * steps)
    trainer.pipeline.train()
    for i, step in enumerate(range(start, start + plan.warmup_steps + plan.timed_steps)):
        if i == plan.warmup_steps:
            started = time.perf_counter()
        for callback in trainer.callbacks:  # as nerfstudio's Trainer.train: callbacks before and after each step
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        trainer.train_iteration(step)
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    return (time.perf_counter() - started) / plan.timed_steps


def run_speed(out: Path, machine: dict) -> dict:
    """Measure the speed table and write ``out/speed.json``.

    Args:
        out: output folder.
        machine: what it runs on (``moisst_ns.bench.run.machine``), recorded in the JSON.

    Returns:
        ``{"presets": {preset: {"s_per_step", "nerfacto_s_per_step", "ratio", "s_per_step_lidar", "ratio_lidar",
        "setup_s", "steps_timed"}}, "machine", "peak_rss_gb", "total_s"}``.
    """
    import torch

    started = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    rig = speed_rig(out)
    result: dict = {"presets": {}, "machine": machine, "rig": str(rig), "torch_threads": torch.get_num_threads()}
    for preset in PRESETS:
        plan = PLANS[preset]
        seconds, setup_s = {}, {}
        for name, kind, lidar in (("nerfacto", "nerfacto", False), ("cameras", "moisst", False), ("lidar", "moisst", True)):
            print(f"[moisst-bench] speed: {preset}, {name}", flush=True)
            trainer, steps, setup_s[name] = _trainer(kind, preset, rig, out / "runs" / f"speed-{preset}-{name}", lidar)
            seconds[name] = step_seconds(trainer, steps, plan)
            del trainer
        row = result["presets"][preset] = {
            "s_per_step": seconds["cameras"], "nerfacto_s_per_step": seconds["nerfacto"], "ratio": seconds["cameras"] / seconds["nerfacto"],
            "s_per_step_lidar": seconds["lidar"], "ratio_lidar": seconds["lidar"] / seconds["nerfacto"], "setup_s": setup_s,
            "steps_timed": plan.timed_steps}
        print(f"[moisst-bench] {preset}: {row['s_per_step']:.3f} s/step (nerfacto {row['nerfacto_s_per_step']:.3f}, "
              f"{row['ratio']:.2f}x), with LiDAR {row['s_per_step_lidar']:.3f} s/step ({row['ratio_lidar']:.2f}x)", flush=True)
    result["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    result["total_s"] = time.perf_counter() - started
    (out / "speed.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def speed_markdown(result: dict) -> str:
    """The speed table of ``run_speed``'s result as Markdown."""
    lines = ["| preset | MOISST s/step (cameras) | nerfacto s/step (same field, same rays) | ratio | MOISST s/step with LiDAR | ratio with LiDAR | set-up s (nerfacto / cameras / LiDAR) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for preset, r in result["presets"].items():
        s = r["setup_s"]
        lines.append(f"| {preset} ({r['steps_timed']} steps timed) | {r['s_per_step']:.3f} | {r['nerfacto_s_per_step']:.3f} | {r['ratio']:.2f} | "
                     f"{r['s_per_step_lidar']:.3f} | {r['ratio_lidar']:.2f} | {s['nerfacto']:.0f} / {s['cameras']:.0f} / {s['lidar']:.0f} |")
    return "\n".join(lines)


SPEED_BLOCK = ("<!-- speed -->", "<!-- /speed -->")
"""Markers of docs/benchmarks.md's speed section (``--speed --docs`` writes its table there; ``--docs`` keeps it)."""


def keep_speed_block(old: str, new: str) -> str:
    """``new`` (a rewritten benchmarks page) with ``old``'s speed section carried over under its title line."""
    start, end = old.find(SPEED_BLOCK[0]), old.find(SPEED_BLOCK[1])
    if start < 0 or end < 0:
        return new
    title_end = new.find("\n") + 1
    return new[:title_end] + "\n" + old[start:end + len(SPEED_BLOCK[1])] + "\n" + new[title_end:]


def with_speed_table(page: str, table: str) -> str:
    """``page`` whose speed table (the first Markdown table inside the speed section) is ``table``; a page without
    a speed section gets one under its title line."""
    start, end = page.find(SPEED_BLOCK[0]), page.find(SPEED_BLOCK[1])
    if start < 0 or end < 0:
        title_end = page.find("\n") + 1
        return page[:title_end] + f"\n{SPEED_BLOCK[0]}\n## Speed\n\n{table}\n{SPEED_BLOCK[1]}\n" + page[title_end:]
    lines = page[start:end].split("\n")
    first = next((i for i, line in enumerate(lines) if line.startswith("| preset | MOISST s/step")), None)
    if first is None:
        lines.append(table + "\n")
    else:
        last = first
        while last + 1 < len(lines) and lines[last + 1].startswith("|"):
            last += 1
        lines[first:last + 1] = table.split("\n")
    return page[:start] + "\n".join(lines) + page[end:]
