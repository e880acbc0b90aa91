"""User-specific hand model: the four scale factors of paper 000, sec. 5.4, with a held-out guard.

One job: fitting and guarding the hand's scale factors; kept together because the fit and the
guard (:func:`validate`) share frame preparation and pose refits (the skin drawing and its
score are in :mod:`.skin`).

Fit.  The user holds an open hand toward the camera (any position and
in-plane orientation).  Each fit frame gets its own pose: the tracked pose when
the caller has one (the node passes the poses it tracked), else one found by a
tracker run over the frames.  Each pose is refined with the current model,
then the fingers are set open (a wrongly sized model bends and spreads the
fingers to make up for it: abduction trades off against width) and the global
pose refitted.  Frames whose fingers are clearly bent are not used.
Candidate shapes are scaled about each frame's palm centre and scored without
further pose changes.  Two rounds of greedy search, each over, in turn, the
overall size (all four factors together), length, width and thickness
(palm depth and finger sigma together: one frontal view does not see the
palm's thickness, and fitted alone it trades off against width through the
palm's outline), in the second round also sigma alone (finger width), every
value of a grid about the best so far tried with the others held; before the
second round the poses are refitted with the model found in the first (a pose
fitted with a wrongly sized model is biased toward that size).  Fingers are
not spread during the search: a spread pose explained with zero abduction
biases the width, and a free abduction trades off against the width (both
measured), so the fit wants frames of an open hand with relaxed fingers
(:func:`select_frames` picks the least spread ones of a history).

Score.  The tracking objective's similarity term is normalised by the data
alone, so a larger model always covers more data and scores higher; fitting
shape with it drifts to the largest model.  Candidates are therefore scored by
a depth-aware silhouette overlap (:func:`shape_score`), which is largest when
the model's skin and the hand's data cover the same pixels at the same depth.
The skin is drawn with OpenCV (about 1 ms a candidate and frame at 320 x 240).

Cost: 0.34-0.41 s on one core for 3 fit frames with tracked poses and 3
held-out frames (the node's case); without poses a tracker run finds them
(0.47-0.55 s for the fit alone).

Guard.  With ``holdout`` frames (not used for the fit), the fitted model must
explain them better than the current model: on each held-out frame both
models get the same short pose refit (:data:`GUARD_RIGID_ITERATIONS` global
then :data:`GUARD_REFIT_ITERATIONS` full iterations of the tracking objective
from the frame's pose, palm centre kept), then :func:`shape_score` is taken; the mean over the frames must rise by
at least :data:`GUARD_MARGIN`, else :class:`CalibrationRejected` is raised
(with both numbers) and the caller must keep (and not save) the current model.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.articulations import OPEN
from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, preprocess, quadtree_sog
from hand_sog_tracker.core.energy import Objective
from hand_sog_tracker.core.hand_model import (
    FINGER_ABD,
    FIRST_JOINT,
    FLEX1,
    FLEX2,
    FLEX3,
    JOINTS,
    N_PARAMS,
    HandModel,
    HandShape,
    chain_slice,
)
from hand_sog_tracker.core.kinematics import global_rotation
from hand_sog_tracker.core.optimizer import maximise
from hand_sog_tracker.core.skin import SCORE_TOLERANCE_MM, ScoreData, overlap_score, score_data, shape_score
from hand_sog_tracker.core.tracker import Tracker, coverage, hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import CalibrationError, HandSogError

__all__ = [
    "CalibrationResult",
    "CalibrationRejected",
    "Validation",
    "calibrate",
    "validate",
    "select_frames",
    "shape_score",
    "SEARCH_RANGE",
    "GUARD_MARGIN",
    "GUARD_REFIT_ITERATIONS",
    "GUARD_RIGID_ITERATIONS",
    "DEFAULT_FIT_FRAMES",
]

#: Fixed search range of every scale factor.
SEARCH_RANGE = (0.8, 1.25)
#: Frames the fit uses by default (the node's ``calibration_frames``); more are accepted.
DEFAULT_FIT_FRAMES = 3
#: The fitted model must raise the mean held-out :func:`shape_score` by at least this much
#: (a 6% size error costs more than this: test_core_calibration.py).
GUARD_MARGIN = 0.01
#: Pose-refit iterations each model gets on a held-out frame before it is scored.
GUARD_REFIT_ITERATIONS = 15
#: Global-pose-only iterations before them (the pose was tracked with the current model).
GUARD_RIGID_ITERATIONS = 8
#: Search rounds: span and step of the grid each factor is searched on about the best so far.
_ROUNDS = ((0.25, 0.05), (0.06, 0.015))
#: Searched in this order in each round: ``size`` scales all four factors together,
#: ``thickness`` sets depth and sigma together; the second round also tries sigma alone
#: (finger width is seen in the silhouette).  Palm depth is never searched alone: one
#: frontal view does not see the palm's thickness, and fitted alone it trades off against
#: width through the palm's outline (errors of 15-20% and a narrower palm, measured).
_FACTORS = (("size", "length", "width", "thickness"), ("size", "length", "width", "thickness", "sigma"))
_SCORE_MARGIN_PX = 12
_REFIT_ITERATIONS = 15
#: A fit frame whose fingers are flexed more than this (mean MCP + PIP flexion, rad) is not open.
_MAX_OPEN_FLEX = 0.6
_FINGER_FLEX = np.array([chain_slice(c).start + k for c in range(1, 5) for k in (FLEX1, FLEX2, FLEX3)])
_RIGID = np.arange(N_PARAMS) < FIRST_JOINT


def _candidate(shape: HandShape, name: str, offset: float) -> HandShape | None:
    """``shape`` with factor ``name`` moved by ``offset`` (None if outside :data:`SEARCH_RANGE`)."""
    values = shape.as_array()  # length, width, depth, sigma
    if name == "size":
        values = values * (1.0 + offset)
    elif name == "thickness":
        values[2:] += offset
    else:
        values[("length", "width", "depth", "sigma").index(name)] += offset
    lo, hi = SEARCH_RANGE
    if np.any(values < lo - 1e-9) or np.any(values > hi + 1e-9):
        return None
    return HandShape(*(float(v) for v in values))


@dataclass(frozen=True)
class Validation:
    """The guard's numbers: mean :func:`shape_score` on held-out frames (higher is better).

    Attributes
    ----------
    frames : int
        Held-out frames scored.
    score_current, score_fitted : float
        Mean score of the current and of the fitted model, each after the same pose refit.
    margin : float
        Required gain (:data:`GUARD_MARGIN`).
    """

    frames: int
    score_current: float
    score_fitted: float
    margin: float

    @property
    def gain(self) -> float:
        """``score_fitted - score_current``."""
        return self.score_fitted - self.score_current

    @property
    def accepted(self) -> bool:
        """Whether the fitted model beats the current one by the margin."""
        return self.gain >= self.margin

    def describe(self) -> str:
        """One line with the numbers, e.g. for a service answer."""
        return (
            f"held-out score {self.score_current:.4f} (current) -> {self.score_fitted:.4f} (fitted) "
            f"on {self.frames} frames, gain {self.gain:+.4f}, margin {self.margin:.4f}"
        )


class CalibrationRejected(CalibrationError):
    """The fitted model did not explain the held-out frames better than the current one.

    Attributes
    ----------
    shape : HandShape
        The rejected fit.
    validation : Validation
        The guard's numbers.
    """

    def __init__(self, shape: HandShape, validation: Validation) -> None:
        self.shape = shape
        self.validation = validation
        super().__init__(
            f"fitted model rejected, kept the current one: {validation.describe()} "
            f"(fit length={shape.length:.3f} width={shape.width:.3f} depth={shape.depth:.3f} "
            f"sigma={shape.sigma:.3f})"
        )


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Outcome of :func:`calibrate`.

    Attributes
    ----------
    shape : HandShape
        Fitted scale factors.
    model : HandModel
        The scaled model.
    pose : array, shape (26,)
        Refined pose on the first fit frame (mm, rad).
    score_before, score_after : float
        Mean :func:`shape_score` of the starting and of the fitted model on the fit frames
        (higher is better; formerly named ``energy_before`` / ``energy_after``, still readable
        under those names).
    seconds : float
        Wall time of the fit (and of the guard).
    poses : array, shape (n, 26)
        Refined pose of every fit frame, in the order of ``frames``.
    used_frames : tuple of int
        Indices into ``frames`` of the frames the fit used (frames without an open hand are dropped).
    validation : Validation or None
        The guard's numbers (None without held-out frames).
    """

    shape: HandShape
    model: HandModel
    pose: NDArray[np.float64]
    score_before: float
    score_after: float
    seconds: float
    poses: NDArray[np.float64] | None = None
    used_frames: tuple[int, ...] = ()
    validation: Validation | None = None

    @property
    def energy_before(self) -> float:
        """Old name of :attr:`score_before`."""
        return self.score_before

    @property
    def energy_after(self) -> float:
        """Old name of :attr:`score_after`."""
        return self.score_after


