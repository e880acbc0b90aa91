"""Up to ``max_hands`` hands in one depth stream, each tracked by its own :class:`Tracker`.

Units: millimetres, camera optical frame, as in :mod:`.tracker`.

Per frame the depth is preprocessed once and shared:

* **Tracked hands** are fitted nearest first (the front hand is the one not hidden).  Each
  hand's data are the quadtree Gaussians near it *minus those another hand explains*: a data
  point belongs to another hand when it lies within :data:`OWN_MARGIN_MM` of that hand's skin
  (its model posed this frame, or its last pose when not fitted yet, plus a forearm capsule)
  and nearer to that skin than to this hand's (at this hand's start pose).  Fingertip
  detections are divided the same way (the detector's cap applies after the division), and a
  fingertip near another hand's skin (within :data:`COVERED_MM`) needs no detection of its own
  for the search (``Tracker.covered_tips``: the detector sees no end there, so its curl
  proposal does not fire), nor does a fingertip another hand hides (:func:`hidden_by`), which
  does not dangle either; a finger whose tip another hand hides keeps its joints in the fit
  (``Tracker.held``: no data speak for it).  The silhouette stays
  the whole image's: another hand in front is an occluder the hidden parts may project onto,
  and another hand's data more than :data:`OCCLUDER_GAP_MM` in front of this hand's skin on
  its line of sight stay in its data as occluders (:func:`in_front`).
* **New hands**: with fewer than ``max_hands`` tracked, the hand finder of a new track
  (:mod:`.search.start`) runs on the depth with every tracked hand's pixels (its skin and
  forearm, :data:`PIXEL_MARGIN_MM`) removed, so a second hand starts its own track without
  touching the first.  Without any track it runs every frame; with one, every
  :data:`SEARCH_EVERY` frames (a one-hand user does not pay for it on every frame), twice as
  many after each search that started no track (up to :data:`SEARCH_EVERY_MAX`).  A track the
  gate drops makes the next frame search only when it was a hand on its last frame.  A new
  track whose every finalist leaves the data around it unexplained (the gate would drop it on
  its first frame) is dropped before the finalists' full fits (:data:`CHECK_FINALISTS`).
* **Handedness** is fixed when a track starts and held while it lasts.  A free label is given
  when the other one is taken (one person, two hands); with both free it comes from the data:
  the new track is started with the right model, the mirrored (left) one from the found pose
  turned half a turn about the hand's long axis, both are tracked for a trial
  (:data:`TRIAL_FRAMES`, both on one shape) and the one that explains the hand better
  (summed :attr:`TrackResult.confidence`, the share of the model on data) wins; two trials at
  once are decided together with different labels.  Unless ``handedness`` fixes it.  A hand
  in its trial is not reported.
* A new track that lands on a tracked hand (palms closer than :data:`SAME_HAND_MM` and the
  two models in one volume, :func:`shared_volume`) is dropped; two tracks that converge on
  one hand keep the older.  Two hands that touch (palm to palm in a clap) are not one: their
  models meet at the skin, they do not share it.
* **Is it a hand?**  Every track's frame ends with the hand decision of the one-hand tracker
  (its own :class:`~.handcheck.HandGate` on the frame's depth, issue 46): a frame that is no
  hand is not reported, and a track the gate would reset is dropped, and the next frame
  searches for a new hand.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Final, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, preprocess
from hand_sog_tracker.core.hand_model import HandModel, chain_slice, default_hand_model
from hand_sog_tracker.core.handcheck import EXPLAINED_LOW, HandGate, Theirs, check_hand
from hand_sog_tracker.core.kinematics import gaussian_centres, global_rotation, keypoint_skeleton, posed_centres
from hand_sog_tracker.core.objective.interhand import InterHand
from hand_sog_tracker.core.region import hand_roi
from hand_sog_tracker.core.salient import RING_RADIUS_MM, TIP_DEPTH_OFFSET_MM, Detections
from hand_sog_tracker.core.search.start import Bounds, Finalists, start_search
from hand_sog_tracker.core.support import without_support
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import HandDecision, Intrinsics, TrackerConfig, TrackerStatus, TrackResult
from hand_sog_tracker.errors import InputError

__all__ = [
    "CHECK_FINALISTS",
    "COVERED_MM",
    "HANDS",
    "OWN_MARGIN_MM",
    "PAIR_LEAD",
    "PIXEL_MARGIN_MM",
    "SAME_HAND_MM",
    "SHARED_VOLUME",
    "SEARCH_EVERY",
    "SEARCH_EVERY_MAX",
    "TRIAL_FRAMES",
    "TRIAL_LEAD",
    "hidden_by",
    "shared_volume",
    "without_hands",
    "HandTrack",
    "HandsResult",
    "MultiHandTracker",
    "skin_distance",
]

HANDS: Final[tuple[str, str]] = ("left", "right")
#: A data point within this of another hand's skin (and nearer to it than to this hand's) is
#: that hand's (mm: depth noise plus the model's fit error at the skin; chosen here).
OWN_MARGIN_MM: Final[float] = 12.0
#: A fingertip (the centre of its sphere) within this of another hand's skin has no end the
#: detector can see (mm): the detector's ring around the tip's end, one radius beyond the
#: centre, meets the other hand (:func:`~.salient.detect_fingertips`).
COVERED_MM: Final[float] = RING_RADIUS_MM + TIP_DEPTH_OFFSET_MM
#: A pixel within this of a tracked hand's skin or forearm is that hand's for the finder of a
#: new hand (mm; wider than :data:`OWN_MARGIN_MM`: the finder must not see a fringe of it).
PIXEL_MARGIN_MM: Final[float] = 20.0
#: The forearm capsule: from the wrist back along the hand's long axis this far, this thick
#: (radius, mm); the hand model has no forearm, and another hand's forearm is not this hand.
FOREARM_LENGTH_MM: Final[float] = 300.0
FOREARM_RADIUS_MM: Final[float] = 35.0
#: Another hand's data this far (mm) in front of a hand's skin stay in that hand's data as
#: occluders (``E_dan`` does not call what they hide dangling; ``E_sim`` ignores data that far
#: in front), unless ``KEEP_OCCLUDERS`` is off.
OCCLUDER_GAP_MM: Final[float] = 30.0
KEEP_OCCLUDERS = True
#: Whether a finger another hand hides keeps its joints in the fit (see :attr:`Tracker.held`).
HOLD_HIDDEN = True
#: The weight of the inter-hand collision term (``- w E_int``, :mod:`.objective.interhand`,
#: seed 001); 0: none.  Off: the scenes' true hands interpenetrate where they come close
#: (doc/design/two_hands.md, "Inter-hand collision term"), and on dev ``approach`` the term
#: then costs 0.4-1.2 mm; it changes nothing on ``occlude``, ``cross`` and ``touch``.
W_INTERHAND = 0.0
#: Another hand's spheres enter a hand's term when they come this near (mm) to touching one of
#: its spheres at the fit's start (a frame's motion and the fit's reach).
INTERHAND_REACH_MM: Final[float] = 30.0
#: Two tracks whose palm centres (the mean of the model's Gaussians) are closer may be one hand
#: (mm); they are when their models also share a volume (:data:`SHARED_VOLUME`).
SAME_HAND_MM: Final[float] = 40.0
#: Two models are in one volume when more than this share of either's Gaussian centres lies
#: inside the other's skin: a majority (two fits of one hand overlap; two hands in contact
#: interpenetrate at their surfaces only, 0-11% of the centres on dev ``clap`` frames 5-31).
SHARED_VOLUME: Final[float] = 0.5
#: Whether a new track's finalists face the hand gate's check before their full fits
#: (:meth:`MultiHandTracker._checked_start`).
CHECK_FINALISTS = True
#: With at least one hand tracked, a new hand is searched for every this many frames; after a
#: search that started no new track, twice as many, up to ``SEARCH_EVERY_MAX`` (a hand that comes
#: into view is then found within 0.67 s at 30 Hz), until a new track is a hand.
SEARCH_EVERY: Final[int] = 5
SEARCH_EVERY_MAX: Final[int] = 4 * SEARCH_EVERY
#: A track started with both labels free is tracked with both models (its trial) until the
#: summed confidence of one model leads by ``TRIAL_LEAD``, at most ``TRIAL_FRAMES`` frames, and
#: reported from then on with the label whose model explained it better.
TRIAL_FRAMES: Final[int] = 10
TRIAL_LEAD: Final[float] = 0.03
#: Two trials at once (two hands that appear together) are decided when the pair's summed
#: preference leads by this: half of ``TRIAL_LEAD``.  The pair's preference is the difference of
#: the two hands' leads, in which a bias of both toward one label cancels (dev ``cross``: both
#: hands' models lean left, the pair's preference is right from the second frame on but
#: reached ``TRIAL_LEAD`` only with the trial's last frame; doc/design/two_hands.md).
PAIR_LEAD: Final[float] = 0.5 * TRIAL_LEAD


def skin_distance(
    model: HandModel, theta: NDArray[np.float64], points: NDArray[np.float64], within: float | None = None
) -> NDArray[np.float64]:
    """Distance (mm) of ``points`` (n, 3) mm from the skin of the hand at ``theta`` (26,) and
    its forearm: the minimum over the model's Gaussians of (distance to the centre - sigma) and
    over the forearm capsule (see :data:`FOREARM_LENGTH_MM`); negative inside.  Shape (n,).

    With ``within`` (mm), only the points inside the box that holds the skin and forearm grown
    by ``within`` are measured, the others are ``inf`` (they are farther than ``within``): a
    caller that asks ``< within`` gets the same answer without the (n, m) distances of points
    far from the hand (another hand's pixels, most of a region's data)."""
    out = np.full(points.shape[0], np.inf)
    if points.shape[0] == 0:
        return out
    centres = posed_centres(model, theta)
    axis = global_rotation(theta)[:, 1]  # wrist -> fingers
    if within is not None:
        grow = model.g_sigmas[:, None] + within
        arm = np.stack([theta[:3], theta[:3] - FOREARM_LENGTH_MM * axis])  # the capsule's ends
        lo = np.minimum((centres - grow).min(axis=0), arm.min(axis=0) - FOREARM_RADIUS_MM - within)
        hi = np.maximum((centres + grow).max(axis=0), arm.max(axis=0) + FOREARM_RADIUS_MM + within)
        near = np.flatnonzero(np.all((points > lo) & (points < hi), axis=1))
        if near.size < points.shape[0]:
            out[near] = _skin(model, theta, centres, axis, points[near])
            return out
    return _skin(model, theta, centres, axis, points)


def _skin(
    model: HandModel, theta: NDArray[np.float64], centres: NDArray[np.float64], axis: NDArray[np.float64],
    points: NDArray[np.float64],
) -> NDArray[np.float64]:
    """:func:`skin_distance` of ``points`` (n, 3) mm, ``centres`` (m, 3) and ``axis`` (3,) posed."""
    if points.shape[0] == 0:
        return np.zeros(0)
    d2 = (
        np.einsum("ij,ij->i", points, points)[:, None]
        - 2.0 * points @ centres.T
        + np.einsum("ij,ij->i", centres, centres)[None, :]
    )
    skin = (np.sqrt(np.maximum(d2, 0.0)) - model.g_sigmas[None, :]).min(axis=1)
    rel = points - theta[:3]
    t = np.clip(-(rel @ axis), 0.0, FOREARM_LENGTH_MM)  # along the forearm, from the wrist
    lateral = np.linalg.norm(rel + t[:, None] * axis[None, :], axis=1)
    return np.minimum(skin, lateral - FOREARM_RADIUS_MM)


def shared_volume(
    a: tuple[HandModel, NDArray[np.float64]], b: tuple[HandModel, NDArray[np.float64]]
) -> float:
    """The larger of the shares of ``a``'s Gaussian centres inside ``b``'s skin and of ``b``'s
    inside ``a``'s (each (model, pose (26,))), in [0, 1]; the forearm is not counted."""
    (ma, xa), (mb, xb) = a, b
    ca, cb = posed_centres(ma, xa), posed_centres(mb, xb)
    d = np.linalg.norm(ca[:, None, :] - cb[None, :, :], axis=2)  # (m_a, m_b) mm
    a_in_b = (d - mb.g_sigmas[None, :]).min(axis=1) < 0.0
    b_in_a = (d - ma.g_sigmas[:, None]).min(axis=0) < 0.0
    return float(max(a_in_b.mean(), b_in_a.mean()))


