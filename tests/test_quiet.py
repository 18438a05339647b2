"""The first ten minutes: light command lines, quiet runs, one-line errors (issue 18).

Speed itself (``--help`` in under a second) is measured, not asserted here: what makes it fast is that parsing a
command line imports neither torch nor nerfstudio, and that is asserted.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import pytest

from moisst_ns import quiet

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
HEAVY = ("torch", "nerfstudio", "open3d", "matplotlib", "cv2")


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_command_line_modules_import_nothing_heavy(script):
    module = SCRIPTS[script].partition(":")[0]
    code = f"import sys, {module}; print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", (script, out)


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_help_works_and_imports_nothing_heavy(script):
    module, _, func = SCRIPTS[script].partition(":")
    code = (f"import sys; sys.argv = [{script!r}, '--help']\nfrom {module} import {func}\ntry:\n    {func}()\n"
            f"except SystemExit as e:\n    assert e.code in (0, None), e.code\n"
            f"print('HEAVY', sorted(m for m in {HEAVY!r} if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout.lower() and result.stdout.strip().endswith("HEAVY []"), result.stdout[-300:]


def test_missing_dataset_folder_is_one_line(tmp_path):
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(tmp_path / "nowhere"), "--output-dir", str(tmp_path / "o")],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.splitlines() == [f"moisst-calibrate: error: {tmp_path / 'nowhere'}: dataset: folder not found"]


def _emit(module: str, category: type, message: str) -> list:
    """Warnings that get through the current filters when ``message`` is warned as from ``module``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.warn_explicit(message, category, filename=module.replace(".", "/") + ".py", lineno=1, module=module)
    return caught


def test_filters_are_narrow(monkeypatch):
    import nerfstudio.utils.printing as printing

    monkeypatch.setattr(printing, "print_tcnn_speed_warning", printing.print_tcnn_speed_warning)  # restored after
    monkeypatch.setattr(sys, "warnoptions", [])
    indexing = "Using a non-tuple sequence for multidimensional indexing is deprecated and will be changed"
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert quiet.quiet_third_party(verbose=False)
        assert _emit("nerfstudio.cameras.cameras", UserWarning, indexing) == []
        # same message from another module, another category, another message: all still shown
        assert len(_emit("moisst_ns.model", UserWarning, indexing)) == 1
        assert len(_emit("nerfstudio.cameras.cameras", DeprecationWarning, indexing)) == 1
        assert len(_emit("nerfstudio.cameras.cameras", UserWarning, "something new")) == 1
        assert printing.print_tcnn_speed_warning is quiet._no_tcnn_banner
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert not quiet.quiet_third_party(verbose=True)
        assert len(_emit("nerfstudio.cameras.cameras", UserWarning, indexing)) == 1


def test_user_warning_options_win(monkeypatch):
    monkeypatch.setattr(sys, "warnoptions", ["default"])
    with warnings.catch_warnings():
        before = list(warnings.filters)
        assert not quiet.quiet_third_party(verbose=False)
        assert warnings.filters == before


@pytest.mark.slow
def test_tiny_calibration_prints_no_third_party_warning(tmp_path):
    """A 5-step calibration of a tiny rig: no ``...Warning:`` line on stderr, no tcnn banner on stdout."""
    rig = tmp_path / "rig"
    subprocess.run([str(BIN / "moisst-synth"), str(rig), "--width", "64", "--height", "48", "--frames", "8"],
                   check=True, capture_output=True, text=True)
    result = subprocess.run([str(BIN / "moisst-calibrate"), str(rig), "--output-dir", str(tmp_path / "out"),
                             "--max-num-iterations", "5", "--threads", "1"], capture_output=True, text=True)
    # 0, or 3 when a sensor is not converged (5 steps): both are finished runs; 2 or a crash is not
    assert result.returncode in (0, 3), result.stderr[-2000:]
    warning_lines = [line for line in result.stderr.splitlines() if re.search(r"\w*Warning\b", line)]
    assert warning_lines == [], "\n".join(warning_lines)
    assert "Install tcnn" not in result.stdout
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert set(summary["verdicts"]) == {"cam_front_right", "cam_left", "lidar"}
    assert result.stdout.rstrip().splitlines()[-1].startswith(("Trust:", "Do not trust:"))


def test_torchvision_and_nerfstudio_import_in_this_venv():
    """Whatever torch/torchvision the install chose (CPU torch beside PyPI's CUDA torchvision included), the
    nerfstudio code paths we use import, and torchvision's pure-torch helpers that nerfstudio calls run."""
    code = ("import torch, torchvision.utils, torchvision.transforms.functional as TF, nerfstudio.pipelines.base_pipeline\n"
            "assert TF.resize(torch.rand(3, 8, 8), [4, 4]).shape == (3, 4, 4)\n"
            "assert torchvision.utils.make_grid(torch.rand(2, 3, 4, 4)).shape[0] == 3\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-1500:]


def test_torchvision_shim_only_for_a_cpu_torch_beside_a_cuda_torchvision(monkeypatch):
    from moisst_ns import torchvision_cpu

    versions = {}
    import importlib.metadata

    monkeypatch.setattr(importlib.metadata, "version", lambda name: versions[name])
    for torch_v, tv_v, expected in (("2.13.0+cpu", "0.28.0", True), ("2.13.0+cpu", "0.28.0+cpu", False),
                                    ("2.14.1", "0.29.1", False)):
        versions.update(torch=torch_v, torchvision=tv_v)
        assert torchvision_cpu.needed() is expected, (torch_v, tv_v)
