"""Frame-to-frame hand tracker: depth in, 26-DOF pose and fingertips out.

Units: depth images and every position in millimetres, camera optical frame (x right, y down,
z forward); angles in radians.

Per frame (paper 000, sec. 5), after a supporting plane much larger than a hand (a table under
the hand, a wall behind it: :mod:`.support`) is dropped from the frame, the depth near the
hand's extrapolated pose is clustered into
Gaussians, the pose is fitted from there by the adaptive gradient ascent, and the search
(:mod:`hand_sog_tracker.core.search`) fits the candidates its proposals make from that fit
(fingers shifted, swapped, curled, pulled onto unexplained detections) as one batch; one
score picks the frame's pose.  Without a track (the first frame, after a loss) the same
search starts from the hand found in the depth (:mod:`.search.start`) with more candidates.
A frame with a curled finger answers with its pose refined on a model with joint Gaussians
(``REFINE_CURL_RAD``); the track goes on from the pose.  Every frame ends with the hand
decision (:mod:`.handcheck`, issue 46): a frame that is no hand is answered without a pose and
may reset the track, and a tracked frame the check doubts competes with a fresh start (the new
track's search on the same frame).  Nothing depends on the wall clock: the same frames give
the same answers.
"""

from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core import handcheck
from hand_sog_tracker.core.depth_sog import (
    MAX_DATA_GAUSSIANS,
    ImageSoG,
    Preprocessed,
    leaf_px,
    preprocess,
    quadtree_sog,
)
from hand_sog_tracker.core.hand_model import FINGER_MCP, FINGER_PIP, HandModel, HandShape, default_hand_model
from hand_sog_tracker.core.handcheck import HAND_THRESHOLD, HandGate
from hand_sog_tracker.core.initialise import INIT_SEARCH
from hand_sog_tracker.core.kinematics import (
    fingertips,
    gaussian_centres,
    global_rotation,
    keep_palm_centre,
    keypoint_skeleton,
    posed_centres,
    skeleton_points,
)
from hand_sog_tracker.core.objective import Objective, TipTargets, contact_shares
from hand_sog_tracker.core.objective.interhand import InterHand
from hand_sog_tracker.core.optimizer import OptimizeResult, StepSizes, maximise
from hand_sog_tracker.core.region import SURFACE_SEARCH_MM, WINDOW_BEHIND_MM, before_surface, coverage, hand_roi
from hand_sog_tracker.core.salient import MAX_DETECTIONS, Detections, assigned_targets, detect_fingertips
from hand_sog_tracker.core.search import (
    ASSIGN_LAMBDA_MM,
    NEW_TRACK_PROPOSALS,
    TRACK_PROPOSALS,
    Frame,
    plain,
    search,
)
from hand_sog_tracker.core.search.candidates import pull_target
from hand_sog_tracker.core.search.fit import fit_batch, with_targets
from hand_sog_tracker.core.search.start import NEW_TRACK_DATA, Finalists, on_hand_side, start_search
from hand_sog_tracker.core.silhouette import Silhouette, silhouette
from hand_sog_tracker.core.support import without_support
from hand_sog_tracker.core.types import HandDecision, Intrinsics, TrackerConfig, TrackerStatus, TrackResult

__all__ = ["ALPHA", "ASSIGN_LAMBDA_MM", "Tracker", "before_surface", "coverage", "hand_roi"]

