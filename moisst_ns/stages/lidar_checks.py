"""The LiDAR-first stage's checks of its own estimate beyond the formal sigma: do the parameters held at their priors
agree with the scans (``release_check``), and do the two halves of the drive agree (``split_half_spread``)? Both
compare fits of the same scans; the fitting itself stays in ``lidar_first``. No nerfstudio import.
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence

import numpy as np
from jaxtyping import Float, Int

from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar_geometry import Extrinsic
from moisst_ns.stages.observability import JACOBIAN_ORDER, PARAMETERS, TEST_STEPS, UNITS, Observability


def release_check(estimate: Extrinsic, released: Extrinsic, free: np.ndarray, observability: Observability,
                  expected: Sequence[int] = ()) -> Dict[str, object]:
    """Are the held parameters consistent with the scans? Compare the held fit with one that also frees them.

    A held parameter is inconsistent when freeing it moves it by more than three formal sigmas and a tenth of a typical
    prior error (1 cm, 0.1 deg, 1 ms): the scans agree better elsewhere, so the value it was held at is likely wrong
    and the free parameters absorbed that error. How far each parameter moves on release is the data's measure of its
    error: for a free one the error the held values put into it, which its formal sigma (conditional on the held
    values) does not contain; for a held one how far the data put it from where it was held.

    Args:
        estimate: the fit with some parameters held at the prior.
        released: the fit from ``estimate`` with every parameter free.
        free: the indices (Jacobian order) the held fit estimated.
        observability: of the held fit (its formal sigma per parameter).
        expected: held parameters (Jacobian order) expected to move when released: held because the data hardly
            determine them (``LidarFirstConfig.hold_weak``), so their move is their sigma, not a disagreement.

    Returns:
        ``{"held": [...], "released_change": [7], "inconsistent": [...], "sigma_release": [7], "note"}`` in
        ``observability.PARAMETERS`` order (m, rad, s); ``sigma_release`` is ``|released_change|``; ``note`` says which
        held parameters disagree and by how much (empty when none does).
    """
    change = np.asarray(parameter_difference(estimate.matrix(), estimate.time_offset, released.matrix(), released.time_offset))
    is_free = np.isin(np.asarray(JACOBIAN_ORDER), free)
    sigma = np.array([d.sigma for d in observability.dofs])
    held = [p for p, f in zip(PARAMETERS, is_free) if not f]
    inconsistent = [p for p, f, c, s, step, j in zip(PARAMETERS, is_free, change, sigma, TEST_STEPS, JACOBIAN_ORDER)
                    if not f and abs(c) > max(3.0 * s, 0.1 * step) and j not in expected]
    moves = ", ".join(f"{p} {c * u:+.3g} {unit}" for p, c, (u, unit) in zip(PARAMETERS, change, UNITS) if p in inconsistent)
    note = f"held at its prior, {', '.join(inconsistent)} disagree with the scans (released, they move by {moves})" if inconsistent else ""
    return {"held": held, "released_change": change.tolist(), "inconsistent": inconsistent,
            "sigma_release": np.abs(change).tolist(), "note": note}


def split_half_spread(fit: Callable[[np.ndarray, np.ndarray], Optional[Extrinsic]], pairs: Int[np.ndarray, "num 2"],
                      baselines: Float[np.ndarray, "num"], num_scans: int) -> Float[np.ndarray, "7"]:
    """Half the difference between the fits of the first and the second half of the drive.

    The scans are split in time; each half keeps the pairs whose two scans both lie in it and is fitted on its own
    (``fit``, from the whole drive's estimate). For two independent halves ``|a - b| / 2`` estimates the standard
    deviation of the whole drive's estimate; unlike the formal sigma it sees what the drive leaves undetermined or
    biased (a lever arm a short, nearly straight drive hardly shows).

    Args:
        fit: ``fit(pairs, baselines) -> Extrinsic``, the stage's fit restricted to those scan pairs (None: the
            half cannot be fitted, e.g. its scans do not overlap).
        pairs: scan index pairs of the whole drive (scans in time order).
        baselines: driving distance of each pair, metres.
        num_scans: how many scans the drive has.

    Returns:
        Per parameter of ``observability.PARAMETERS`` (m, rad, s); NaN everywhere (not measured, not "undetermined":
        the whole drive may still determine them) when a half has no pair or cannot be fitted.
    """
    middle = num_scans // 2
    halves = [(pairs[:, 1] < middle), (pairs[:, 0] >= middle)]
    if not all(h.any() for h in halves):
        return np.full(7, np.nan)
    first, second = (fit(pairs[h], baselines[h]) for h in halves)
    if first is None or second is None:
        return np.full(7, np.nan)
    return np.abs(np.asarray(parameter_difference(first.matrix(), first.time_offset, second.matrix(), second.time_offset))) / 2

