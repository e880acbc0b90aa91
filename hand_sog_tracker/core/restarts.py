"""The tracker's restart strategies (seeds 001 and 004): ways out of local optima after a frame's fit.

:class:`RestartStrategies` is a mixin of :class:`hand_sog_tracker.core.tracker.Tracker`
(it uses the tracker's ``_model``, ``_config``, ``_frame_count``, ``_restart_wait``, ``_fit``
and ``_limits``); :meth:`~RestartStrategies._restarts` runs them for a tracked frame:

- :meth:`~RestartStrategies._finger_restarts`: a finger hanging in empty space is restarted
  extended, curled and like the other fingers;
- :meth:`~RestartStrategies._swap_restarts`: a finger held at its abduction limit over a curled
  neighbour's place swaps flexions with that neighbour;
- :meth:`~RestartStrategies._curl_restarts`: an open finger without a fingertip detection of its
  own is tried curled into the palm;
- :meth:`~RestartStrategies._shift_restarts`: every finger takes its neighbour's articulation;
- :meth:`~RestartStrategies._detection_restarts`: a finger is pulled onto a fingertip
  detection no model finger explains;
- :meth:`~RestartStrategies._lateral_restarts` (after an initialisation): the hand moved
  sideways, with and without its fingers shifted.

Candidates are judged by :meth:`~RestartStrategies._score`: the objective without the salient
term minus the assignment cost of the detections (seed 001, eq. 11).
"""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import replace as replace_config
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.articulations import FINGER_CURLED, FINGER_EXTENDED
from hand_sog_tracker.core.depth_sog import ImageSoG
from hand_sog_tracker.core.energy import SALIENT_SCALE_MM, Objective, TipTargets
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
from hand_sog_tracker.core.kinematics import fingertips, global_rotation
from hand_sog_tracker.core.optimizer import OptimizeResult, Steps
from hand_sog_tracker.core.salient import Detections, assign_detections
from hand_sog_tracker.core.types import TrackerConfig

__all__ = [
    "RestartStrategies",
    "ShiftCandidate",
    "RESTART_TIP_MM",
    "RESTART_ITERATIONS",
    "ASSIGN_LAMBDA_MM",
    "UNEXPLAINED_DETECTION_MM",
    "UNEXPLAINED_CONFIDENCE",
    "FAR_UNEXPLAINED_MM",
    "FAR_UNEXPLAINED_CONFIDENCE",
    "SHIFT_EVERY",
    "SHIFT_CHUNK",
    "SHIFT_SKIP_MM",
    "RESTART_COOLDOWN",
    "LATERAL_MM",
    "LATERAL_MARGIN",
    "HIDDEN_TIP_LAMBDA",
    "HIDDEN_PALM_COS",
    "OPEN_TIP_RAD",
    "CURLED_TIP_RAD",
    "SWAP_ABD_MARGIN_RAD",
    "SWAP_CURL_GAP_RAD",
    "SWAP_MAX_CURL_RAD",
    "SWAP_PALM_COS",
    "SWAP_MARGIN",
    "CURL_MAX_FLEX_RAD",
    "CURL_MARGIN",
    "CURL_WAIT",
]

