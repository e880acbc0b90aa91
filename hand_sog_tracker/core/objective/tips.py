"""``E_sal``: fingertips pulled toward the detections assigned to them (seed 001, eq. 12)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.objective.arrays import _UNSET, Backward, _as_slice, _per_pose, _sum
from hand_sog_tracker.core.objective.constants import SALIENT_SCALE_MM, SALIENT_SOFT_MM
from hand_sog_tracker.core.silhouette import run_or_defer

__all__ = ["TipTargets", "SalientTerm"]


@dataclass(frozen=True, eq=False)
class TipTargets:
    """Where the fingertips should be: the detections assigned to them.

    Attributes
    ----------
    points : array, shape (5, 3), mm
        Target of each fingertip (thumb .. little), camera frame; ignored where the weight is 0.
    weights : array, shape (5,)
        Confidence of each target, 0 for a fingertip without a detection.
    """

    points: NDArray[np.float64]
    weights: NDArray[np.float64]



def _stacked_targets(targets: Sequence[TipTargets | None], tips: slice | NDArray[np.int64]) -> tuple | None:
    """The salient term's constants of one :class:`TipTargets` (or None) per pose: the
    fingertips ``tips``, points (B, 5, 3) mm and weights (B, 5) per :data:`SALIENT_SCALE_MM`
    (0 without targets); None when no pose has a weight."""
    points = np.zeros((len(targets), 5, 3))
    weights = np.zeros((len(targets), 5))
    for b, t in enumerate(targets):
        if t is not None:
            points[b], weights[b] = t.points, t.weights
    if not np.any(weights > 0):
        return None
    return tips, points, weights / SALIENT_SCALE_MM



class SalientTerm:
    """``E_sal`` of :class:`~hand_sog_tracker.core.objective.Objective` (a mixin: reads its
    ``model``, ``targets`` and ``_sal``)."""

    def _salient(
        self,
        P: NDArray[np.float64],
        g3: NDArray[np.float64] | None,
        w_sal: float,
        later: list[Backward] | None = None,
        each: object = _UNSET,
    ) -> float | NDArray[np.float64]:
        """``E_sal``; adds ``-w_sal dE_sal/dP`` into ``g3`` at the fingertip Gaussians (or
        appends the function that does to ``later``).  ``P``, ``g3``: (m, 3) or (B, m, 3)
        (then ``E_sal`` is (B,)); ``each``: the constants of every pose's own targets
        (:func:`_stacked_targets`: points (B, 5, 3), weights (B, 5)) in place of ``targets``'."""
        if each is not _UNSET:
            const = each
        else:
            t = self.targets
            key, const = self._sal
            if t is not key:  # the targets' constants, once per targets object
                const = None
                if t is not None and np.any(t.weights > 0):
                    const = (_as_slice(self.model.tip_index), np.asarray(t.points), t.weights / SALIENT_SCALE_MM)
                self._sal = (t, const)
        if const is None or w_sal <= 0:
            return 0.0
        tips, points, w = const
        diff = P[..., tips, :] - points  # (tips: a slice of evenly spaced indices, else an index array)
        sq = diff * diff
        root = np.sqrt(sq[..., 0] + sq[..., 1] + sq[..., 2] + SALIENT_SOFT_MM**2)
        val = _per_pose(_sum(w * (root - SALIENT_SOFT_MM), axis=-1))
        if g3 is None and later is None:
            return val

        def backward(g3: NDArray[np.float64]) -> None:
            g3[..., tips, :] -= w_sal * (w / root)[..., None] * diff  # (a slice: in place, no scatter)

        run_or_defer(backward, g3, later)
        return val
