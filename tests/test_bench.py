"""moisst-bench: scenario validation, aggregation (exact values) and a micro run through every table."""

import json

import numpy as np
import pytest

from moisst_ns.bench import REPO, BenchConfig, BenchError, load_scenarios, packaged_scenarios, pooled, run_bench, time_to_target

MICRO = """
name = "micro"
steps = 8
rays = 128
lidar_rays = 32
last = 1
rig = { width = 48, height = 36, frames = 6, lidar_azimuth_steps = 256, lidar_max_points = 3000 }
seeds = [[0, "street"], [1, "plaza"]]
target = { translation_cm = 1.0, rotation_deg = 0.05, time_ms = 0.5 }
timing = [["moisst", 1]]
baseline = { steps = 4, seeds = "first" }
floor = { steps = 6, register_steps = 2, depth_rays = 200, seeds = "first" }

[[case]]
id = "combined"
tables = ["III", "V:both", "VII:L_C+L_D+SSIM+DS"]
perturb = { translation = 0.5, rotation = 5.0, time = 0.1 }
seeds = "all"

[[case]]
id = "rotation-10"
tables = ["IV:rotation 10 deg"]
perturb = { translation = 0.0, rotation = 10.0, time = 0.0 }
seeds = "first"

[[case]]
id = "only-temporal"
tables = ["V:only temporal"]
perturb = { translation = 0.5, rotation = 5.0, time = 0.1 }
optimise = "temporal"
losses = ["no-depth"]
seeds = "first"
"""


def test_shipped_scenarios_cover_the_paper_protocol():
    quick = load_scenarios(packaged_scenarios("quick"))
    full = load_scenarios(packaged_scenarios("full"))
    for raw in (quick, full):
        tables = {t.partition(":")[0] for c in raw["case"] for t in c["tables"]}
        assert tables == {"I", "II", "III", "IV", "V", "VII"}
        assert {layout for _, layout in raw["seeds"]} == {"street", "plaza"}
        assert raw["baseline"] and raw["timing"] and raw["floor"]
    cells = {(c["perturb"]["rotation"], c["perturb"]["translation"]) for c in full["case"] if any(t.startswith("IV") for t in c["tables"])}
    assert cells == {(2.0, 0.0), (5.0, 0.0), (10.0, 0.0), (15.0, 0.0), (0.0, 0.2), (0.0, 0.5), (0.0, 1.0)}
    assert {c["perturb"]["time"] for c in full["case"] if any(t.startswith("II:") for t in c["tables"])} == {0.1, 0.2}


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace('steps = 8\n', ''), "steps: missing"),
        (lambda s: s.replace('optimise = "temporal"', 'optimise = "everything"'), "case[2].optimise: must be one of"),
        (lambda s: s.replace('losses = ["no-depth"]', 'losses = ["no-lpips"]'), "case[2].losses: unknown 'no-lpips'"),
        (lambda s: s.replace('[1, "plaza"]', '[1, "forest"]'), "seeds: must be a non-empty list"),
        (lambda s: s.replace('rotation = 10.0', 'rotation = -1.0'), "case[1].perturb.rotation: must be a number >= 0"),
        (lambda s: s.replace('id = "rotation-10"', 'id = "combined"'), "case[1].id: missing or repeated"),
        (lambda s: s + "\n[[case]\n", "(toml)"),
        (lambda s: s.replace('optimise = "temporal"', 'optimise = "temporal"\npatch_size = 0'), "case[2].patch_size: must be a positive integer"),
        (lambda s: s.replace('register_steps = 2', 'register_steps = 0'), "floor.register_steps: must be a positive integer"),
        (lambda s: s.replace('register_steps = 2', 'register_steps = 2, scene = 3'), "floor.scene: unknown key"),
        (lambda s: s.replace('frames = 6, ', 'frames = 6, lidar_spin = 2, '), "rig.lidar_spin: unknown moisst-synth setting"),
        (lambda s: s.replace('frames = 6, ', ''), "rig.frames: missing"),
    ],
)
def test_bad_scenario_file_gets_one_line_error(tmp_path, edit, message):
    path = tmp_path / "s.toml"
    path.write_text(edit(MICRO))
    with pytest.raises(BenchError) as err:
        load_scenarios(path)
    assert str(path) in str(err.value) and message in str(err.value) and "\n" not in str(err.value)


def _history(trans, rot, ms, elapsed):
    return {"step": list(range(len(trans))), "err_translation_cm": trans, "err_rotation_deg": rot, "err_time_ms": ms, "elapsed_s": elapsed}


def test_pooled_statistics_and_time_to_target_are_exact():
    a = {"history": {"cam": _history([5.0, 2.0, 0.9, 0.8], [1.0, 0.1, 0.04, 0.03], [9.0, 1.0, 0.4, 0.2], [0.0, 10.0, 20.0, 30.0]),
                     "cam2": _history([5.0, 0.5, 3.0, 0.5], [1.0, 0.01, 0.01, 0.01], [9.0, 0.1, 0.1, 0.1], [0.0, 10.0, 20.0, 30.0])}}
    b = {"history": {"cam": _history([7.0, 1.0], [2.0, 0.05], [3.0, 1.0], [0.0, 12.0])}}
    stats = pooled([a, b, {"failed": "x"}], last=2)
    vals = [0.9, 0.8, 7.0, 1.0]
    assert stats["cam"]["translation_cm"] == pytest.approx((np.mean(vals), np.std(vals)))
    assert stats["cam2"]["time_ms"] == pytest.approx((0.1, 0.0))
    # both cameras within 1 cm / 0.05 deg / 0.5 ms first at the 4th row (cam2 is off at the 3rd)
    assert time_to_target(a, {"translation_cm": 1.0, "rotation_deg": 0.05, "time_ms": 0.5}, ["cam", "cam2"]) == 30.0
    assert time_to_target(a, {"translation_cm": 1.0, "rotation_deg": 0.05, "time_ms": 0.5}, ["cam"]) == 20.0
    assert time_to_target(b, {"translation_cm": 1.0, "rotation_deg": 0.05, "time_ms": 0.5}, ["cam"]) is None


