"""A frame's candidates: the proposals, small generators with a name and a reason.

Each looks at the frame's fit (:class:`Frame`) and yields start poses (:class:`Candidate`) out of
a local optimum the fit may be in, or nothing when its reason does not apply.  ``margin``: what a
candidate must beat the fit's score by where the score tells them apart poorly (doc/design/search.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Callable, Iterator

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.articulations import FINGER_CURLED, FINGER_EXTENDED
from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.hand_model import (
    ABD,
    CHAIN_JOINTS,
    FINGER_ABD,
    FINGER_DIP,
    FINGER_MCP,
    FINGER_PIP,
    JOINTS,
    HandModel,
    chain_slice,
)
from hand_sog_tracker.core.kinematics import centres_batch, fingertips, global_rotation
from hand_sog_tracker.core.objective import Objective, TipTargets
from hand_sog_tracker.core.optimizer import OptimizeResult
from hand_sog_tracker.core.rotations import euler_from_matrix, rot_y
from hand_sog_tracker.core.salient import Detections, assign_detections
from hand_sog_tracker.core.search.score import (
    ASSIGN_LAMBDA_MM,
    assignment_cost,
    lonely_detections,
    own_detections,
    plain,
    score,
    sq_distances,
)

__all__ = [
    "Candidate", "Frame", "Proposal", "TRACK_PROPOSALS", "NEW_TRACK_PROPOSALS", "pull_objective", "pull_target",
    "rolled", "shifted", "swapped",
]

DANGLING_TIP_MM = 25.0  #: a fingertip this far (mm) from all data hangs in empty space (seed 004's restarts)
DANGLING_MARGIN = 0.02  #: ... and its candidates must win by this (without, they won wrongly on rotating hands)
#: Swap: a finger this near (rad) its abduction limit toward a neighbour curled ``SWAP_CURL_GAP_RAD``
#: more (MCP + PIP), itself curled at most ``SWAP_MAX_CURL_RAD`` (issue 11).
SWAP_ABD_MARGIN_RAD = float(np.radians(0.5))
SWAP_CURL_GAP_RAD = 0.8
SWAP_MAX_CURL_RAD = 2.2
SWAP_MARGIN = 0.02
FACING_COS = 0.85  #: swaps and curls need |palm normal . view| >= this (from the side fingers score alike)
CURL_MAX_FLEX_RAD = 1.5  #: curl: an open finger (MCP + PIP + DIP under this, rad) without a detection of its own
CURL_MARGIN = 0.04
EDGE_ON_PALM_COS = 0.6  #: a hand this nearly edge-on (|palm normal . view| under) overlaps its fingers ...
EDGE_ON_MARGIN = SWAP_MARGIN  #: ... and a detection pull must win by this (issue 11)
SAME_DETECTION_MM = 10.0  #: within this (mm, a few frames' motion) of a detection whose pulls lost: the same
PULL_WEIGHT = 20.0  #: the salient weight of a detection pull: this x ``w_sal`` (at least this)
SHIFT_MARGIN = 0.02  #: a shift without an unexplained detection wins by this (at an angle fingers one over score alike)
LATERAL_MM = 15.0  #: a new track's lateral candidates move the hand this far across the palm (mm: a finger's spacing)
LATERAL_MARGIN = 0.01  #: ... and must win by this (issue 11)
ROLL_MARGIN = 0.0  #: a hand turned about its finger axis wins by this
SLIDE_MM = 20.0  #: a fist seen from its back moved this far (mm) toward its fingers (15, 25: worse on dev)


@dataclass(frozen=True, eq=False)
class Frame:
    """What the proposals look at: one frame's fit and data."""

    model: HandModel
    fit: OptimizeResult  #: the frame's fit (a tracked frame's, or a new track's best finalist)
    obj: Objective  #: the frame's objective (with the salient term's targets)
    data: ImageSoG
    det: Detections
    limits: tuple[NDArray[np.float64], NDArray[np.float64]]  #: joint limits (low, high) (26,) each, +-inf: wrist
    new_track: bool = False  #: a new track: no hidden-tip discount, lateral candidates, both shifts
    #: (k, 3) mm: detections whose pulls lost on the frame before (see :func:`pull_target`)
    lost_pulls: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    #: ``covered(tips (5, 3) mm) -> (5,) bool``: the fingertips against or behind another hand (no end to
    #: see: no curl, no dangling; :mod:`..hands`); None: none
    covered: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None

    # (Made when first read, once: most tracked frames make no candidate; several proposals ask.)
    @cached_property
    def plain(self) -> Objective:
        """``obj`` without its salient term (:func:`~.score.plain`): candidates are fitted and scored on it."""
        return plain(self.obj)

    @cached_property
    def own(self) -> NDArray[np.bool_]:
        """:func:`~.score.own_detections` at the fit's pose (5,): not to be written."""
        return own_detections(self.model, self.fit.x, self.det)

    @cached_property
    def lonely(self) -> NDArray[np.int64]:
        """:func:`~.score.lonely_detections` at the fit's pose (k,)."""
        return lonely_detections(self.model, self.fit.x, self.det)

    def score(self, theta: NDArray[np.float64], value: float | None = None) -> float:
        """:func:`~hand_sog_tracker.core.search.score.score` of ``theta`` (26,) on this frame."""
        return score(self.plain, theta, self.det, self.obj.config.w_sal, not self.new_track, value)