# Module constants, not TrackerConfig fields (which become ROS parameters): none is meant to be
# tuned per camera or user.  The measurements behind them: doc/design/search.md.
#: Velocity extrapolation of the start pose (paper 000 sec. 5.3: alpha = 0.5).
ALPHA = 0.5
#: A tracked frame starts from the last frame's final step lengths x ``WARM_GROW``, within
#: ``[WARM_MIN, 1]`` x the initial ones (settled parameters start small; chosen here).
WARM_GROW = 2.0
WARM_MIN = 0.1
#: A fit still climbing after ``iterations`` gets up to this many more while the last raised the
#: objective by ``EXTRA_GAIN`` x |E(start)| (fast rotations outran 7 iterations; chosen here).
EXTRA_ITERATIONS = 3
EXTRA_GAIN = 0.002
#: Whether detections of fingers seen end-on pull fingertips (off: they only seed candidates).
SALIENT_END_ON = False
#: A PIP flexed over this (rad) has the answer refined on the joint-Gaussian model (issue 11:
#: the tracking model opens curled fingers into claws; refining only the answer keeps the
#: track's choices).
REFINE_CURL_RAD = math.radians(60.0)
#: After a refined frame the refinement starts from the track's pose plus that frame's
#: correction, its steps x this (issue 14: the correction changes little frame to frame).
REFINE_WARM_STEPS = 0.5
#: The refinement weights the overlaps by visibility at the pose (a fist's hidden palm and tips).
REFINE_VISIBILITY = True
#: On the default model a new track's finalists are also fitted on the model scaled to this
#: length, which wins by ``SMALL_HAND_GAIN`` of the score with open fingers (mean MCP + PIP
#: under ``SMALL_HAND_MAX_FLEX`` rad: curled fingers do not show their length), tried on the
#: best ``SMALL_HAND_FINALISTS`` (issue 11: a small hand started with its fingers one over).
SMALL_HAND_LENGTH = 0.85
SMALL_HAND_GAIN = 0.04
SMALL_HAND_MAX_FLEX = 0.6
SMALL_HAND_FINALISTS = 2
#: A tracked frame whose hand check is below this competes with a fresh start from the hand
#: found in the frame, which wins when its check is ``FRESH_MARGIN`` higher (issue 46; the
#: gate's threshold: a frame it would not report; the margin chosen on scenes_dev).
FRESH_BELOW = HAND_THRESHOLD
FRESH_MARGIN = 0.1
#: ... and its palm lies this far (mm) from the track's: about half a palm's width (chosen here).
FRESH_APART_MM = 40.0
_PALM_ROWS = (0, 5, 9, 13, 17)  #: wrist and finger MCPs among the skeleton's 21 points
_INITIAL_STEPS = StepSizes().expand(StepSizes().initial)
#: ``(data, detections, theta (26,)) -> (data, detections)``: see :attr:`Tracker.data_filter`.
DataFilter = Callable[[ImageSoG, Detections, NDArray[np.float64]], tuple[ImageSoG, Detections]]


class _Keep:
    """What the hand gate resets when the tracker keeps its track (``withhold=False``)."""

    def reset(self) -> None:
        pass


_KEEP = _Keep()
_NO_POINTS = np.zeros((0, 3))


def _apart(track: TrackResult, track_model: HandModel, fresh: TrackResult, fresh_model: HandModel) -> bool:
    """Whether the palms (the skeleton's wrist and finger MCPs, mean) of two results, each
    with its model, lie ``FRESH_APART_MM`` apart (a track without a pose: always): the fresh
    start found a hand elsewhere."""
    if track.pose is None or fresh.pose is None:
        return True
    palm = list(_PALM_ROWS)
    a = skeleton_points(track_model, track.pose)[palm].mean(0)
    b = skeleton_points(fresh_model, fresh.pose)[palm].mean(0)
    return float(np.linalg.norm(a - b)) > FRESH_APART_MM


def _open(theta: NDArray[np.float64]) -> bool:
    """Whether the fingers at ``theta`` are open enough to tell a hand's size."""
    return float(np.mean(theta[FINGER_MCP] + theta[FINGER_PIP])) < SMALL_HAND_MAX_FLEX


def _size_models(right: bool) -> tuple[HandModel, HandModel]:
    """The default model of this handedness and the same scaled to ``SMALL_HAND_LENGTH``."""
    default = default_hand_model(right)
    return default, default.scaled(HandShape(length=SMALL_HAND_LENGTH))