# Tuning constants, documented like those of :mod:`hand_sog_tracker.core.tracker` (what, unit,
# and where the value comes from).
#: A fingertip this far from all data (mm) triggers a restart of its finger (seed 004's
#: restarts; the distance is chosen here).
RESTART_TIP_MM = 25.0
#: Iterations each restart candidate gets (count; chosen here, raised to 12 in commit f16019d).
RESTART_ITERATIONS = 12
#: Cost (mm) of a fingertip without a detection in the assignment (the role of seed 001's
#: lambda, eq. 11; its value 1.2 is in another unit, 30 mm is chosen here); a detection costs
#: this times its confidence when declared a false positive.
ASSIGN_LAMBDA_MM = 30.0
#: A confident detection this far (mm) from its nearest fingertip is a finger the model
#: has not found: the neighbouring fingers are restarted onto it (chosen here; about the
#: spacing of neighbouring MCP joints in the default hand, 18-20 mm).
UNEXPLAINED_DETECTION_MM = 20.0
#: Smallest detection confidence (in [0, 1]) that counts as unexplained (chosen here).
UNEXPLAINED_CONFIDENCE = 0.5
#: A detection this far (mm) from its nearest fingertip counts as unexplained from the lower
#: confidence ``FAR_UNEXPLAINED_CONFIDENCE``: that far from every model finger it is no
#: neighbour's partly seen tip.  (Issue 11, chosen here.  A thin finger's tip makes a small
#: detection region: on labelled real frame 3 (ring finger curled) the extended little finger's
#: tip had confidence 0.49, 52 mm from the model's little fingertip, which lay curled on the
#: ring finger's data; nothing restarted it.  Over the 112 shifted and mirrored copies of the
#: eight real frames: 11.6 -> 9.6 mm, 18 -> 14 copies over 20 mm, frame 2 11.5 -> 6.1 and
#: frame 3 15.7 -> 5.2 mm; 30 mm scores the same, 50 mm is too far for frame 3.  No such
#: detection arises on the 288 mesh dev and validation renders or the 84 capsule renders: all
#: score bit for bit as before (and Table 1's errors are unchanged).  The lower confidence alone (0.3 for every
#: detection beyond 20 mm) also fixed the real frames but cost a validation render of finger
#: counting 18 mm: the index's tip, first seen rising with low confidence, pulled the middle
#: finger onto it.)
FAR_UNEXPLAINED_MM = 40.0
FAR_UNEXPLAINED_CONFIDENCE = 0.3
#: Without an unexplained detection, a finger-shifted restart (seed 004) starts every this many
#: frames (count; chosen here: 12 with its iterations spread over ``RESTART_ITERATIONS /
#: SHIFT_CHUNK`` frames tracks as 6 did with all of them on one frame, on 240 dev renders).
SHIFT_EVERY = 12
#: Iterations a scheduled shift candidate gets per frame (count; chosen here, issue 14: no
#: frame pays for a whole restart, the 95th percentile of a frame's objective evaluations went
#: from 22 to 13 on 18 dev sequences).
SHIFT_CHUNK = 3
#: A scheduled shift candidate does not start when every fingertip has its own detection
#: (the assignment of seed 001) within this distance (mm): a finger on its neighbour's place
#: leaves a seen fingertip without a model finger or a model finger without one.  (Chosen here,
#: issue 14: on 144 + 96 dev renders this skips 47% of the scheduled candidates and leaves
#: every score unchanged; the 7 candidates that won there had a fingertip without a detection
#: or one 10.5 mm or more from it.)
SHIFT_SKIP_MM = 10.0
#: A fingertip without a detection costs ``ASSIGN_LAMBDA_MM`` in the assignment cost of the
#: candidates (:meth:`RestartStrategies._assignment_cost`), except a curled one while the palm
#: faces the camera (the palm normal within ``acos(HIDDEN_PALM_COS)`` of the camera's axis): its
#: tip lies hidden against the palm, so that the detector cannot see it.  From ``OPEN_TIP_RAD``
#: to ``CURLED_TIP_RAD`` of PIP + DIP flexion (rad) its cost falls linearly to
#: ``HIDDEN_TIP_LAMBDA x ASSIGN_LAMBDA_MM`` (issue 11, chosen here).  With the full cost a
#: finger counting hand's model finger that lies extended on its neighbour's data (one of two
#: model tips on one seen tip: no detection) scored as well as the finger curled into the palm
#: where it is (no detection either), and a restart pulling a curled finger onto a spurious
#: detection won by the detection's false-positive cost it saved.
HIDDEN_TIP_LAMBDA = 0.0
HIDDEN_PALM_COS = 0.5
OPEN_TIP_RAD = 1.0
CURLED_TIP_RAD = 2.0
#: Swap restarts (:meth:`RestartStrategies._swap_restarts`, issue 11, all chosen here).  A
#: finger of index .. little held at its MCP abduction limit (within ``SWAP_ABD_MARGIN_RAD``)
#: toward a neighbour more curled than itself by ``SWAP_CURL_GAP_RAD`` (MCP + PIP flexion,
#: rad), itself curled at most ``SWAP_MAX_CURL_RAD``, with the palm or the back of the hand
#: toward the camera (``|cos|`` of the palm normal to the camera's axis at least
#: ``SWAP_PALM_COS``), is tried with the neighbour's flexions and the neighbour with its; the
#: candidate wins only by ``SWAP_MARGIN`` of :meth:`RestartStrategies._score`.  On mesh renders
#: of finger counting the model's middle finger rose onto the index's data while the model's
#: index stayed curled (validation seed 5085: 12 frames at 35-113 mm), or its ring finger onto the
#: middle's (5076); the scheduled shift (every finger moved) put 5085 right 12 frames later.  The
#: conditions keep the swap off where the score cannot tell neighbours apart: a hand seen from
#: the side (random motion, palm normal at 0.66-0.7: the swap won there and was wrong), two
#: curled fingers of a fist, and score gains of 0.01-0.015 (also wrong on a render of random
#: motion of seeds 7000-7143, 4.8 -> 14.3 mm; the right swaps gained 0.037 and 0.045).
#: Validation (144 renders): 7.08 -> 7.01 mm (5085 13.3 -> 7.5, 5076 14.1 -> 10.5 mm, no other
#: render changed); dev (144), seeds 7000-7143 (144), the capsule renders (84) and Table 1 score
#: bit for bit as before.
SWAP_ABD_MARGIN_RAD = float(np.radians(0.5))
SWAP_CURL_GAP_RAD = 0.8
SWAP_MAX_CURL_RAD = 2.2
SWAP_PALM_COS = 0.85
SWAP_MARGIN = 0.02
#: Curl restarts (:meth:`RestartStrategies._curl_restarts`, issue 11, all chosen here).  When
#: a finger of index .. little flexed less than ``CURL_MAX_FLEX_RAD`` (MCP + PIP + DIP, rad) has
#: no detection of its own within ``SHIFT_SKIP_MM`` (the optimal assignment), with the palm or
#: the back of the hand toward the camera (``SWAP_PALM_COS``), every such open finger is tried
#: with :data:`FINGER_CURLED`; a candidate wins by ``CURL_MARGIN`` of
#: :meth:`RestartStrategies._score`.  After a try none is tried for ``CURL_WAIT`` rounds of the
#: restarts (tracked frames: every frame at 30 Hz, see ``Tracker.restart_interval_s``).
#: On mesh renders of finger counting (clean depth, palm to the camera) the ring finger, as it
#: curled into the palm, stayed open on the middle finger's data for the last 8-12 frames
#: (110-124 mm); the candidate with the ring curled scored 0.043-0.049 higher.  The open finger
#: without a detection of its own may be the neighbour (the ring fingertip took the middle
#: finger's detection): hence every open finger is tried.  The other
#: scores seen: wrong curls (an open finger whose detection was missing) won at margins 0.01
#: (dev 5.83 -> 6.57 mm, 29 renders worse) and 0.02 (5.83 -> 5.95, 8 worse), and in hands seen
#: from the side (a rotating hand, validation 9.6 -> 12.4 mm without the palm condition).
#: Without the wait it fired on up to 27 of 60 frames of a render, with it on 4-5.
CURL_MAX_FLEX_RAD = 1.5
CURL_MARGIN = 0.04
CURL_WAIT = 10
#: After restarts triggered by an unexplained detection all lost, they are not tried again
#: for this many frames (count; chosen here).
RESTART_COOLDOWN = 5
#: Detection restarts of a hand seen nearly edge-on (``|palm normal . view axis|`` under
#: ``EDGE_ON_PALM_COS``) win only by ``EDGE_ON_MARGIN`` of :meth:`RestartStrategies._score`
#: (unitless; chosen here, issue 11).  Edge-on, the fingers overlap in the image and the
#: score cannot tell them apart: on rotating hands a detection restart curled the index finger
#: and moved the others one place over (validation 5078, frames 43-49 at 20-42 mm, palm
#: normal at 0.38-0.54; the margin of the swaps, ``SWAP_MARGIN``, kept it right).  Only rotating
#: hands changed: validation 5.878 -> 5.840 mm (5078 10.3 -> 7.3 mm), further 5.801 -> 5.761
#: (7008 8.5 -> 6.3, 7088 6.9 -> 5.3), seeds 9000-9095, not looked at before, 5.757 -> 5.721
#: (9068 9.5 -> 5.7); dev 5.848 -> 5.852 (3018 7.6 -> 8.0); frames over 20 mm 26 -> 14, 30 ->
#: 17, 18 -> 10 and 30 -> 30.
EDGE_ON_PALM_COS = 0.6
EDGE_ON_MARGIN = SWAP_MARGIN
#: The lateral restarts of a new track (:meth:`RestartStrategies._lateral_restarts`) move the
#: hand this far (mm) along its own x axis (palm width; chosen here, issue 11: about one
#: finger's spacing, 18-20 mm in the default hand).  On mesh dev renders whose hand was small
#: or wide (lengths 0.87-1.0, widths 0.87-1.06), initialisation put the model's index..little
#: on three fingers' data, two on one, and left the outermost finger unexplained: the fit and
#: the finger shifts stay in that optimum (the fingers move, the palm does not); from the
#: palm moved 15 mm either way, a fit of 12 iterations reached the right hand and scored
#: higher (0.48 against 0.46, 0.52 against 0.41).  12 mm and 20 mm helped the same renders.
LATERAL_MM = 15.0
#: ... and a candidate wins only by this much of :meth:`RestartStrategies._score` (unitless;
#: chosen here).  Without a margin, 67 of 144 validation renders took a candidate on their
#: first frame, most by less than 0.005, and the 128 widely shifted copies of the labelled
#: real frames went from 11.03 to 11.51 mm (frame 4, whose objective prefers its fingers one
#: place over, more often there); with 0.01 they stay at 11.03 mm, and most right candidates
#: of the renders above still win (gains of 0.010-0.076; one of 0.009 no longer does).
LATERAL_MARGIN = 0.01


