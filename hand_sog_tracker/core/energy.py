"""The tracking objective and its analytic gradient (paper 000, sec. 5.2).

One job: the objective and its gradient; kept together because every term shares the model
constants and the pose's kinematics, and each gradient reads best next to its energy.

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

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import (
    FINGER_ABD,
    FINGER_DIP,
    FINGER_MCP,
    FINGER_PIP,
    JOINTS,
    N_PARAMS,
    HandModel,
    rest_pose,
)
from hand_sog_tracker.core.kinematics import (
    CentresPullback,
    centres_batch,
    centres_with_pullback,
    check_poses,
    gaussian_centres,
)
from hand_sog_tracker.core.silhouette import Silhouette, run_or_defer, silhouette_term
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import InputError

__all__ = [
    "EnergyTerms",
    "gaussian_support",
    "Objective",
    "TipTargets",
    "TAU1_MM",
    "TAU2_MM",
    "SMOOTH_TRANSLATION_MM",
    "ORDER_MIN_GAP_RAD",
    "COUPLING_DIP_PIP",
    "CURL_MAX_RAD",
    "SALIENT_SOFT_MM",
    "SALIENT_SCALE_MM",
    "SIM_SATURATION",
    "SIM_GAIN",
    "PALM_DISTAL_COLLISION",
    "COLLISION_CONTACT_FREE",
    "CONTACT_CURL_RAD",
    "contact_shares",
    "visibility_weights",
]

#: Near threshold ``tau_1`` of the dangling term (mm): a model Gaussian this close to data is
#: not dangling (paper 000 sec. 5.2 names tau_1, tau_2 without values: chosen here).
TAU1_MM = 15.0
#: Far threshold ``tau_2`` of the dangling term (mm): the penalty ramp ends here (chosen here).
TAU2_MM = 60.0
#: Translation unit of the smoothness term (mm per rad-equivalent; chosen here, paper 000
#: eq. 9 mixes mm and rad unweighted).
SMOOTH_TRANSLATION_MM = 50.0
#: Smallest allowed difference of neighbouring fingers' palm-plane directions (rad, chosen here); at rest
#: they fan out by 0.07-0.09 rad; a finger on its neighbour's data needs about -0.25.
ORDER_MIN_GAP_RAD = -0.05
#: PIP + DIP flexion (rad) beyond which ``E_curl`` costs: 165 deg (chosen here, issue 11: of
#: 150, 160, 165, 170 and 180 deg with ``w_curl`` 0.5, and 165 deg with 1.0, 165 / 0.5 scored
#: best on the dev and the validation renders; the synthetic fist is 95 + 55 = 150 deg, the
#: claw 95 + 75 = 170 deg, and the joint limits allow 110 + 90 = 200 deg).
CURL_MAX_RAD = float(np.deg2rad(165.0))
#: DIP flexion per PIP flexion beyond which ``E_cpl`` costs (unitless; seed 004: DIP = 2/3 PIP).
COUPLING_DIP_PIP = 2.0 / 3.0
#: Width of the flat bottom of the salient-point cost (mm; chosen here, seed 001 ignores pairs
#: under 10 mm).
SALIENT_SOFT_MM = 8.0
#: The salient cost is measured in units of this distance (mm; chosen here).
SALIENT_SCALE_MM = 100.0
#: Overlap (in units of its self-overlap ``pi s_q^2``) at which an image Gaussian's share of
#: ``E_sim`` is 63% saturated (chosen here, issue 11: 3 against 2-16 and none on 240 dev mesh
#: renders and the labelled real frames under small shifts; see the module docstring).
SIM_SATURATION = 3.0
#: Gain of the saturated ``E_sim`` (chosen with ``SIM_SATURATION``, see the module docstring).
SIM_GAIN = 2.0
#: Weight of a palm Gaussian's collision with a distal-segment Gaussian in ``E_col`` (the
#: other pairs weigh 1).  In a fist the finger pads press into the palm, soft tissue that the
#: model's rigid Gaussians count as overlap: at full weight the model held curled fingers off
#: the palm, as claws.  (Chosen here, issue 11: with 0.3 the fist-and-open and finger-counting
#: dev renders went 10.7 -> 10.1 mm on 64 renders, validation fist-and-open 9.3 -> 9.0 mm, the
#: labelled real frames 7.2 -> 6.7 mm; 0 and 0.15 put real frame 4's middle finger on the
#: index, 19 mm mean.)
PALM_DISTAL_COLLISION = 0.3
#: Share of the touching overlap that ``E_col`` does not count for two curled fingers of index
#: .. little and for the palm against a curled finger's distal segment (see the module
#: docstring; chosen here, issue 11, on the 144 dev mesh renders, 7.06 mm before: 0.75 gives
#: 6.45 mm, 1 gives 6.52 mm; for every finger regardless of its curl 0.5, 0.75 and 1 gave 6.65,
#: 6.36 and 6.49 mm).
COLLISION_CONTACT_FREE = 0.75
#: A finger's MCP + PIP flexion (rad) from which its touching pairs get a free share, and the
#: flexion over which the share grows to all of ``COLLISION_CONTACT_FREE``: 0 up to 57 deg, 0.84
#: for MCP 45 and PIP 60 deg, 1 for the synthetic fist's 80 + 95 deg (chosen here, issue 11: from
#: 0.6, 1.0 or 1.4 rad, the dev renders scored 6.65, 6.45 and 6.56 mm, with 5, 0 and 1 renders
#: over 12 mm).  With the free share for every finger, curled or not, two model fingers lay side
#: by side on one finger's data: ``bags/random`` 4.9 -> 8.1 mm, and with a share of 0.5 four dev
#: renders were over 12 mm.
CONTACT_CURL_RAD: tuple[float, float] = (1.0, 1.0)
_TWO_PI = 2.0 * np.pi
_UNSET = object()
_INV_SQRT2 = 1.0 / np.sqrt(2.0)
#: ``x.sum(axis)`` without the method's Python layer (it calls exactly this): the objective
#: runs a few dozen NumPy calls on small arrays per evaluation, where that layer counts.
_sum = np.add.reduce
#: A term's deferred gradient: adds its ``dE/dP`` (with sign and weight) into ``g3`` (m, 3).
Backward = Callable[[NDArray[np.float64]], None]


def _accumulate(index: NDArray[np.int64], weights: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """Sum ``weights`` per ``index`` into a float array of length ``size`` (empty-safe)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