@dataclass(frozen=True, eq=False)
class Candidate:
    """One start pose ``x0`` (26,) of ``proposal``, the ``margin`` it must beat the fit's score by and,
    optionally, fingertip targets it is first ``pull``-ed onto with only its ``active`` (26,) free."""

    proposal: str
    x0: NDArray[np.float64]
    margin: float = 0.0
    pull: TipTargets | None = None
    active: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class Proposal:
    """A named generator of candidates: ``generate(frame)`` yields them when ``reason`` applies."""

    name: str
    reason: str
    generate: Callable[[Frame], Iterator[Candidate]]
    #: its candidates join a search only beside another proposal's (they add no batch of their own)
    rides_along: bool = False


def _proposal(
    name: str, reason: str, rides_along: bool = False
) -> Callable[[Callable[[Frame], Iterator[Candidate]]], Proposal]:
    """Decorator: the generator of candidates it decorates as the :class:`Proposal` ``name``."""
    return lambda generate: Proposal(name, reason, generate, rides_along)


def shifted(theta: NDArray[np.float64], side: int) -> NDArray[np.float64]:
    """``theta`` (26,) with index .. little given the flexions of their neighbour on ``side``
    (+1: toward the little finger; the last keeps its own) and neutral abductions."""
    q = theta[JOINTS].reshape(5, CHAIN_JOINTS)
    moved = q[np.clip(np.arange(1, 5) + side, 1, 4)].copy()
    moved[:, 1] = 0.0
    x0 = theta.copy()
    x0[chain_slice(1).start :] = moved.ravel()
    return x0


def swapped(theta: NDArray[np.float64], a: int, b: int) -> NDArray[np.float64]:
    """``theta`` (26,) with chains ``a`` and ``b`` (1-4) exchanging flexions, abductions neutral."""
    x0 = theta.copy()
    sa, sb = chain_slice(a), chain_slice(b)
    x0[sa], x0[sb] = theta[sb], theta[sa]
    x0[sa.start + ABD] = 0.0
    x0[sb.start + ABD] = 0.0
    return x0


def _with_chain(theta: NDArray[np.float64], c: int, joints: NDArray[np.float64]) -> NDArray[np.float64]:
    x0 = theta.copy()
    x0[chain_slice(c)] = joints
    return x0


def _view_cos(theta: NDArray[np.float64]) -> float:
    """|palm normal . view axis| at ``theta``: 1 palm or back to the camera, 0 edge-on."""
    return abs(global_rotation(theta)[2, 2])


@_proposal("dangling", "a fingertip hangs in empty space: its finger extended, curled, like the others")
def DANGLING(f: Frame) -> Iterator[Candidate]:
    if f.data.n == 0:
        return
    x = f.fit.x
    tips = fingertips(f.model, x)
    far = np.sqrt(sq_distances(tips, f.data.points).min(axis=1))
    if f.covered is not None:
        far[f.covered(tips)] = 0.0  # (a tip another hand hides or touches hangs in no empty space)
    c = int(np.argmax(far))
    if far[c] < DANGLING_TIP_MM:
        return
    yield Candidate("dangling", _with_chain(x, c, FINGER_EXTENDED), DANGLING_MARGIN)
    yield Candidate("dangling", _with_chain(x, c, FINGER_CURLED), DANGLING_MARGIN)
    if c > 0:
        others = np.mean([x[chain_slice(k)] for k in range(1, 5) if k != c], axis=0)
        yield Candidate("dangling", _with_chain(x, c, others), DANGLING_MARGIN)