@dataclass(frozen=True, eq=False)
class ShiftCandidate:
    """A scheduled finger-shifted restart whose iterations are spread over frames.

    Attributes
    ----------
    x : array, shape (26,)
        The candidate pose after its iterations so far.
    steps : array, shape (26,)
        Its optimiser's step lengths (mm / rad), to continue with.
    iterations : int
        Iterations done.
    anchor : array, shape (26,)
        The track's pose on the frame the candidate was last refined on: the next frame moves
        the candidate's wrist as the track's wrist moved.
    """

    x: NDArray[np.float64]
    steps: NDArray[np.float64]
    iterations: int
    anchor: NDArray[np.float64]


class RestartStrategies:
    """Mixin of :class:`~hand_sog_tracker.core.tracker.Tracker`: the restart strategies."""

    _model: HandModel
    _config: TrackerConfig
    _frame_count: int
    _restart_wait: int
    _shift_pending: ShiftCandidate | None
    #: Rounds of the restarts until :meth:`_curl_restarts` may try again.
    _curl_wait: int
    _limits: Callable[[], tuple[NDArray[np.float64], NDArray[np.float64]]]
    #: The tracker's fit that pauses after every iteration (``Tracker._fit``).
    _fit: Callable[..., Steps[OptimizeResult]]

    # The strategies are :data:`~hand_sog_tracker.core.optimizer.Steps`: they pause after every
    # iteration of their fits, so that a caller with a deadline can leave the rest for later
    # (``Tracker.finish_frame``); ``optimizer.run`` runs one at once.

    def _restarts(
        self, obj: Objective, res: OptimizeResult, data: ImageSoG, det: Detections
    ) -> Steps[OptimizeResult]:
        """A tracked frame's restarts: finger, swap, curl, then shift, then detection restarts.

        When the restarts set off by an unexplained detection all lost, the shift and detection
        restarts wait ``RESTART_COOLDOWN`` frames (such a detection is often a knuckle or a
        forearm edge); the finger, swap and curl restarts run every time (the curl restarts
        with their own wait after a try, ``CURL_WAIT``).
        """
        res = yield from self._finger_restarts(obj, res, data)
        res = yield from self._swap_restarts(obj, res, det)
        res = yield from self._curl_restarts(obj, res, det)
        if self._restart_wait > 0:
            self._restart_wait -= 1
            self._frame_count += 1  # (the shift restarts' schedule goes on)
            return res
        lonely = self._lonely(res.x, det)
        before = res
        res = yield from self._shift_restarts(obj, res, det, lonely=lonely)
        res = yield from self._detection_restarts(obj, res, det, lonely=lonely if res is before else None)
        if lonely.size and res is before:  # (all tried, all lost)
            self._restart_wait = RESTART_COOLDOWN
        return res

    def _scheduled_restarts(self, obj: Objective, res: OptimizeResult, det: Detections) -> Steps[OptimizeResult]:
        """A tracked frame's restarts between two frames that run them all (a fast camera, see
        :attr:`~hand_sog_tracker.core.tracker.Tracker.restart_interval_s`): only the scheduled
        finger shift (:meth:`_scheduled_shift`: ``SHIFT_CHUNK`` iterations on the frames that
        have a candidate, about 1 ms), so that its schedule goes on frame by frame.

        Issue 11/14: with the whole restarts at most 5 times a second, a shift candidate
        started every ``SHIFT_EVERY`` x 0.2 s and needed 0.8 s to be judged; fed 100 Hz finger
        counting, the node left fingers on their neighbours' places for 1-2 s (18 mm mean
        error, 68% of frames within 20 mm, against 8.8 mm and 100% in core mode).  The
        cooldown of the detection restarts (``RESTART_COOLDOWN`` frames) counts these frames
        too: counted only at the frames that run all the restarts, it lasted 1 s at 100 Hz, and
        a finger lost meanwhile stayed lost (a dev render's ring finger, 130 mm off).
        """
        self._frame_count += 1
        if self._restart_wait > 0:  # (the cooldown counts camera frames as well)
            self._restart_wait -= 1
        return (yield from self._scheduled_shift(obj, res, det))

    def _finger_restarts(self, obj: Objective, res: OptimizeResult, data: ImageSoG) -> Steps[OptimizeResult]:
        """Restart a dangling finger from other configurations (seed 004).

        When a fingertip is farther than ``RESTART_TIP_MM`` from every data
        point, the finger hangs in empty space (typically left extended over a
        fist).  The chain whose tip is farthest is re-set to an extended, a
        curled and (for the four fingers) the other fingers' mean
        configuration; each candidate gets ``RESTART_ITERATIONS`` iterations
        and the best objective wins.  At most one chain per frame.
        """
        if data.n == 0:
            return res
        tips = fingertips(self._model, res.x)
        far = np.sqrt(_sq_distances(tips, data.points).min(axis=1))
        c = int(np.argmax(far))
        if far[c] < RESTART_TIP_MM:
            return res
        sl = chain_slice(c)
        candidates = [FINGER_EXTENDED, FINGER_CURLED]
        if c > 0:
            others = [k for k in range(1, 5) if k != c]
            candidates.append(np.mean([res.x[chain_slice(k)] for k in others], axis=0))
        best = res
        for joints in candidates:
            x0 = res.x.copy()
            x0[sl] = joints
            cand = yield from self._fit(obj, x0, iterations=RESTART_ITERATIONS)
            if cand.fun > best.fun:
                best = cand
        return best

    def _swap_restarts(self, obj: Objective, res: OptimizeResult, det: Detections) -> Steps[OptimizeResult]:
        """Swap a finger that lies on its curled neighbour's place with that neighbour.

        A model finger lying extended on its neighbour's data, while the neighbour's model
        finger is curled, reaches it by abducting: the data hold it at its abduction limit.
        For such a finger (:meth:`_swap_pair`) the candidate gives the two fingers each
        other's flexions with neutral abductions; it is refined for ``RESTART_ITERATIONS``
        and kept if its :meth:`_score` is higher by ``SWAP_MARGIN``.  At most one pair per
        frame: the one with the largest difference in curl.
        """
        pair = self._swap_pair(res.x)
        if pair is None:
            return res
        plain = self._plain(obj)
        best_val = self._score(plain, res.x, det)
        cand = yield from self._fit(plain, _swapped(res.x, *pair), iterations=RESTART_ITERATIONS)
        if self._score(plain, cand.x, det, value=cand.fun) > best_val + SWAP_MARGIN:
            return cand
        return res

    def _curl_restarts(self, obj: Objective, res: OptimizeResult, det: Detections) -> Steps[OptimizeResult]:
        """Curl an open finger that has no fingertip detection of its own into the palm.

        When a finger curls into the palm, its model finger can stay open on the neighbouring
        finger's data: every model Gaussian still explains data, and neither the finger
        restarts (the tip is on data) nor the swaps (the neighbour is open too) see it.  Its
        fingertip, or its open neighbour's, then has no detection of its own, like a curled
        finger's.  When a finger of index .. little flexed less than ``CURL_MAX_FLEX_RAD`` has no
        detection of its own within ``SHIFT_SKIP_MM`` (with the palm or the back of the hand
        toward the camera, ``SWAP_PALM_COS``), each such open finger is tried with
        :data:`FINGER_CURLED`, refined ``RESTART_ITERATIONS``; the best candidate replaces
        ``res`` if its :meth:`_score` is higher by ``CURL_MARGIN``.  After a try, the next
        ``CURL_WAIT`` rounds of the restarts try none.
        """
        if self._curl_wait > 0:
            self._curl_wait -= 1
            return res
        if det.n == 0 or abs(global_rotation(res.x)[2, 2]) < SWAP_PALM_COS:
            return res
        flex = res.x[FINGER_MCP] + res.x[FINGER_PIP] + res.x[FINGER_DIP]  # index .. little (4,)
        fingers = [c for c in range(1, 5) if flex[c - 1] < CURL_MAX_FLEX_RAD]
        if not fingers:
            return res
        if self._own_detections(res.x, det)[fingers].all():
            return res
        self._curl_wait = CURL_WAIT
        plain = self._plain(obj)
        best, best_val = res, self._score(plain, res.x, det) + CURL_MARGIN
        for c in fingers:
            x0 = res.x.copy()
            x0[chain_slice(c)] = FINGER_CURLED
            cand = yield from self._fit(plain, x0, iterations=RESTART_ITERATIONS)
            val = self._score(plain, cand.x, det, value=cand.fun)
            if val > best_val:
                best, best_val = cand, val
        return best

    def _swap_pair(self, theta: NDArray[np.float64]) -> tuple[int, int] | None:
        """``(finger, neighbour)`` (chains 1-4) for :meth:`_swap_restarts` at ``theta`` (26,),
        or None: a finger curled at most ``SWAP_MAX_CURL_RAD`` (MCP + PIP flexion), within
        ``SWAP_ABD_MARGIN_RAD`` of its abduction limit toward a neighbour curled more than it
        by ``SWAP_CURL_GAP_RAD``, the palm or the back of the hand toward the camera
        (``SWAP_PALM_COS``); of several, the pair with the largest difference in curl."""
        if abs(global_rotation(theta)[2, 2]) < SWAP_PALM_COS:
            return None
        lo, hi = self._limits()
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

    def _shift_restarts(
        self,
        obj: Objective,
        res: OptimizeResult,
        det: Detections,
        force: bool = False,
        lonely: NDArray[np.int64] | None = None,
    ) -> Steps[OptimizeResult]:
        """Move every finger's articulation to its neighbour (seed 004's finger-shifted restarts).

        A model whose fingers each lie on their neighbour's data (one curled into the palm,
        the others spread over its place) is a deep local optimum: every finger explains
        data.  The candidate gives index .. little the flexions of their neighbour on one
        side (the last finger keeps its own) and neutral abductions, is refined for
        ``RESTART_ITERATIONS`` and is kept only if its :meth:`_score` is higher.  Tried in
        both directions on this frame when a confident detection is unexplained (see
        :meth:`_detection_restarts`) or with ``force`` (initialisation); otherwise one
        direction starts every ``SHIFT_EVERY`` frames and is refined ``SHIFT_CHUNK``
        iterations per frame (:meth:`_scheduled_shift`).  ``lonely``: :meth:`_lonely` at
        ``res.x`` when already known.
        """
        if not force:
            self._frame_count += 1
        if not (force or (self._lonely(res.x, det) if lonely is None else lonely).size):
            return (yield from self._scheduled_shift(obj, res, det))
        plain = self._plain(obj)
        hidden = not force  # (initialisation: see _assignment_cost)
        best, best_val = res, self._score(plain, res.x, det, hidden_tips=hidden)
        for side in (1, -1):
            cand = yield from self._fit(plain, _shifted(res.x, side), iterations=RESTART_ITERATIONS)
            val = self._score(plain, cand.x, det, value=cand.fun, hidden_tips=hidden)
            if val > best_val:
                best, best_val = cand, val
        return best

    def _lateral_restarts(self, obj: Objective, res: OptimizeResult, det: Detections) -> Steps[OptimizeResult]:
        """Restart a new track's pose with the hand moved sideways (after an initialisation).

        Six candidates: the pose of ``res`` with the hand translated ``LATERAL_MM`` along its
        own x axis (across the palm), either way, with its fingers as they are and shifted
        one place either way (:func:`_shifted`), each refined ``RESTART_ITERATIONS``; the best
        by :meth:`_score` (without the hidden-tip discount, as the initialisation's other
        candidates) replaces ``res`` if it scores higher.  A model whose index .. little lie
        on three fingers' data leaves the fourth unexplained; moving its fingers alone (the
        finger shifts) does not get out of that, moving the palm with them does.
        """
        plain = self._plain(obj)
        best, best_val = res, self._score(plain, res.x, det, hidden_tips=False)
        across = global_rotation(res.x)[:, 0] * LATERAL_MM
        for sign in (1.0, -1.0):
            for side in (0, 1, -1):
                x0 = res.x.copy() if side == 0 else _shifted(res.x, side)
                x0[:3] += sign * across
                cand = yield from self._fit(plain, x0, iterations=RESTART_ITERATIONS)
                val = self._score(plain, cand.x, det, value=cand.fun, hidden_tips=False)
                if val > best_val + LATERAL_MARGIN:
                    best, best_val = cand, val
        return best

    def _scheduled_shift(self, obj: Objective, res: OptimizeResult, det: Detections) -> Steps[OptimizeResult]:
        """Refine the pending shift candidate ``SHIFT_CHUNK`` iterations on this frame.

        A candidate starts every ``SHIFT_EVERY`` frames, on the side :meth:`_shift_side` picks,
        unless every fingertip is within ``SHIFT_SKIP_MM`` of a detection of its own
        (:meth:`_tips_seen`); between frames its wrist moves as the track's did.  Once it has
        had ``RESTART_ITERATIONS`` it replaces the frame's fit if its :meth:`_score` is higher,
        and is dropped either way.
        """
        pending = self._shift_pending
        if pending is None and (self._frame_count % SHIFT_EVERY or self._tips_seen(res.x, det)):
            return res
        plain = self._plain(obj)
        if pending is None:
            side = self._shift_side(res.x, det)
            cand = yield from self._fit(plain, _shifted(res.x, side), iterations=SHIFT_CHUNK)
            done = SHIFT_CHUNK
        else:
            x0 = pending.x.copy()
            x0[:6] += res.x[:6] - pending.anchor[:6]
            cand = yield from self._fit(plain, x0, iterations=SHIFT_CHUNK, initial_steps=pending.steps)
            done = pending.iterations + SHIFT_CHUNK
        if done < RESTART_ITERATIONS:
            self._shift_pending = ShiftCandidate(cand.x, cand.steps, done, res.x)
            return res
        self._shift_pending = None
        if self._score(plain, cand.x, det, value=cand.fun) > self._score(plain, res.x, det):
            return cand
        return res

    def _shift_side(self, theta: NDArray[np.float64], det: Detections) -> int:
        """The side (+1 or -1, see :func:`_shifted`) of the next scheduled shift candidate at
        ``theta`` (26,): the one whose shifted start pose leaves the lower assignment cost
        (:meth:`_assignment_cost`); without detections, or on a tie, the sides alternate every
        ``SHIFT_EVERY`` frames.  (Issue 11: alternating, a finger counting hand whose fingers
        sat one place over waited up to 24 frames for the side that put them back; on 64 dev
        renders of finger counting and fist-and-open, 2 renders gained 4 mm, one lost 1.3.)"""
        alternate = 1 if (self._frame_count // SHIFT_EVERY) % 2 else -1
        if det.n == 0:
            return alternate
        cost = {side: self._assignment_cost(_shifted(theta, side), det) for side in (1, -1)}
        if cost[1] == cost[-1]:
            return alternate
        return 1 if cost[1] < cost[-1] else -1

    def _detection_restarts(
        self,
        obj: Objective,
        res: OptimizeResult,
        det: Detections,
        lonely: NDArray[np.int64] | None = None,
    ) -> Steps[OptimizeResult]:
        """Put a finger onto a detection that no model finger explains (seed 001 + 004).

        A confident detection farther than ``UNEXPLAINED_DETECTION_MM`` from every model
        fingertip (a less confident one farther than ``FAR_UNEXPLAINED_MM``, :meth:`_lonely`)
        is a finger the model has missed (typically one curled toward the camera
        while the model finger lies on its neighbour).  Each of the two model fingers
        nearest to it is pulled onto it by the salient term, strongly weighted, for
        ``RESTART_ITERATIONS``, twice: with only that finger's joints free (the other fingers
        stay on their data), and with the whole pose free (when the hand itself sits wrong)
        while every other finger is pulled onto its own detection as well (the optimal
        assignment of the other fingertips to the remaining detections, :meth:`_joint_targets`:
        a model finger that lay on its neighbour's data moves back; issue 11: labelled real
        frame 2, started one finger over, stayed there when the one finger was pulled alone
        with the whole pose free, as before); each pull is then released into the objective
        without the salient term (which would favour the assignment the frame started with); a
        candidate is kept only if its :meth:`_score` is higher than before (by ``EDGE_ON_MARGIN``
        for a hand seen nearly edge-on, ``EDGE_ON_PALM_COS``).  ``lonely``:
        :meth:`_lonely` at ``res.x`` when already known.
        """
        if lonely is None:
            lonely = self._lonely(res.x, det)
        if lonely.size == 0:
            return res
        s = int(lonely[np.argmax(det.confidence[lonely])])
        dist = np.linalg.norm(det.points[s] - fingertips(self._model, res.x), axis=1)
        cfg = self._config
        plain = self._plain(obj)
        edge_on = abs(global_rotation(res.x)[2, 2]) < EDGE_ON_PALM_COS
        best, best_val = res, self._score(plain, res.x, det) + (EDGE_ON_MARGIN if edge_on else 0.0)
        strong = replace_config(cfg, w_sal=max(cfg.w_sal, 1.0) * 20.0)  # (the pulls' salient weight)
        for c in np.argsort(dist)[:2]:
            w = np.zeros(5)
            w[c] = 1.0
            pts = np.zeros((5, 3))
            pts[c] = det.points[s]
            pull = obj.variant(strong, TipTargets(pts, w))
            finger = np.zeros(res.x.size, dtype=bool)
            finger[chain_slice(c)] = True
            joint = obj.variant(strong, self._joint_targets(res.x, det, int(c), s))
            # Start poses: the two pulls (objective, active parameters) and a pose.
            starts: list[tuple[Objective, NDArray[np.bool_] | None] | NDArray[np.float64]] = [
                (pull, finger),
                (joint, None),
            ]
            if det.end_on[s] and c > 0:
                # A finger seen end-on is curled toward the camera: also try it curled.
                curled = res.x.copy()
                curled[chain_slice(c)] = FINGER_CURLED
                starts.append(curled)
            for start in starts:
                if isinstance(start, tuple):
                    pulled = yield from self._fit(start[0], res.x, iterations=RESTART_ITERATIONS, active=start[1])
                    start = pulled.x
                cand = yield from self._fit(plain, start, iterations=RESTART_ITERATIONS)
                val = self._score(plain, cand.x, det, value=cand.fun)
                if val > best_val:
                    best, best_val = cand, val
        return best

    def _joint_targets(self, theta: NDArray[np.float64], det: Detections, c: int, s: int) -> TipTargets:
        """Targets for fingertip ``c`` on detection ``s`` (weight 1) and for the other fingertips
        at ``theta`` (26,) on the detections the optimal assignment (:func:`assign_detections`)
        gives them among the others (their confidence; none for a detection seen end-on, as
        in the tracked frames' salient term)."""
        rest = np.ones(det.n, dtype=bool)
        rest[s] = False
        others = np.flatnonzero(np.arange(5) != c)
        sub = det.subset(rest)
        assigned = assign_detections(fingertips(self._model, theta)[others], sub, ASSIGN_LAMBDA_MM)
        points = np.zeros((5, 3))
        weights = np.zeros(5)
        points[c], weights[c] = det.points[s], 1.0
        for o, a in zip(others, assigned):
            if a >= 0 and not sub.end_on[a]:
                points[o], weights[o] = sub.points[a], sub.confidence[a]
        return TipTargets(points, weights)

    def _tips_seen(self, theta: NDArray[np.float64], det: Detections) -> bool:
        """Whether every fingertip at ``theta`` (26,) has a detection of its own
        (:meth:`_own_detections`)."""
        return det.n >= 5 and bool(self._own_detections(theta, det).all())

    def _own_detections(self, theta: NDArray[np.float64], det: Detections) -> NDArray[np.bool_]:
        """Per fingertip at ``theta`` (26,), thumb .. little (5,): whether it has a detection of
        its own (the optimal assignment, :func:`assign_detections`) within ``SHIFT_SKIP_MM``."""
        tips = fingertips(self._model, theta)
        assigned = assign_detections(tips, det, ASSIGN_LAMBDA_MM)
        own = assigned >= 0
        own[own] = np.linalg.norm(tips[own] - det.points[assigned[own]], axis=1) < SHIFT_SKIP_MM
        return own

    def _lonely(self, theta: NDArray[np.float64], det: Detections) -> NDArray[np.int64]:
        """The detections no fingertip at ``theta`` (26,) explains: confident ones farther than
        ``UNEXPLAINED_DETECTION_MM`` from every fingertip, less confident ones farther than
        ``FAR_UNEXPLAINED_MM``."""
        if det.n == 0:
            return np.zeros(0, dtype=np.int64)
        tips = fingertips(self._model, theta)
        dist = np.sqrt(_sq_distances(det.points, tips)).min(axis=1)  # = np.linalg.norm(.., axis=-1)
        conf = det.confidence
        return np.flatnonzero(
            ((dist > UNEXPLAINED_DETECTION_MM) & (conf >= UNEXPLAINED_CONFIDENCE))
            | ((dist > FAR_UNEXPLAINED_MM) & (conf >= FAR_UNEXPLAINED_CONFIDENCE))
        )

    def _score(
        self,
        plain: Objective,
        theta: NDArray[np.float64],
        det: Detections,
        value: float | None = None,
        hidden_tips: bool = True,
    ) -> float:
        """How well ``theta`` explains the frame: the objective without the salient term,
        minus the assignment cost of the detections at ``theta`` (fresh, not the one the
        frame started with), weighted like the salient term.  ``value``: ``plain`` at
        ``theta`` when already known (a fit of ``plain`` returns it).  ``hidden_tips``: see
        :meth:`_assignment_cost`."""
        if value is None:
            value = plain(theta, gradient=False)[0]
        return value - self._config.w_sal * self._assignment_cost(theta, det, hidden_tips)

    def _plain(self, obj: Objective) -> Objective:
        """``obj`` without the salient term (to judge candidates built from detections)."""
        if obj.targets is None or self._config.w_sal == 0:
            return obj
        return obj.variant(replace_config(self._config, w_sal=0.0), None)

    def _assignment_cost(
        self, theta: NDArray[np.float64], det: Detections, hidden_tips: bool = True
    ) -> float:
        """Seed 001's assignment cost (eq. 11) at ``theta``, in units of ``SALIENT_SCALE_MM``.

        Assigned pairs cost their distance, detections left over ``lambda * confidence``,
        fingertips without a detection ``lambda``: a hypothesis whose fingertips are not
        where the fingertips are seen (a hand flipped palm-for-back, fingers swapped) scores
        worse even where the depth overlap cannot tell.  With ``hidden_tips`` (tracking) a
        fingertip curled against a palm facing the camera costs less (:func:`_tip_lambdas`);
        initialisation scores without it (``False``): while the palm's side is still open, it
        favours a palm turned to the camera with curled fingers (labelled real frame 7, a
        fist seen from the back: 22.6 -> 80 mm with it; frame 4: 7.5 -> 32 mm).
        """
        if det.n == 0:
            return 0.0
        tips = fingertips(self._model, theta)
        lam = _tip_lambdas(theta) if hidden_tips else np.full(5, ASSIGN_LAMBDA_MM)
        assigned = assign_detections(tips, det, ASSIGN_LAMBDA_MM, lam)
        has = assigned >= 0
        d = np.linalg.norm(tips[has] - det.points[assigned[has]], axis=1).sum()
        unused = np.ones(det.n, bool)
        unused[assigned[has]] = False
        cost = d + lam[~has].sum() + ASSIGN_LAMBDA_MM * det.confidence[unused].sum()
        return float(cost / SALIENT_SCALE_MM)


def _tip_lambdas(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cost (mm) of leaving each fingertip (5,) at ``theta`` (26,) without a detection.

    ``ASSIGN_LAMBDA_MM``, but for a finger curled past ``OPEN_TIP_RAD`` (PIP + DIP flexion)
    while the palm faces the camera it falls linearly to ``HIDDEN_TIP_LAMBDA x
    ASSIGN_LAMBDA_MM`` at ``CURLED_TIP_RAD``: such a tip lies against the palm, hidden, and no
    detection is expected for it.
    """
    lam = np.full(5, ASSIGN_LAMBDA_MM)
    if HIDDEN_TIP_LAMBDA != 1.0 and -global_rotation(theta)[2, 2] > HIDDEN_PALM_COS:
        curl = theta[FINGER_PIP] + theta[FINGER_DIP]  # index .. little, rad
        share = np.clip((curl - OPEN_TIP_RAD) / (CURLED_TIP_RAD - OPEN_TIP_RAD), 0.0, 1.0)
        lam[1:] *= 1.0 - (1.0 - HIDDEN_TIP_LAMBDA) * share
    return lam


def _sq_distances(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Squared distances (k, l) between the points ``a`` (k, 3) and ``b`` (l, 3).

    The same sums as ``((a[:, None] - b[None]) ** 2).sum(-1)`` (``(x^2 + y^2) + z^2`` in that
    order, bit for bit; several times cheaper: no reduction over an axis of length 3).
    """
    diff = a[:, None, :] - b[None, :, :]
    sq = np.multiply(diff, diff, out=diff)
    d2 = sq[..., 0] + sq[..., 1]
    d2 += sq[..., 2]
    return d2


def _swapped(theta: NDArray[np.float64], a: int, b: int) -> NDArray[np.float64]:
    """``theta`` (26,) with chains ``a`` and ``b`` (1-4) exchanging their flexions, both with
    neutral abductions."""
    x0 = theta.copy()
    sa, sb = chain_slice(a), chain_slice(b)
    x0[sa], x0[sb] = theta[sb], theta[sa]
    x0[sa.start + ABD] = 0.0
    x0[sb.start + ABD] = 0.0
    return x0


def _shifted(theta: NDArray[np.float64], side: int) -> NDArray[np.float64]:
    """``theta`` (26,) with index .. little given the flexions of their neighbour on ``side``
    (+1: toward the little finger; the last finger keeps its own) and neutral abductions: the
    neighbour's abduction is what carried it over onto this finger's data."""
    q = theta[JOINTS].reshape(5, CHAIN_JOINTS)
    shifted = q[np.clip(np.arange(1, 5) + side, 1, 4)].copy()
    shifted[:, 1] = 0.0
    x0 = theta.copy()
    x0[chain_slice(1).start :] = shifted.ravel()
    return x0
