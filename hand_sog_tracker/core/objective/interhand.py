"""``E_int``: a hand's spheres may not penetrate another hand's (seed 001, sec. 3.2.4).

Seed 001 tracks two interacting hands with one objective whose collision term penalises the
squared penetration depth between the two meshes (eq. 10).  Here each hand keeps its own fit
(:mod:`hand_sog_tracker.core.hands`) and sees the other hand as fixed for that frame's fit
(its pose of this frame when fitted already, else its last one): the term is one hand's
spheres (its model's Gaussians, radius one sigma, the skin of
:func:`~hand_sog_tracker.core.hands.skin_distance`) against the other hand's,

``E_int = sum_{i, j} max(r_i + r_j - |p_i - q_j|, 0)^2 / INTERHAND_SCALE_MM^2``

over this hand's centres ``p_i`` and the other hand's ``q_j`` (mm), and enters the objective
as ``- w E_int``.  Its gradient is analytic (:meth:`InterHand.term`), pose by pose in a batch.
Only the other hand's spheres that this hand's can reach are kept (:meth:`InterHand.near`),
so hands apart pay nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.objective.arrays import Backward
from hand_sog_tracker.core.silhouette import run_or_defer

__all__ = ["INTERHAND_SCALE_MM", "InterHand"]

#: Penetration is measured in this unit (mm): a sphere 1 unit deep into the other hand's costs
#: ``w`` (the depth noise of the data, chosen here).
INTERHAND_SCALE_MM: Final[float] = 5.0


@dataclass(frozen=True, eq=False)
class InterHand:
    """The other hand's spheres, fixed for one fit, and the term's weight.

    Attributes
    ----------
    centres : array, shape (k, 3), mm
        The other hand's sphere centres (camera frame).
    radii : array, shape (k,), mm
        Their radii.
    weight : float
        ``w`` of ``- w E_int``.
    """

    centres: NDArray[np.float64]
    radii: NDArray[np.float64]
    weight: float

    @staticmethod
    def near(
        centres: NDArray[np.float64],
        radii: NDArray[np.float64],
        own_centres: NDArray[np.float64],
        radii_own: NDArray[np.float64],
        weight: float,
        reach_mm: float,
    ) -> InterHand | None:
        """The term against the spheres (``centres`` (k, 3), ``radii`` (k,) mm) that come within
        ``reach_mm`` of touching one of this hand's at ``own_centres`` (m, 3) (the fit's start),
        or None when none does (the hands are apart: no term)."""
        d = np.sqrt(((centres[:, None, :] - own_centres[None, :, :]) ** 2).sum(-1))
        gap = d - radii[:, None] - radii_own[None, :]
        keep = (gap < reach_mm).any(axis=1)
        if not keep.any():
            return None
        return InterHand(centres[keep].copy(), radii[keep].copy(), float(weight))

    def term(
        self,
        P: NDArray[np.float64],
        radii_own: NDArray[np.float64],
        g3: NDArray[np.float64] | None,
        later: list[Backward] | None = None,
    ) -> float | NDArray[np.float64]:
        """``w E_int`` at this hand's sphere centres ``P`` (m, 3) or (B, m, 3) mm, radii
        ``radii_own`` (m,) mm (a float, or (B,)); adds ``-w dE_int/dP`` into ``g3`` (same
        shape as ``P``), or appends the function that
        does to ``later``, unless both are None."""
        diff = P[..., :, None, :] - self.centres  # (..., m, k, 3) mm
        dist = np.sqrt((diff * diff).sum(-1))  # (..., m, k)
        pen = (radii_own[:, None] + self.radii[None, :]) - dist
        pen = np.maximum(pen, 0.0, out=pen)
        scale = self.weight / (INTERHAND_SCALE_MM * INTERHAND_SCALE_MM)
        value = scale * (pen * pen).sum(axis=(-2, -1))
        if P.ndim == 2:
            value = float(value)
        if g3 is None and later is None:
            return value

        def backward(g3: NDArray[np.float64]) -> None:
            # d pen / d p_i = -(p_i - q_j) / |p_i - q_j|; -w dE/dp_i = 2 scale pen (p_i - q_j) / d.
            coef = np.divide(2.0 * scale * pen, dist, out=np.zeros_like(pen), where=pen > 0.0)
            g3 += (coef[..., None] * diff).sum(axis=-2)

        run_or_defer(backward, g3, later)
        return value
