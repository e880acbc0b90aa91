"""Frame-to-frame hand tracker: depth in, 26-DOF pose and fingertips out.

Units: mm (camera optical frame: x right, y down, z forward) and radians.  Per frame (paper 000,
sec. 5): the supporting plane dropped (:mod:`.support`), the depth near the extrapolated pose
clustered into Gaussians, the pose fitted by adaptive gradient ascent, then searched
(:mod:`.search`; without a track from the hand found in the depth, :mod:`.search.start`); a curled
finger's answer refined on joint Gaussians; the hand decision last (:mod:`.handcheck`, issue 46).
Nothing depends on the wall clock: the same frames give the same answers.
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
from hand_sog_tracker.core.handcheck import HandGate
from hand_sog_tracker.core.initialise import INIT_SEARCH
from hand_sog_tracker.core.kinematics import (
    PALM_ROWS,
    fingertips,
    gaussian_centres,
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
from hand_sog_tracker.core.search import ASSIGN_LAMBDA_MM, NEW_TRACK_PROPOSALS, TRACK_PROPOSALS, Frame, search
from hand_sog_tracker.core.search.candidates import ROLL, pull_target
from hand_sog_tracker.core.search.fit import fit_parts, part
from hand_sog_tracker.core.search.start import NEW_TRACK_DATA, Finalists, on_hand_side, start_search
from hand_sog_tracker.core.silhouette import Silhouette, silhouette
from hand_sog_tracker.core.support import without_support
from hand_sog_tracker.core.types import HandDecision, Intrinsics, TrackerConfig, TrackerStatus, TrackResult

__all__ = ["ALPHA", "ASSIGN_LAMBDA_MM", "Tracker", "before_surface", "coverage", "hand_roi"]

# Module constants, not TrackerConfig fields (which become ROS parameters): none is meant to be
# tuned per camera or user; all chosen here unless said.  The measurements: doc/design/search.md.
ALPHA = 0.5  #: velocity extrapolation of the start pose (paper 000 sec. 5.3: alpha = 0.5)
WARM_GROW = 2.0  #: a tracked frame's steps start at the last frame's final ones x this ...
WARM_MIN = 0.1  #: ... within [this, 1] x the initial ones (settled parameters start small)
EXTRA_ITERATIONS = 3  #: a fit still climbing after ``iterations`` gets up to this many more ...
EXTRA_GAIN = 0.002  #: ... while the last raised E by this x abs(E(start)) (fast rotations outran 7)
SALIENT_END_ON = False  #: whether detections of fingers seen end-on pull tips (off: they seed candidates)
#: A PIP flexed over this (rad) has the answer refined on the joint-Gaussian model (issue 11: the
#: tracking model opens curled fingers into claws; refining only the answer keeps the track's).
REFINE_CURL_RAD = math.radians(60.0)
REFINE_WARM_STEPS = 0.5  #: steps x this from the frame before's correction (issue 14: it changes little)
REFINE_VISIBILITY = True  #: the refinement weights overlaps by visibility (a fist's hidden palm and tips)
#: A new track also fits its best ``SMALL_HAND_FINALISTS`` on a model of this length, which wins by
#: ``SMALL_HAND_GAIN`` with open fingers (mean MCP + PIP < ``SMALL_HAND_MAX_FLEX`` rad; issue 11).
SMALL_HAND_LENGTH = 0.85
SMALL_HAND_GAIN = 0.04
SMALL_HAND_MAX_FLEX = 0.6
SMALL_HAND_FINALISTS = 2
FRESH_BELOW = 0.5  #: a tracked frame checked below this competes with a fresh start (issue 46, hand_check.md) ...
FRESH_MARGIN = 0.1  #: ... which wins with a check this much higher (chosen on scenes_dev) ...
FRESH_APART_MM = 40.0  #: ... and its palm this far (mm, half a palm's width) from the track's
_INITIAL_STEPS = StepSizes().expand(StepSizes().initial)
#: What :meth:`Tracker._fresh_start` keeps of the track when the fresh start loses.
_TRACK_STATE = ("_prev", "_steps", "_low_frames", "_status", "_model", "_refine_last", "last_proposal", "_lost_pulls")
#: ``(data, detections, theta (26,)) -> (data, detections)``: see :attr:`Tracker.data_filter`.
DataFilter = Callable[[ImageSoG, Detections, NDArray[np.float64]], tuple[ImageSoG, Detections]]
_NO_POINTS = np.zeros((0, 3))
RoiWindow = tuple[tuple[int, int, int, int], tuple[float, float]]  #: :func:`hand_roi`'s (box px, window mm)


class _Keep:
    def reset(self) -> None:
        """What the hand gate resets when the tracker keeps its track (``withhold=False``): nothing."""


def _apart(track: TrackResult, track_model: HandModel, fresh: TrackResult, fresh_model: HandModel) -> bool:
    """Whether the palms (wrist and MCPs) of two results lie ``FRESH_APART_MM`` apart (or one has none)."""
    if track.pose is None or fresh.pose is None:
        return True
    a, b = (skeleton_points(m, r.pose).take(PALM_ROWS, 0) for m, r in ((track_model, track), (fresh_model, fresh)))
    return float(np.linalg.norm(a.mean(0) - b.mean(0))) > FRESH_APART_MM


def _open(theta: NDArray[np.float64]) -> bool:
    """Whether the fingers at ``theta`` are open enough to tell a hand's size."""
    return float(np.mean(theta[FINGER_MCP] + theta[FINGER_PIP])) < SMALL_HAND_MAX_FLEX