_FLAT_COLS: dict[tuple[int, int], NDArray[np.int64]] = {}


def _flat_cols(m: int, n: int) -> NDArray[np.int64]:
    """Column of every flat index of an (m, n) array, shape (m n,) (cached: divmod is slow)."""
    hit = _FLAT_COLS.get((m, n))
    if hit is None:
        if len(_FLAT_COLS) >= 4:  # n changes from frame to frame: keep only the latest few
            _FLAT_COLS.clear()
        hit = np.empty((m, n), dtype=np.int64)
        hit[:] = np.arange(n)  # (= np.tile(np.arange(n), m), several times cheaper)
        hit = _FLAT_COLS[(m, n)] = hit.reshape(-1)
    return hit


def _as_slice(index: NDArray[np.int64]) -> slice | NDArray[np.int64]:
    """``index`` (k,) as the equivalent slice when its entries are evenly spaced and increasing
    (a slice indexes a view: cheaper than a gather and a scatter), else ``index`` itself."""
    idx = np.asarray(index)
    if idx.ndim != 1 or idx.size < 2 or idx[0] < 0:
        return index
    step = int(idx[1] - idx[0])
    if step <= 0 or not (np.diff(idx) == step).all():
        return index
    return slice(int(idx[0]), int(idx[-1]) + 1, step)


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


_DATA_CACHE: list = [(None, 0, None)]  # (data, m, constants) of the last data: one tuple

#: A candidate pair whose ``r2 scale^2 + min(dd, 0)^2`` is at most this (mm^2) is within
#: ``TAU1_MM`` of its model Gaussian for certain (see :meth:`Objective._data_terms`; the
#: factor leaves 1e-12 for rounding errors below 1e-14).
_NEAR_SAFE = TAU1_MM * TAU1_MM * (1.0 - 1e-12)


def _data_constants(data: ImageSoG, m: int) -> tuple:
    """Constants of the data terms for a frame's data and ``m`` model Gaussians (cached for
    the last data: a frame builds several objectives on the same data).

    Returns ``mu_u, mu_v, sigma^2, half side`` (n,) each, the candidate matrix (2, 6, n) of
    :meth:`Objective._data_terms`, the first flat index of each model Gaussian's row (m + 1,)
    and the per-data values read per pair (4, n): ``mu_u, mu_v, depth, sigma^2``.
    """
    hit = _DATA_CACHE[0]
    if hit[0] is data and hit[1] == m:
        return hit[2]
    n = data.n
    mu_u = np.ascontiguousarray(data.mu[:, 0], dtype=np.float64)
    mu_v = np.ascontiguousarray(data.mu[:, 1], dtype=np.float64)
    sq2 = data.sigma**2
    half = data.sigma * _INV_SQRT2  # half a quad's side, px
    depth = np.asarray(data.depth, dtype=np.float64)
    # Both candidate tests of every (model, data) pair are one matrix product: six values per
    # model Gaussian times two (6, n) blocks (expanded squares, see _data_terms).
    cand = np.zeros((2, 6, n))
    cand[0, 0] = 1.0
    cand[0, 2] = mu_u * mu_u + mu_v * mu_v - 36.0 * sq2
    cand[0, 3] = -2.0 * mu_u
    cand[0, 4] = -2.0 * mu_v
    cand[1, 1] = 1.0
    cand[1, 2] = depth * depth
    cand[1, 5] = -2.0 * depth
    const = (mu_u, mu_v, sq2, half, cand, np.arange(m + 1) * n, np.array([mu_u, mu_v, depth, sq2]))
    _DATA_CACHE[0] = (data, m, const)
    return const


