"""README's "Where it stands" table is rendered from docs/figures.json (``moisst_ns.runs.figures``, ``moisst-figures``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from moisst_ns.cli import figures as cli
from moisst_ns.runs import RunError
from moisst_ns.runs.figures import BEGIN, END, load_figures, record_run, render_block, run_from_output, update_readme

ROOT = Path(__file__).resolve().parents[1]
E = lambda t, r, m: {"translation_cm": t, "rotation_deg": r, "time_ms": m}  # noqa: E731


def test_readme_holds_exactly_what_docs_figures_json_renders():
    text = (ROOT / "README.md").read_text()
    figures = load_figures(ROOT / "docs" / "figures.json")
    assert update_readme(text, figures) == text, "README.md's figures block is stale: run moisst-figures"
    block = text[text.index(BEGIN):text.index(END)]
    for run in figures["runs"]:  # every recorded number is in the table
        assert run["label"] in block
        for name, entry in run["sensors"].items():
            assert name in block and " / ".join(f"{entry['after'][k]:.4g}" for k in ("translation_cm", "rotation_deg", "time_ms")) in block


def calibrate_output(folder: Path, after_left: float) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    summary = {"method": "moisst-lite", "iterations": 1500, "wall_time_s": 512.0, "seed": 42,
               "errors_before": {"cam_left": E(86.6, 8.5, 100.0), "lidar": E(86.6, 8.8, 100.0)},
               "errors_after": {"cam_left": E(after_left, 2.0, 10.0), "lidar": E(0.01, 0.003, 0.0)}}
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


def test_record_replaces_the_run_with_the_same_label_and_renders(tmp_path):
    figures = {"runs": [{"label": "old", "sensors": {"cam_left": {"before": E(86.6, 8.5, 100.0), "after": E(99.0, 9.0, 50.0)}}}]}
    run = run_from_output(calibrate_output(tmp_path / "a", 12.345), "today", {"command": "moisst-calibrate R"})
    assert run["source"]["iterations"] == 1500 and run["source"]["command"] == "moisst-calibrate R"
    figures = record_run(figures, run)
    figures = record_run(figures, run_from_output(calibrate_output(tmp_path / "b", 7.0), "today", {}))
    assert [r["label"] for r in figures["runs"]] == ["old", "today"]
    block = render_block(figures)
    assert "| cam_left | 86.6 / 8.5 / 100 | 99 / 9 / 50 | 7 / 2 / 10 |" in block
    assert "| lidar | 86.6 / 8.8 / 100 | - | 0.01 / 0.003 / 0 |" in block


def test_update_readme_needs_the_markers():
    with pytest.raises(RunError, match="markers not found"):
        update_readme("no block here", {"runs": []})


def test_command_records_renders_and_checks(tmp_path, monkeypatch, capsys):
    fig, readme = tmp_path / "figures.json", tmp_path / "README.md"
    fig.write_text(json.dumps({"runs": [{"label": "old", "sensors": {"cam_left": {"before": E(1, 1, 1), "after": E(2, 2, 2)}}}]}))
    readme.write_text(f"intro\n{BEGIN}\nstale\n{END}\noutro\n")

    def run(*argv):
        monkeypatch.setattr(sys, "argv", ["moisst-figures", "--figures", str(fig), "--readme", str(readme), *map(str, argv)])
        try:
            cli.main()
        except SystemExit as exit_:
            return exit_.code
        return 0

    assert run("--check") == 1
    assert run("--record", calibrate_output(tmp_path / "out", 3.0), "--label", "new", "--wall", "9 min") == 0
    assert run("--check") == 0
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith("outro\n") and "| cam_left | 1 / 1 / 1 | 2 / 2 / 2 | 3 / 2 / 10 |" in text
    assert "9 min wall" in text and [r["label"] for r in json.loads(fig.read_text())["runs"]] == ["old", "new"]
    capsys.readouterr()
    assert run("--record", tmp_path / "nowhere", "--label", "x") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("moisst-figures: error: ") and "summary.json: (file): not found" in err[0]
    fig.write_text('{"runs": [')
    assert run() == 2
    assert "figures.json: line 1, column 11: invalid JSON" in capsys.readouterr().err
