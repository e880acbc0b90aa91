"""The calibration guard: does a fitted hand model explain frames not used for the fit better?

One job: judging a fit of :func:`~hand_sog_tracker.core.calibration.calibrate` on held-out
frames (:func:`validate`), with the frame preparation and pose refits the fit shares.  The
user-facing API is re-exported by :mod:`.calibration`.

Guard.  With ``holdout`` frames (not used for the fit), the fitted model must explain them
better than the current model by several kinds of evidence (:meth:`Validation.evidence`), each
against its own noise (:data:`GUARD_NOISE_SE` standard errors of its mean over the frames, at
least a floor; the frames count as independent only as far as the hand moved between them,
:func:`independent_frames`): on each held-out frame both models get the same pose refit from
the frame's pose, palm centre kept (:data:`GUARD_RIGID_ITERATIONS` global, then
:data:`GUARD_REFIT_ITERATIONS` full iterations of the tracking objective with its silhouette
and fingertip-detection terms, as the tracker fits a frame) and are compared by the
:func:`shape_score` and by the distance of their fingertips to the fingertip detections; each
model also re-tracks the held-out frames in order from its own pose on the previous one (in the
same batch as the refit) and is scored again.  Any evidence worse beyond its noise, or one frame
losing more than :data:`GUARD_FRAME_DROP`, refuses the fit; the best-pose score (each model's
better score of its two pose fits on a frame: the refit from the tracked pose favours the
current model) must rise beyond its noise, or the re-track corroborate the gain (the
re-tracked score up beyond its own noise, the best-pose and held-out scores up by the margin:
:meth:`Validation.corroborated`), else "the current model already fits" (nothing to do).
Either way :class:`CalibrationRejected` is raised
(with the numbers) and the caller keeps (and does not save) the current model.  None of this
has fingertip truth: the measurements that chose the rules, the predictors tried and the hands
whose true shape tracks worse than the default model are in ``doc/design/calibration_guard.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, leaf_px, preprocess, quadtree_sog
from hand_sog_tracker.core.hand_model import FIRST_JOINT, N_PARAMS, HandModel, HandShape
from hand_sog_tracker.core.kinematics import fingertips, keep_palm_centre
from hand_sog_tracker.core.objective import EnergyTerms, Objective, TipTargets
from hand_sog_tracker.core.optimizer import maximise_batch
from hand_sog_tracker.core.salient import Detections, assign_detections, assigned_targets, detect_fingertips
from hand_sog_tracker.core.search.fit import with_targets
from hand_sog_tracker.core.silhouette import Silhouette, silhouette
from hand_sog_tracker.core.skin import SCORE_TOLERANCE_MM, ScoreData, overlap_score, score_data
from hand_sog_tracker.core.tracker import Tracker, coverage, hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus
from hand_sog_tracker.errors import CalibrationError, HandSogError

__all__ = [
    "CalibrationRejected",
    "Evidence",
    "Validation",
    "validate",
    "independent_frames",
    "retrack",
    "GUARD_MARGIN",
    "GUARD_NOISE_SE",
    "GUARD_TIP_FLOOR_MM",
    "GUARD_REFIT_ITERATIONS",
    "GUARD_RIGID_ITERATIONS",
    "GUARD_FRAME_DROP",
    "GUARD_TIP_LAMBDA_MM",
    "GUARD_THICKNESS_NOISE",
    "DEFAULT_HOLDOUT_FRAMES",
    "PER_FRAME_COLUMNS",
    "RETRACK_COLUMNS",
]

#: The fitted model must raise the mean held-out :func:`shape_score` by at least this much
#: (a 6% size error costs more than this: test_core_calibration.py; the same model twice gains
#: exactly 0).  0.01 while width and thickness came from the search; with measured widths
#: correct fits gain less on the held-out frames.  0.005 until 2026-11-23; 0.003 since: on the
#: 24 dev hands (seeds 2000-2011, mesh and capsule) of the README's lost script every margin
#: from 0 to 0.005 accepted and refused the same fits (no gain lay in between; on those of
#: ``calibration_benchmark --split dev`` a refused mesh fit gains 0.0021 and an accepted capsule
#: fit 0.0047, both within 2% of the truth), and the issue's large mesh hand (1.12 x 1.1
#: x 1.1), fitted within 2%, gains 0.0039 and tracks 1.15 mm better.  Raising it does not stop
#: fits that track worse: at 0.02 a third of the dev fits that track better are refused and two
#: that track worse (0.17-0.61 mm) still pass, at 0.03 two thirds are refused.
GUARD_MARGIN = 0.003
#: A measure of the guard is worse (or better) beyond its noise when its mean change over the
#: held-out frames exceeds this many standard errors of that mean, and its floor: the margin
#: for the scores, :data:`GUARD_TIP_FLOOR_MM` for the fingertip-detection distances.
GUARD_NOISE_SE = 2.0
#: Floor of the fingertip-detection distances' noise (mm).
GUARD_TIP_FLOOR_MM = 0.5
#: Held-out frames the guard checks by default (the node holds out this many of its history).
DEFAULT_HOLDOUT_FRAMES = 4
#: Pose-refit iterations each model gets on a held-out frame before it is scored (in two
#: halves, the fingertip detections re-assigned in between, as the tracker does).
GUARD_REFIT_ITERATIONS = 16
#: Global-pose-only iterations before them (the pose was tracked with the current model).
GUARD_RIGID_ITERATIONS = 8
#: No held-out frame may lose more than this :func:`shape_score` with the fitted model (a
#: model fitted to some poses that explains another pose clearly worse is wrong).
GUARD_FRAME_DROP = 0.05
#: The guard's fingertip-detection distance (``tip_current`` / ``tip_fitted``, one kind of its
#: evidence): a model fingertip without a detection within this (mm) counts as this far.
GUARD_TIP_LAMBDA_MM = 30.0
#: Noise of the measured finger thickness (sigma factor, unitless): 2 SD of measured minus true
#: thickness per width on the capsule dev hands (SD 0.022).  A fit whose thickness bound makes
#: the fingers thinner than the current model's while the measurement says they are thicker by
#: more than this is refused (:meth:`Validation.thickness_contradicted`).
GUARD_THICKNESS_NOISE = 0.044
_SCORE_MARGIN_PX = 12
_RIGID = np.arange(N_PARAMS) < FIRST_JOINT






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
    leaf = leaf_px(config.min_quad_px, 0.5 * (window[0] + window[1]), pre.intrinsics)
    data = quadtree_sog(pre, config.quadtree_threshold_mm, roi, window, leaf)
    if data.n == 0:
        return None
    # Score only around the hand's data (plus a margin for a model too large).
    lo = np.floor((data.mu - data.sigma[:, None]).min(axis=0)) - _SCORE_MARGIN_PX
    hi = np.ceil((data.mu + data.sigma[:, None]).max(axis=0)) + _SCORE_MARGIN_PX
    box = (int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1)
    return _Frame(pre, data, score_data(pre, box, window), np.asarray(pose, dtype=np.float64).copy())


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




@dataclass(frozen=True)
class Evidence:
    """One kind of the guard's evidence: the mean change (fitted - current) and its noise.

    Attributes
    ----------
    name : str
    change : float
        Mean over the frames of fitted minus current (score: unitless; distances: mm).
    noise : float
        :data:`GUARD_NOISE_SE` standard errors of that mean, at least the measure's floor.
    higher_is_better : bool
    frames : int
    decides : bool
        Whether the fit is accepted only when this evidence is better beyond its noise (every
        evidence refuses when worse beyond it).
    """

    name: str
    change: float
    noise: float
    higher_is_better: bool
    frames: int
    decides: bool = False

    @property
    def worse(self) -> bool:
        """Worse with the fitted model beyond the noise."""
        return bool(-self.change > self.noise if self.higher_is_better else self.change > self.noise)

    @property
    def better(self) -> bool:
        """Better with the fitted model by at least the noise."""
        return bool(self.change >= self.noise if self.higher_is_better else -self.change >= self.noise)

    def describe(self) -> str:
        return f"{self.change:+.4f} (noise {self.noise:.4f}, {self.frames} frames)"


def _evidence(
    name: str,
    diff: NDArray[np.float64],
    floor: float,
    higher_is_better: bool,
    decides: bool = False,
    independent: float = float("inf"),
) -> Evidence:
    """:class:`Evidence` of per-frame changes ``diff`` (NaN: not measured on that frame).

    The standard error of the mean divides the frames' spread by the square root of the number
    of frames, at most ``independent`` (:attr:`Validation.independent_frames`: frames of a hand
    held still are one observation of its pose, repeated).
    """
    d = diff[np.isfinite(diff)]
    n = min(float(len(d)), max(float(independent), 1.0))
    se = float(np.std(d, ddof=1) / np.sqrt(n)) if len(d) > 1 else 0.0
    return Evidence(name, float(d.mean()), max(floor, GUARD_NOISE_SE * se), higher_is_better, len(d), decides)


@dataclass(frozen=True)
class Validation:
    """The guard's numbers on held-out frames (scores: higher is better; tips: lower is better).

    Attributes
    ----------
    frames : int
        Held-out frames scored.
    score_current, score_fitted : float
        Mean :func:`shape_score` of the current and of the fitted model, each after the same
        pose refit.
    margin : float
        Required gain of the mean score (:data:`GUARD_MARGIN`).
    worst_frame_gain : float
        Smallest per-frame score gain (fitted - current); must be >= ``-frame_drop``.
    frame_drop : float
        :data:`GUARD_FRAME_DROP`.
    tip_current, tip_fitted : float
        Mean distance (mm) of the refitted model's fingertips to the fingertip detections
        (:func:`~hand_sog_tracker.core.salient.detect_fingertips`; an unmatched fingertip
        counts :data:`GUARD_TIP_LAMBDA_MM`), over frames with detections; NaN without any.
        One kind of the guard's evidence (per frame in :attr:`per_frame`).
    tip_frames : int
        Held-out frames with fingertip detections.
    measured_finger_mm : tuple of float
        Widths (mm) of the index .. little finger measured in the fit frames
        (:func:`~hand_sog_tracker.core.measure.measure_widths`; empty: not measured).
    measured_knuckle_mm, measured_palm_mm : float
        Knuckle span and palm width measured there (mm; NaN: not measured).
    measured_sigma, measured_width : float
        The factors these widths give (:func:`~hand_sog_tracker.core.measure.shape_from_widths`).
    widths_from_measurement : bool
        Whether the fit took width, depth and sigma from the measurement (else from the search).
    current_sigma, fitted_sigma : float
        The finger thickness (sigma factor) of the current and of the fitted model (NaN: not
        known); with :attr:`measured_sigma` for :meth:`thickness_contradicted`.
    per_frame : tuple of tuple of float
        Per held-out frame, :data:`PER_FRAME_COLUMNS` each as (current, fitted) (16 values).
    retrack_frames : tuple of tuple of float
        Per re-tracked held-out frame (the second on), :data:`RETRACK_COLUMNS` each as
        (current, fitted) (8 values).
    independent_frames : float
        How many independent observations the held-out frames are (:func:`independent_frames`;
        inf: as many as frames).  The evidence's standard errors use it.
    """

    frames: int
    score_current: float
    score_fitted: float
    margin: float
    worst_frame_gain: float = float("nan")
    frame_drop: float = GUARD_FRAME_DROP
    tip_current: float = float("nan")
    tip_fitted: float = float("nan")
    tip_frames: int = 0
    measured_finger_mm: tuple[float, ...] = ()
    measured_knuckle_mm: float = float("nan")
    measured_palm_mm: float = float("nan")
    measured_sigma: float = float("nan")
    measured_width: float = float("nan")
    widths_from_measurement: bool = False
    current_sigma: float = float("nan")
    fitted_sigma: float = float("nan")
    per_frame: tuple[tuple[float, ...], ...] = ()
    retrack_frames: tuple[tuple[float, ...], ...] = ()
    independent_frames: float = float("inf")

    @property
    def gain(self) -> float:
        """``score_fitted - score_current``."""
        return self.score_fitted - self.score_current

    def best_pose_scores(self) -> NDArray[np.float64]:
        """Per held-out frame, each model's score at the better of its two pose fits, shape (n, 2)
        (current, fitted; unitless).

        A model's score on a frame is its score at its best pose: the refit from the tracked
        pose favours the current model (the pose was tracked with it), the re-track from its own
        previous pose favours neither, and either fit can stop short of that model's best pose.
        The re-tracked rows belong to the last ``len(retrack_frames)`` held-out frames (the
        first frame has only the refit).
        """
        pf = np.array(self.per_frame, dtype=float).reshape(-1, 2 * len(PER_FRAME_COLUMNS))
        best = pf[:, :2].copy()
        rt = np.array(self.retrack_frames, dtype=float).reshape(-1, 2 * len(RETRACK_COLUMNS))[: len(best)]
        if len(rt):
            tail = best[len(best) - len(rt):]
            tail[:] = np.where(np.isfinite(rt[:, :2]), np.fmax(tail, rt[:, :2]), tail)
        return best

    def evidence(self) -> list[Evidence]:
        """Each kind of evidence the guard weighs (see :class:`Evidence`), on held-out frames.

        The best-pose score (:meth:`best_pose_scores`, floor :attr:`margin`; the one that must
        rise beyond its noise), the held-out score after the refit from the tracked pose
        (:attr:`gain`), the fingertip-detection distance at those poses (with detections), and
        the score along the held-out frames re-tracked with each model from its own pose on the
        previous frame (:attr:`retrack_frames`, from the second held-out frame on).  Without
        per-frame rows (a :class:`Validation` built by hand) the mean score alone, its noise the
        margin.
        """
        out = []
        pf = np.array(self.per_frame, dtype=float).reshape(-1, 2 * len(PER_FRAME_COLUMNS))
        n = self.independent_frames
        if len(pf):
            best = self.best_pose_scores()
            out.append(_evidence("best-pose score", best[:, 1] - best[:, 0], self.margin, True, True, n))
            out.append(_evidence("held-out score", pf[:, 1] - pf[:, 0], self.margin, True, independent=n))
            tips = pf[:, 3] - pf[:, 2]
            if np.isfinite(tips).any():
                name = "fingertip-detection distance (mm)"
                out.append(_evidence(name, tips, GUARD_TIP_FLOOR_MM, False, independent=n))
        else:
            out.append(Evidence("held-out score", self.gain, self.margin, True, self.frames, decides=True))
        rt = np.array(self.retrack_frames, dtype=float).reshape(-1, 2 * len(RETRACK_COLUMNS))
        both = np.isfinite(rt[:, 0]) & np.isfinite(rt[:, 1])
        if both.any():
            out.append(_evidence("re-tracked score", rt[both, 1] - rt[both, 0], self.margin, True, independent=n))
        return out

    def corroborated(self) -> bool:
        """Whether the re-track corroborates a gain the best-pose score alone does not carry
        beyond its noise: the re-tracked score (each model following the held-out frames from its
        own pose) rises beyond its own noise, and the best-pose and the held-out score (the
        refit from the tracked pose) each rise by at least :attr:`margin`.

        Two kinds of pose fit agreeing is evidence the best-pose score's noise does not see: on
        a hand held still its frames are one pose (few :attr:`independent_frames`), and a
        re-track that gains on every frame is the fitted model following that pose better
        (doc/design/calibration_guard.md, "Corroborated gains").
        """
        ev = {e.name: e for e in self.evidence()}
        rt, best, held = ev.get("re-tracked score"), ev.get("best-pose score"), ev.get("held-out score")
        if rt is None or best is None or held is None or not self.per_frame:
            return False
        return bool(rt.better and best.change >= self.margin and held.change >= self.margin)

    def combined(self) -> float:
        """The three scores' changes combined, in units of their noise (unitless; NaN without
        the three): the best-pose, held-out and re-tracked score's change over its noise,
        summed and divided by the square root of three (Stouffer's combination; each noise is
        :data:`GUARD_NOISE_SE` standard errors, so 1 is a combined gain beyond the noise).

        Three small gains that each stay within their own noise, all of one sign, are more
        evidence than any one of them (doc/design/calibration_guard.md, "Combined evidence").
        The three share their frames and the best-pose score is made of the other two's pose
        fits, so they are not independent and this overstates the evidence; the dev hands it
        adds all track better.
        """
        ev = {e.name: e for e in self.evidence()}
        names = ("best-pose score", "held-out score", "re-tracked score")
        if not self.per_frame or any(n not in ev for n in names):
            return float("nan")
        return float(sum(ev[n].change / ev[n].noise for n in names) / np.sqrt(len(names)))

    def gains_together(self) -> bool:
        """Whether the three scores gain together: their combination (:meth:`combined`) at
        least 1, the deciding best-pose score up by at least :attr:`margin` (gains under the
        margin are no gain, however many agree)."""
        ev = {e.name: e for e in self.evidence()}
        names = ("best-pose score", "held-out score", "re-tracked score")
        if not self.per_frame or any(n not in ev for n in names):
            return False
        return bool(ev["best-pose score"].change >= self.margin and self.combined() >= 1.0)

    def thickness_contradicted(self) -> bool:
        """Whether the fit moves the finger thickness away from its own measurement: measured
        thicker than the current model by more than :data:`GUARD_THICKNESS_NOISE`, fitted
        thinner than it (the fit's thickness bound, depth and sigma at most the width, cut it).

        The fitted model is then not the measured hand, and these are the thick-fingered hands
        whose fits pass every score and track worse (the tracker's side-by-side finger bias:
        doc/design/calibration_guard.md, "Fits that contradict their measurement").
        """
        m, c, f = self.measured_sigma, self.current_sigma, self.fitted_sigma
        if not (np.isfinite(m) and np.isfinite(c) and np.isfinite(f)):
            return False
        return bool(m > c + GUARD_THICKNESS_NOISE and f < c)

    def failures(self) -> list[str]:
        """Why the guard does not accept the fitted model (empty: accepted).

        Refused when any evidence is worse beyond its noise, one held-out frame loses more
        than :attr:`frame_drop` or the fitted thickness contradicts its measurement
        (:meth:`thickness_contradicted`); "the current model already fits" when nothing is worse but the
        deciding score (the best-pose score) does not rise beyond its noise, unless the re-track
        corroborates the gain (:meth:`corroborated`) or the three scores gain together
        (:meth:`gains_together`).
        """
        ev = self.evidence()
        out = [f"{e.name} worse: {e.describe()}" for e in ev if e.worse]
        if np.isfinite(self.worst_frame_gain) and self.worst_frame_gain < -self.frame_drop:
            out.append(f"one held-out frame loses {-self.worst_frame_gain:.4f} > {self.frame_drop:.4f}")
        if self.thickness_contradicted():
            out.append(
                f"fitted finger thickness {self.fitted_sigma:.3f} below the current {self.current_sigma:.3f} "
                f"while measured {self.measured_sigma:.3f} (the thickness bound: the fit is not the measured hand)"
            )
        if not out:
            flat = [e for e in ev if e.decides and not e.better]
            if flat and (self.corroborated() or self.gains_together()):
                flat = []
            if flat:
                out.append(
                    "the current model already fits: "
                    + "; ".join(f"{e.name} {e.describe()} (within the noise)" for e in flat)
                )
        return out

    @property
    def already_fits(self) -> bool:
        """Nothing worse beyond the noise, and no score that rises beyond it either."""
        f = self.failures()
        return len(f) == 1 and f[0].startswith("the current model already fits")

    @property
    def accepted_by_corroboration(self) -> bool:
        """Accepted only through :meth:`corroborated` or :meth:`gains_together` (the best-pose score
        within its noise)."""
        ev = self.evidence()
        return self.accepted and bool(self.per_frame) and not any(e.better for e in ev if e.decides)

    @property
    def accepted(self) -> bool:
        """Whether the fitted model passes every rule of the guard (:meth:`failures`)."""
        return not self.failures()

    def metadata(self) -> dict[str, float | int | str]:
        """The guard's numbers beyond :func:`~hand_sog_tracker.core.model_io.calibration_metadata`'s.

        Flat extras for the model file: ``guard_rules``, ``holdout_worst_frame_gain``,
        ``guard_frame_drop``, with a width measurement ``measured_finger_mm`` (4 values, index
        .. little), ``measured_knuckle_mm``, ``measured_palm_mm``, ``measured_sigma``,
        ``measured_width`` (those measured) and ``widths_from_measurement`` (0/1), and, with
        detections, ``holdout_tip_frames``,
        ``holdout_tip_current_mm``, ``holdout_tip_fitted_mm`` (reported, not a rule).
        """
        out: dict[str, float | int | str] = {
            "guard_rules": (
                "no evidence worse beyond its noise; best-pose score higher by its noise, or "
                "re-tracked score higher by its noise with best-pose and held-out scores higher by "
                "the margin, or the three scores combined higher by their noise with the best-pose score higher "
                "by the margin; every held-out frame's gain >= -guard_frame_drop; the fitted finger "
                "thickness not below the current one where the depth data show thicker fingers (beyond their noise)"
            ),
            "guard_frame_drop": float(self.frame_drop),
        }
        if self.per_frame:
            out["guard_evidence"] = "; ".join(f"{e.name} {e.describe()}" for e in self.evidence())
        if np.isfinite(self.worst_frame_gain):
            out["holdout_worst_frame_gain"] = float(self.worst_frame_gain)
        if self.measured_finger_mm:
            out["measured_finger_mm"] = " ".join(f"{v:.2f}" for v in self.measured_finger_mm)
            for key in ("measured_knuckle_mm", "measured_palm_mm", "measured_sigma", "measured_width"):
                if np.isfinite(getattr(self, key)):
                    out[key] = float(getattr(self, key))
            out["widths_from_measurement"] = int(self.widths_from_measurement)
        if self.tip_frames:
            out.update(
                holdout_tip_frames=int(self.tip_frames),
                holdout_tip_current_mm=float(self.tip_current),
                holdout_tip_fitted_mm=float(self.tip_fitted),
            )
        return out

    def describe(self) -> str:
        """One line with the numbers, e.g. for a service answer."""
        text = (
            f"held-out score {self.score_current:.4f} (current) -> {self.score_fitted:.4f} (fitted) "
            f"on {self.frames} frames, gain {self.gain:+.4f}, margin {self.margin:.4f}"
        )
        if np.isfinite(self.worst_frame_gain):
            text += f", worst frame {self.worst_frame_gain:+.4f} (limit {-self.frame_drop:+.4f})"
        if self.measured_finger_mm:
            text += (
                f"; measured sigma {self.measured_sigma:.3f}, width {self.measured_width:.3f} "
                f"(knuckle span {self.measured_knuckle_mm:.1f} mm)"
            )
        if self.tip_frames:
            text += (
                f"; fingertip-detection distance {self.tip_current:.2f} -> {self.tip_fitted:.2f} mm "
                f"on {self.tip_frames} frames"
            )
        if np.isfinite(self.independent_frames):
            text += f"; {self.independent_frames:.1f} independent frames"
        if self.per_frame:
            text += "; change (fitted - current): " + ", ".join(
                f"{e.name} {e.describe()}" for e in self.evidence()
            )
        return text


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
        self._args = (shape, validation)
        if validation.already_fits:
            text = f"the current model already fits: {validation.describe()} (fit {shape.describe()} not used)"
        else:
            why = "; ".join(validation.failures()) or "refused"
            text = (
                f"fitted model rejected ({why}), kept the current one: {validation.describe()} "
                f"(fit {shape.describe()})"
            )
        super().__init__(text)

    def __reduce__(self):  # type: ignore[no-untyped-def]
        """Pickle with the constructor's arguments (the fit may run in another process)."""
        return (type(self), self._args)



def validate(
    frames: Sequence[NDArray],
    poses: Sequence[NDArray[np.float64] | None],
    intrinsics: Intrinsics,
    config: TrackerConfig,
    current: HandModel,
    fitted: HandModel,
    margin: float = GUARD_MARGIN,
    frame_drop: float = GUARD_FRAME_DROP,
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
    frame_drop : float
        Largest score loss allowed on any one held-out frame.

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
    scores: list[tuple[float, float]] = []
    tips: list[tuple[float, float]] = []
    per_frame: list[tuple[float, ...]] = []
    re_frames: list[tuple[float, ...]] = []
    carried: list[NDArray[np.float64] | None] = [None, None]
    scored_poses: list[NDArray[np.float64]] = []
    for pre, pose in zip(pres, found):
        if pose is None:
            continue
        fr = _prepare(pre, pose, current, config)
        if fr is None:
            continue
        roi, window = hand_roi(current, fr.pose, pre.intrinsics, config.roi_radius_mm)
        det = detect_fingertips(pre, roi, window)
        sil = silhouette(pre, window, roi) if config.w_sil > 0 else None
        frame_scores, frame_tips, row, re_row = [], [], [], []
        for j, m in enumerate((current, fitted)):
            # The refit from the tracked pose and the re-track (each model follows the held-out
            # frames in order from its own pose on the previous one; on the first frame the
            # refit is its start), as one batch.
            starts = [keep_palm_centre(fr.pose, current, m)] + ([carried[j]] if carried[j] is not None else [])
            refits = _guard_refit(m, np.array(starts), fr.data, config, det, sil)
            th, terms = refits[0]
            frame_scores.append(overlap_score(m, th, fr.scoring, pre.intrinsics, SCORE_TOLERANCE_MM))
            frame_tips.append(_tip_distance(m, th, det))
            row.append((frame_scores[-1], frame_tips[-1], terms.total, coverage(m, th, fr.data),
                        terms.sim, terms.col, terms.sil, terms.sal))
            if len(refits) > 1:
                th, terms = refits[1]
                re_row.append((overlap_score(m, th, fr.scoring, pre.intrinsics, SCORE_TOLERANCE_MM),
                               _tip_distance(m, th, det), terms.total, coverage(m, th, fr.data)))
            carried[j] = th
        per_frame.append(tuple(float(v) for pair in zip(*row) for v in pair))
        scored_poses.append(fr.pose)
        if re_row:
            re_frames.append(tuple(float(v) for pair in zip(*re_row) for v in pair))
        scores.append((frame_scores[0], frame_scores[1]))
        if det.n:
            tips.append((frame_tips[0], frame_tips[1]))
    if not scores:
        raise CalibrationError("no hand in the held-out frames (hold an open hand toward the camera)")
    sc = np.array(scores)
    tp = np.array(tips).reshape(-1, 2)
    return Validation(
        frames=len(scores),
        score_current=float(sc[:, 0].mean()),
        score_fitted=float(sc[:, 1].mean()),
        margin=float(margin),
        worst_frame_gain=float((sc[:, 1] - sc[:, 0]).min()),
        frame_drop=float(frame_drop),
        tip_current=float(tp[:, 0].mean()) if len(tp) else float("nan"),
        tip_fitted=float(tp[:, 1].mean()) if len(tp) else float("nan"),
        tip_frames=len(tp),
        per_frame=tuple(per_frame),
        retrack_frames=tuple(re_frames),
        independent_frames=independent_frames(current, scored_poses),
    )


def independent_frames(model: HandModel, poses: Sequence[NDArray[np.float64]]) -> float:
    """How many independent observations of the hand's pose the frames at ``poses`` are (unitless).

    Each frame after the first adds its largest fingertip displacement (mm, ``model``'s
    fingertips) from the previous frame's pose divided by the mean fingertip radius, at most 1:
    a hand held still shows the same pose on every frame (only sensor noise differs, and the
    guard's per-frame changes agree more than a new pose would let them), a moving hand a new
    pose on each frame further than a fingertip's width.  In [1, len(poses)] (1 for one frame).
    """
    if len(poses) < 2:
        return 1.0
    tips = np.array([fingertips(model, th) for th in poses])  # (n, 5, 3) mm
    moved = np.linalg.norm(np.diff(tips, axis=0), axis=2).max(axis=1)  # (n - 1,) mm
    return float(1.0 + np.minimum(moved / float(model.tip_radii.mean()), 1.0).sum())


#: Columns of :attr:`Validation.per_frame`'s rows, each as (current, fitted): the score, the
#: fingertip-detection distance (mm), the tracking objective and the tracker's coverage at the
#: guard's refit, and the objective's similarity, collision, silhouette and salient terms.
PER_FRAME_COLUMNS = ("score", "tip_mm", "objective", "coverage", "sim", "col", "sil", "sal")
#: Columns of :func:`retrack`'s rows (energy and confidence: the tracker's) and, each as
#: (current, fitted), of :attr:`Validation.retrack_frames`' (there the objective and the
#: coverage at the re-tracked pose).
RETRACK_COLUMNS = ("score", "tip_mm", "energy", "confidence")


def retrack(
    frames: Sequence[NDArray], intrinsics: Intrinsics, config: TrackerConfig, model: HandModel
) -> NDArray[np.float64]:
    """Track ``frames`` in order with a fresh tracker and ``model``; per frame the numbers of
    :data:`RETRACK_COLUMNS`.

    Returns
    -------
    array, shape (n, 4)
        Per frame: :func:`shape_score` at the tracked pose, mean fingertip-detection distance
        there (mm, as :attr:`Validation.tip_current`), the tracker's energy and confidence; NaN
        where the tracker does not report TRACKING.
    """
    mirrored = model.mirrored(config.right_hand)
    tracker = Tracker(config, mirrored)
    out = np.full((len(frames), len(RETRACK_COLUMNS)), np.nan)
    for k, frame in enumerate(frames):
        res = tracker.process(frame, intrinsics)
        if res.status is not TrackerStatus.TRACKING or res.pose is None:
            continue
        pre = preprocess(frame, intrinsics, config)
        fr = _prepare(pre, res.pose, mirrored, config)
        if fr is None:
            continue
        roi, window = hand_roi(mirrored, res.pose, pre.intrinsics, config.roi_radius_mm)
        det = detect_fingertips(pre, roi, window)
        out[k] = (
            overlap_score(mirrored, res.pose, fr.scoring, pre.intrinsics, SCORE_TOLERANCE_MM),
            _tip_distance(mirrored, res.pose, det),
            res.energy,
            res.confidence,
        )
    return out


def _tip_targets(model: HandModel, theta: NDArray[np.float64], det: Detections) -> TipTargets | None:
    """The detections assigned to the fingertips at ``theta`` (as the tracker's salient term, but
    detections of fingers seen end-on count here)."""
    if det.n == 0:
        return None
    return assigned_targets(fingertips(model, theta), det, GUARD_TIP_LAMBDA_MM, end_on=True)


def _tip_distance(model: HandModel, theta: NDArray[np.float64], det: Detections) -> float:
    """Mean distance (mm) of the fingertips at ``theta`` to their assigned detections.

    A fingertip without a detection counts :data:`GUARD_TIP_LAMBDA_MM`; NaN without detections.
    """
    if det.n == 0:
        return float("nan")
    tips = fingertips(model, theta)
    assigned = assign_detections(tips, det, GUARD_TIP_LAMBDA_MM)
    dist = np.linalg.norm(tips - det.points[np.maximum(assigned, 0)], axis=1)
    return float(np.where(assigned >= 0, dist, GUARD_TIP_LAMBDA_MM).mean())


def _guard_refit(
    model: HandModel,
    starts: NDArray[np.float64],
    data: ImageSoG,
    config: TrackerConfig,
    det: Detections,
    sil: Silhouette | None,
) -> list[tuple[NDArray[np.float64], EnergyTerms]]:
    """The guard's pose refits of one held-out frame with ``model``, as the tracker fits a frame.

    From each start pose of ``starts`` (k, 26): :data:`GUARD_RIGID_ITERATIONS` global-pose
    iterations, then :data:`GUARD_REFIT_ITERATIONS` full ones in two halves with the tracker's
    salient (fingertip detections, re-assigned to each fit before each half) and silhouette
    terms.  The k fits run as one batch (:func:`maximise_batch`: the iterates of one fit each).
    Returns per start the pose (26,) and the tracking objective's terms there (the second
    half's objective).
    """
    starts = np.atleast_2d(np.asarray(starts, dtype=np.float64))
    obj = Objective(model, data, config, silhouette=sil)
    ths = np.array([r.x for r in maximise_batch(obj.batch, starts, iterations=GUARD_RIGID_ITERATIONS, active=_RIGID)])
    half = max(GUARD_REFIT_ITERATIONS // 2, 1)
    targets: list[TipTargets | None] = []
    for _ in range(2):
        targets = [_tip_targets(model, th, det) for th in ths]
        fits = maximise_batch(with_targets(obj, targets), ths, iterations=half, with_index=True)
        ths = np.array([r.x for r in fits])
    return [(th, obj.variant(config, t).evaluate(th, gradient=False)[0]) for th, t in zip(ths, targets)]