class _Rows:
    """The model Gaussians' constants and buffers of :meth:`Objective._data_terms` (and the
    collision term's scatter) for one pose or a batch of B poses, whose B m model Gaussians
    stand pose after pose (a plain class with slots; see :meth:`Objective._layout`).

    ``rows`` (11, B m) per model Gaussian values (rows 2 and 8 constant), ``tests`` (2, B m,
    n) and ``neg`` (B m, n) the candidate tests' buffers, ``row_starts`` (B m + 1,) the flat
    index of each row's first pair, ``col_of`` (B m n,) the image Gaussian of every flat
    index, in the pose's block (``b n + q``), ``per_q`` (4, B n) and ``sat_k`` (B n,) the
    image Gaussians' values (once per pose), ``sigmas``, ``shf``, ``two_sh``, ``four_sh2``
    and ``visibility`` (B m,) the model Gaussians' (``visibility`` None: all 1),
    ``col_scatter`` the collision gradient's flat indices into (B m 3,).
    """

    __slots__ = (
        "B", "batch", "rows", "tests", "neg", "row_starts", "col_of", "per_q", "sat_k", "sigmas", "shf",
        "two_sh", "four_sh2", "visibility", "col_scatter",
    )

    def __init__(self, B: int, batch: bool, *arrays: NDArray | None) -> None:
        self.B, self.batch = B, batch
        (
            self.rows, self.tests, self.neg, self.row_starts, self.col_of, self.per_q, self.sat_k, self.sigmas,
            self.shf, self.two_sh, self.four_sh2, self.visibility, self.col_scatter,
        ) = arrays


#: Slack (px^2 and mm^2) of the expanded-square candidate tests in :func:`gaussian_support`:
#: far above their rounding (below 1e-7 for images up to 4096 px and depths up to 10 m), so
#: that every pair the exact tests pass is a candidate.
_SUPPORT_SLACK = 1e-3