def _palm_mean(model: HandModel) -> NDArray[np.float64]:
    """Mean palm-Gaussian offset in the hand frame (mm), mirrored for a left hand."""
    mean = model.g_offsets[model.g_chain < 0].mean(axis=0)
    return mean if model.right else mean * np.array([-1.0, 1.0, 1.0])


def _keep_palm_centre(theta: NDArray[np.float64], old: HandModel, new: HandModel) -> NDArray[np.float64]:
    """Move the wrist so that the palm centre stays put when the model is rescaled.

    The palm Gaussians are rigid in the hand frame, so their centre is
    ``t + R @ mean offset``.
    """
    out = theta.copy()
    out[:3] += global_rotation(theta) @ (_palm_mean(old) - _palm_mean(new))
    return out


def _refine(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ImageSoG,
    config: TrackerConfig,
    iters: int,
    active: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """``theta`` (26,) refined by the tracking objective over the ``active`` parameters."""
    return maximise(Objective(model, data, config), theta, iterations=iters, active=active).x


@dataclass
class _Frame:
    """One frame prepared for fitting or validation (mutable pose)."""

    pre: Preprocessed
    data: ImageSoG
    scoring: ScoreData
    pose: NDArray[np.float64]


def _prepare(pre: Preprocessed, pose: NDArray[np.float64], model: HandModel, config: TrackerConfig) -> _Frame | None:
    """Data around the hand at ``pose``; None when no hand data are there."""
    roi, window = hand_roi(model, pose, pre.intrinsics, config.roi_radius_mm)
    data = quadtree_sog(pre, config.quadtree_threshold_mm, roi, window, config.min_quad_px)
    if data.n == 0:
        return None
    # Score only around the hand's data (plus a margin for a model too large).
    lo = np.floor((data.mu - data.sigma[:, None]).min(axis=0)) - _SCORE_MARGIN_PX
    hi = np.ceil((data.mu + data.sigma[:, None]).max(axis=0)) + _SCORE_MARGIN_PX
    box = (int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1)
    return _Frame(pre, data, score_data(pre, box), np.asarray(pose, dtype=np.float64).copy())


def _preprocess_all(frames: Sequence[NDArray], intrinsics: Intrinsics, config: TrackerConfig) -> list[Preprocessed]:
    try:
        return [preprocess(f, intrinsics, config) for f in frames]
    except HandSogError as err:
        raise CalibrationError(f"unusable depth frame: {err}") from err


def _find_poses(
    frames: Sequence[NDArray],
    poses: Sequence[NDArray[np.float64] | None],
    intrinsics: Intrinsics,
    config: TrackerConfig,
    model: HandModel,
) -> list[NDArray[np.float64] | None]:
    """The given poses; missing ones from one tracker run over the frames in order."""
    if all(p is not None for p in poses):
        return [np.asarray(p, dtype=np.float64) for p in poses]
    tracker = Tracker(config, model)
    out: list[NDArray[np.float64] | None] = []
    for frame, pose in zip(frames, poses):
        res = tracker.process(frame, intrinsics)
        out.append(np.asarray(pose, dtype=np.float64) if pose is not None else res.pose)
    return out


def select_frames(
    poses: Sequence[NDArray[np.float64] | None], n_fit: int = DEFAULT_FIT_FRAMES, n_holdout: int = 3
) -> tuple[list[int], list[int]]:
    """Choose fit and held-out frames from a history of tracked poses.

    Fit frames: open hands (finger flexion below the limit the fit accepts) with the
    fingers least spread (abduction trades off against width), not adjacent to each
    other where possible.  Held-out frames: the other frames with a pose, spread evenly
    over the history (so they show other poses than the fit frames).

    Parameters
    ----------
    poses : sequence of arrays (26,) or None
        Tracked pose of each history frame (None: not tracked), oldest first.
    n_fit, n_holdout : int
        How many of each to return (fewer when the history is short; the fit frames
        are served first).

    Returns
    -------
    fit, holdout : list of int
        Indices into ``poses``.
    """
    valid = [i for i, p in enumerate(poses) if p is not None]
    flex = {i: float(np.asarray(poses[i])[_FINGER_FLEX].reshape(4, 3)[:, :2].mean()) for i in valid}
    spread = {i: float(np.abs(np.asarray(poses[i])[FINGER_ABD]).sum()) for i in valid}
    open_ = sorted((i for i in valid if flex[i] <= _MAX_OPEN_FLEX), key=lambda i: (spread[i], -i))
    fit: list[int] = []
    for gap in (2, 1):
        for i in open_:
            if len(fit) < n_fit and i not in fit and all(abs(i - j) >= gap for j in fit):
                fit.append(i)
    rest = [i for i in valid if i not in fit]
    if len(rest) > n_holdout > 0:
        rest = [rest[int(round(k))] for k in np.linspace(0, len(rest) - 1, n_holdout)]
    return sorted(fit), rest[:n_holdout] if n_holdout > 0 else []


def validate(
    frames: Sequence[NDArray],
    poses: Sequence[NDArray[np.float64] | None],
    intrinsics: Intrinsics,
    config: TrackerConfig,
    current: HandModel,
    fitted: HandModel,
    margin: float = GUARD_MARGIN,
) -> Validation:
    """Score the current and the fitted model on frames not used for the fit (the guard).

    Parameters
    ----------
    frames : sequence of arrays, shape (H, W)
        Held-out depth images (mm).
    poses : sequence of arrays, shape (26,), or None
        Pose of the hand in each frame as tracked with ``current`` (None: found by a tracker run).
    intrinsics : Intrinsics
    config : TrackerConfig
    current, fitted : HandModel
        The model in use and the candidate.
    margin : float
        Required gain of the mean score.

    Returns
    -------
    Validation
        Frames without hand data are skipped (``frames`` counts the scored ones).

    Raises
    ------
    CalibrationError
        No held-out frame has the hand in view.
    """
    pres = _preprocess_all(frames, intrinsics, config)
    right = config.right_hand
    current, fitted = current.mirrored(right), fitted.mirrored(right)
    found = _find_poses(frames, list(poses), intrinsics, config, current)
    sums = np.zeros(2)
    n = 0
    for pre, pose in zip(pres, found):
        if pose is None:
            continue
        fr = _prepare(pre, pose, current, config)
        if fr is None:
            continue
        for k, m in enumerate((current, fitted)):
            th = _keep_palm_centre(fr.pose, current, m)
            th = _refine(m, th, fr.data, config, GUARD_RIGID_ITERATIONS, _RIGID)
            th = _refine(m, th, fr.data, config, GUARD_REFIT_ITERATIONS)
            sums[k] += overlap_score(m, th, fr.scoring, pre.intrinsics, SCORE_TOLERANCE_MM)
        n += 1
    if n == 0:
        raise CalibrationError("no hand in the held-out frames (hold an open hand toward the camera)")
    return Validation(frames=n, score_current=float(sums[0] / n), score_fitted=float(sums[1] / n), margin=float(margin))


def calibrate(
    frames: Sequence[NDArray],
    intrinsics: Intrinsics,
    config: TrackerConfig,
    model: HandModel,
    start_pose: NDArray[np.float64] | None = None,
    *,
    poses: Sequence[NDArray[np.float64] | None] | None = None,
    holdout: Sequence[NDArray] = (),
    holdout_poses: Sequence[NDArray[np.float64] | None] | None = None,
    margin: float = GUARD_MARGIN,
) -> CalibrationResult:
    """Fit the four scale factors of ``model`` to frames of an open hand.

    Parameters
    ----------
    frames : sequence of arrays, shape (H, W)
        Depth images (mm) of the open hand to fit on (:data:`DEFAULT_FIT_FRAMES`
        by default; more cost proportionally more time).  Poses that differ
        (fingers together and spread, a turned hand) separate width from the
        other factors better.
    intrinsics : Intrinsics
    config : TrackerConfig
    model : HandModel
        Current model; its handedness is kept, its shape is the starting point.
    start_pose : array, shape (26,), optional
        Pose of the hand in the first frame (kept for compatibility; ``poses`` wins).
    poses : sequence of arrays (26,) or None, optional
        Pose of the hand in each frame (e.g. as tracked); missing ones are found by a
        tracker run over the frames in order (0.2-0.3 s for the first).
    holdout : sequence of arrays, shape (H, W)
        Frames NOT used for the fit.  When given, the guard runs (:func:`validate`):
        the fit is returned only if it explains them better than ``model`` by ``margin``.
    holdout_poses : sequence of arrays (26,) or None, optional
        Poses of the held-out frames, as for ``poses``.
    margin : float
        Required gain of the guard's mean held-out score.

    Raises
    ------
    CalibrationRejected
        The guard refused the fit (the exception carries the numbers).
    CalibrationError
        No frames, no (open) hand in view, or no candidate scored better than
        the starting model on the fit frames.
    """
    t0 = time.perf_counter()
    if len(frames) == 0:
        raise CalibrationError("no depth frames to calibrate on")
    frames = list(frames)
    pres = _preprocess_all(frames, intrinsics, config)
    given: list[NDArray[np.float64] | None] = list(poses) if poses is not None else [None] * len(frames)
    if len(given) != len(frames):
        raise CalibrationError(f"got {len(given)} poses for {len(frames)} frames")
    if given[0] is None and start_pose is not None:
        given[0] = np.asarray(start_pose, dtype=np.float64)
    mirrored = model.mirrored(config.right_hand)
    found = _find_poses(frames, given, intrinsics, config, mirrored)

    fits: list[_Frame] = []
    used: list[int] = []
    bent = 0
    for i, (pre, pose) in enumerate(zip(pres, found)):
        if pose is None:
            continue
        fr = _prepare(pre, pose, mirrored, config)
        if fr is None or coverage(mirrored, pose, fr.data) < config.lost_confidence:
            continue
        th = _refine(mirrored, fr.pose, fr.data, config, _REFIT_ITERATIONS)
        if th[_FINGER_FLEX].reshape(4, 3)[:, :2].mean() > _MAX_OPEN_FLEX:
            bent += 1  # not an open hand
            continue
        # The user holds an open hand: the joints are set open (a wrongly sized model bends
        # and spreads the fingers to make up for it: abduction trades off against width).
        th[JOINTS] = OPEN
        fr.pose = _refine(mirrored, th, fr.data, config, _REFIT_ITERATIONS, _RIGID)
        fits.append(fr)
        used.append(i)
    if not fits:
        if bent:
            raise CalibrationError(
                f"the fingers are bent on all {bent} frames with a hand (hold an open hand toward the camera)"
            )
        raise CalibrationError("no hand in view (hold an open hand toward the camera)")
    intr = pres[0].intrinsics

    def evaluate(shape: HandShape, ref_model: HandModel) -> tuple[float, list[NDArray[np.float64]]]:
        """Mean score of ``shape`` over the fit frames, scaled about each palm centre."""
        m = mirrored.scaled(shape)
        ths = [_keep_palm_centre(fr.pose, ref_model, m) for fr in fits]
        return (
            sum(overlap_score(m, th, fr.scoring, intr, SCORE_TOLERANCE_MM) for th, fr in zip(ths, fits)) / len(fits),
            ths,
        )

    best_shape = model.shape
    ref_model = mirrored.scaled(best_shape)
    before, best_poses = evaluate(best_shape, ref_model)
    best_val = before
    for round_no, (span, step) in enumerate(_ROUNDS):
        if round_no > 0:
            # Refit the poses with the model found so far: a pose fitted with a
            # wrongly sized model is biased toward that size.
            new_ref = mirrored.scaled(best_shape)
            saved = [fr.pose for fr in fits]
            for fr, th in zip(fits, best_poses):
                fr.pose = _refine(new_ref, th, fr.data, config, _REFIT_ITERATIONS, _RIGID)
            val, ths = evaluate(best_shape, new_ref)
            if val > best_val:
                ref_model, best_val, best_poses = new_ref, val, ths
            else:
                for fr, th in zip(fits, saved):
                    fr.pose = th
        for name in _FACTORS[round_no]:
            base_shape = best_shape
            for off in np.arange(-span, span + 1e-9, step):
                cand = _candidate(base_shape, name, float(off)) if abs(off) > 1e-9 else None
                if cand is None:
                    continue
                val, ths = evaluate(cand, ref_model)
                if val > best_val:
                    best_val, best_shape, best_poses = val, cand, ths
    fitted = mirrored.scaled(best_shape)
    after = best_val
    if not after > before:
        raise CalibrationError(
            f"fit not better than the current model on the fit frames (score {after:.4f} <= {before:.4f})"
        )
    for fr, th in zip(fits, best_poses):
        fr.pose = th
    validation = None
    if len(holdout):
        hp = list(holdout_poses) if holdout_poses is not None else [None] * len(holdout)
        if len(hp) != len(holdout):
            raise CalibrationError(f"got {len(hp)} poses for {len(holdout)} held-out frames")
        validation = validate(holdout, hp, intrinsics, config, mirrored, fitted, margin)
        if not validation.accepted:
            raise CalibrationRejected(best_shape, validation)
    poses_out = np.array([fr.pose for fr in fits])
    return CalibrationResult(
        shape=best_shape,
        model=fitted,
        pose=poses_out[0].copy(),
        score_before=float(before),
        score_after=float(after),
        seconds=time.perf_counter() - t0,
        poses=poses_out,
        used_frames=tuple(used),
        validation=validation,
    )