def _size_models(right: bool) -> tuple[HandModel, HandModel]:
    """The default model of this handedness and the same scaled to ``SMALL_HAND_LENGTH``."""
    default = default_hand_model(right)
    return default, default.scaled(HandShape(length=SMALL_HAND_LENGTH))


def _warm(steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """Start steps (26,) from a fit's final ``steps`` (``WARM_GROW``, ``WARM_MIN``)."""
    return np.minimum(np.maximum(steps * WARM_GROW, _INITIAL_STEPS * WARM_MIN), _INITIAL_STEPS)


class Tracker:
    """Tracks one hand through a depth sequence.

    Parameters
    ----------
    config : TrackerConfig, optional
    model : HandModel, optional
        Hand model (mm), kept as given; default: the default adult hand of ``config.right_hand``,
        on which every new track may start the small hand instead (until :meth:`set_model`).
    withhold : bool
        Every result carries its hand decision (:class:`~.handcheck.HandGate`); True (what the node
        publishes): a frame that is no hand has no pose and may reset the track, a doubted track
        competes with a fresh start.  False keeps every fitted pose and track (for the tools).
    """

    def __init__(
        self, config: TrackerConfig | None = None, model: HandModel | None = None, withhold: bool = True
    ) -> None:
        self._config = config or TrackerConfig()
        self._gate = HandGate()
        self._withhold = bool(withhold)
        #: The last frame's result before its hand decision withheld the pose (for the tools).
        self.last_fit: TrackResult | None = None
        #: The proposal the last frame's pose came from (None: its fit), for the tools.
        self.last_proposal: str | None = None
        self._track_frame: tuple[Frame, NDArray[np.float64]] | None = None  # (this frame's, its pose)
        self._sizes: tuple[HandModel, HandModel] | None = None  # (default, small) while the default
        if model is None:
            self._sizes = _size_models(self._config.right_hand)
            self._model = self._sizes[0]
        else:
            self._model = model.mirrored(self._config.right_hand)
        self._prev: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None  # last two poses
        self._steps: NDArray[np.float64] | None = None  # last frame's final step lengths (26,)
        self._low_frames, self._status = 0, TrackerStatus.NO_HAND  # (frames of low confidence in a row)
        self._joint_model: tuple[HandModel, HandModel] | None = None  # (model, with joint Gaussians)
        self._refine_last: tuple[NDArray, NDArray] | None = None  # (track pose, answer) (26,) if refined last frame
        self._lost_pulls = _NO_POINTS  # the detection (1, 3) mm whose pulls lost last frame, or none
        self.start_search = start_search  #: a new track's search (:mod:`.hands` checks its finalists)
        # Set by the multi-hand tracker (:mod:`.hands`); None: not used.
        #: What of the data near the hand at ``theta`` is this hand's (drops another hand's).
        self.data_filter: DataFilter | None = None
        #: ``tips (5, 3) mm -> (5,) bool``: the fingertips against another hand (:attr:`Frame.covered`).
        self.covered_tips: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None
        #: ``theta (26,) -> (26,) bool``: what a tracked frame's fit holds at its start (hidden fingers).
        self.held: Callable[[NDArray[np.float64]], NDArray[np.bool_]] | None = None
        #: ``(centres (m, 3), radii (m,)) mm -> InterHand or None``: the other hands' spheres this hand's
        #: may not penetrate, posed at a tracked frame's start (:mod:`.objective.interhand`).
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
        """Use another hand model (e.g. after calibration); keeps the track, its poses moved so
        that the palm centre stays where it was tracked (:func:`~.kinematics.keep_palm_centre`)."""
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
        """Go on as if the last frame had been tracked at ``pose`` (26,), at rest (the multi-hand
        tracker starts the other label's model of a new hand so, :mod:`.hands`)."""
        self._restart((np.array(pose, dtype=np.float64), np.array(pose, dtype=np.float64)), TrackerStatus.TRACKING)
        self._steps = None

    def reset(self) -> None:
        """Forget the track: the next frame initialises from scratch."""
        self._restart(None, TrackerStatus.NO_HAND)
        self._gate.forget()

    def _restart(self, prev: tuple[NDArray[np.float64], NDArray[np.float64]] | None, status: TrackerStatus) -> None:
        """A track starting at ``prev`` (the last two poses (26,); None: no track) with ``status``."""
        self._prev, self._low_frames, self._status, self._lost_pulls = prev, 0, status, _NO_POINTS

    def process(self, depth_mm: NDArray, intrinsics: Intrinsics) -> TrackResult:
        """Track the hand in one depth frame ``depth_mm`` (H, W) mm (0, NaN and Inf invalid) with
        the ``intrinsics`` of its size; raises DepthImageError or IntrinsicsError (the track left
        untouched) when the frame cannot be used."""
        t0 = time.perf_counter()  # (timings only: nothing below depends on the clock)
        # (Raises before any change of state; without a table under the hand: the check reads it all.)
        pre = without_support(preprocess(depth_mm, intrinsics, self._config))
        t1 = time.perf_counter()
        result, checked = self._fit(pre, (depth_mm, intrinsics) if self._withhold else None)
        t2 = time.perf_counter()
        keeper = self if self._withhold else _Keep()  # (the decision may reset the track)
        result = self._gate.gate(keeper, depth_mm, intrinsics, self._model, result, self._withhold, checked)
        result.timings_ms["check"] = (time.perf_counter() - t2) * 1e3
        return _timed(result, t0, t1, t2)

    def process_preprocessed(self, pre: Preprocessed) -> TrackResult:
        """:meth:`process` of a frame preprocessed with this tracker's configuration, without check
        and gate (the multi-hand tracker decides for its hands, :mod:`.hands`); no preprocess time."""
        t1 = time.perf_counter()
        return _timed(self._fit(pre)[0], t1, t1, time.perf_counter())

    # -- internals -----------------------------------------------------------
    def _fit(
        self, pre: Preprocessed, image: tuple[NDArray, Intrinsics] | None = None
    ) -> tuple[TrackResult, HandDecision | None]:
        """The frame's result before the gate and, with ``image`` (depth mm, intrinsics), a tracked
        frame's hand check (a lost track's is 0), below ``FRESH_BELOW`` against a fresh start."""
        checked = None
        if self._prev is None:
            result = self._initialise(pre)
        else:
            result = self._track(pre)
            if image is not None:
                checked = handcheck.check_hand(*image, self._model, result)
                if checked.confidence < FRESH_BELOW:
                    result, checked = self._fresh_start(pre, image, result, checked)
            self._track_frame = None  # (the frame's data are not kept)
        self.last_fit = result
        return result, checked

    def _fresh_start(
        self, pre: Preprocessed, image: tuple[NDArray, Intrinsics], track: TrackResult, checked: HandDecision
    ) -> tuple[TrackResult, HandDecision]:
        """(result, its check): a doubted tracked frame, or a new track on it that wins with a check
        ``FRESH_MARGIN`` higher and a palm elsewhere (:func:`_apart`) or, on the same hand, a higher
        score on the track's frame (the check does not judge articulation); else the track is kept."""
        kept = {name: getattr(self, name) for name in _TRACK_STATE}
        on_track = self._track_frame if track.pose is not None else None
        fresh = self._initialise(pre)
        if fresh.pose is not None:
            fresh_check = handcheck.check_hand(*image, self._model, fresh)
            better = fresh_check.confidence >= checked.confidence + FRESH_MARGIN
            same = on_track is not None and not _apart(track, kept["_model"], fresh, self._model)
            if better and same:
                frame, x = on_track  # (the same hand: the track's own score judges the articulation)
                better = frame.score(fresh.pose) > frame.score(x)
            if better:
                if same:  # (the same hand, confirmed, goes on moving as tracked: a new track's would be at rest)
                    self._prev = (fresh.pose, fresh.pose - np.subtract(*kept["_prev"]))
                else:  # (elsewhere: a new track, reported once a finger is seen to end)
                    self._gate.forget()
                self.last_proposal = "fresh_start"
                fresh.timings_ms["quadtree"] = fresh.timings_ms.get("quadtree", 0.0) + track.timings_ms["quadtree"]
                return fresh, fresh_check
        for name, value in kept.items():
            setattr(self, name, value)
        return track, checked

    def _data_near(
        self, pre: Preprocessed, theta: NDArray[np.float64], end_mm: float | None = None,
        roi_window: RoiWindow | None = None, max_gaussians: int = MAX_DATA_GAUSSIANS,
    ) -> tuple[ImageSoG, Detections, Silhouette | None]:
        """Data Gaussians (at most ``max_gaussians``), detections and silhouette (None without ``w_sil``)
        of the depth window (ending by ``end_mm``) around the hand at ``theta``, on its hand side."""
        if roi_window is None:
            roi_window = hand_roi(self._model, theta, pre.intrinsics, self._config.roi_radius_mm)
        roi, window = roi_window
        leaf = leaf_px(self._config.min_quad_px, 0.5 * (window[0] + window[1]), pre.intrinsics)  # (the hand's depth)
        if end_mm is not None:
            window = (window[0], min(window[1], end_mm))
        sil = silhouette(pre, window, roi) if self._config.w_sil > 0 else None
        # (With a data filter the cap applies to what it leaves: another hand's tips would take places.)
        det = detect_fingertips(pre, roi, window, None if self.data_filter is not None else MAX_DETECTIONS)
        if det.n:
            det = det.subset(on_hand_side(det.points, theta))
        data = quadtree_sog(pre, self._config.quadtree_threshold_mm, roi, window, leaf, max_gaussians)
        if data.n:
            data = part(data, on_hand_side(data.points, theta))
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
        # (The paper prints Theta_{t-1} + alpha Theta_{t-2}: read as a damped constant velocity.)
        x0 = p1 + ALPHA * (p1 - p2)
        tq = time.perf_counter()
        start_centres = posed_centres(self._model, x0)
        far = float(np.max(start_centres[:, 2]))
        roi_window = hand_roi(self._model, x0, pre.intrinsics, cfg.roi_radius_mm, start_centres)
        end = before_surface(
            pre.depth_mm, pre.intrinsics, roi_window[0], far + SURFACE_SEARCH_MM, far + WINDOW_BEHIND_MM
        )
        data, det, sil = self._data_near(pre, x0, end_mm=end, roi_window=roi_window)
        timings = {"quadtree": (time.perf_counter() - tq) * 1e3}
        obj = Objective(
            self._model, data, cfg, previous=(p1, p2), targets=self._targets(x0, det), silhouette=sil,
            contact=contact_shares(p1),
        )
        if self.interhand is not None:
            obj.interhand = self.interhand(start_centres, self._model.g_sigmas)
        held = None if self.held is None else self.held(x0)
        start = _INITIAL_STEPS if self._steps is None else _warm(self._steps)
        fit = maximise(
            obj, x0, iterations=cfg.iterations, initial_steps=start, extra_iterations=EXTRA_ITERATIONS,
            extra_gain=EXTRA_GAIN, active=None if held is None or not held.any() else ~held, bounds=self._limits(),
        )
        self._steps = fit.steps
        frame = Frame(
            self._model, fit, obj, data, det, self._limits(), lost_pulls=self._lost_pulls, covered=self.covered_tips
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
            self._restart(None, TrackerStatus.LOST)
            return self._result(None, conf, res.fun, data.n, timings)
        # A hand turned over by the roll proposal did not turn so between the frames: no velocity
        # from the jump (else the next frame's start and prior turn it on, measured in two_hands.md).
        self._prev = (res.x, res.x) if self.last_proposal == ROLL.name else (res.x, p1)
        self._status = TrackerStatus.TRACKING
        answer = self._refined(obj, res, p1)
        if res is not fit:
            self._refine_last = None  # (a candidate won: the next refinement starts from its pose)
        if answer is not res.x:
            centres = gaussian_centres(self._model, answer)
        return self._result(answer, conf, res.fun, data.n, timings, centres)

    def _refined(self, obj: Objective, res: OptimizeResult, p1: NDArray[np.float64]) -> NDArray[np.float64]:
        """A tracked frame's answer (26,): ``res.x`` or, with a PIP over ``REFINE_CURL_RAD``, that refined
        on ``obj`` of the joint model (from the last correction when the track went on from ``p1``)."""
        x, iterations = res.x, self._config.refine_iterations
        last, self._refine_last = self._refine_last, None
        if iterations <= 0 or np.max(x[FINGER_PIP]) <= REFINE_CURL_RAD:
            return x
        joint = self._joint_model
        if joint is None or joint[0] is not self._model:
            joint = self._joint_model = (self._model, self._model.with_joint_gaussians())
        refine = Objective(joint[1], obj.data, obj.config, obj.previous, obj.targets, obj.silhouette, obj.contact,
                           visible_from=x if REFINE_VISIBILITY else None)
        refine.interhand = obj.interhand
        steps, x0 = _warm(res.steps), x
        if last is not None and last[0] is p1:
            x0 = np.clip(x + (last[1] - last[0]), *self._limits())
            steps *= REFINE_WARM_STEPS
        fit = maximise(refine, x0, bounds=self._limits(), iterations=iterations, initial_steps=steps)
        self._refine_last = (x, fit.x)
        return fit.x

    def _limits(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The model's joint limits as bounds (low, high) (26,) each (:attr:`HandModel.bounds`)."""
        return self._model.bounds

    def _initialise(self, pre: Preprocessed) -> TrackResult:
        """A new track: the start search's finalists refined on one data extraction, the best searched
        (:data:`NEW_TRACK_PROPOSALS`); on the default model the small one may win (``SMALL_HAND_*``)."""
        self._steps, self._lost_pulls, self.last_proposal = None, _NO_POINTS, None
        if self._sizes is not None:
            self._model = self._sizes[0]
        found = self.start_search(pre, self._model, self._config, self._limits())
        if found is None:
            return self._no_hand({})
        tq = time.perf_counter()
        data, det, sil = self._data_near(pre, found.poses[0], end_mm=found.end_mm, max_gaussians=NEW_TRACK_DATA)
        timings = {"quadtree": (time.perf_counter() - tq) * 1e3}
        if data.n == 0:
            return self._no_hand(timings)
        fits = self._finalist_fits(found, data, det, sil)
        fits = [f for f in fits if f[0] not in found.tilted or f[1][0] >= INIT_SEARCH.combination_below]
        best = fits[0][1] if fits else None
        if best is not None and self._sizes is not None and _open(best[1].fit.x):
            self._model = self._sizes[1]
            tried = sorted(k for k, _ in fits[:SMALL_HAND_FINALISTS])  # (in the finalists' order)
            small_fits = self._finalist_fits(Finalists([found.poses[k] for k in tried]), data, det, sil)
            small = small_fits[0][1] if small_fits else None
            if small is not None and small[0] > best[0] + SMALL_HAND_GAIN and _open(small[1].fit.x):
                best = small
            else:
                self._model = self._sizes[0]
        if best is None:
            return self._no_hand(timings)
        frame = best[1]
        res, self.last_proposal = search(frame, NEW_TRACK_PROPOSALS)
        conf = coverage(self._model, res.x, frame.data)
        if conf < self._config.lost_confidence:
            return self._no_hand(timings, conf, res.fun, frame.data.n)
        self._restart((res.x, res.x), TrackerStatus.TRACKING)
        return self._result(res.x, conf, res.fun, frame.data.n, timings)

    def _no_hand(self, timings: dict[str, float], conf: float = 0.0, energy: float = 0.0, n: int = 0) -> TrackResult:
        self._status = TrackerStatus.NO_HAND
        return self._result(None, conf, energy, n, timings)

    def _finalist_fits(
        self, found: Finalists, data: ImageSoG, det: Detections, sil: Silhouette | None
    ) -> list[tuple[int, tuple[float, Frame]]]:
        """(index, (score, :class:`Frame`)) of each finalist with data on its hand side, refined with the
        full objective of its part of ``data`` as one batch; best first (the earlier on a tie)."""
        items = []
        for k, x in enumerate(found.poses):
            keep = on_hand_side(data.points, x)
            if keep.any():
                targets = self._targets(x, det)
                items.append((k, keep, Objective(self._model, part(data, keep), self._config, None, targets, sil)))
        if not items:
            return []
        shared = Objective(self._model, data, self._config, silhouette=sil)
        parts = np.array([keep for _, keep, _ in items])
        results = fit_parts(
            shared, np.array([found.poses[k] for k, _, _ in items]), parts, [obj.targets for _, _, obj in items],
            iterations=INIT_SEARCH.final_iterations, bounds=self._limits(),
        )
        # (The finalists' plain values: ``shared`` on their parts without targets, one batch.)
        values = shared.batch(np.array([r.x for r in results]), gradient=False, parts=None if parts.all() else parts)[0]
        fits = []
        for (k, _, obj), fit, value in zip(items, results, values.tolist()):
            frame = Frame(self._model, fit, obj, obj.data, det, self._limits(), new_track=True)
            fits.append((k, (frame.score(fit.x, value), frame)))
        fits.sort(key=lambda f: f[1][0], reverse=True)  # (stable: the earlier first on a tie)
        return fits

    def _result(
        self, theta: NDArray[np.float64] | None, conf: float, energy: float, n: int, timings: dict[str, float],
        centres: NDArray[np.float64] | None = None,
    ) -> TrackResult:
        if theta is None:
            return TrackResult(self._status, None, None, None, float(conf), float(energy), n, dict(timings))
        if centres is None:  # (forward kinematics once: the fingertips are the tip Gaussians' centres)
            centres = gaussian_centres(self._model, theta)
        m = self._model
        return TrackResult(
            self._status, theta.copy(), centres[m.tip_index], keypoint_skeleton(m, theta), float(conf), float(energy),
            n, dict(timings), gaussians_mm=centres, gaussian_radii_mm=m.g_sigmas.copy(),
        )


def _timed(result: TrackResult, t0: float, t1: float, t2: float) -> TrackResult:
    """``result`` with its ``timings_ms``: preprocessing ``t0``-``t1``, fit ``t1``-``t2`` (s) less data, total."""
    ms = result.timings_ms
    ms["preprocess"] = (t1 - t0) * 1e3
    ms.setdefault("quadtree", 0.0)
    ms["optimise"] = (t2 - t1) * 1e3 - ms["quadtree"]
    ms["total"] = (time.perf_counter() - t0) * 1e3
    return result