def gaussian_support(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ImageSoG,
    centres: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """How well the data explain each model Gaussian at ``theta``, shape (m,), in [0, 1].

    For Gaussian ``p`` the depth-weighted overlap with the data, ``sum_q Delta_pq D_pq``,
    divided by its value under a gap-free data tiling at the right depth (``2 pi^2 sp^2``,
    px), capped at 1.  ``centres``: the model Gaussians' centres at ``theta`` (m, 3) mm, when
    already computed.  Only the pairs that can contribute count (as in the objective):
    ``Delta = 0`` beyond two radii in depth, ``D`` is below 1.6e-8 of its peak beyond six
    combined standard deviations.

    The pairs are found as in :meth:`Objective._data_terms` (both tests as one matrix
    product, here with a slack that keeps every pair the exact tests pass), and the exact
    tests and values are then computed on those candidates only: bit-identical to computing
    them on all ``m x n`` pairs, several times cheaper.
    """
    m = model.n_gaussians
    n = data.n
    if n == 0:
        return np.zeros(m)
    intr = data.intrinsics
    P = gaussian_centres(model, theta) if centres is None else centres
    sh = model.g_sigmas
    z = np.maximum(P[:, 2], 1.0)
    # Per model Gaussian (rows): the two tests' own terms, ones, u, v, dp, sp^2, 2 sigma_h
    # (written in place: the same operations as the expressions in the comments).
    rows = np.empty((8, m))
    u, v, dp, sp2, two_sh = rows[3:]
    np.multiply(intr.fx, P[:, 0], out=u)
    u /= z
    u += intr.cx  # fx x / z + cx
    np.multiply(intr.fy, P[:, 1], out=v)
    v /= z
    v += intr.cy  # fy y / z + cy
    np.multiply(sh, np.sqrt(intr.fx * intr.fy), out=sp2)
    sp2 /= z
    np.multiply(sp2, sp2, out=sp2)  # (sh f / z)^2
    np.subtract(z, sh, out=dp)
    np.multiply(2.0, sh, out=two_sh)
    t = u * u
    t += v * v
    t -= 36.0 * sp2
    rows[0] = t  # u^2 + v^2 - 36 sp^2
    np.multiply(dp, dp, out=rows[1])
    rows[1] -= two_sh * two_sh  # dp^2 - (2 sigma_h)^2
    rows[2] = 1.0
    cand, row_starts, per_q = _data_constants(data, m)[4:]
    near = np.matmul(rows[:6].T, cand) < _SUPPORT_SLACK  # (2, m, n): candidates of both tests
    flat = np.logical_and(near[0], near[1], out=near[0]).ravel().nonzero()[0]
    bounds = flat.searchsorted(row_starts)
    per_row = bounds[1:] - bounds[:-1]
    p = np.arange(m).repeat(per_row)
    per_p = rows[3:].repeat(per_row, axis=1)  # u, v, dp, sp^2, 2 sigma_h per pair
    sp2_p, two_sh_p = per_p[3:]
    q = per_q[:4].take(_flat_cols(m, n).take(flat), axis=1)  # mu_u, mu_v, depth, sigma_q^2
    sq2_q = q[3]
    diffs = np.subtract(per_p[:3], q[:3], out=q[:3])  # du, dv, dp - depth
    sq = diffs[:2] * diffs[:2]
    r2 = np.add(sq[0], sq[1], out=sq[0])  # du^2 + dv^2
    dd = np.abs(diffs[2], out=diffs[2])
    s2 = np.add(sp2_p, sq2_q, out=per_p[0])  # s2 = sp^2 + sq^2
    # D = 2 pi sp^2 sq^2 / s2 exp(-0.5 r2 / s2), in this order
    e = np.multiply(-0.5, r2, out=sq[1])
    e /= s2
    np.exp(e, out=e)
    D = np.multiply(_TWO_PI, sp2_p, out=sp2_p)
    D *= sq2_q
    D /= s2
    D *= e
    # The exact tests; a candidate failing them adds an exact 0 (the sums are unchanged).
    passed = np.less(dd, two_sh_p)
    passed &= r2 < np.multiply(36.0, s2, out=s2)
    delta = np.divide(dd, two_sh_p, out=dd)
    np.subtract(1.0, delta, out=delta)  # Delta = 1 - dd / (2 sigma_h)
    delta *= D
    support = _accumulate(p, np.where(passed, delta, 0.0), m)
    support /= 2 * np.pi**2 * sp2
    return np.minimum(support, 1.0, out=support)


def visibility_weights(model: HandModel, theta: NDArray[np.float64], intr: Intrinsics) -> NDArray[np.float64]:
    """How visible each model Gaussian is at ``theta`` (26,) to the camera ``intr``, as a
    weight of its overlaps in ``E_sim``, shape (m,) in [0, 1].

    Only the Gaussians whose overlaps the fingers can steal are weighted: the palm's and the
    distal segments' of index .. little (``g_segment`` 2, a joint model's DIP Gaussians
    included); the others keep 1.  Such a Gaussian ``i`` is hidden by each finger Gaussian ``j``
    (the thumb's included; ``j != i``) by ``cover_ij front_ij``: ``cover_ij = exp(-r_ij^2 / (2
    s_j^2))`` with ``r_ij`` the image distance (px) of their projected centres and ``s_j`` the
    projected sigma of ``j`` (px); ``front_ij`` ramps from 0 to 1 as the front of ``j``
    (``z_j - sigma_j``, mm) lies 0 to ``sigma_i`` in front of the front of ``i``.  The weight
    is ``prod_j (1 - cover_ij front_ij)``: 1 for a Gaussian in plain view, near 0 for the
    palm behind a curled finger or a fingertip tucked behind its own middle segment or the
    thumb.  (Without the thumb's Gaussians as occluders the mesh sets scored 0.08-0.10 mm
    worse: dev 5.70, validation 5.83, further 5.66 mm.)
    """
    P = gaussian_centres(model, theta)
    z = np.maximum(P[:, 2], 1.0)
    u = intr.fx * P[:, 0] / z
    v = intr.fy * P[:, 1] / z
    sigma = model.g_sigmas
    s = sigma * float(np.sqrt(intr.fx * intr.fy)) / z  # projected sigmas (px)
    chain = model.g_chain
    hidden = np.flatnonzero((chain < 0) | ((chain >= 1) & (model.g_segment == 2)))
    occluders = np.flatnonzero(chain >= 0)
    r2 = np.square(u[hidden, None] - u[None, occluders]) + np.square(v[hidden, None] - v[None, occluders])
    cover = np.exp(-0.5 * r2 / np.square(s[occluders])[None, :])
    front = z - sigma
    ahead = np.clip((front[hidden, None] - front[None, occluders]) / sigma[hidden, None], 0.0, 1.0)
    ahead[hidden[:, None] == occluders[None, :]] = 0.0  # (a Gaussian does not hide itself)
    weights = np.ones(model.n_gaussians)
    weights[hidden] = np.prod(1.0 - cover * ahead, axis=1)
    return weights


def contact_shares(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """How curled each chain is at ``theta`` (26,), for :class:`Objective`'s ``contact``,
    shape (5,) in [0, 1]: 0 for the thumb; for index .. little their MCP + PIP flexion mapped
    linearly from ``CONTACT_CURL_RAD[0]`` (0) over ``CONTACT_CURL_RAD[1]`` rad (1)."""
    lo, span = CONTACT_CURL_RAD
    share = np.zeros(5)
    share[1:] = np.clip((theta[FINGER_MCP] + theta[FINGER_PIP] - lo) / span, 0.0, 1.0)
    return share


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


def _per_pose(value: NDArray[np.float64]) -> float | NDArray[np.float64]:
    """A term's value as a float for one pose (a 0-d result), else the (B,) values."""
    return float(value) if value.ndim == 0 else value


def _squares(x: NDArray[np.float64]) -> float | NDArray[np.float64]:
    """Sum of squares of ``x`` (k,) >= 0 as a float, or of each row of ``x`` (B, k) (the same
    bits as the row alone: its own product; the rows of zeros are 0)."""
    if x.ndim == 1:
        return float(x @ x)
    out = np.zeros(x.shape[0])
    for b in np.flatnonzero(np.logical_or.reduce(x > 0.0, axis=1)).tolist():
        out[b] = x[b] @ x[b]
    return out


def _segment_sums(values: NDArray[np.float64], bounds: NDArray[np.int64]) -> NDArray[np.float64]:
    """Sums of ``values[bounds[b]:bounds[b + 1]]`` (B,), each as the sum of that segment
    alone (np.add.reduceat adds in another order: other bits)."""
    out = np.zeros(bounds.size - 1)
    for b in np.flatnonzero(bounds[1:] > bounds[:-1]).tolist():
        out[b] = _sum(values[bounds[b] : bounds[b + 1]])
    return out


@lru_cache(maxsize=1)
def _smooth_scale() -> NDArray[np.float64]:
    s = np.ones(N_PARAMS)
    s[:3] = 1.0 / SMOOTH_TRANSLATION_MM
    return s


class Objective:
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
        unlimited = np.full(N_PARAMS - model.limits_low.size, np.inf)
        self._limits_low = np.concatenate([-unlimited, model.limits_low])  # (26,) rad
        self._limits_high = np.concatenate([unlimited, model.limits_high])
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
        # The batches' layouts by their number of poses, and the buffers they share (see _layout).
        self._batches: dict[int, _Rows] = {}
        self._batch_buffers: tuple[int, tuple[NDArray, ...]] = (0, ())
        # (targets, their constants or None) of the last targets seen by _salient.
        self._sal: tuple[object, tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]] | None] = (
            _UNSET, None
        )
        # What :meth:`support` needs of the last evaluation: the pose's bytes, and per pair
        # (sorted by model Gaussian) ``Delta D`` with the pairs' row bounds and the depths z.
        self._support_key = b""
        self._evaluations = 0  # (counts evaluations: a deferred gradient checks it is current)
        self._support_src: tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]] | None = None

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
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """``E`` at every pose of ``thetas`` (B, 26) and, with ``gradient``, ``dE/dtheta``
        (B, 26): pose by pose what :meth:`__call__` returns (the same bits; the gradient None
        without ``gradient``).

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
        if B == 1 and targets is None:  # (one pose: the one-pose path, faster, the same bits)
            value, grad = self(thetas[0], gradient)
            return np.array([value]), None if grad is None else grad[None]
        each = _UNSET if targets is None else _stacked_targets(targets, _as_slice(self.model.tip_index))
        values, grads = self._evaluate(thetas, gradient, False, targets_each=each)
        return values[0], grads

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
        other._one.visibility = self._visibility
        return other

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
        candidates out) makes no new arrays.
        """
        hit = self._batches.get(B)
        if hit is not None:
            return hit
        m, n = self.model.n_gaussians, self.data.n
        cap, full = self._batch_buffers
        if B > cap:
            self._batches.clear()
            cap = B
            col_of = np.empty((cap, m, n), dtype=np.int64)
            col_of[:] = (n * np.arange(cap))[:, None, None] + np.arange(n)
            rows = np.empty((11, cap * m))
            rows[2] = 1.0
            rows[8] = np.tile(self._two_sh, cap)
            c = self._const
            # The collision gradient's scatter, pose after pose (each pose's i's, then its j's).
            offsets = 3 * m * np.arange(cap)[:, None, None, None]
            scatter = (np.stack([c.gather_i, c.gather_j]) + offsets).reshape(-1)
            vis = None if self._visibility is None else np.tile(self._visibility, cap)
            full = (
                rows, np.empty(2 * cap * m * n), np.empty(cap * m * n, dtype=bool), np.arange(cap * m + 1) * n,
                col_of.reshape(-1), np.tile(self._per_q, (1, cap)), np.tile(self._sat, cap),
                np.tile(self.model.g_sigmas, cap), np.tile(self._shf, cap), np.tile(self._two_sh, cap),
                np.tile(self._four_sh2, cap), vis, scatter,
            )
            self._batch_buffers = (cap, full)
        rows, tests, neg, row_starts, col_of, per_q, sat_k, sigmas, shf, two_sh, four_sh2, vis, scatter = full
        k = B * m
        lay = self._batches[B] = _Rows(
            B, True, rows[:, :k], tests[: 2 * k * n].reshape(2, k, n), neg[: k * n].reshape(k, n),
            row_starts[: k + 1], col_of[: k * n], per_q[:, : B * n], sat_k[: B * n], sigmas[:k], shf[:k],
            two_sh[:k], four_sh2[:k], None if vis is None else vis[:k], scatter[: scatter.size // cap * B],
        )
        return lay

    def _evaluate(
        self,
        theta: NDArray[np.float64],
        gradient: bool,
        terms: bool = True,
        later: list[Backward] | None = None,
        targets_each: tuple | None | object = _UNSET,
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
        sim, dan = self._data_terms(P_rows, g3_rows, cfg.w_dan, z, proj, later, lay)
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
        if batch:  # (every term 0: a scalar total)
            total = np.broadcast_to(total, theta.shape[:1]).copy()
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

    # -- terms ---------------------------------------------------------------
    def _data_terms(
        self,
        P: NDArray[np.float64],
        g3: NDArray[np.float64] | None,
        w_dan: float,
        z: NDArray[np.float64] | None = None,
        proj: NDArray[np.float64] | None = None,
        later: list[Backward] | None = None,
        lay: _Rows | None = None,
    ) -> tuple[float | NDArray[np.float64], float | NDArray[np.float64]]:
        """``E_sim`` and ``E_dan``; adds ``dE/dP`` (with signs and weights) into ``g3``.

        ``lay``: the layout of a batch of B poses (:meth:`_layout`), whose B m model
        Gaussians ``P`` (B m, 3) holds pose after pose; then both are (B,) arrays.  Every step
        below runs on the B m rows as on the m rows of one pose; only the image Gaussians'
        saturation (per pose and image Gaussian) and the two sums are taken per pose.

        ``z``, ``proj``: ``max(P_z, 1)`` (m,) mm and ``(fx x / z, fy y / z)`` (2, m) px when
        already computed (the same operations as here: the same bits).  ``later``: instead of
        adding into ``g3`` now, append the function that does (see :meth:`value_then_gradient`).

        ``E_sim`` is summed over the pairs that can contribute: depth difference
        under ``2 sigma_h`` (else ``Delta = 0`` exactly) and image distance under
        6 combined standard deviations (else ``D_pq < 1.6e-8 D_pq^0``).
        ``E_dan`` is evaluated on the rows of dangling Gaussians only.

        Both candidate tests of all m x n pairs are one matrix product (expanded squares:
        ``r^2 - 36 (s_p^2 + s_q^2) = (u_p^2 + v_p^2 - 36 s_p^2) + (mu_q^2 - 36 s_q^2)
        - 2 u_p mu_uq - 2 v_p mu_vq`` and ``dd^2 - (2 sigma_h)^2`` likewise); the values of
        the pairs that pass are then computed exactly as their definitions (the expansion
        can only decide pairs within rounding of a test's boundary, where both the overlap
        and ``Delta`` vanish).
        """
        data = self.data
        n = data.n
        if n == 0 or data.norm <= 0:
            return 0.0, 0.0
        m = P.shape[0]
        if z is None or proj is None:
            z = np.maximum(P[:, 2], 1.0)
            proj = np.multiply(self._fxy, P[:, :2].T)
            proj /= z
        # Per model Gaussian (rows): 0 and 1 the tests' own terms, 2 ones, 3-5 u, v, dp (rows
        # 0-5 enter the candidate product), 6-9 sp^2, 2 pi sp^2 (times the visibility weight, if
        # any), 2 sigma_h, (mm per px)^2
        # (rows 3-9 are read per pair: contiguous rows, strided columns would slow down exp),
        # 10 sp.  Rows 2 and 8 are constant.  u, v as one (2, m) array: NumPy's per-call cost
        # dominates at this size.
        L = self._one if lay is None else lay
        rows = L.rows
        uv, dp, sp_sq, sp = rows[3:5], rows[5], rows[6], rows[10]
        u, v = uv
        np.add(proj, self._cxy, out=uv)  # u = fx x / z + cx, v = fy y / z + cy
        np.subtract(z, L.sigmas, out=dp)
        np.divide(L.shf, z, out=sp)
        np.multiply(sp, sp, out=sp_sq)
        np.multiply(_TWO_PI, sp_sq, out=rows[7])
        if L.visibility is not None:  # (a factor of every overlap of the Gaussian: D)
            rows[7] *= L.visibility
        scale = z / self._f  # mm per px at the model's depth
        np.multiply(scale, scale, out=rows[9])
        # rows 0-1: u^2 + v^2 - 36 sp^2, dp^2 - (2 sigma_h)^2
        uv2 = uv * uv
        np.add(uv2[0], uv2[1], out=rows[0])
        rows[0] -= 36.0 * sp * sp
        np.multiply(dp, dp, out=rows[1])
        rows[1] -= L.four_sh2
        tests = np.matmul(rows[:6].T, self._cand, out=L.tests)  # (2, m, n): < 0: pass
        # Both tests pass (< 0) exactly when the larger does: one comparison of (m, n) values.
        worst = np.maximum(tests[0], tests[1], out=tests[0])
        flat = np.less(worst, 0.0, out=L.neg).ravel().nonzero()[0]
        # Pairs per model Gaussian (the pairs come sorted by it): where each row's run starts.
        bounds = flat.searchsorted(L.row_starts)
        per_row = bounds[1:] - bounds[:-1]
        qi = L.col_of.take(flat)  # (in a batch: its pose's block of image Gaussians, b n + q)
        # Rows 3-9 of each pair's model Gaussian: its values repeated over its run (one call
        # instead of a gather per value); its data Gaussian's values, one gather.
        per_p = rows[3:10].repeat(per_row, axis=1)
        sp_sq_p, tpsp_p, two_sh_p, scale2_p = per_p[3:]
        per_q = L.per_q.take(qi, axis=1)  # mu_u, mu_v, depth, sigma^2
        diffs = np.subtract(per_p[:3], per_q[:3], out=per_q[:3])
        du, dv, dd = diffs  # u - mu_u, v - mu_v, dp - depth
        # Per pair, in place where a value is not needed again (the same operations, fewer
        # temporary arrays).
        sq = diffs[:2] * diffs[:2]
        r2 = np.add(sq[0], sq[1], out=sq[0])  # du^2 + dv^2
        sq2 = per_q[3]
        inv_s2 = np.add(sp_sq_p, sq2, out=sp_sq_p)  # s2 = sp^2 + sq^2 ...
        np.divide(1.0, inv_s2, out=inv_s2)  # ... inverted
        r2_s2 = r2 * inv_s2
        e = np.multiply(r2_s2, -0.5, out=sq[1])
        np.exp(e, out=e)  # = exp(-0.5 r2 inv_s2) exactly (0.5: exact scaling)
        D = np.multiply(tpsp_p, sq2, out=tpsp_p)
        D *= inv_s2
        D *= e  # 2 pi sp^2 sq^2 / s2 e
        delta_D = np.abs(dd)
        delta_D /= two_sh_p
        np.subtract(1.0, delta_D, out=delta_D)  # Delta = 1 - |dd| / (2 sigma_h) ...
        delta_D *= D  # ... times D
        if not L.batch:
            self._support_src = (delta_D, bounds, z)
        inv_norm = 1.0 / data.norm
        # Saturated per image Gaussian (module docstring): S_q, then G k_q (1 - exp(-S_q / k_q)).
        k = L.sat_k
        sat = _accumulate(qi, delta_D, k.size)
        sat /= k
        np.negative(sat, out=sat)
        np.expm1(sat, out=sat)  # exp(-S_q / k_q) - 1 (exact for small overlaps)
        if L.batch:
            sim: float | NDArray[np.float64] = _sum((k * sat).reshape(L.B, n), axis=1) * (-SIM_GAIN * inv_norm)
        else:
            sim = float(_sum(k * sat) * (-SIM_GAIN * inv_norm))
        sat += 1.0  # exp(-S_q / k_q): dE_sim/dS_q in units of G / norm
        # Dangling Gaussians (eq. 7): distance from each model Gaussian to the data,
        # occlusion-aware (see the module docstring), dmin its minimum over the data:
        # ``dist^2 = lat^2 scale^2 + beh^2`` with ``lat = max(sqrt(r2) - half, 0)`` and
        # ``beh = min(dd, 0)``.  A model Gaussian with dmin <= TAU1 has weight 0.  As ``lat``
        # is at most ``sqrt(r2)``, a candidate pair with ``r2 scale^2 + beh^2 <= _NEAR_SAFE``
        # settles dmin <= TAU1 (four passes over the pairs fewer than ``dist``; typically it
        # settles every row but none to a few).  The other rows get the distances to all data
        # Gaussians, computed per element as ``dist`` is on a pair: a row with a pair within
        # TAU1 has dmin <= TAU1 there, weight 0, and drops out as if it had been settled here.
        beh_c = np.minimum(dd, 0.0, out=e)  # minus how far the data lie behind: squared below
        beh_c *= beh_c
        bound_c = np.multiply(r2, scale2_p, out=r2)  # (r2 is not needed again)
        bound_c += beh_c
        near_c = bound_c <= _NEAR_SAFE
        nz = per_row > 0
        every_row = bool(np.logical_and.reduce(nz))  # (typical: then the segmented sums need no scatter)
        starts = bounds[:-1] if every_row else bounds[:-1][nz]
        if every_row:
            settled = np.logical_or.reduceat(near_c, starts)
        else:
            settled = np.zeros(m, dtype=bool)
            if flat.size:
                settled[nz] = np.logical_or.reduceat(near_c, starts)
        U = (~settled).nonzero()[0]
        dan: float | NDArray[np.float64] = np.zeros(L.B) if L.batch else 0.0
        sel = U[:0]
        if U.size:
            # (Per element the same operations as on the pairs; the rows' values in one gather,
            # u and v together: the per-call cost dominates at this size.)
            rows_U = rows.take(U, axis=1)
            duv_U = rows_U[3:5, :, None] - self._mu_uv  # (2, U, n): u - mu_u, v - mu_v
            du_U, dv_U = duv_U
            sq_U = duv_U * duv_U
            r2_U = np.add(sq_U[0], sq_U[1], out=sq_U[0])
            r_U = np.sqrt(r2_U)
            lat_U = r_U - self._half
            np.maximum(lat_U, 0.0, out=lat_U)
            scale_U = scale[U][:, None]
            # minus how far the data lie behind the model's surface (data in front: 0)
            nbeh_U = rows_U[5][:, None] - data.depth
            np.minimum(nbeh_U, 0.0, out=nbeh_U)
            dist2_U = lat_U * lat_U
            dist2_U *= rows_U[9][:, None]  # (row 9: scale * scale)
            dist2_U += nbeh_U * nbeh_U
            dmin_U = np.sqrt(np.minimum.reduce(dist2_U, axis=1))
            # The dangling weight is positive exactly where dmin > TAU1 (typically nowhere).
            sel = (dmin_U > TAU1_MM).nonzero()[0]
        drows = U[sel]
        if drows.size:
            # (minimum of maximum: np.clip, several times cheaper on small arrays)
            wdang_r = np.minimum(np.maximum((dmin_U[sel] - TAU1_MM) / TAU1_MM, 0.0), 1.0)
            dist_r = np.sqrt(dist2_U[sel])
            phi = np.minimum(np.maximum((dist_r - TAU1_MM) / (TAU2_MM - TAU1_MM), 0.0), 1.0)
            s2r = (sp[drows] ** 2)[:, None] + self._sq2[None, :]
            r2_r = r2_U[sel]
            er = np.exp(-0.5 * r2_r / s2r)
            per_row_dan = _sum(phi * (1.0 - er), axis=1) / n
            if L.batch:  # (each pose's rows summed as one pose's: the same bits)
                dan = _segment_sums(wdang_r * per_row_dan, drows.searchsorted(m // L.B * np.arange(L.B + 1)))
            else:
                dan = float(_sum(wdang_r * per_row_dan))
        if g3 is None and later is None:
            return sim, dan

        def backward(g3: NDArray[np.float64]) -> None:
            """Add the data terms' ``dE/dP`` into ``g3`` (m, 3) (only reads this evaluation's
            values: valid until the objective's next evaluation reuses its buffers)."""
            # d/d(u, v, sigma_p, d_p) of E_sim, accumulated per model Gaussian.
            # The pairs come sorted by model Gaussian (row-major order of the mask): the sums per
            # Gaussian are one segmented sum over the rows of W.  Factors of a model Gaussian alone
            # are taken out of its sums: with wD = Delta D / norm,
            # dE/dsp = sum wD (2 / sp - 2 sp / s2 + r2 sp / s2^2)
            #        = 2 / sp sum wD + sp sum wD / s2 (r2 / s2 - 2).
            W = np.empty((5, flat.size))
            np.multiply(sat, SIM_GAIN, out=sat)  # (per image Gaussian: fewer products than per pair, the same bits)
            w_pair = sat.take(qi)  # each pair's share of dE_sim/dS_q
            np.multiply(delta_D, w_pair, out=W[2])
            wD = np.multiply(W[2], inv_norm, out=W[2])
            a = np.multiply(wD, inv_s2, out=inv_s2)
            np.multiply(a, du, out=W[0])  # (two contiguous products: cheaper than one broadcast)
            np.multiply(a, dv, out=W[1])
            np.subtract(r2_s2, 2.0, out=r2_s2)
            np.multiply(a, r2_s2, out=W[3])
            np.copysign(D, dd, out=W[4])  # D sign(dd), weighted like wD
            W[4] *= w_pair
            if every_row:
                g = np.add.reduceat(W, starts, axis=1)
            else:
                g = np.zeros((5, m))
                if flat.size:
                    g[:, nz] = np.add.reduceat(W, starts, axis=1)
            # g[0:2] = -dE/d(u, v), then dE/dsp, dE/dp, and the explicit z-dependence of the
            # dangle distances (rows 2-4 replaced in place by what they are made of).
            g[2] = 2.0 * g[2] / sp + sp * g[3]
            g[3] = g[4] / L.two_sh * -inv_norm
            dangling = drows.size > 0 and w_dan > 0
            if dangling:
                g[4] = 0.0
                wn = (w_dan * wdang_r / n)[:, None]
                pe = wn * phi * er
                inv_s2r = 1.0 / s2r
                spr = sp[drows][:, None]
                du_r, dv_r = du_U[sel], dv_U[sel]
                # d(1 - e)/du = e du / s2 ; d(1 - e)/dsp = -e r2 sp / s2^2
                pe_s2 = pe * inv_s2r
                # Derivatives of the distance: lat = max(r - half, 0) z / f, behind = max(dq - dp, 0)
                # (both terms vanish off the lateral part, where lat = 0).
                lat_px_r, scale_r = lat_U[sel], scale_U[sel]
                lat_r = lat_px_r * scale_r
                r_r = np.maximum(r_U[sel], 1e-9)
                inv_dist = 1.0 / np.maximum(dist_r, 1e-9)
                k_u = lat_r * scale_r / r_r * inv_dist  # d dist / du per du
                k_z = lat_r * lat_px_r / self._f * inv_dist
                k_dp = nbeh_U[sel] * inv_dist  # d dist / d dp
                ramp = (dist_r > TAU1_MM) & (dist_r < TAU2_MM)
                c = wn * (ramp * (1.0 / (TAU2_MM - TAU1_MM))) * (1.0 - er)
                # Through the dangling weight: d dmin / d(.) at the nearest data Gaussian.
                dmin_r = dmin_U[sel]
                on_ramp = (dmin_r > TAU1_MM) & (dmin_r < 2.0 * TAU1_MM)
                nearest_r = dist2_U[sel].argmin(axis=1)
                c[np.arange(drows.size), nearest_r] += w_dan * on_ramp * per_row_dan / TAU1_MM
                k_uv = pe_s2 + c * k_u
                rows_sums = np.empty((5, drows.size))
                _sum(k_uv * du_r, axis=1, out=rows_sums[0])
                _sum(k_uv * dv_r, axis=1, out=rows_sums[1])
                _sum(pe_s2 * r2_r * spr * inv_s2r, axis=1, out=rows_sums[2])
                np.negative(_sum(c * k_dp, axis=1), out=rows_sums[3])
                np.negative(_sum(c * k_z, axis=1), out=rows_sums[4])
                g[:, drows] += rows_sums
            # Through u = fx x / z + cx, v = fy y / z + cy, sp = sh f / z, dp = z - sh.
            t_uv = g[:2] * self._fxy / z  # (2, m): dE/d(x, y) at fixed z, negated
            g3[:, :2] -= t_uv.T
            g_z = (t_uv[0] * P[:, 0] + t_uv[1] * P[:, 1] - g[2] * L.shf / z) / z + g[3]
            if dangling:  # (else g[4] is 0: g3, zeros before this first term, gets the same bits)
                g_z += g[4]
            g3[:, 2] += g_z

        run_or_defer(backward, g3, later)
        return sim, dan

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

    def _smoothness(self, theta: NDArray[np.float64]) -> tuple[float | NDArray[np.float64], NDArray[np.float64]]:
        """``E_smo`` (eq. 9) and its gradient, shape (26,) (for poses (B, 26): (B,), (B, 26))."""
        if self.previous is None:
            return 0.0, np.zeros(theta.shape)
        p1, p2 = self.previous
        s = _smooth_scale()
        r = s * (0.5 * (p2 + theta) - p1)
        return _per_pose(_sum(r * r, axis=-1)), r * s
