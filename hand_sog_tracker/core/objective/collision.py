"""``E_col``: the model's Gaussians of different chains may not overlap (paper 000, eq. 6)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import FINGER_MCP, FINGER_PIP, HandModel, rest_pose
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.objective.arrays import _TWO_PI, Backward, _sum
from hand_sog_tracker.core.objective.constants import COLLISION_CONTACT_FREE, CONTACT_CURL_RAD, PALM_DISTAL_COLLISION
from hand_sog_tracker.core.silhouette import run_or_defer

if TYPE_CHECKING:
    from hand_sog_tracker.core.objective.data import _Rows

__all__ = ["CollisionTerm", "contact_shares", "model_constants"]


@dataclass(frozen=True, eq=False)
class _ModelConstants:
    pair_s2: NDArray[np.float64]  # sigma_i^2 + sigma_j^2, mm^2
    pair_amp: NDArray[np.float64]  # overlap at zero distance, (2 pi s_i^2 s_j^2 / s2)^1.5, x weight
    pair_free: NDArray[np.float64]  # overlap free of two curled fingers: a share of the touching one, x weight
    pair_chain: NDArray[np.int64]  # (2, pairs) chain of each pair's i and j, -1 for the palm
    # Flat indices into (m, 3) centres: (3, pairs) of the i's and the j's coordinates (row x
    # of every pair, then y, then z), and both as the scatter (2 3 pairs,) of the gradient.
    gather_i: NDArray[np.int64]
    gather_j: NDArray[np.int64]
    scatter: NDArray[np.int64]
    norm_h: float
    fan: NDArray[np.float64]  # (4,) rest direction of index .. little in the palm plane, rad


def _collision_pairs(
    model: HandModel,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """The Gaussian pairs ``i, j`` (pairs,) of ``E_col``, their weights (pairs,): 1, but
    ``PALM_DISTAL_COLLISION`` for the palm against a distal segment, and the share of their
    touching overlap that is free (pairs,): ``COLLISION_CONTACT_FREE`` for two of the fingers
    index .. little and for the palm against a distal segment, else 0."""
    ch, sg = model.g_chain, model.g_segment
    i, j = np.triu_indices(model.n_gaussians, k=1)
    fingers = (ch[i] >= 0) & (ch[j] >= 0) & (ch[i] != ch[j])
    palm_finger = ((ch[i] < 0) & (ch[j] >= 0) & (sg[j] >= 1)) | (
        (ch[j] < 0) & (ch[i] >= 0) & (sg[i] >= 1)
    )
    keep = fingers | palm_finger
    i, j = i[keep], j[keep]
    palm_distal = ((ch[i] < 0) & (sg[j] == 2)) | ((ch[j] < 0) & (sg[i] == 2))
    side_by_side = (ch[i] >= 1) & (ch[j] >= 1)  # (the thumb is chain 0)
    free = np.where(palm_distal | side_by_side, COLLISION_CONTACT_FREE, 0.0)
    return i, j, np.where(palm_distal, PALM_DISTAL_COLLISION, 1.0), free


_CONST_CACHE: dict[int, tuple[HandModel, _ModelConstants]] = {}


def model_constants(model: HandModel) -> _ModelConstants:
    """Collision pairs and ``E(C_h, C_h)`` of a model (cached per model object)."""
    hit = _CONST_CACHE.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    pi, pj, weight, free = _collision_pairs(model)
    centres = gaussian_centres(model, rest_pose())
    d2 = ((centres[:, None, :] - centres[None, :, :]) ** 2).sum(-1)
    s2 = model.g_sigmas**2
    ss = s2[:, None] + s2[None, :]
    norm_h = float(((_TWO_PI * s2[:, None] * s2[None, :] / ss) ** 1.5 * np.exp(-0.5 * d2 / ss)).sum())
    s2p = s2[pi] + s2[pj]
    amp = (_TWO_PI * s2[pi] * s2[pj] / s2p) ** 1.5 * weight
    touch = model.g_sigmas[pi] + model.g_sigmas[pj]
    gather_i = 3 * pi[None, :] + np.arange(3)[:, None]
    gather_j = 3 * pj[None, :] + np.arange(3)[:, None]
    const = _ModelConstants(
        pair_s2=s2p,
        pair_amp=amp,
        pair_free=amp * np.exp(-0.5 * touch * touch / s2p) * free,
        pair_chain=np.stack([model.g_chain[pi], model.g_chain[pj]]),
        gather_i=gather_i,
        gather_j=gather_j,
        scatter=np.concatenate([gather_i.ravel(), gather_j.ravel()]),
        norm_h=norm_h,
        fan=np.arctan2(model.rest_rotations[1:, 1, 0], model.rest_rotations[1:, 0, 0]),
    )
    if len(_CONST_CACHE) > 32:
        _CONST_CACHE.clear()
    _CONST_CACHE[id(model)] = (model, const)
    return const



def contact_shares(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """How curled each chain is at ``theta`` (26,), for :class:`Objective`'s ``contact``,
    shape (5,) in [0, 1]: 0 for the thumb; for index .. little their MCP + PIP flexion mapped
    linearly from ``CONTACT_CURL_RAD[0]`` (0) over ``CONTACT_CURL_RAD[1]`` rad (1)."""
    lo, span = CONTACT_CURL_RAD
    share = np.zeros(5)
    share[1:] = np.clip((theta[FINGER_MCP] + theta[FINGER_PIP] - lo) / span, 0.0, 1.0)
    return share



class CollisionTerm:
    """``E_col`` of :class:`~hand_sog_tracker.core.objective.Objective` (a mixin: reads its
    ``_const`` and ``_col_free``)."""

    def _collision(
        self,
        P: NDArray[np.float64],
        g3: NDArray[np.float64] | None,
        w_col: float,
        later: list[Backward] | None = None,
        lay: _Rows | None = None,
    ) -> float | NDArray[np.float64]:
        """``E_col`` (eq. 6); adds ``-w_col dE_col/dP`` into ``g3`` (or appends the function
        that does to ``later``).  ``P``, ``g3``: (m, 3), or (B, m, 3) with the batch's layout
        ``lay`` (then ``E_col`` is (B,))."""
        c = self._const
        # The pairs' differences as rows x, y, z (..., 3, pairs): every step below runs along
        # contiguous rows.  (In place where a value is not needed again: the same operations,
        # fewer temporaries.)
        flat = P.reshape(P.shape[:-2] + (-1,))
        diff = flat.take(c.gather_i, axis=-1)
        diff -= flat.take(c.gather_j, axis=-1)
        sq = diff * diff
        r2 = sq[..., 0, :] + sq[..., 1, :]
        r2 += sq[..., 2, :]  # = sq.sum(-2), several times cheaper
        D = np.multiply(r2, -0.5, out=r2)
        D /= c.pair_s2
        np.exp(D, out=D)
        D *= c.pair_amp  # pair_amp exp(-0.5 r2 / s2)
        over = np.subtract(D, self._col_free)  # the overlap beyond the free share: counts if > 0
        col = _sum(np.maximum(over, 0.0, out=over), axis=-1) / c.norm_h
        if lay is None:
            col = float(col)
        if (g3 is None and later is None) or w_col <= 0:
            return col
        scatter = c.scatter if lay is None else lay.col_scatter

        def backward(g3: NDArray[np.float64]) -> None:
            D2 = np.multiply(D, w_col / c.norm_h, out=D)
            D2 *= over > 0.0  # (0 for the pairs within their free share)
            D2 /= c.pair_s2
            # -w_col dE_col/dP_i (3, pairs), then its negative: the weights of the incidence
            # product (+ g at each pair's i, - g at its j) as one bincount.  (Every centre
            # coordinate sums its pairs in the same order as with the pairs' rows (pairs, 3):
            # the i's in pair order, then the j's.)
            # (In a batch, pose after pose: each pose's i's, then its j's.)
            weights = np.empty(diff.shape[:-2] + (2,) + diff.shape[-2:])
            np.multiply(D2[..., None, :], diff, out=weights[..., 0, :, :])
            np.negative(weights[..., 0, :, :], out=weights[..., 1, :, :])
            g3 += np.bincount(scatter, weights=weights.reshape(-1), minlength=g3.size).reshape(g3.shape)

        run_or_defer(backward, g3, later)
        return col