class Tracker:
    """Tracks one hand through a depth sequence.

    Parameters
    ----------
    config : TrackerConfig, optional
    model : HandModel, optional
        Hand model (mm), kept as given; default: the default adult hand of
        ``config.right_hand``, on which every new track may start the smaller hand of
        ``SMALL_HAND_LENGTH`` instead (until :meth:`set_model`).
    withhold : bool
        Every frame's result carries its hand decision (:class:`~.handcheck.HandGate`, issue
        46); by default a frame that is no hand has no pose and resets the track as the gate
        says (what the node publishes), and a doubted track competes with a fresh start
        (:meth:`_fresh_start`).  False keeps every fitted pose and track, without fresh starts
        (the raw fit's evidence, for the tools).
    """

    def __init__(
        self, config: TrackerConfig | None = None, model: HandModel | None = None, withhold: bool = True
    ) -> None:
        self._config = config or TrackerConfig()
        self._gate = HandGate()
        self._withhold = bool(withhold)
        #: The last frame's result before its hand decision withheld the pose (for the tools).
        self.last_fit: TrackResult | None = None
        #: This tracked frame's search :class:`Frame` and its pose (26,), for the fresh start.
        self._track_frame: tuple[Frame, NDArray[np.float64]] | None = None
        # (the default model, the small one) while the model is the default (SMALL_HAND_LENGTH).
        self._sizes: tuple[HandModel, HandModel] | None = None
        if model is None:
            self._sizes = _size_models(self._config.right_hand)
            self._model = self._sizes[0]
        else:
            self._model = model.mirrored(self._config.right_hand)
        self._prev: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._steps: NDArray[np.float64] | None = None  # last frame's final step lengths (26,)
        self._low_frames = 0
        self._status = TrackerStatus.NO_HAND
        #: (model, low, high): the joint limits as bounds (26,) each, read-only.
        self._bounds: tuple[HandModel, NDArray[np.float64], NDArray[np.float64]] | None = None
        #: (tracking model, its :meth:`HandModel.with_joint_gaussians`) of :meth:`_refined`.
        self._joint_model: tuple[HandModel, HandModel] | None = None
        #: (track pose, answer) (26,) each of the frame before, when it was refined.
        self._refine_last: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        #: The proposal the last frame's pose came from (None: its fit), for the tools.
        self.last_proposal: str | None = None
        #: The detection (1, 3) mm whose pulls lost on the last frame, or none (0, 3).
        self._lost_pulls = _NO_POINTS
        #: ``(data, detections, theta) -> (data, detections)``: what of the data near the hand
        #: at ``theta`` (26,) is this hand's (the multi-hand tracker drops what another hand's
        #: model explains, :mod:`.hands`); None: all of it.
        self.data_filter: DataFilter | None = None
        #: ``tips (5, 3) mm -> (5,) bool``: the fingertips against another hand (the search's
        #: :attr:`Frame.covered`, set by the multi-hand tracker); None: none.
        self.covered_tips: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None
        #: ``theta (26,) -> (26,) bool``: the parameters a tracked frame's fit holds at its start
        #: pose ``theta`` (the joints of fingers another hand hides: no data speak for them; set by
        #: the multi-hand tracker); None: none.
        self.held: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None
        #: ``(centres (m, 3) mm, radii (m,) mm) -> InterHand or None``: the other hands' spheres
        #: that this hand's, posed at a tracked frame's start, may not penetrate in its fit
        #: (:mod:`.objective.interhand`; set by the multi-hand tracker); None: none.
        self.interhand: Callable[[NDArray[np.float64], NDArray[np.float64]], InterHand | None] | None = None

    @property
    def config(self) -> TrackerConfig:
        """The tracker's configuration."""
        return self._config

    @property
    def model(self) -> HandModel:
        """The hand model in use (handedness applied)."""
        return self._model

    @property
    def status(self) -> TrackerStatus:
        """Status after the last processed frame."""
        return self._status

    @property
    def last_pose(self) -> NDArray[np.float64] | None:
        """Pose (26,) of the last tracked frame, or None."""
        return None if self._prev is None else self._prev[0].copy()

    def set_model(self, model: HandModel) -> None:
        """Use another hand model (e.g. after calibration); keeps the track.

        The track's poses are moved so that the palm centre stays where it was tracked
        (:func:`~hand_sog_tracker.core.kinematics.keep_palm_centre`): a rescaled model at the
        same wrist position would have its palm, and its fingers, off the hand.
        """
        new = model.mirrored(self._config.right_hand)
        if self._prev is not None:
            old = self._model
            self._prev = (keep_palm_centre(self._prev[0], old, new), keep_palm_centre(self._prev[1], old, new))
        self._model = new
        self._sizes = None

    def set_config(self, config: TrackerConfig) -> None:
        """Change the configuration; a handedness change also resets the track."""
        if config.right_hand != self._config.right_hand:
            self._model = self._model.mirrored(config.right_hand)
            if self._sizes is not None:
                self._sizes = _size_models(config.right_hand)
            self.reset()
        self._config = config

    def start_at(self, pose: NDArray[np.float64]) -> None:
        """Go on as if the last frame had been tracked at ``pose`` (26,), at rest: the next
        frame is a tracked frame from there (the multi-hand tracker starts the other label's
        model of a new hand so, :mod:`.hands`)."""
        self._prev = (np.array(pose, dtype=np.float64), np.array(pose, dtype=np.float64))
        self._steps = None
        self._low_frames = 0
        self._lost_pulls = _NO_POINTS
        self._status = TrackerStatus.TRACKING

    def reset(self) -> None:
        """Forget the track: the next frame initialises from scratch."""
        self._prev = None
        self._low_frames = 0
        self._status = TrackerStatus.NO_HAND
        self._lost_pulls = _NO_POINTS
        self._gate.forget()

    def process(self, depth_mm: NDArray, intrinsics: Intrinsics) -> TrackResult:
        """Track the hand in one depth frame.

        Parameters
        ----------
        depth_mm : array, shape (H, W)
            Depth in millimetres; 0, NaN and Inf are invalid.
        intrinsics : Intrinsics
            Intrinsics of this image (same H, W).

        Raises
        ------
        DepthImageError, IntrinsicsError
            When the frame cannot be used; the track is left untouched.
        """
        t0 = time.perf_counter()  # (timings only: nothing below depends on the clock)
        pre = preprocess(depth_mm, intrinsics, self._config)  # raises before any change of state
        pre = without_support(pre)  # (a table under the hand; the hand check reads the frame as it is)
        t1 = time.perf_counter()
        checked = None
        if self._prev is not None:
            result = self._track(pre)
            if self._withhold:
                checked = handcheck.check_hand(depth_mm, intrinsics, self._model, result)
                # (A lost track's check is 0.  The fresh start's data are capped at
                # ``NEW_TRACK_DATA`` whatever the track's: a frame costs at most a tracked frame
                # at the data cap and one new track, issue 50.)
                if checked.confidence < FRESH_BELOW:
                    result, checked = self._fresh_start(pre, depth_mm, intrinsics, result, checked)
            self._track_frame = None  # (the frame's data are not kept)
        else:
            result = self._new_track(pre)
        t2 = time.perf_counter()
        self.last_fit = result
        # The hand decision (may reset the track: the next frame searches afresh).
        keeper = self if self._withhold else _KEEP
        result = self._gate.gate(keeper, depth_mm, intrinsics, self._model, result, self._withhold, checked)
        t3 = time.perf_counter()
        result.timings_ms["preprocess"] = (t1 - t0) * 1e3
        result.timings_ms.setdefault("quadtree", 0.0)
        result.timings_ms["optimise"] = (t2 - t1) * 1e3 - result.timings_ms["quadtree"]
        result.timings_ms["check"] = (t3 - t2) * 1e3
        result.timings_ms["total"] = (t3 - t0) * 1e3
        return result

    def process_preprocessed(self, pre: Preprocessed) -> TrackResult:
        """:meth:`process` of a frame already preprocessed with this tracker's configuration,
        without the hand check and gate (several hands share one preprocessing and the
        multi-hand tracker decides for its hands, :mod:`.hands`: a gate's reset would search
        the whole image, the other hand's data too); ``timings_ms["preprocess"]`` 0."""
        t1 = time.perf_counter()
        result = self._track(pre) if self._prev is not None else self._new_track(pre)
        self._track_frame = None
        t2 = time.perf_counter()
        self.last_fit = result
        result.timings_ms["preprocess"] = 0.0
        result.timings_ms.setdefault("quadtree", 0.0)
        result.timings_ms["optimise"] = (t2 - t1) * 1e3 - result.timings_ms["quadtree"]
        result.timings_ms["total"] = (t2 - t1) * 1e3
        return result

    # -- internals -----------------------------------------------------------
    def _new_track(self, pre: Preprocessed) -> TrackResult:
        """A new track's search on ``pre`` (see :meth:`_initialise`), from fresh step lengths
        and, on the default model, with its size chosen again."""
        self._steps = None
        self._lost_pulls = _NO_POINTS
        if self._sizes is not None:
            self._model = self._sizes[0]
        return self._initialise(pre)

    def _fresh_start(
        self, pre: Preprocessed, depth_mm: NDArray, intrinsics: Intrinsics, track: TrackResult, checked: HandDecision
    ) -> tuple[TrackResult, HandDecision]:
        """A tracked frame the hand check doubts (``checked`` below ``FRESH_BELOW``; a track
        lost on this frame too) against a fresh start from the hand found in the same frame:
        the new track's search on ``pre`` replaces the track when its check's confidence is
        ``FRESH_MARGIN`` higher and its palm lies elsewhere (:func:`_apart`: a wrong lock
        replaced at once, not after the gate's reset and the next frame's search) or, on the
        same hand, when its pose also scores higher on the track's frame (the check does not
        judge the articulation: a doubted curled hand was replaced by a worse fresh start);
        else the track and its state are kept.  Returns (result, its check)."""
        kept = (
            self._prev, self._steps, self._low_frames, self._status, self._model, self._refine_last,
            self.last_proposal, self._lost_pulls,
        )
        on_track = self._track_frame if track.pose is not None else None
        fresh = self._new_track(pre)
        if fresh.pose is not None:
            fresh_check = handcheck.check_hand(depth_mm, intrinsics, self._model, fresh)
            better = fresh_check.confidence >= checked.confidence + FRESH_MARGIN
            if better and on_track is not None and not _apart(track, kept[4], fresh, self._model):
                # (the same hand: the track's own score judges the articulation)
                frame, x = on_track
                better = frame.score(fresh.pose) > frame.score(x)
            if better:
                self._gate.forget()  # (a new track: reported once a finger is seen to end)
                self.last_proposal = "fresh_start"
                fresh.timings_ms["quadtree"] = fresh.timings_ms.get("quadtree", 0.0) + track.timings_ms["quadtree"]
                return fresh, fresh_check
        (
            self._prev, self._steps, self._low_frames, self._status, self._model, self._refine_last,
            self.last_proposal, self._lost_pulls,
        ) = kept
        return track, checked

    def _data_near(
        self,
        pre: Preprocessed,
        theta: NDArray[np.float64],
        detect: bool = False,
        outline: bool = True,
        end_mm: float | None = None,
        roi_window: tuple[tuple[int, int, int, int], tuple[float, float]] | None = None,
        max_gaussians: int = MAX_DATA_GAUSSIANS,
    ) -> tuple[ImageSoG, Detections, Silhouette | None]:
        """Data Gaussians around the hand at ``theta``, without the forearm.

        Quads and (with ``detect``) fingertip detections beyond the wrist plane at ``theta``
        are dropped (the model has no forearm); with ``outline`` also the silhouette of the
        depth window (None without it or when ``w_sil`` is 0).  ``end_mm``: the window ends
        there at the latest (a wall behind the hand is no data).  ``roi_window``:
        :func:`hand_roi` at ``theta`` when already computed.  ``max_gaussians``: the quadtree's
        cap (a new track's is ``NEW_TRACK_DATA``).
        """
        if roi_window is None:
            roi_window = hand_roi(self._model, theta, pre.intrinsics, self._config.roi_radius_mm)
        roi, window = roi_window
        # (The leaves follow the window's centre, the hand's depth, whatever ``end_mm``.)
        leaf = leaf_px(self._config.min_quad_px, 0.5 * (window[0] + window[1]), pre.intrinsics)
        if end_mm is not None:
            window = (window[0], min(window[1], end_mm))
        sil = silhouette(pre, window, roi) if outline and self._config.w_sil > 0 else None
        det = Detections.empty()
        axis = global_rotation(theta)[:, 1]  # the hand's long axis (camera frame)
        if detect:
            # (With a data filter the cap applies to what the filter leaves: another hand's
            # tips in the region would take this hand's places, and the filter drops them.)
            det = detect_fingertips(pre, roi, window, None if self.data_filter is not None else MAX_DETECTIONS)
            if det.n:
                det = det.subset((det.points - theta[:3]) @ axis > 0.0)
        data = quadtree_sog(pre, self._config.quadtree_threshold_mm, roi, window, leaf, max_gaussians)
        if data.n:
            keep = (data.points - theta[:3]) @ axis > 0.0
            data = data if keep.all() else data.subset(keep)
        if self.data_filter is not None:
            data, det = self.data_filter(data, det, theta)
            if det.n > MAX_DETECTIONS:  # (most confident first: the detector's order)
                det = det.subset(np.arange(det.n) < MAX_DETECTIONS)
        return data, det, sil

    def _targets(self, theta: NDArray[np.float64], det: Detections) -> TipTargets | None:
        """Detections assigned to the fingertips at ``theta`` (seed 001, Table 1)."""
        if det.n == 0:
            return None
        return assigned_targets(fingertips(self._model, theta), det, ASSIGN_LAMBDA_MM, SALIENT_END_ON)

    def _track(self, pre: Preprocessed) -> TrackResult:
        cfg = self._config
        assert self._prev is not None
        p1, p2 = self._prev
        # The paper prints Theta_{t-1} + alpha Theta_{t-2}; we read it as a constant-velocity
        # extrapolation damped by alpha.
        x0 = p1 + ALPHA * (p1 - p2)
        tq = time.perf_counter()
        start_centres = posed_centres(self._model, x0)
        far = float(np.max(start_centres[:, 2]))
        roi_window = hand_roi(self._model, x0, pre.intrinsics, cfg.roi_radius_mm, start_centres)
        end = before_surface(
            pre.depth_mm, pre.intrinsics, roi_window[0], far + SURFACE_SEARCH_MM, far + WINDOW_BEHIND_MM
        )
        data, det, sil = self._data_near(pre, x0, detect=True, end_mm=end, roi_window=roi_window)
        timings = {"quadtree": (time.perf_counter() - tq) * 1e3}
        obj = Objective(
            self._model, data, cfg, previous=(p1, p2), targets=self._targets(x0, det), silhouette=sil,
            contact=contact_shares(p1),
        )
        if self.interhand is not None:
            obj.interhand = self.interhand(start_centres, self._model.g_sigmas)
        base = _INITIAL_STEPS
        start = base if self._steps is None else np.minimum(np.maximum(self._steps * WARM_GROW, base * WARM_MIN), base)
        held = None if self.held is None else self.held(x0)
        fit = self._maximise(
            obj, x0, iterations=cfg.iterations, initial_steps=start,
            extra_iterations=EXTRA_ITERATIONS, extra_gain=EXTRA_GAIN,
            active=None if held is None or not held.any() else ~held,
        )
        self._steps = fit.steps
        frame = Frame(
            self._model, fit, obj, plain(obj), data, det, self._limits(), lost_pulls=self._lost_pulls,
            covered=self.covered_tips,
        )
        res, self.last_proposal = search(frame, TRACK_PROPOSALS)
        self._track_frame = (frame, res.x)
        # A detection whose pulls lost is not pulled onto again while it stays where it is.
        target = pull_target(frame)
        lost = target is not None and self.last_proposal != "detection"
        self._lost_pulls = det.points[[target]] if lost else _NO_POINTS
        centres = gaussian_centres(self._model, res.x)
        conf = coverage(self._model, res.x, data, centres, obj.support(res.x))
        self._low_frames = self._low_frames + 1 if conf < cfg.lost_confidence else 0
        if self._low_frames >= cfg.lost_frames or data.n == 0:
            self._prev = None
            self._low_frames = 0
            self._status = TrackerStatus.LOST
            return self._result(None, conf, res.fun, data.n, timings)
        self._prev = (res.x, p1)
        self._status = TrackerStatus.TRACKING
        answer = self._refined(obj, res, p1)
        if res is not fit:
            self._refine_last = None  # (a candidate won: the next refinement starts from its pose)
        if answer is not res.x:
            centres = gaussian_centres(self._model, answer)
        return self._result(answer, conf, res.fun, data.n, timings, centres)

    def _refined(self, obj: Objective, res: OptimizeResult, p1: NDArray[np.float64]) -> NDArray[np.float64]:
        """The answer of a tracked frame whose pose is ``res`` on ``obj``: ``res.x`` (26,), or,
        with a PIP flexed over ``REFINE_CURL_RAD``, ``res.x`` refined ``refine_iterations`` on the
        same frame's objective of the joint model (warm steps as a tracked frame's; from
        ``res.x`` plus the frame before's correction when that frame was refined and the track
        went on from its pose ``p1``, ``REFINE_WARM_STEPS``; overlaps weighted by visibility)."""
        x = res.x
        iterations = self._config.refine_iterations
        last, self._refine_last = self._refine_last, None
        if iterations <= 0 or np.max(x[FINGER_PIP]) <= REFINE_CURL_RAD:
            return x
        joint = self._joint_model
        if joint is None or joint[0] is not self._model:
            joint = self._joint_model = (self._model, self._model.with_joint_gaussians())
        refine = Objective(
            joint[1], obj.data, obj.config, obj.previous, obj.targets, obj.silhouette, obj.contact,
            visible_from=x if REFINE_VISIBILITY else None,
        )
        refine.interhand = obj.interhand
        steps = np.minimum(np.maximum(res.steps * WARM_GROW, _INITIAL_STEPS * WARM_MIN), _INITIAL_STEPS)
        x0 = x
        if last is not None and last[0] is p1:  # (the frame before's refinement, from this frame's start)
            lo, hi = self._limits()
            x0 = np.minimum(np.maximum(x + (last[1] - last[0]), lo), hi)
            steps *= REFINE_WARM_STEPS
        fit = self._maximise(refine, x0, iterations=iterations, initial_steps=steps)
        self._refine_last = (x, fit.x)
        return fit.x

    def _maximise(self, obj: Objective, x0: NDArray[np.float64], **kwargs: object) -> OptimizeResult:
        """:func:`maximise` with the joint angles projected into the model's limits."""
        return maximise(obj, x0, bounds=self._limits(), **kwargs)  # type: ignore[arg-type]

    def _limits(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The model's joint limits as bounds (low, high), shape (26,) each, read-only
        (+-inf for the wrist; computed once per model)."""
        m = self._model
        cached = self._bounds
        if cached is None or cached[0] is not m:
            lo = np.concatenate([np.full(6, -np.inf), m.limits_low])
            hi = np.concatenate([np.full(6, np.inf), m.limits_high])
            lo.setflags(write=False)
            hi.setflags(write=False)
            cached = self._bounds = (m, lo, hi)
        return cached[1:]

    def _initialise(self, pre: Preprocessed) -> TrackResult:
        """A new track (first frame, after a loss): the start search's finalists
        (:func:`~hand_sog_tracker.core.search.start.start_search`) refined
        ``final_iterations`` with the full objective on one data extraction around the first
        (its window ending where the search's did); the best by the score, after the new
        track's candidates (:data:`NEW_TRACK_PROPOSALS`), starts the track.  On the default
        model the best ``SMALL_HAND_FINALISTS`` are also fitted on the small model, which the
        track starts on when it scores ``SMALL_HAND_GAIN`` higher with open fingers."""
        self.last_proposal = None
        found = start_search(pre, self._model, self._config, self._limits())
        if found is None:
            return self._no_hand({})
        tq = time.perf_counter()
        data, det, sil = self._data_near(
            pre, found.poses[0], detect=True, end_mm=found.end_mm, max_gaussians=NEW_TRACK_DATA
        )
        timings = {"quadtree": (time.perf_counter() - tq) * 1e3}
        if data.n == 0:
            return self._no_hand(timings)
        fits = self._finalist_fits(found, data, det, sil)
        best = fits[0][1] if fits else None
        if best is not None and self._sizes is not None and _open(best[1].fit.x):
            default = self._model
            self._model = self._sizes[1]
            tried = sorted(k for k, _ in fits[:SMALL_HAND_FINALISTS])  # (in the finalists' order)
            small_fits = self._finalist_fits(Finalists([found.poses[k] for k in tried]), data, det, sil)
            small = small_fits[0][1] if small_fits else None
            if small is not None and small[0] > best[0] + SMALL_HAND_GAIN and _open(small[1].fit.x):
                best = small
            else:
                self._model = default
        if best is None:
            return self._no_hand(timings)
        frame = best[1]
        res, self.last_proposal = search(frame, NEW_TRACK_PROPOSALS)
        conf = coverage(self._model, res.x, frame.data)
        if conf < self._config.lost_confidence:
            return self._no_hand(timings, conf, res.fun, frame.data.n)
        self._prev = (res.x, res.x)
        self._low_frames = 0
        self._status = TrackerStatus.TRACKING
        return self._result(res.x, conf, res.fun, frame.data.n, timings)

    def _no_hand(self, timings: dict[str, float], conf: float = 0.0, energy: float = 0.0, n: int = 0) -> TrackResult:
        self._status = TrackerStatus.NO_HAND
        return self._result(None, conf, energy, n, timings)

    def _finalist_fits(
        self, found: Finalists, data: ImageSoG, det: Detections, sil: Silhouette | None
    ) -> list[tuple[int, tuple[float, Frame]]]:
        """Each finalist of ``found`` refined ``final_iterations`` on the tracker's model with
        the full objective of its hand side of ``data``: (index, (score, its :class:`Frame`)),
        best first by score (the earlier on a tie); finalists without data left out."""
        # All finalists are fitted as one batch on one objective of ``data``, each on its hand
        # side (``parts``) with its own targets (what its own objective gives it, up to rounding).
        items = []
        for k, x in enumerate(found.poses):
            keep = on_hand_side(data.points, x)
            if keep.any():
                data_x = data if keep.all() else data.subset(keep)
                obj = Objective(self._model, data_x, self._config, targets=self._targets(x, det), silhouette=sil)
                items.append((k, keep, data_x, obj))
        fits = []
        if not items:
            return fits
        shared = Objective(self._model, data, self._config, silhouette=sil)
        parts = np.array([keep for _, keep, _, _ in items])
        part_rows = None if parts.all() else parts
        targets = [obj.targets for _, _, _, obj in items]
        starts = np.array([found.poses[k] for k, _, _, _ in items])
        results = fit_batch(
            with_targets(shared, targets, part_rows), starts, data.n,
            iterations=INIT_SEARCH.final_iterations, bounds=self._limits(), with_index=True,
        )
        # (The finalists' plain objectives: ``shared`` on their parts without targets, one batch.)
        values = shared.batch(np.array([fit.x for fit in results]), gradient=False, parts=part_rows)[0]
        for (k, _, data_x, obj), fit, value in zip(items, results, values.tolist()):
            frame = Frame(self._model, fit, obj, plain(obj), data_x, det, self._limits(), new_track=True)
            fits.append((k, (frame.score(fit.x, value), frame)))
        fits.sort(key=lambda f: f[0])
        fits.sort(key=lambda f: f[1][0], reverse=True)  # (stable: the earlier first on a tie)
        return fits

    def _result(
        self,
        theta: NDArray[np.float64] | None,
        conf: float,
        energy: float,
        n: int,
        timings: dict[str, float],
        centres: NDArray[np.float64] | None = None,
    ) -> TrackResult:
        if theta is None:
            return TrackResult(self._status, None, None, None, float(conf), float(energy), n, dict(timings))
        if centres is None:  # (forward kinematics once: the fingertips are the tip Gaussians' centres)
            centres = gaussian_centres(self._model, theta)
        return TrackResult(
            status=self._status,
            pose=theta.copy(),
            fingertips_mm=centres[self._model.tip_index],
            skeleton_mm=keypoint_skeleton(self._model, theta),
            confidence=float(conf),
            energy=float(energy),
            n_image_gaussians=n,
            timings_ms=dict(timings),
            gaussians_mm=centres,
            gaussian_radii_mm=self._model.g_sigmas.copy(),
        )