def swap_pair(theta: NDArray[np.float64], limits: tuple[NDArray, NDArray]) -> tuple[int, int] | None:
    """``(finger, neighbour)`` (chains 1-4) to swap at ``theta`` (26,), or None: a finger at its
    abduction limit toward a neighbour curled more (``SWAP_*``), of several the largest gap."""
    if _view_cos(theta) < FACING_COS:
        return None
    lo, hi = limits
    abd = theta[FINGER_ABD]
    at_limit = {1: hi[FINGER_ABD] - abd <= SWAP_ABD_MARGIN_RAD, -1: abd - lo[FINGER_ABD] <= SWAP_ABD_MARGIN_RAD}
    curl = theta[FINGER_MCP] + theta[FINGER_PIP]  # index .. little (4,), rad
    best, best_gap = None, SWAP_CURL_GAP_RAD
    for i in np.flatnonzero(curl <= SWAP_MAX_CURL_RAD):
        for side in (1, -1):
            n = i + side
            if 0 <= n < 4 and at_limit[side][i] and curl[n] - curl[i] > best_gap:
                best, best_gap = (int(i) + 1, int(n) + 1), curl[n] - curl[i]
    return best


@_proposal("swap", "a finger held at its abduction limit over a more curled neighbour's place: the two swap flexions")
def SWAP(f: Frame) -> Iterator[Candidate]:
    pair = swap_pair(f.fit.x, f.limits)
    if pair is not None:
        yield Candidate("swap", swapped(f.fit.x, *pair), SWAP_MARGIN)


@_proposal("curl", "an open finger without a detection of its own: each open finger curled into the palm")
def CURL(f: Frame) -> Iterator[Candidate]:
    x = f.fit.x
    if f.det.n == 0 or _view_cos(x) < FACING_COS:
        return
    flex = x[FINGER_MCP] + x[FINGER_PIP] + x[FINGER_DIP]  # index .. little (4,)
    fingers = [c for c in range(1, 5) if flex[c - 1] < CURL_MAX_FLEX_RAD]
    if not fingers:
        return
    seen = f.own
    if f.covered is not None and not seen[fingers].all():
        seen = seen | f.covered(fingertips(f.model, x))  # (a tip against another hand has no end to see)
    if not seen[fingers].all():
        for c in fingers:
            yield Candidate("curl", _with_chain(x, c, FINGER_CURLED), CURL_MARGIN)


@_proposal("shift", "an unexplained detection, or detections a pose with every finger one place over explains better")
def SHIFT(f: Frame) -> Iterator[Candidate]:
    x = f.fit.x
    margin = SHIFT_MARGIN
    if f.new_track or f.lonely.size:
        sides: tuple[int, ...] = (1, -1)
        margin = 0.0
    elif f.det.n == 0 or _view_cos(x) < EDGE_ON_PALM_COS:
        return  # no detection says where the fingers are, or they overlap in the image (edge-on)
    elif f.det.n >= 5 and f.own.all():
        return  # each fingertip has a detection of its own
    else:
        # The side whose shifted pose the detections explain better than the fit, if any.
        poses = np.array([shifted(x, s) for s in (0, 1, -1)])  # (their fingertips from one batch: the same bits)
        tips = centres_batch(f.model, poses, pullback=False)[0].take(f.model.tip_index, axis=1)
        cost = {s: assignment_cost(f.model, p, f.det, True, t) for s, p, t in zip((0, 1, -1), poses, tips)}
        sides = tuple(s for s in (1, -1) if cost[s] < cost[0] and cost[s] <= cost[-s])
    for side in sides:
        yield Candidate("shift", shifted(x, side), margin)


def _joint_targets(model: HandModel, theta: NDArray[np.float64], det: Detections, c: int, s: int) -> TipTargets:
    """Targets: fingertip ``c`` on detection ``s`` (weight 1), the others at ``theta`` (26,) on
    what the optimal assignment gives them of the rest (their confidence; none seen end-on)."""
    rest = np.ones(det.n, dtype=bool)
    rest[s] = False
    others = np.flatnonzero(np.arange(5) != c)
    sub = det.subset(rest)
    assigned = assign_detections(fingertips(model, theta)[others], sub, ASSIGN_LAMBDA_MM)
    points, weights = np.zeros((5, 3)), np.zeros(5)
    points[c], weights[c] = det.points[s], 1.0
    for o, a in zip(others, assigned):
        if a >= 0 and not sub.end_on[a]:
            points[o], weights[o] = sub.points[a], sub.confidence[a]
    return TipTargets(points, weights)


