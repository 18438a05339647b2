"""nerfacto's L-infinity scene contraction (MipNeRF-360 eq. 10 with the max norm) without ``torch.linalg.norm``.

On the CPU build of torch 2.13, ``torch.linalg.norm(x, ord=inf, dim=-1)`` of an (N, 3) tensor runs through a
generic reduction that is ~100x slower than ``x.abs().amax(-1)`` (65536 samples: 12 ms against 0.1 ms forward,
measured), and nerfstudio's ``SceneContraction`` calls it for every sample of the two proposal networks and the
field: ~18 % of a ``moisst-lite`` step (torch profiler, docs/benchmarks.md). ``LinfSceneContraction`` computes the
same function from one ``abs().amax()``; values are bit-identical and so is the gradient (both spread it evenly over
tied components). Gaussian inputs (unused by nerfacto) go to nerfstudio's own code.
"""

from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor, nn

from nerfstudio.field_components.spatial_distortions import SceneContraction


def contract_linf(positions: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
    """MipNeRF-360's contraction with the max norm: ``x`` inside the unit cube, ``(2 - 1/|x|) x/|x|`` outside.

    Args:
        positions: points, model units.

    Returns:
        The contracted points, inside the cube of half side 2.
    """
    magnitude = positions.abs().amax(dim=-1, keepdim=True)
    return torch.where(magnitude < 1, positions, (2 - (1 / magnitude)) * (positions / magnitude))


class LinfSceneContraction(SceneContraction):
    """``SceneContraction(order=inf)`` whose tensor path is ``contract_linf``."""

    def __init__(self) -> None:
        super().__init__(order=math.inf)

    def forward(self, positions):
        if isinstance(positions, Tensor):
            return contract_linf(positions)
        return super().forward(positions)


def use_linf_contraction(model: nn.Module) -> int:
    """Replace every ``SceneContraction(order=inf)`` held as ``spatial_distortion`` by a module of ``model`` (the
    field and the proposal networks of nerfacto share one) with a ``LinfSceneContraction``.

    Args:
        model: a nerfstudio model.

    Returns:
        How many modules now use it.
    """
    replaced = 0
    fast = LinfSceneContraction()
    for module in model.modules():
        distortion = getattr(module, "spatial_distortion", None)
        if type(distortion) is SceneContraction and distortion.order == math.inf:
            module.spatial_distortion = fast
            replaced += 1
    return replaced