def in_front(model: HandModel, theta: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which ``points`` (n, 3) mm hide the hand at ``theta`` (26,): each lies on the line of
    sight of one of its Gaussians (within its radius, laterally at its depth) and more than
    :data:`OCCLUDER_GAP_MM` in front of that Gaussian's skin.  Shape (n,)."""
    c = posed_centres(model, theta)
    s = model.g_sigmas
    pz = np.maximum(points[:, 2:3], 1e-6)
    cz = np.maximum(c[:, 2], 1e-6)
    du = points[:, 0:1] / pz - (c[:, 0] / cz)[None, :]
    dv = points[:, 1:2] / pz - (c[:, 1] / cz)[None, :]
    lateral = np.sqrt(du * du + dv * dv) * cz[None, :]
    ahead = points[:, 2:3] < (cz - s - OCCLUDER_GAP_MM)[None, :]
    return np.any((lateral < s[None, :]) & ahead, axis=1)


def hidden_by(
    pre: Preprocessed,
    hands: Sequence[tuple[HandModel, NDArray[np.float64]]],
    points: NDArray[np.float64],
    radii: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Which spheres (centres ``points`` (k, 3) mm, ``radii`` (k,) mm) one of ``hands`` ((model,
    pose (26,)) each) hides in the frame ``pre``: the depth at the centre's pixel lies more than
    :data:`OCCLUDER_GAP_MM` in front of the sphere and on that hand (within
    :data:`OWN_MARGIN_MM` of its skin), so no data can speak for the sphere.  Shape (k,)."""
    out = np.zeros(points.shape[0], dtype=bool)
    intr, depth = pre.intrinsics, pre.depth_mm
    z = points[:, 2]
    ok = z > 1.0
    if not hands or not ok.any():
        return out
    zs = np.where(ok, z, 1.0)
    u = np.rint(intr.fx * points[:, 0] / zs + intr.cx)
    v = np.rint(intr.fy * points[:, 1] / zs + intr.cy)
    ok &= (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
    k = np.flatnonzero(ok)
    d = depth[v[k].astype(np.int64), u[k].astype(np.int64)].astype(np.float64)
    front = (d > 0) & (d < z[k] - radii[k] - OCCLUDER_GAP_MM)
    k, d = k[front], d[front]
    if k.size == 0:
        return out
    pts = intr.backproject(np.stack([u[k], v[k]], 1), d)
    theirs = np.zeros(k.size, dtype=bool)
    for m, x in hands:
        theirs |= skin_distance(m, x, pts, OWN_MARGIN_MM) < OWN_MARGIN_MM
    out[k[theirs]] = True
    return out


def without_hands(
    depth_mm: NDArray,
    intrinsics: Intrinsics,
    hands: Sequence[tuple[HandModel, NDArray[np.float64]]],
    roi_radius_mm: float,
) -> NDArray:
    """``depth_mm`` (H, W) mm without the pixels of ``hands`` ((model, pose (26,)) each): every
    valid pixel within :data:`PIXEL_MARGIN_MM` of a hand's skin or forearm (:func:`skin_distance`),
    looked for in the hand's pixel box (:func:`~.region.hand_roi` of ``roi_radius_mm`` plus the
    forearm's length), set to 0 (invalid).  A new array; ``depth_mm`` itself when ``hands`` is
    empty.  The finder of a new hand sees the frame so (:meth:`MultiHandTracker._masked`), and so
    does the calibration of one hand beside another (:class:`~.autocalibration.HistoryFrame`)."""
    if not hands:
        return depth_mm
    depth = depth_mm.copy()
    for model, x in hands:
        roi, _ = hand_roi(model, x, intrinsics, roi_radius_mm + FOREARM_LENGTH_MM)
        u0, v0, u1, v1 = roi
        box = depth[v0:v1, u0:u1]
        vs, us = np.nonzero(box > 0)
        if vs.size == 0:
            continue
        uv = np.stack([us + u0, vs + v0], 1).astype(np.float64)
        pts = intrinsics.backproject(uv, box[vs, us].astype(np.float64))
        near = skin_distance(model, x, pts, PIXEL_MARGIN_MM) < PIXEL_MARGIN_MM
        box[vs[near], us[near]] = 0.0
    return depth


@dataclass(frozen=True, eq=False)
class HandTrack:
    """One tracked hand in one frame: its label, its track's id (new per track) and result."""

    handedness: str
    track_id: int
    result: TrackResult
    model: HandModel


@dataclass(frozen=True, eq=False)
class HandsResult:
    """Output of :meth:`MultiHandTracker.process`: the hands tracked in this frame (those whose
    status is TRACKING), in track order (oldest first), and the frame's wall times (ms:
    ``preprocess``, ``track``, ``search``, ``check`` (the hand gates), ``total``).
    ``withheld`` holds, per label, the hand gate's decision on a labelled track that it
    withheld this frame (its confidence is published, as the one-hand node does)."""

    hands: tuple[HandTrack, ...]
    timings_ms: dict[str, float] = field(default_factory=dict)
    withheld: dict[str, HandDecision] = field(default_factory=dict)

    def hand(self, side: str) -> HandTrack | None:
        """The tracked hand labelled ``side``, or None."""
        return next((h for h in self.hands if h.handedness == side), None)


@dataclass(eq=False)
class _Slot:
    """A live track: its tracker, label, id and result of the current frame; during its trial
    (:data:`TRIAL_FRAMES`) also the tracker of the other label, its result, the summed energy
    (confidence) lead of ``tracker`` over it and the frames tracked so far; the track's hand
    gate (whichever label leads), whether it reset the track (``dropped``) and whether its
    last decision was a hand (``present``)."""

    tracker: Tracker
    side: str
    track_id: int
    result: TrackResult | None = None
    alt: Tracker | None = None
    alt_result: TrackResult | None = None
    lead: float = 0.0
    age: int = 0
    gate: HandGate = field(default_factory=HandGate)
    dropped: bool = False
    present: bool = False  # the gate's last decision: a hand
    reported: bool = False  # the gate said "a hand" on some frame of the track

    def reset(self) -> None:
        """The gate's reset of the track: drop it (:meth:`MultiHandTracker._gate`)."""
        self.dropped = True

    def swap(self) -> None:
        """Make the other label's tracker the track's (during the trial)."""
        assert self.alt is not None
        self.tracker, self.alt = self.alt, self.tracker
        self.result, self.alt_result = self.alt_result, self.result
        self.side = "left" if self.side == "right" else "right"
        self.lead = -self.lead


def _theirs(
    model: HandModel, theta: NDArray[np.float64], others: Sequence[tuple[HandModel, NDArray[np.float64]]]
) -> Theirs:
    """``points (n, 3) mm -> (n,) bool``: the points another hand of ``others`` ((model, pose
    (26,)) each) explains beside the hand ``model`` at ``theta`` (26,): within
    :data:`OWN_MARGIN_MM` of its skin and nearer to it than to this hand's."""

    def theirs(points: NDArray[np.float64]) -> NDArray[np.bool_]:
        out = np.zeros(points.shape[0], dtype=bool)
        for m, x in others:  # (only a point near another hand asks for its own skin's distance)
            d = skin_distance(m, x, points, OWN_MARGIN_MM)
            k = np.flatnonzero(d < OWN_MARGIN_MM)
            if k.size:
                out[k] |= d[k] < skin_distance(model, theta, points[k])
        return out

    return theirs


def _palm(model: HandModel, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mean of the posed model's Gaussian centres (3,) mm."""
    return posed_centres(model, theta).mean(axis=0)


class MultiHandTracker:
    """Tracks up to ``max_hands`` hands (see the module docstring).

    Parameters
    ----------
    config : TrackerConfig, optional
        Shared by the hands (``right_hand`` is set per hand).
    max_hands : int
        1 or 2 (a person's two hands; labels are left and right).
    handedness : {"left", "right"} or None
        The label of a new track when both are free; None: from the data.
    """

    def __init__(self, config: TrackerConfig | None = None, max_hands: int = 2, handedness: str | None = None) -> None:
        if max_hands not in (1, 2):
            raise InputError(f"max_hands must be 1 or 2, got {max_hands}")
        if handedness is not None and handedness not in HANDS:
            raise InputError(f"handedness must be 'left', 'right' or None, got {handedness!r}")
        self._config = config or TrackerConfig()
        self.max_hands = max_hands
        self.handedness = handedness
        self._models: dict[str, HandModel | None] = {s: None for s in HANDS}
        self._slots: list[_Slot] = []
        self._next_id = 0
        self._frame = 0
        self._searched = -SEARCH_EVERY  # frame of the last search for a new hand
        self._every = SEARCH_EVERY  # frames between two searches (SEARCH_EVERY_MAX)
        self._doomed = False  # this frame's search ended at finalists the gate would drop (_checked_start)

    @property
    def config(self) -> TrackerConfig:
        """The shared configuration."""
        return self._config

    @property
    def tracks(self) -> tuple[tuple[str, int], ...]:
        """(label, track id) of the live tracks, oldest first."""
        return tuple((s.side, s.track_id) for s in self._slots)

    def set_model(self, side: str, model: HandModel) -> None:
        """Use ``model`` (e.g. a calibration; mirrored to ``side``) for the hand labelled ``side``
        from now on: its live track switches to it (:meth:`Tracker.set_model`, the palm centre
        kept), every new track of that label starts with it (no small-size choice), and a track
        whose trial gives it that label takes it from the frame after (the trial's two models
        share one shape)."""
        if side not in HANDS:
            raise InputError(f"side must be 'left' or 'right', got {side!r}")
        model = model.mirrored(side == "right")
        self._models[side] = model
        for s in self._slots:
            if s.side == side and s.alt is None:
                s.tracker.set_model(model)

    def model(self, side: str) -> HandModel:
        """The model of the hand labelled ``side``: its live track's (a trial's not counted),
        else the one :meth:`set_model` gave, else the default of that side."""
        track = next((s for s in self._slots if s.side == side and s.alt is None), None)
        if track is not None:
            return track.tracker.model
        given = self._models[side]
        return given if given is not None else default_hand_model(side == "right")

    def hands_in_view(self) -> tuple[tuple[int, HandModel, NDArray[np.float64]], ...]:
        """(track id, model, pose (26,) mm / rad) of every live track with a pose after the last
        frame, trials and withheld tracks included (what the calibration of one hand masks out of
        its frames: :class:`~.autocalibration.HistoryFrame`)."""
        out = []
        for s in self._slots:
            x = self._pose(s)
            if x is not None:
                out.append((s.track_id, s.tracker.model, x))
        return tuple(out)

    def reset(self) -> None:
        """Forget every track."""
        self._slots = []
        self._searched = -SEARCH_EVERY
        self._every = SEARCH_EVERY

    def process(self, depth_mm: NDArray, intrinsics: Intrinsics) -> HandsResult:
        """Track the hands in one depth frame (``depth_mm`` (H, W) mm, as :meth:`Tracker.process`).

        Raises
        ------
        DepthImageError, IntrinsicsError
            When the frame cannot be used; the tracks are left untouched.
        """
        import time

        t0 = time.perf_counter()
        pre = preprocess(depth_mm, intrinsics, self._config)
        pre = without_support(pre)  # (a table under the hands, core/support.py)
        t1 = time.perf_counter()
        self._track(pre)
        t2 = time.perf_counter()
        if len(self._slots) < self.max_hands and (
            not self._slots or self._frame - self._searched >= self._every
        ):
            self._searched, n, self._doomed = self._frame, len(self._slots), False
            self._search(pre, (depth_mm, intrinsics))
            # (No new track: the next search waits twice as long; not after one the gate would drop.)
            if n and len(self._slots) == n and not self._doomed:
                self._every = min(2 * self._every, SEARCH_EVERY_MAX)
        self._decide()
        t3 = time.perf_counter()
        answers = self._gate(depth_mm, intrinsics)
        t4 = time.perf_counter()
        self._frame += 1
        hands = tuple(
            HandTrack(s.side, s.track_id, a, s.tracker.model)
            for s, a in answers
            if s.alt is None and a.status is TrackerStatus.TRACKING
        )
        withheld = {
            s.side: a.hand
            for s, a in answers
            if s.alt is None and a.status is not TrackerStatus.TRACKING and a.hand is not None
        }
        ms = {"preprocess": (t1 - t0) * 1e3, "track": (t2 - t1) * 1e3, "search": (t3 - t2) * 1e3}
        ms["check"] = (t4 - t3) * 1e3
        ms["total"] = (t4 - t0) * 1e3
        return HandsResult(hands, ms, withheld)

    # -- internals -----------------------------------------------------------
    def _pose(self, slot: _Slot) -> NDArray[np.float64] | None:
        """The slot's pose of this frame when fitted, else its last one (26,), or None."""
        if slot.result is not None and slot.result.pose is not None:
            return slot.result.pose
        return slot.tracker.last_pose

    def _track(self, pre: Preprocessed) -> None:
        """Fit every live track, nearest first, each on its share of the data; drop the lost
        ones and the younger of two on one hand."""
        for s in self._slots:
            s.result = None
            given = self._models[s.side]
            if s.alt is None and given is not None and s.tracker.model.shape != given.shape:
                # (its trial ran on the first model's shape: the label's own model from this frame on)
                s.tracker.set_model(given)
        order = sorted(self._slots, key=lambda s: float(s.tracker.last_pose[2]))  # type: ignore[index]
        for slot in order:
            others = [o for o in self._slots if o is not slot]
            for tracker in (slot.tracker, slot.alt):
                if tracker is not None:
                    tracker.data_filter = self._filter(tracker, others) if others else None
                    tracker.covered_tips = self._covered(pre, others, tracker.model) if others else None
                    tracker.held = self._held(pre, tracker, others) if others and HOLD_HIDDEN else None
                    tracker.interhand = self._interhand(others) if others and W_INTERHAND > 0 else None
            slot.result = slot.tracker.process_preprocessed(pre)
            if slot.alt is not None:
                slot.alt_result = slot.alt.process_preprocessed(pre)
                self._judge(slot)
        self._slots = [s for s in self._slots if s.result is not None and s.result.status is TrackerStatus.TRACKING]
        kept: list[_Slot] = []
        for s in self._slots:  # (oldest first)
            if not any(self._same_hand(s, k) for k in kept):
                kept.append(s)
        self._slots = kept

    def _gate(self, depth_mm: NDArray, intrinsics: Intrinsics) -> list[tuple[_Slot, TrackResult]]:
        """(slot, its result after its hand gate) of every live track with a pose (trials too:
        the gate's state is the track's), as :meth:`Tracker.process` gates its frame, on the
        data that no other hand explains (:func:`_theirs`, the split of the data; their pixels
        count neither way in the check).  Only a track that was a hand on its last frame
        explains data so: two tracks on one forearm or head must not vouch for each other.
        The tracks the gate resets are dropped, and the next frame searches for a new hand."""
        vouched = [s.present for s in self._slots]  # (the last frame's: in no order of the slots)
        out = []
        for s in self._slots:
            if s.result is None or s.result.pose is None:
                continue
            poses = [(o.tracker.model, self._pose(o)) for o, ok in zip(self._slots, vouched) if o is not s and ok]
            poses = [(m, x) for m, x in poses if x is not None]
            theirs = _theirs(s.tracker.model, s.result.pose, poses) if poses else None
            answer = s.gate.gate(s, depth_mm, intrinsics, s.tracker.model, s.result, theirs=theirs)
            s.present = answer.hand is not None and answer.hand.present
            if s.present and not s.reported:
                s.reported, self._every = True, SEARCH_EVERY  # (a new hand: the search found one)
            out.append((s, answer))
        if any(s.dropped for s in self._slots):
            if any(s.dropped and ok for s, ok in zip(self._slots, vouched)):
                self._searched = self._frame + 1 - self._every  # (a hand lost: look for it at once)
            self._slots = [s for s in self._slots if not s.dropped]
        return out

    def _judge(self, slot: _Slot) -> None:
        """One frame of ``slot``'s trial: its confidence lead summed, its leader the track's
        tracker; a model that lost the hand is out of the trial (the other decides it)."""
        main, alt = slot.result, slot.alt_result
        assert main is not None and alt is not None
        ok_main, ok_alt = main.status is TrackerStatus.TRACKING, alt.status is TrackerStatus.TRACKING
        if ok_main and ok_alt:
            slot.lead += main.confidence - alt.confidence
        if (ok_alt and not ok_main) or (ok_main and ok_alt and slot.lead < 0.0):
            slot.swap()
        slot.age += 1
        if not (ok_main and ok_alt):
            slot.alt = slot.alt_result = None

    def _decide(self) -> None:
        """End the trials that are decided.  A trial beside a decided track takes the free
        label; two trials are decided together (the labels differ: the pair's summed preference
        for right on the first, left on the second, or the other way); a trial is decided when
        its lead exceeds :data:`TRIAL_LEAD` (the pair's :data:`PAIR_LEAD`) or after
        :data:`TRIAL_FRAMES`."""
        trials = [s for s in self._slots if s.alt is not None]
        if not trials:
            return
        decided = [s for s in self._slots if s.alt is None]
        if decided:
            taken = {s.side for s in decided}
            for t in trials:
                if t.side in taken:
                    t.swap()
                t.alt = t.alt_result = None
            return
        if len(trials) == 1:
            t = trials[0]
            if abs(t.lead) > TRIAL_LEAD or t.age >= TRIAL_FRAMES:
                t.alt = t.alt_result = None
            return
        a, b = trials
        pref = (a.lead if a.side == "right" else -a.lead) - (b.lead if b.side == "right" else -b.lead)
        if abs(pref) > PAIR_LEAD or min(a.age, b.age) >= TRIAL_FRAMES:
            if (a.side == "right") != (pref >= 0.0):
                a.swap()
            if (b.side == "right") == (pref >= 0.0):
                b.swap()
            a.alt = a.alt_result = b.alt = b.alt_result = None

    def _same_hand(self, a: _Slot, b: _Slot) -> bool:
        """Whether ``a`` and ``b`` track one hand: their palms are closer than
        :data:`SAME_HAND_MM` and their models share a volume (:func:`shared_volume`)."""
        pa, pb = self._pose(a), self._pose(b)
        if pa is None or pb is None:
            return False
        ma, mb = a.tracker.model, b.tracker.model
        if np.linalg.norm(_palm(ma, pa) - _palm(mb, pb)) >= SAME_HAND_MM:
            return False
        return shared_volume((ma, pa), (mb, pb)) > SHARED_VOLUME

    def _filter(self, tracker: Tracker, others: Sequence[_Slot]):
        """The :attr:`Tracker.data_filter` of ``tracker``: drop data and detections that one of
        ``others`` explains (see the module docstring)."""
        poses = [(o.tracker.model, self._pose(o)) for o in others]
        poses = [(m, x) for m, x in poses if x is not None]
        model = tracker.model

        def filt(data: ImageSoG, det: Detections, theta: NDArray[np.float64]) -> tuple[ImageSoG, Detections]:
            theirs = _theirs(model, theta, poses)
            if data.n:
                drop = theirs(data.points)
                if drop.any() and KEEP_OCCLUDERS:  # (pointwise: asked of the dropped points only)
                    drop[drop] = ~in_front(model, theta, data.points[drop])
                if drop.any():
                    data = data.subset(~drop)
            if det.n:
                drop = theirs(det.points)
                if drop.any():
                    det = det.subset(~drop)
            return data, det

        return filt

    def _hidden(self, pre: Preprocessed, others: Sequence[_Slot]):
        """``hidden(points, radii)``: :func:`hidden_by` the hands of ``others`` in ``pre``."""
        poses = [(o.tracker.model, self._pose(o)) for o in others]
        hands = [(m, x) for m, x in poses if x is not None]

        def hidden(points: NDArray[np.float64], radii: NDArray[np.float64]) -> NDArray[np.bool_]:
            return hidden_by(pre, hands, points, radii)

        return hidden

    def _covered(self, pre: Preprocessed, others: Sequence[_Slot], model: HandModel):
        """The :attr:`Tracker.covered_tips` of a hand (``model``) beside ``others``: its
        fingertips (5, 3) mm within :data:`COVERED_MM` of another hand's skin or forearm, or
        hidden by another hand (:meth:`_hidden`), (5,) bool."""
        poses = [(o.tracker.model, self._pose(o)) for o in others]
        poses = [(m, x) for m, x in poses if x is not None]
        hidden = self._hidden(pre, others)
        radii = model.g_sigmas[model.tip_index]

        def covered(tips: NDArray[np.float64]) -> NDArray[np.bool_]:
            out = np.zeros(tips.shape[0], dtype=bool)
            for m, x in poses:
                out |= skin_distance(m, x, tips, COVERED_MM) < COVERED_MM
            if HOLD_HIDDEN:
                out |= hidden(tips, radii)
            return out

        return covered

    def _held(self, pre: Preprocessed, tracker: Tracker, others: Sequence[_Slot]):
        """The :attr:`Tracker.held` of ``tracker`` beside ``others``: the four joints of each
        finger whose fingertip another hand hides (:meth:`_hidden`) at the fit's start pose,
        (26,) bool."""
        hidden = self._hidden(pre, others)
        model = tracker.model
        radii = model.g_sigmas[model.tip_index]

        def held(theta: NDArray[np.float64]) -> NDArray[np.bool_]:
            tips = posed_centres(model, theta)[model.tip_index]
            out = np.zeros(theta.shape[0], dtype=bool)
            for c in np.flatnonzero(hidden(tips, radii)):
                out[chain_slice(int(c))] = True
            return out

        return held

    def _interhand(self, others: Sequence[_Slot]):
        """The :attr:`Tracker.interhand` of a hand beside ``others``: their spheres (posed this
        frame, or at their last pose) near this hand's at the fit's start."""
        poses = [(o.tracker.model, self._pose(o)) for o in others]
        spheres = [(posed_centres(m, x), m.g_sigmas) for m, x in poses if x is not None]
        if not spheres:
            return None
        centres = np.concatenate([c for c, _ in spheres])
        radii = np.concatenate([r for _, r in spheres])

        def interhand(own: NDArray[np.float64], own_radii: NDArray[np.float64]) -> InterHand | None:
            return InterHand.near(centres, radii, own, own_radii, W_INTERHAND, INTERHAND_REACH_MM)

        return interhand

    def _masked(self, pre: Preprocessed, doomed: Sequence[tuple[HandModel, NDArray[np.float64]]] = ()) -> Preprocessed:
        """``pre`` without the pixels of the live tracks' hands and forearms and of ``doomed``
        ((model, pose (26,)) each: new tracks the gate would drop, :meth:`_checked_start`), a new copy
        (:func:`without_hands`)."""
        hands = [(s.tracker.model, self._pose(s)) for s in self._slots] + list(doomed)
        hands = [(m, x) for m, x in hands if x is not None]
        depth = without_hands(pre.depth_mm, pre.intrinsics, hands, self._config.roi_radius_mm)
        if depth is pre.depth_mm:
            depth = depth.copy()
        return Preprocessed(depth_mm=depth, intrinsics=pre.intrinsics, decimation=pre.decimation)

    def _new_tracker(self, side: str) -> Tracker:
        cfg = replace(self._config, right_hand=side == "right")
        return Tracker(cfg, self._models[side])

    def _checked_start(
        self, image: tuple[NDArray, Intrinsics], doomed: list[tuple[HandModel, NDArray[np.float64]]]
    ) -> Callable[[Preprocessed, HandModel, TrackerConfig, Bounds], Finalists | None]:
        """A new track's :attr:`Tracker.start_search` in the frame ``image`` (depth (H, W) mm,
        intrinsics) that finds no hand when the hand gate would reset the track on its first
        frame whichever finalist won: at every finalist, the data around the model that it
        explains (``explained``, as :meth:`_gate` checks: beside the hands that were one on
        their last frame) lie below :data:`~.handcheck.EXPLAINED_LOW` (the check's confidence
        0).  Decided before the finalists' full fits: those articulate a model where it lies,
        and do not reach the data near it that it leaves out (doc/design/two_hands.md)."""
        poses = [(o.tracker.model, self._pose(o)) for o in self._slots if o.present]
        poses = [(m, x) for m, x in poses if x is not None]

        def start(pre: Preprocessed, model: HandModel, config: TrackerConfig, bounds: Bounds) -> Finalists | None:
            found = start_search(pre, model, config, bounds)
            for x in [] if found is None else found.poses:
                centres = gaussian_centres(model, x)
                posed = TrackResult(
                    TrackerStatus.TRACKING, x, centres[model.tip_index], keypoint_skeleton(model, x), 0.0, 0.0, 0,
                    gaussians_mm=centres,
                )
                evidence = check_hand(*image, model, posed, _theirs(model, x, poses) if poses else None).evidence
                if evidence is None or evidence.explained >= EXPLAINED_LOW:
                    return found
            if found is not None:  # (the best finalist: where the track the gate drops would be)
                self._doomed = True
                doomed.append((model, found.poses[0]))
            return None

        return start

    def _search(self, pre: Preprocessed, image: tuple[NDArray, Intrinsics]) -> None:
        """Start tracks on the hands that no live track holds, until ``max_hands`` (the hand
        gate's check of the new track's finalists first, :meth:`_checked_start`: a track it would
        drop takes its id and its pixels are masked for the next search, as after the gate)."""
        doomed: list[tuple[HandModel, NDArray[np.float64]]] = []
        while len(self._slots) + len(doomed) < self.max_hands:
            masked = self._masked(pre, doomed) if self._slots or doomed else pre
            free = [s for s in HANDS if s not in {t.side for t in self._slots if t.alt is None}]
            if len(free) == 1 or self.handedness is not None:
                sides = free if len(free) == 1 else [self.handedness]
            else:
                sides = ["right", "left"]  # (a trial: see _judge)
            tracker = self._new_tracker(sides[0])
            if CHECK_FINALISTS:
                tracker.start_search = self._checked_start(image, doomed)
            k = len(doomed)
            res = tracker.process_preprocessed(masked)
            if len(doomed) > k:
                self._next_id += 1
                continue
            if res.status is not TrackerStatus.TRACKING or res.pose is None:
                return
            slot = _Slot(tracker, sides[0], self._next_id, res)
            if len(sides) == 2:
                # The trial's other model starts from the mirror image of the found hand: the
                # same pose turned half a turn about the hand's long axis (ry + pi: palm toward
                # <-> back toward), on the same shape (the size the start chose would decide it
                # otherwise), fitted as a tracked frame (no second search).
                alt = self._new_tracker(sides[1])
                alt.set_model(tracker.model)
                flipped = res.pose.copy()
                flipped[4] += np.pi
                alt.start_at(flipped)
                slot.alt, slot.alt_result = alt, alt.process_preprocessed(masked)
                slot.age = 1
                if slot.alt_result.status is not TrackerStatus.TRACKING:
                    slot.alt = slot.alt_result = None
                elif res.confidence < slot.alt_result.confidence:
                    slot.swap()
            if any(self._same_hand(slot, s) for s in self._slots):
                return
            self._next_id += 1
            self._slots.append(slot)
