"""The terms of the pose alone: ``E_lim``, ``E_smo``, ``E_ord``, ``E_cpl`` and ``E_curl``."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import FINGER_ABD, FINGER_DIP, FINGER_PIP, JOINTS, N_PARAMS
from hand_sog_tracker.core.objective.arrays import _per_pose, _squares, _sum
from hand_sog_tracker.core.objective.constants import (
    COUPLING_DIP_PIP,
    CURL_MAX_RAD,
    ORDER_MIN_GAP_RAD,
    SMOOTH_TRANSLATION_MM,
)

__all__ = ["PoseTerms"]


@lru_cache(maxsize=1)
def _smooth_scale() -> NDArray[np.float64]:
    s = np.ones(N_PARAMS)
    s[:3] = 1.0 / SMOOTH_TRANSLATION_MM
    return s



class PoseTerms:
    """The pose terms of :class:`~hand_sog_tracker.core.objective.Objective` (a mixin: reads
    its ``previous``, ``_limits_low``, ``_limits_high`` and ``_const``)."""

    def _limits(self, theta: NDArray[np.float64]) -> tuple[float | NDArray[np.float64], NDArray[np.float64] | None]:
        """``E_lim`` (eq. 8) and its gradient, shape (26,), or None for a zero gradient (every
        joint within its limits, as the tracker's projected iterates always are).  For poses
        (B, 26) (this and the other pose terms): the values (B,) (0.0: 0 at every pose) and
        the gradients (B, 26)."""
        # (Within the limits when clipping changes no bit: two calls instead of four.  A pose
        # with a zero of the other sign at a limit of 0 takes the exact path below: the same
        # E_lim = 0, a zero gradient.)
        clipped = np.maximum(theta, self._limits_low)
        np.minimum(clipped, self._limits_high, out=clipped)
        if clipped.tobytes() == theta.tobytes():
            return 0.0, None  # (lo = hi = 0 below: E_lim = 0, gradient 0)
        # On all 26 parameters, the global ones unlimited (their lo, hi and gradient are 0).
        lo = np.minimum(theta - self._limits_low, 0.0)
        hi = np.maximum(theta - self._limits_high, 0.0)
        g = 2.0 * (lo + hi)
        return _per_pose(_sum((lo * lo)[..., JOINTS], axis=-1) + _sum((hi * hi)[..., JOINTS], axis=-1)), g

    @staticmethod
    def _coupling(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64] | None]:
        """``E_cpl`` and its gradient, shape (26,) (None when ``E_cpl`` is 0: a zero gradient):
        each finger's DIP flexed beyond :data:`COUPLING_DIP_PIP` times its PIP flexion costs."""
        excess = theta[..., FINGER_DIP] - COUPLING_DIP_PIP * theta[..., FINGER_PIP]  # (..., 4) rad
        if not (excess > 0.0).any():
            return 0.0, None
        np.maximum(excess, 0.0, out=excess)
        g = np.zeros(theta.shape)
        g[..., FINGER_DIP] = 2.0 * excess
        g[..., FINGER_PIP] = (-2.0 * COUPLING_DIP_PIP) * excess
        return _squares(excess), g

    @staticmethod
    def _curl(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64] | None]:
        """``E_curl`` and its gradient, shape (26,) (None when ``E_curl`` is 0: a zero
        gradient): each finger's PIP + DIP flexion beyond :data:`CURL_MAX_RAD` costs."""
        excess = theta[..., FINGER_PIP] + theta[..., FINGER_DIP]  # (..., 4) rad
        excess -= CURL_MAX_RAD
        if not (excess > 0.0).any():
            return 0.0, None
        np.maximum(excess, 0.0, out=excess)
        g = np.zeros(theta.shape)
        g[..., FINGER_PIP] = g[..., FINGER_DIP] = 2.0 * excess
        return _squares(excess), g

    def _order(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64] | None]:
        """``E_ord`` and its gradient, shape (26,) (None when ``E_ord`` is 0: a zero
        gradient): neighbouring fingers may not cross."""
        abd = theta[..., FINGER_ABD]  # MCP abduction of index .. little, shape (..., 4)
        a = self._const.fan + abd
        if a.ndim == 1:
            # Every gap at least ORDER_MIN_GAP_RAD (typical): E_ord = 0.  (The gaps as below, by
            # Python floats: the same IEEE differences; fl(gap - c) < 0 exactly when gap < c.)
            a0, a1, a2, a3 = a.tolist()
            if a1 - a0 >= ORDER_MIN_GAP_RAD and a2 - a1 >= ORDER_MIN_GAP_RAD and a3 - a2 >= ORDER_MIN_GAP_RAD:
                return 0.0, None
        gap = a[..., 1:] - a[..., :-1]  # (..., 3), as np.diff
        short = np.minimum(gap - ORDER_MIN_GAP_RAD, 0.0)
        if not short.any():
            return 0.0, None
        g = np.zeros(theta.shape)
        # d/d abd_{c+1} of short^2 is 2 short, d/d abd_c is -2 short.
        g_abd = np.zeros(a.shape)
        g_abd[..., 1:] += 2.0 * short
        g_abd[..., :-1] -= 2.0 * short
        g[..., FINGER_ABD] = g_abd
        return _per_pose(_sum(short * short, axis=-1)), g

    def _smoothness(self, theta: NDArray[np.float64]) -> tuple[float | NDArray[np.float64], NDArray[np.float64]]:
        """``E_smo`` (eq. 9) and its gradient, shape (26,) (for poses (B, 26): (B,), (B, 26))."""
        if self.previous is None:
            return 0.0, np.zeros(theta.shape)
        p1, p2 = self.previous
        s = _smooth_scale()
        r = s * (0.5 * (p2 + theta) - p1)
        return _per_pose(_sum(r * r, axis=-1)), r * s