def pull_objective(obj: Objective) -> Objective:
    """The frame's objective ``obj`` with the salient weight of a pull (``PULL_WEIGHT``), no targets."""
    return obj.variant(replace(obj.config, w_sal=max(obj.config.w_sal, 1.0) * PULL_WEIGHT), None)


def pull_target(f: Frame) -> int | None:
    """The detection the detection proposal pulls fingers onto, or None: the most confident one no
    fingertip explains, unless its pulls lost last frame there (``SAME_DETECTION_MM``, ``lost_pulls``)."""
    lonely = f.lonely
    if lonely.size and f.lost_pulls.shape[0]:
        near = np.sqrt(sq_distances(f.det.points[lonely], f.lost_pulls)).min(axis=1) < SAME_DETECTION_MM
        lonely = lonely[~near]
    return int(lonely[np.argmax(f.det.confidence[lonely])]) if lonely.size else None


@_proposal("detection", "a detection no fingertip explains (pulls not lost before): the 2 nearest fingers pulled on it")
def DETECTION(f: Frame) -> Iterator[Candidate]:
    x, det = f.fit.x, f.det
    s = pull_target(f)
    if s is None:
        return
    dist = np.linalg.norm(det.points[s] - fingertips(f.model, x), axis=1)
    margin = EDGE_ON_MARGIN if _view_cos(x) < EDGE_ON_PALM_COS else 0.0
    for c in np.argsort(dist)[:2]:
        c = int(c)
        pts, w = np.zeros((5, 3)), np.zeros(5)
        pts[c], w[c] = det.points[s], 1.0
        finger = np.zeros(x.size, dtype=bool)
        finger[chain_slice(c)] = True
        # The finger alone pulled onto it, and the whole pose with every other fingertip
        # pulled onto its own detection (a model finger on its neighbour's data moves back).
        yield Candidate("detection", x, margin, TipTargets(pts, w), finger)
        yield Candidate("detection", x, margin, _joint_targets(f.model, x, det, c, s))
        if det.end_on[s] and c > 0:  # a finger seen end-on is curled toward the camera
            yield Candidate("detection", _with_chain(x, c, FINGER_CURLED), margin)


@_proposal("lateral", "a new track: the hand moved one finger's spacing sideways, fingers as they are and shifted")
def LATERAL(f: Frame) -> Iterator[Candidate]:
    if not f.new_track:
        return
    x = f.fit.x
    across = global_rotation(x)[:, 0] * LATERAL_MM
    for sign in (1.0, -1.0):
        for side in (0, 1, -1):
            x0 = x.copy() if side == 0 else shifted(x, side)
            x0[:3] += sign * across
            yield Candidate("lateral", x0, LATERAL_MARGIN)


def rolled(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """``theta`` (26,) turned half a turn about the hand's own finger axis (the hand frame's y,
    through the wrist and the palm centre): the other face of the same strip of data."""
    x0 = theta.copy()
    x0[3:6] = euler_from_matrix(global_rotation(theta) @ rot_y(np.pi))
    return x0


# (Rides along: a frame that needs no search pays nothing for it.)
@_proposal("roll", "a hand seen from its side, beside other candidates: turned half a turn about its finger axis", True)
def ROLL(f: Frame) -> Iterator[Candidate]:
    if _view_cos(f.fit.x) < FACING_COS:
        yield Candidate("roll", rolled(f.fit.x), ROLL_MARGIN)


@_proposal("slide", "a fist seen from its back, the knuckles hiding the fingers: the hand moved toward its fingers")
def SLIDE(f: Frame) -> Iterator[Candidate]:
    x, R = f.fit.x, global_rotation(f.fit.x)  # (fingers not open: mean MCP + PIP + DIP over CURL_MAX_FLEX_RAD)
    if R[2, 2] >= FACING_COS and np.mean(x[FINGER_MCP] + x[FINGER_PIP] + x[FINGER_DIP]) >= CURL_MAX_FLEX_RAD:
        yield Candidate("slide", np.concatenate([x[:3] + SLIDE_MM * R[:, 1], x[3:]]))


#: The proposals of a tracked frame and of a new track's first frame.
TRACK_PROPOSALS: tuple[Proposal, ...] = (DANGLING, SWAP, CURL, SHIFT, DETECTION, SLIDE, ROLL)
NEW_TRACK_PROPOSALS: tuple[Proposal, ...] = (DANGLING, SHIFT, LATERAL)