def test_micro_bench_fills_every_section(tmp_path):
    path = tmp_path / "micro.toml"
    path.write_text(MICRO)
    before = (REPO / "docs" / "benchmarks.md").read_bytes() if (REPO / "docs" / "benchmarks.md").exists() else None
    result = run_bench(BenchConfig(scenarios=path, out=tmp_path / "out"))
    md = (tmp_path / "out" / "benchmarks.md").read_text()
    for heading in ("Table III", "Table IV", "Table V", "Table VI", "Table VII", "Speed and cost", "## Floor", "## Uncertainty"):
        assert heading in md, heading
    saved = json.loads((tmp_path / "out" / "bench.json").read_text())
    combined = next(c for c in saved["cases"] if c["id"] == "combined")
    assert len(combined["runs"]) == 2 and all("history" in r for r in combined["runs"])
    # every run's sensors with sigmas are judged against the truth; the summary counts them
    judged = sum(len(r["coverage"]) for c in saved["cases"] for r in c["runs"] if "coverage" in r)
    assert judged > 0 and saved["coverage"]["finite"] >= judged
    # the priors of the combined rigs are the paper's perturbation: 86.6 cm, 100 ms for every sensor
    assert combined["before"]["cam_front_right"]["translation_cm"] == pytest.approx(86.6, abs=0.1)
    assert combined["before"]["lidar"]["time_ms"] == pytest.approx(100.0, abs=1e-6)
    # only-temporal never moves the extrinsics
    only_t = next(c for c in saved["cases"] if c["id"] == "only-temporal")
    assert only_t["pooled"]["cam_front_right"]["translation_cm"][0] == pytest.approx(86.6, abs=0.1)
    # the LiDAR-first stage ran in every case (rigs with a LiDAR): its own column, and temporal-only holds the extrinsic
    assert set(combined["lidar_first"]) == {"lidar"} and combined["lidar_first"]["lidar"]["wall_s"] > 0
    assert only_t["lidar_first"]["lidar"]["translation_cm"] == pytest.approx(86.6, abs=0.1)
    assert "LiDAR-first stage alone" in md
    timing = result["timing"][0]
    assert timing["method_run"] == ["moisst", "moisst"]
    assert timing["moisst_s"] > 0 and timing["nerfacto_s"] > 0 and timing["ratio"] == pytest.approx(timing["moisst_s"] / timing["nerfacto_s"])
    assert set(result["baseline"]["frame_errors"]) == {"cam_front_right", "cam_left"}
    (floor,) = result["floor"]  # seeds = "first": one rig
    assert (floor["layout"], floor["seed"], floor["scene_steps"], floor["register_steps"]) == ("street", 0, 6, 2)
    assert set(floor["floor"]) == {"cam_front_right", "cam_left", "lidar"} and floor["depth"]["camera_rays"] > 0
    assert set(floor["stages"]["floor"]) == {"lidar"} and len(floor["stages"]["unfitted"]) == 2  # 6 frames: no camera fit
    assert "Floor of the pre-NeRF stages" in md and "NeRF floor" in md
    assert (tmp_path / "out" / "bench_error_vs_time.png").stat().st_size > 1000
    after = (REPO / "docs" / "benchmarks.md").read_bytes() if (REPO / "docs" / "benchmarks.md").exists() else None
    assert after == before  # --docs not given: the repository is not touched


def test_perturbed_variant_rig_equals_what_moisst_synth_writes(tmp_path):
    from moisst_ns.bench import make_bench_rig
    from moisst_ns.datasets.synth import SynthConfig, make_rig

    raw = {"rig": {"width": 48, "height": 36, "frames": 4}}
    perturb = {"translation": 0.2, "rotation": 2.0, "time": 0.05}
    variant = make_bench_rig(tmp_path / "bench", raw, 3, "plaza", perturb)
    direct = make_rig(SynthConfig(out=tmp_path / "direct", seed=3, layout="plaza", width=48, height=36, frames=4, perturb="paper",
                                  perturb_translation=0.2, perturb_rotation=2.0, perturb_time=0.05))
    a, b = json.loads((variant / "rig.json").read_text()), json.loads((direct / "rig.json").read_text())
    assert a["sensors"] == b["sensors"] and a["frames"] == b["frames"]
    for rel in [f["file_path"] for f in b["frames"]] + ["reference_poses.txt", "ground_truth.json"]:
        assert (variant / rel).read_bytes() == (direct / rel).read_bytes(), rel
    assert make_bench_rig(tmp_path / "bench", raw, 3, "plaza", perturb) == variant  # generated once
