"""A faster training step on CPU: nerfstudio's torch hash-grid encoding compiled by ``torch.compile`` (inductor).

Without tiny-cuda-nn, nerfstudio's ``HashEncoding.pytorch_fwd`` hashes the 8 corners of every level in separate
tensor operations and gathers them with 8 indexings; on 2 CPU cores that forward and its backward are ~70 % of a
``moisst-lite`` step (torch profiler, docs/benchmarks.md). Inductor fuses them into C++ loops: 1.4-1.9x on the
encoding, 1.7x on the whole step. The math is nerfstudio's own method, compiled, not re-implemented.

Two guarantees are kept:

* determinism: inductor lowers the table's scatter-add (the backward of the corner gathers) to parallel atomic adds,
  whose order and so whose float sums change from run to run. ``torch.use_deterministic_algorithms(True,
  warn_only=True)`` makes it lower them to aten's deterministic kernel (the same seed, the same result; measured
  cost < 2 % of a step). It is switched on for the process when an encoding is compiled.
* a clean fallback: without a C++ compiler, on CUDA (tiny-cuda-nn fuses the encoding there) or when compiling
  fails, the encodings stay eager and the reason is returned in one line.
"""

from __future__ import annotations

import shutil
from typing import Callable, Optional, Sequence

import torch
from jaxtyping import Float
from torch import Tensor, nn

_MIN_RECOMPILE_LIMIT = 32
"""Each encoding compiles one graph per (gradient w.r.t. positions or not, grad mode): 3 encodings x 3 cases is
above dynamo's default limit of 8 graphs per code object, after which it would silently run eager."""


def cpp_compiler() -> Optional[str]:
    """The C++ compiler inductor would use on CPU, or None when none is on PATH.

    Returns:
        Its path, or None.
    """
    return next(filter(None, map(shutil.which, ("g++", "c++", "clang++"))), None)


def _compiled_forward(encoding: nn.Module) -> Callable[[Tensor], Tensor]:
    """``encoding.pytorch_fwd`` compiled with dynamic shapes (ray batches change size between steps)."""
    return torch.compile(encoding.pytorch_fwd, dynamic=True)


def _probe(encoding: nn.Module, device: torch.device) -> None:
    """Run forward + backward once per case the training and the viewer meet (positions with and without gradient,
    no-grad rendering), so that every graph is compiled now and a failure shows here, not in the middle of a run."""
    table = encoding.hash_table
    grad_before = None if table.grad is None else table.grad.clone()
    points: Float[Tensor, "64 3"] = torch.rand(64, 3, device=device, generator=torch.Generator(device).manual_seed(0))
    for positions_need_grad in (True, False):
        x = points.clone().requires_grad_(positions_need_grad)
        encoding(x).square().sum().backward()
    with torch.no_grad():
        encoding(points)
    table.grad = grad_before


def compile_hash_encodings(encodings: Sequence[nn.Module], device: torch.device | str = "cpu") -> Optional[str]:
    """Replace each encoding's torch forward by its compiled form, or leave all of them eager.

    Args:
        encodings: nerfstudio ``HashEncoding`` modules without tcnn (the model's own list, ``MoisstModel._hash_encodings``).
        device: where the encodings' tables are (the probe runs there).

    Returns:
        None when every encoding is compiled; else why none is (one line), and all are eager.
    """
    device = torch.device(device)
    if not encodings:
        return "no torch hash-grid encoding (tiny-cuda-nn fuses them)"
    if device.type != "cpu":
        return f"device {device.type}: compiled only on CPU (untested elsewhere)"
    if cpp_compiler() is None:
        return "no C++ compiler on PATH (g++, c++ or clang++): inductor cannot build its CPU kernels"
    from torch import _dynamo

    _dynamo.config.recompile_limit = max(_dynamo.config.recompile_limit, _MIN_RECOMPILE_LIMIT)
    deterministic = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    if not deterministic[0]:
        torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        for encoding in encodings:
            encoding.pytorch_fwd = _compiled_forward(encoding)
            _probe(encoding, device)
    except Exception as err:  # noqa: BLE001 - any compiler failure means: run eager
        for encoding in encodings:
            encoding.__dict__.pop("pytorch_fwd", None)
        torch.use_deterministic_algorithms(deterministic[0], warn_only=deterministic[1])
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        return f"torch.compile failed ({type(err).__name__}: {first[:160]})"
    return None
