"""The tracking objective and its analytic gradient (paper 000, sec. 5.2).

:class:`Objective` sums the terms (each in its own module of this package, with its gradient
beside its energy) on one evaluation of the pose's kinematics.

``E = E_sim - w_c E_col - w_d E_dan - w_l E_lim - w_s E_smo - w_o E_ord - w_cpl E_cpl
- w_curl E_curl - w_sal E_sal - w_sil E_sil`` is maximised over the 26 pose parameters.
``E_sil`` (every model Gaussian projects onto the hand's pixels) lives in
:mod:`hand_sog_tracker.core.silhouette`.  The last five terms are not in paper 000:
``E_ord`` keeps the four fingers in their order across the palm (no finger may swing over
onto its neighbour's data), ``E_cpl`` couples each finger's DIP to its PIP (seed 004),
``E_curl`` keeps a finger's bend from piling up at its last two joints, and
``E_sal`` pulls fingertips toward the detections assigned to them (seed 001, eq. 12; see
:mod:`hand_sog_tracker.core.salient`).  Overlaps of unnormalised isotropic Gaussians (eq. 4)
have closed forms: in d dimensions

``D_pq = (2 pi s_p^2 s_q^2 / (s_p^2 + s_q^2))^(d/2) exp(-|mu_p - mu_q|^2 / (2 (s_p^2 + s_q^2)))``.

Choices the paper leaves open (documented here, used everywhere):

* the projected sigma uses ``f = sqrt(fx * fy)``;
* ``E_sim`` saturates per image Gaussian (not in eq. 5): image Gaussian ``q``'s overlap with
  the model, ``S_q = sum_p Delta_pq D_pq``, counts as ``G k_q (1 - exp(-S_q / k_q))`` with
  ``k_q = SIM_SATURATION pi s_q^2`` (``pi s_q^2`` is its overlap with itself) and
  ``G = SIM_GAIN``.  With eq. 5's plain sum two model fingers on one finger's data score
  twice, which is how a finger takes its neighbour's place when the neighbour curls into the
  palm (more so on a hand larger than the model); saturated, the second finger adds little
  and the data that only a curled finger explains win.  ``G`` keeps the term's gradient at
  its plain scale where the data are covered once (``S_q`` about 2.4 ``pi s_q^2`` on
  correctly fitted frames: ``G exp(-0.8) = 0.9``);
* ``E_col`` counts pairs of Gaussians on different chains, and palm Gaussians
  against finger Gaussians beyond the first segment (neighbours on one chain
  overlap by design), the palm against distal segments weighted down
  (``PALM_DISTAL_COLLISION``: a fist presses the finger pads into the palm);
  curled fingers touch by nature (side by side in a fist, the pads on the palm): two of the
  fingers index .. little, or the palm and a distal segment, pay only their overlap beyond
  ``COLLISION_CONTACT_FREE`` of the overlap they have touching (centres ``s_i + s_j`` apart,
  as two of the renderer's capsules), scaled by how curled the fingers were in the previous
  frame (:func:`contact_shares`; the less curled finger of a pair counts).  At full cost two
  fingers touching pay ``exp(-1) = 37%`` of lying on each other, and the model spread curled
  fingers apart and off their data; for open fingers the full cost stays, because there the
  spacing tells the fingers apart (free for open fingers too, two model fingers lay side by
  side on one finger's data).  Initialisation and calibration use the full cost;
  ``E(C_h, C_h)`` is computed once per model in the rest pose;
* ``E_dan`` (eq. 7) measures how far a model Gaussian is from the data with an
  occlusion-aware distance instead of the plain 3D distance to back-projected
  quad centres (which calls every occluded or quad-interior Gaussian dangling
  and pulls a correct pose away): lateral distance in mm at the Gaussian's depth
  from its projected centre to the quad's extent, combined with how far the
  data lie *behind* the model's surface (data in front of it are occluders, not
  evidence of dangling).  The term is made continuous so that the gradient
  exists almost everywhere: membership of the dangling set ``D`` is a weight
  that ramps from 0 to 1 as the distance to the nearest data Gaussian grows from
  ``TAU1_MM`` to ``2 TAU1_MM``; ``phi`` ramps from 0 to 1 between ``TAU1_MM`` and
  ``TAU2_MM`` (the paper's ramp drops back to 0 beyond ``TAU2_MM``, a jump); the
  sum over data Gaussians is divided by their number so the term does not grow
  with image resolution;
* ``E_sim`` can weight each model Gaussian's overlaps by its visibility at a given pose
  (:func:`visibility_weights`; the ``visible_from`` pose of :class:`Objective`, kept fixed
  while the objective is maximised: the gradient is that of a fixed weighting).  Without
  it, a model Gaussian hidden behind others still earns overlap with the surface in front
  of it (``Delta`` ramps over ``2 sigma_h`` either side); in a fist facing the camera the
  palm behind the curled fingers and the fingertips tucked behind their middle segments
  pull the model forward onto the fingers' surface.  The tracker uses it only to refine the
  answer of a frame with a curled finger (:class:`~hand_sog_tracker.core.tracker.Tracker`);
* ``E_smo`` (eq. 9) measures translations in units of ``SMOOTH_TRANSLATION_MM``
  so that millimetres and radians are weighed alike;
* ``E_ord = sum_c max(ORDER_MIN_GAP_RAD - (a_{c+1} - a_c), 0)^2`` over the neighbouring
  finger pairs (index-middle, middle-ring, ring-little), where ``a_c`` is finger ``c``'s
  direction in the palm plane (its rest fan-out angle plus its MCP abduction), rad^2 like
  ``E_lim``;
* ``E_cpl = sum_c max(DIP_c - COUPLING_DIP_PIP PIP_c, 0)^2`` over index .. little (rad^2 like
  ``E_lim``): seed 004's coupled joints (DIP = 2/3 PIP), one-sided.  A finger curled toward
  the camera hides its distal segments behind its proximal ones, and the overlap terms then
  prefer a half-flexed MCP with PIP and DIP at their limits (the bend moved to the end of the
  finger, the fingertip 15-25 mm from a fist's) to the true curl; a DIP flexed less than 2/3
  of its PIP costs nothing (the claw of a hand pressing on a surface, a DIP held straight);
* ``E_curl = sum_c max(PIP_c + DIP_c - CURL_MAX_RAD, 0)^2`` over index .. little (rad^2 like
  ``E_lim``; not in the seeds, issue 11): the same failure as ``E_cpl``'s, seen as its cause.
  A finger curled into the palm of a hand facing the camera hides its distal segments, and the
  overlap terms then fold it at PIP and DIP to their limits (110 + 90 deg) with the MCP at
  25-35 deg instead of 80: the fingertip 20-24 mm from a fist's.  No real finger bends its
  last two joints that far (a fist: about 100 + 60 deg), so the term only costs past
  165 deg; unlike ``E_cpl`` it leaves a DIP flexed with a straight PIP alone (labelled real
  frame 4 is fitted that way and kept with it; with ``E_cpl`` it lost two fingers);
* ``E_sal = sum_t w_t (sqrt(d_t^2 + c^2) - c) / SALIENT_SCALE_MM`` with ``d_t`` the distance
  (mm) of fingertip ``t`` from its assigned detection, ``w_t`` the detection's confidence
  (0 without one) and ``c = SALIENT_SOFT_MM``: a pseudo-Huber cost, flat within a few mm
  (the detector is not more precise, seed 001 ignores pairs under 10 mm) and growing
  linearly far away, so a wrong detection cannot dominate the data term.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import N_PARAMS, HandModel
from hand_sog_tracker.core.kinematics import (
    CentresPullback,
    centres_batch,
    centres_with_pullback,
    check_poses,
    gaussian_centres,
    posed_centres,
)
from hand_sog_tracker.core.objective.arrays import _UNSET, Backward, _accumulate, _as_slice, _flat_cols
from hand_sog_tracker.core.objective.collision import CollisionTerm, model_constants
from hand_sog_tracker.core.objective.constants import SIM_SATURATION
from hand_sog_tracker.core.objective.data import DataTerms, _data_constants, _Rows, visibility_weights
from hand_sog_tracker.core.objective.interhand import InterHand
from hand_sog_tracker.core.objective.pose import PoseTerms
from hand_sog_tracker.core.objective.tips import SalientTerm, TipTargets, _stacked_targets
from hand_sog_tracker.core.silhouette import Silhouette, silhouette_term
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import InputError

__all__ = ["EnergyTerms", "Objective"]


@dataclass(frozen=True)
class EnergyTerms:
    """Values of the objective and its terms (unitless)."""

    total: float
    sim: float
    col: float
    dan: float
    lim: float
    smo: float
    ord: float = 0.0
    sal: float = 0.0
    sil: float = 0.0
    cpl: float = 0.0
    curl: float = 0.0




def _batch_total(sim: NDArray[np.float64] | float, terms: tuple) -> NDArray[np.float64] | float:
    """``sim - w_1 v_1 - w_2 v_2 - ...`` of a batch, in this order, for ``terms`` ``(w, v)``: a
    term whose value is the scalar 0 (0 at every pose) or whose weight is 0 is left out (it
    would subtract zeros: the same bits, one NumPy call per term fewer)."""
    total = sim
    for w, v in terms:
        if w != 0.0 and (type(v) is not float or v != 0.0):  # (the terms' zeros are the float 0.0)
            total = total - w * v
    return total


class _BatchState:
    """The batch layouts of one model, data and visibility weights (see
    :meth:`Objective._layout`): ``layouts`` by batch size, the capacity ``cap`` (poses) of the
    ``buffers`` they are views of (a plain class with slots)."""

    __slots__ = ("model", "data", "visibility", "layouts", "cap", "buffers")

    def __init__(self, model: HandModel, data: ImageSoG, visibility: NDArray[np.float64] | None) -> None:
        self.model, self.data, self.visibility = model, data, visibility
        self.layouts: dict[int, _Rows] = {}
        self.cap, self.buffers = 0, ()


#: The last few :class:`_BatchState` of this thread (oldest first): a frame's objectives share
#: one, and a thread of its own gets its own (their buffers are scratch of an evaluation).
_BATCH_STATES = threading.local()
_BATCH_STATES_SIZE = 3


def _batch_state(model: HandModel, data: ImageSoG, visibility: NDArray[np.float64] | None) -> _BatchState:
    """The :class:`_BatchState` of ``model``, ``data`` and ``visibility`` (by identity)."""
    states: list[_BatchState] | None = getattr(_BATCH_STATES, "states", None)
    if states is None:
        states = _BATCH_STATES.states = []
    for st in states:
        if st.model is model and st.data is data and st.visibility is visibility:
            return st
    st = _BatchState(model, data, visibility)
    if len(states) >= _BATCH_STATES_SIZE:
        del states[0]
    states.append(st)
    return st

#: The pair buffers of this thread by ``(m, n)`` (see :func:`_pair_buffers`), the latest few.
_PAIR_BUFFERS = threading.local()
_PAIR_BUFFERS_SIZE = 4


def _pair_buffers(cap: int, m: int, n: int) -> tuple[NDArray, ...]:
    """The batch layouts' buffers that depend on the shapes alone, for at least ``cap`` poses
    of ``m`` model and ``n`` data Gaussians: the candidate tests (2 cap m n,) and their outcome
    (cap m n,) (scratch), each row's first flat pair index (cap m + 1,) and each flat index's
    image Gaussian in its pose's block (cap m n,) (read-only).  Shared by every layout of this
    thread with these shapes (a frame's and a new track's stages make several data of one
    size): a new layout's first touch of fresh buffers of megabytes costs as much as a batch.
    Grown (made anew) when a layout needs more poses."""
    cache: dict | None = getattr(_PAIR_BUFFERS, "by_shape", None)
    if cache is None:
        cache = _PAIR_BUFFERS.by_shape = {}
    hit = cache.get((m, n))
    if hit is None or hit[0] < cap:
        col_of = np.empty((cap, m, n), dtype=np.int64)
        col_of[:] = (n * np.arange(cap))[:, None, None] + np.arange(n)
        row_starts = np.arange(cap * m + 1) * n
        for arr in (col_of, row_starts):
            arr.setflags(write=False)
        hit = (cap, np.empty(2 * cap * m * n), np.empty(cap * m * n, dtype=bool), row_starts, col_of.reshape(-1))
        cache.pop((m, n), None)
        if len(cache) >= _PAIR_BUFFERS_SIZE:
            del cache[next(iter(cache))]
        cache[(m, n)] = hit
    return hit[1:]


def _tile(x: NDArray[np.float64], cap: int) -> NDArray[np.float64]:
    """``np.tile(x, cap)`` of a 1-D ``x`` (its values ``cap`` times over, (cap k,)), without the
    Python layer of ``np.tile``."""
    out = np.empty((cap, x.size))
    out[:] = x
    return out.reshape(-1)


#: The collision gradient's scatter of a batch by model constants (with them, which keeps the
#: ids valid): for the most poses asked for so far; fewer poses read its first part.
_SCATTERS: dict[int, tuple[object, int, NDArray[np.int64]]] = {}


def _collision_scatter(c, cap: int, m: int) -> NDArray[np.int64]:
    """The flat indices into (cap m 3,) of the collision gradient's weights, pose after pose
    (each pose's i's, then its j's), for the model constants ``c`` and at least ``cap`` poses
    (read-only; cached per model constants)."""
    hit = _SCATTERS.get(id(c))
    if hit is None or hit[0] is not c or hit[1] < cap:
        offsets = 3 * m * np.arange(cap)[:, None, None, None]
        scatter = (np.stack([c.gather_i, c.gather_j]) + offsets).reshape(-1)
        scatter.setflags(write=False)
        if len(_SCATTERS) >= 16:
            _SCATTERS.clear()
        hit = _SCATTERS[id(c)] = (c, cap, scatter)
    return hit[2]


class Objective(DataTerms, CollisionTerm, PoseTerms, SalientTerm):
    """The objective ``E(theta)`` for one frame, at one pose (:meth:`__call__`) or at a batch
    of poses in one evaluation (:meth:`batch`).

    Parameters
    ----------
    model : HandModel
    data : ImageSoG
        The frame's depth Gaussians.
    config : TrackerConfig
        Term weights ``w_col``, ``w_dan``, ``w_lim``, ``w_smo``.
    previous : (theta_{t-1}, theta_{t-2}) or None
        The two previous poses, shape (26,) each; None disables ``E_smo``.
    silhouette : Silhouette or None
        The hand's silhouette for ``E_sil`` (:mod:`hand_sog_tracker.core.silhouette`);
        None disables it.
    targets : TipTargets or None
        Assigned fingertip detections; None disables ``E_sal``.
    contact : array, shape (5,), or None
        How curled each chain is, in [0, 1] (:func:`contact_shares` of the previous frame's
        pose): the touching pairs of curled fingers pay only their overlap beyond a share of
        their touching overlap (see the module docstring).  None: every pair pays its whole
        overlap (initialisation and calibration, where no track tells the fingers apart and
        their spacing does).
    visible_from : array, shape (26,), or None
        A pose whose :func:`visibility_weights` weight each model Gaussian's overlaps in
        ``E_sim`` (fixed for this objective); None: every Gaussian counts in full.
    """

    def __init__(
        self,
        model: HandModel,
        data: ImageSoG,
        config: TrackerConfig,
        previous: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
        targets: TipTargets | None = None,
        silhouette: Silhouette | None = None,
        contact: NDArray[np.float64] | None = None,
        visible_from: NDArray[np.float64] | None = None,
    ) -> None:
        self.model = model
        self.data = data
        self.config = config
        self.previous = previous
        self.targets = targets
        self.silhouette = silhouette
        self.contact = contact
        self.visible_from = visible_from
        #: Another hand's spheres this hand's may not penetrate (``- w E_int``,
        #: :mod:`.interhand`; set by the multi-hand tracker); None: no such term.
        self.interhand: InterHand | None = None
        self._visibility = (
            None if visible_from is None else visibility_weights(model, visible_from, data.intrinsics)
        )
        self._const = model_constants(model)
        # The overlap each collision pair has free, (pairs,) or 0; a pair's share is its less
        # curled finger's (the palm's entry, chain -1, is 1).
        self._col_free: NDArray[np.float64] | float = 0.0
        if contact is not None:
            share = np.append(contact, 1.0).take(self._const.pair_chain)  # (2, pairs)
            self._col_free = self._const.pair_free * np.minimum(share[0], share[1])
        intr = data.intrinsics
        self._f = float(np.sqrt(intr.fx * intr.fy))
        # Per-frame constants of the data terms (shared by the frame's objectives).
        (
            self._mu_u, self._mu_v, self._sq2, self._half, self._cand, self._row_starts, self._per_q,
        ) = _data_constants(data, model.n_gaussians)
        self._col_of = _flat_cols(model.n_gaussians, data.n)
        # The silhouette term reads the data terms' projections when both use the same camera.
        self._sil_shares_projection = silhouette is not None and silhouette.intrinsics == intr
        self._mu_uv = self._per_q[:2, None, :]  # (2, 1, n) px: mu_u, mu_v (a view)
        self._sat = (SIM_SATURATION * np.pi) * self._per_q[3]  # k_q of E_sim, (n,) px^2
        sh = model.g_sigmas
        self._shf = sh * self._f
        self._fxy = np.array([[intr.fx], [intr.fy]], dtype=np.float64)
        self._cxy = np.array([[intr.cx], [intr.cy]], dtype=np.float64)
        self._two_sh = 2.0 * sh
        self._four_sh2 = self._two_sh * self._two_sh
        # Per model Gaussian values of one evaluation of _data_terms, rows 2 (ones) and 8
        # (2 sigma_h) set once (see there).
        self._limits_low, self._limits_high = model.bounds  # (26,) rad
        rows = np.empty((11, model.n_gaussians))
        rows[2] = 1.0
        rows[8] = self._two_sh
        # The candidate tests of all pairs and their outcome (filled by every evaluation).
        tests = np.empty((2, model.n_gaussians, data.n))
        neg = np.empty((model.n_gaussians, data.n), dtype=bool)
        self._one = _Rows(
            1, False, rows, tests, neg, self._row_starts, self._col_of, self._per_q, self._sat,
            model.g_sigmas, self._shf, self._two_sh, self._four_sh2, self._visibility, self._const.scatter,
        )
        # The batches' layouts (see _layout), shared by the objectives of this model, data and
        # visibility weights (found at the first batch).
        self._batch_state: _BatchState | None = None
        # (targets, their constants or None) of the last targets seen by _salient.
        self._sal: tuple[object, tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]] | None] = (
            _UNSET, None
        )
        # What :meth:`support` needs of the last evaluation: the pose's bytes, and per pair
        # (sorted by model Gaussian) ``Delta D`` with the pairs' row bounds and the depths z.
        self._support_key = b""
        self._evaluations = 0  # (counts evaluations: a deferred gradient checks it is current)
        self._support_src: tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]] | None = None
        # The fingertips as a slice or indices (the batches' targets), and the last batch's
        # parts with what the data terms need of them (see _batch_parts); made when first used.
        self._tips: slice | NDArray[np.int64] | None = None
        self._parts: tuple[tuple, tuple[NDArray, ...]] | None = None

    def __call__(
        self, theta: NDArray[np.float64], gradient: bool = True
    ) -> tuple[float, NDArray[np.float64] | None]:
        """Return ``E(theta)`` and, with ``gradient``, ``dE/dtheta`` of shape (26,)."""
        values, grad = self._evaluate(theta, gradient, False)
        return values[0], grad

    def batch(
        self,
        thetas: NDArray[np.float64],
        gradient: bool = True,
        targets: Sequence[TipTargets | None] | None = None,
        parts: NDArray[np.bool_] | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """``E`` at every pose of ``thetas`` (B, 26) and, with ``gradient``, ``dE/dtheta``
        (B, 26): pose by pose what :meth:`__call__` returns (the same bits; the gradient None
        without ``gradient``).

        ``parts`` (B, n) bool: pose ``b`` sees only the data Gaussians ``parts[b]`` (at least
        one): it gets what the objective of ``data.subset(parts[b])`` gives it, up to rounding
        (e.g. start poses that each drop the data beyond their own wrist, fitted as one batch).

        ``targets``: one :class:`TipTargets` (or None: no ``E_sal``) per pose, in place of the
        objective's ``targets`` (e.g. each candidate's own fingertip assignment): pose ``b``
        then gets what ``self.variant(self.config, targets[b])(thetas[b])`` returns.

        One evaluation with a leading batch axis through every term: the kinematics, the data
        terms (the B m model Gaussians against the data as the m of one pose), collision,
        silhouette, salient and the pose terms, so that B poses cost about the per-call cost of
        one evaluation plus B times its arithmetic.
        """
        thetas = check_poses(thetas)
        B = thetas.shape[0]
        if targets is not None and len(targets) != B:
            raise InputError(f"targets: one per pose ({B}), got {len(targets)}")
        if B == 0:
            return np.zeros(0), np.zeros((0, N_PARAMS)) if gradient else None
        if parts is not None and parts.shape != (B, self.data.n):
            raise InputError(f"parts: one (n,) mask per pose, shape ({B}, {self.data.n}), got {parts.shape}")
        if B == 1 and targets is None and parts is None:  # (one pose: the one-pose path, faster, the same bits)
            value, grad = self(thetas[0], gradient)
            return np.array([value]), None if grad is None else grad[None]
        if targets is None:
            each = _UNSET
        else:
            if self._tips is None:
                self._tips = _as_slice(self.model.tip_index)
            each = _stacked_targets(targets, self._tips)
        values, grads = self._evaluate(
            thetas, gradient, False, targets_each=each, parts=None if parts is None else self._batch_parts(parts)
        )
        return values[0], grads

    def _batch_parts(self, parts: NDArray[np.bool_]) -> tuple[NDArray[np.float64], ...]:
        """What the data terms need of the poses' parts (B, n): 0 or +inf per pose and data
        Gaussian (B, n), each part's ``1 / norm`` (B,) and size (B,), the parts as 0 / 1 (B, n)
        and as bool (B, n).  Kept for the last parts: a batch fit passes the same parts (or
        those of the candidates still running) every iteration."""
        key = (parts.dtype.str, parts.shape, parts.tobytes())
        if self._parts is not None and self._parts[0] == key:
            return self._parts[1]
        keep = np.asarray(parts, dtype=np.float64)
        sizes = keep.sum(axis=1)
        if not (sizes > 0).all():
            raise InputError("parts: every pose needs at least one data Gaussian")
        norm = (2.0 * np.pi**2) * (keep @ (self.data.sigma * self.data.sigma))  # (as ImageSoG.subset's)
        made = np.where(parts, 0.0, np.inf), 1.0 / norm, sizes, keep, np.array(parts, dtype=bool)
        self._parts = (key, made)
        return made

    def value_then_gradient(
        self, theta: NDArray[np.float64]
    ) -> tuple[float, Callable[[], NDArray[np.float64]]]:
        """``E(theta)`` now and ``dE/dtheta`` (26,) on demand: the returned function computes
        the gradient that ``self(theta)`` would return (the same bits) from what this
        evaluation kept, at the cost of the gradient's share only (about a third of an
        evaluation with gradient).

        For an optimiser that decides from the value whether it needs the gradient (the last
        iterate of :func:`~hand_sog_tracker.core.optimizer.maximise`).  The function must be
        called before the objective is evaluated again (its buffers are reused): later it
        raises :class:`RuntimeError`.
        """
        later: list[Backward] = []
        values, finish = self._evaluate(theta, True, False, later)
        assert finish is not None
        return values[0], finish

    def evaluate(
        self, theta: NDArray[np.float64], gradient: bool = True
    ) -> tuple[EnergyTerms, NDArray[np.float64] | None]:
        """Return every term of ``E(theta)`` and optionally the gradient, shape (26,)."""
        v, grad = self._evaluate(theta, gradient, True)
        terms = EnergyTerms(
            total=v[0], sim=v[1], col=v[2], dan=v[3], lim=v[4], smo=v[5], ord=v[6], sal=v[7], sil=v[8],
            cpl=v[9], curl=v[10],
        )
        return terms, grad

    def variant(self, config: TrackerConfig, targets: TipTargets | None) -> Objective:
        """This frame's objective with other term weights ``config`` and ``targets`` (the same
        model, data, previous poses, silhouette, ``contact`` and visibility; the collision
        pairs' free overlap and the visibility weights are shared, not computed again)."""
        other = Objective(self.model, self.data, config, self.previous, targets, self.silhouette)
        other.contact, other._col_free = self.contact, self._col_free
        other.visible_from, other._visibility = self.visible_from, self._visibility
        other.interhand = self.interhand
        other._one.visibility = self._visibility
        return other

    def salient(self, theta: NDArray[np.float64]) -> float:
        """``E_sal`` at ``theta`` (26,), unweighted (0 without targets or with ``w_sal`` 0): what
        the objective without its targets lacks, ``E + w_sal E_sal``, costs no data terms."""
        return float(self._salient(posed_centres(self.model, theta), None, self.config.w_sal))

    def support(self, theta: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """:func:`gaussian_support` at ``theta`` (m,) from the last evaluation, when that was at
        ``theta`` (the same sums up to rounding: the same pairs and values); else None.

        A tracked frame's fit usually ends at its best pose: its confidence then costs no
        second pass over the pairs.  None too for an objective with visibility weights (its
        overlaps are weighted).
        """
        src = self._support_src
        if src is None or self._visibility is not None or theta.tobytes() != self._support_key:
            return None
        delta_D, bounds, z = src
        m = z.size
        support = _accumulate(np.arange(m).repeat(bounds[1:] - bounds[:-1]), delta_D, m)
        sp = self._shf / z
        support /= 2 * np.pi**2 * sp * sp
        return np.minimum(support, 1.0, out=support)

    def _layout(self, B: int) -> _Rows:
        """The :class:`_Rows` of a batch of ``B`` poses (cached per ``B``).

        Made once for the largest batch so far; a smaller batch's layout is the first B m rows
        (B m n pairs, B n image Gaussians) of it, as views: a batch that shrinks from call to
        call (:func:`~hand_sog_tracker.core.optimizer.maximise_batch` leaves settled
        candidates out) makes no new arrays.  The layouts are shared by every objective of
        the same model, data and visibility weights (a frame's objective, its variants and
        its pulls; a new track's stages): their buffers are scratch that each batch
        evaluation writes before it reads them, and the rest is the model's and the data's.
        The pair buffers and index tables that depend on the shapes alone are shared further,
        by every layout of this thread with the same m and n (:func:`_pair_buffers`), and the
        collision scatter by every layout of the model (:func:`_collision_scatter`).
        """
        state = self._batch_state
        if state is None or state.visibility is not self._visibility:
            state = self._batch_state = _batch_state(self.model, self.data, self._visibility)
        hit = state.layouts.get(B)
        if hit is not None:
            return hit
        m, n = self.model.n_gaussians, self.data.n
        cap, full = state.cap, state.buffers
        if B > cap:
            state.layouts.clear()
            cap = B
            tests, neg, row_starts, col_of = _pair_buffers(cap, m, n)
            rows = np.empty((11, cap * m))
            rows[2] = 1.0
            two_sh = _tile(self._two_sh, cap)
            rows[8] = two_sh
            vis = None if self._visibility is None else _tile(self._visibility, cap)
            per_q = np.empty((self._per_q.shape[0], cap, n))
            per_q[:] = self._per_q[:, None, :]
            full = (
                rows, tests, neg, row_starts, col_of, per_q.reshape(-1, cap * n), _tile(self._sat, cap),
                _tile(self.model.g_sigmas, cap), _tile(self._shf, cap), two_sh, _tile(self._four_sh2, cap), vis,
                _collision_scatter(self._const, cap, m),
            )
            state.cap, state.buffers = cap, full
        rows, tests, neg, row_starts, col_of, per_q, sat_k, sigmas, shf, two_sh, four_sh2, vis, scatter = full
        k = B * m
        lay = state.layouts[B] = _Rows(
            B, True, rows[:, :k], tests[: 2 * k * n].reshape(2, k, n), neg[: k * n].reshape(k, n),
            row_starts[: k + 1], col_of[: k * n], per_q[:, : B * n], sat_k[: B * n], sigmas[:k], shf[:k],
            two_sh[:k], four_sh2[:k], None if vis is None else vis[:k], scatter[: 2 * self._const.gather_i.size * B],
        )
        return lay

    def _evaluate(
        self,
        theta: NDArray[np.float64],
        gradient: bool,
        terms: bool = True,
        later: list[Backward] | None = None,
        targets_each: tuple | None | object = _UNSET,
        parts: tuple[NDArray[np.float64], ...] | None = None,
    ) -> tuple[tuple[float, ...], NDArray[np.float64] | Callable[[], NDArray[np.float64]] | None]:
        """``(total, sim, col, dan, lim, smo, ord, sal, sil, cpl, curl)`` and the gradient (or None).

        ``theta``: one pose (26,) (floats and a gradient (26,)) or a batch (B, 26) (from
        :meth:`batch`: the total (B,), the terms (B,) arrays or 0.0 for a term 0 at every pose,
        the gradient (B, 26); not with ``later``).

        The shared body of :meth:`__call__` (the optimiser's path: no :class:`EnergyTerms`),
        :meth:`evaluate` and :meth:`value_then_gradient`.  Without ``terms`` (only the total
        and the gradient are read) a term whose weight is 0 is not evaluated (reported as 0):
        the total and the gradient are the same bits (it would add ``0 * value``).  With
        ``later`` (an empty list) the terms append their gradients' functions there and the
        function that finishes the gradient is returned in its place.  ``targets_each``: the
        salient term's constants for poses (B, 26) with their own targets (see :meth:`_salient`).
        """
        batch = theta.ndim == 2
        self._support_key = b"" if batch else theta.tobytes()
        self._support_src = None
        self._evaluations += 1
        cfg = self.config
        if batch:  # P (B, m, 3), the data terms' rows (B m, 3) (views)
            P, pullback = centres_batch(self.model, theta, gradient)
            g3 = np.zeros(P.shape) if gradient else None
            lay: _Rows | None = self._layout(theta.shape[0])
            P_rows, g3_rows = P.reshape(-1, 3), None if g3 is None else g3.reshape(-1, 3)
        elif later is not None:
            P, pullback, g3 = gaussian_centres(self.model, theta), None, None
        elif gradient:
            P, pullback = centres_with_pullback(self.model, theta)
            g3 = np.zeros(P.shape)
        else:
            P, pullback, g3 = gaussian_centres(self.model, theta), None, None
        if not batch:
            lay, P_rows, g3_rows = None, P, g3
        # The model Gaussians' depths and projections (fx x / z, fy y / z), shared by the data
        # and silhouette terms.
        z = np.maximum(P_rows[:, 2], 1.0)
        proj = np.multiply(self._fxy, P_rows[:, :2].T)
        proj /= z
        sim, dan = self._data_terms(P_rows, g3_rows, cfg.w_dan, z, proj, later, lay, parts)
        col = self._collision(P, g3, cfg.w_col, later, lay)
        lim, g_lim = self._limits(theta)
        if terms or cfg.w_smo != 0.0:
            smo, g_smo = self._smoothness(theta)
        else:  # (the default weight is 0: the optimiser's path skips the term)
            smo, g_smo = 0.0, None
        ordv, g_ord = self._order(theta)
        if terms or cfg.w_cpl != 0.0:
            cpl, g_cpl = self._coupling(theta)
        else:  # (the default weight is 0: the optimiser's path skips the term)
            cpl, g_cpl = 0.0, None
        if terms or cfg.w_curl != 0.0:
            curl, g_curl = self._curl(theta)
        else:  # (a weight of 0: the optimiser's path skips the term, as for E_cpl)
            curl, g_curl = 0.0, None
        # The order, coupling and curl terms' weighted gradient (None: 0, the typical case).
        g_pose = None if g_ord is None else cfg.w_ord * g_ord
        for w, g in ((cfg.w_cpl, g_cpl), (cfg.w_curl, g_curl)):
            if g is not None:
                g_pose = w * g if g_pose is None else g_pose + w * g
        sal = self._salient(P, g3, cfg.w_sal, later, targets_each)
        sil = 0.0
        if self.silhouette is not None and cfg.w_sil > 0:
            sil = silhouette_term(
                self.silhouette, P, g3, cfg.w_sil, (z, proj) if self._sil_shares_projection else None, later
            )
        if batch:
            total = _batch_total(sim, (
                (cfg.w_col, col), (cfg.w_dan, dan), (cfg.w_lim, lim), (cfg.w_smo, smo), (cfg.w_ord, ordv),
                (cfg.w_cpl, cpl), (cfg.w_curl, curl), (cfg.w_sal, sal), (cfg.w_sil, sil),
            ))
        else:
            total = (
                sim
                - cfg.w_col * col
                - cfg.w_dan * dan
                - cfg.w_lim * lim
                - cfg.w_smo * smo
                - cfg.w_ord * ordv
                - cfg.w_cpl * cpl
                - cfg.w_curl * curl
                - cfg.w_sal * sal
                - cfg.w_sil * sil
            )
        if self.interhand is not None:  # (two hands only: one hand's total is unchanged)
            total = total - self.interhand.term(P, self.model.g_sigmas, g3, later)
        if batch and np.ndim(total) == 0:  # (every term 0: a scalar total)
            total = np.full(theta.shape[0], total)
        values = (total, sim, col, dan, lim, smo, ordv, sal, sil, cpl, curl)
        if later is not None:
            stamp = self._evaluations
            theta = theta.copy()

            def finish() -> NDArray[np.float64]:
                if self._evaluations != stamp:
                    raise RuntimeError("a deferred gradient was asked for after a later evaluation")
                P2, pullback = centres_with_pullback(self.model, theta)
                g3 = np.zeros(P2.shape)
                for backward in later:
                    backward(g3)
                return self._gradient(pullback, g3, g_lim, g_smo, g_pose)

            return values, finish
        if pullback is None:
            return values, None
        return values, self._gradient(pullback, g3, g_lim, g_smo, g_pose)

    def _gradient(
        self,
        pullback: CentresPullback,
        g3: NDArray[np.float64],
        g_lim: NDArray[np.float64] | None,
        g_smo: NDArray[np.float64] | None,
        g_pose: NDArray[np.float64] | None,
    ) -> NDArray[np.float64]:
        """``dE/dtheta`` (26,) from ``dE/dP`` (m, 3) and the pose terms' gradients (``g_pose``:
        the order, coupling and curl terms' weighted sum, None for 0)."""
        cfg = self.config
        grad = pullback(g3)  # = einsum("mk,mkj->j", g3, J) up to rounding
        # (A zero g_lim or w_smo = 0: subtracting 0 would change no bit.)
        if g_smo is not None:
            grad -= cfg.w_lim * g_lim + cfg.w_smo * g_smo if g_lim is not None else cfg.w_smo * g_smo
        elif g_lim is not None:
            grad -= cfg.w_lim * g_lim
        if g_pose is not None:
            grad -= g_pose
        return grad
