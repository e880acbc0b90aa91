"""Frame-to-frame hand tracker: depth in, 26-DOF pose and fingertips out.

One job: one frame's tracking (data near the hand, fit, restarts, loss) and the two-stage
initialisation; kept together because both share the track's state (last poses, step lengths,
the pending search); the restarts are in :mod:`.restarts`, the start poses in :mod:`.initialise`.

Units: depth images and every position in millimetres, camera optical frame
(x right, y down, z forward); angles in radians.

Per frame (paper 000, sec. 5): preprocess and cluster the depth near the last
hand position into Gaussians, start from the pose extrapolated from the last
two frames, and run the adaptive gradient ascent on the objective.  When there
is no track yet (first frame, or after a loss) the tracker finds the hand in
the depth by itself and tries several starting poses (see :mod:`.initialise`).
After each frame's fit the restart strategies of :mod:`.restarts` (a mixin of
:class:`Tracker`) try ways out of local optima.  A frame whose hand has a curled finger
answers with its fit refined on a model with Gaussians on the finger joints (see
``REFINE_CURL_RAD``); the track goes on from the fit.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, leaf_px, preprocess, quadtree_sog
from hand_sog_tracker.core.energy import Objective, TipTargets, contact_shares, gaussian_support
from hand_sog_tracker.core.hand_model import (
    FINGER_MCP,
    FINGER_PIP,
    HandModel,
    HandShape,
    default_hand_model,
)
from hand_sog_tracker.core.initialise import (
    INIT_SEARCH,
    HandBlob,
    InitFinalists,
    best_combination,
    detection_direction,
    find_hand,
    initial_hypotheses,
)
from hand_sog_tracker.core.kinematics import (
    fingertips,
    gaussian_centres,
    global_rotation,
    posed_centres,
    skeleton_points,
)
from hand_sog_tracker.core.optimizer import OptimizeResult, Steps, StepSizes, maximise, maximise_steps, run
from hand_sog_tracker.core.restarts import (
    ASSIGN_LAMBDA_MM,
    RestartStrategies,
    ShiftCandidate,
)
from hand_sog_tracker.core.salient import Detections, assigned_targets, detect_fingertips
from hand_sog_tracker.core.silhouette import Silhouette, silhouette
from hand_sog_tracker.core.types import (
    Intrinsics,
    TrackerConfig,
    TrackerStatus,
    TrackResult,
)

__all__ = ["Tracker", "before_surface", "coverage", "hand_roi"]

# Tuning constants.  Each says what it is, its unit and where its value comes from: "paper 000"
# (the tracker's paper), "seed 001/004" (the salient-point and restart papers) or "chosen
# here" (set while developing this package against the synthetic bag sets; commit noted
# where the value was last changed).  They are module constants, not TrackerConfig fields
# (which become ROS parameters), because none is meant to be tuned per camera or user.
# The restarts' constants (RESTART_TIP_MM, ASSIGN_LAMBDA_MM, ...) are in :mod:`.restarts`.

#: Velocity extrapolation factor of the start pose (unitless; paper 000 sec. 5.3: alpha = 0.5).
ALPHA = 0.5
#: Warm start of the step lengths (unitless; chosen here): a tracked frame starts from the
#: previous frame's final step lengths times ``WARM_GROW``, kept within ``[WARM_MIN, 1]`` x
#: the optimiser's initial ones.  Parameters that settled start with small steps (a fresh
#: start overshot in the first iterations of most frames: the best pose came only in the last
#: iterations), parameters that keep moving keep theirs.  With it 7 iterations per frame
#: track better than 10 without (dev renders 7.1 against 7.3 mm mean error).
WARM_GROW = 2.0
WARM_MIN = 0.1
#: A tracked frame's fit still climbing after ``iterations`` gets up to this many more, one at
#: a time while the last raised the objective by more than ``EXTRA_GAIN x |E(start)|`` (count,
#: unitless; chosen here: fast rotations at 640x480 outran 7 iterations, 8.8 mm against 7.6
#: with the previous release; with it 7.2 mm, at 5-8% more time per frame).
EXTRA_ITERATIONS = 3
EXTRA_GAIN = 0.002
# The initialisation's effort (iterations, hypotheses kept, finalists) is
# :data:`hand_sog_tracker.core.initialise.INIT_SEARCH`.
#: Data farther than this beyond the wrist plane are treated as forearm (mm; chosen here: 0,
#: the model has no forearm).
WRIST_MARGIN_MM = 0.0
#: A tracked frame's depth window ends this far behind the farthest Gaussian centre of its
#: start pose (mm; chosen here), or ``roi_radius_mm`` behind the hand's centre when that is
#: nearer: a wall or a table top closer behind the hand than the window's half depth would
#: otherwise be data, and the silhouette of the window would be the whole image.
WINDOW_BEHIND_MM = 70.0
#: ... and before a surface behind the hand (:func:`before_surface`; chosen here): the first
#: ``SURFACE_SLICE_MM`` slice of depths, from ``SURFACE_SEARCH_MM`` behind the farthest Gaussian
#: centre on, whose pixels in the hand's region of interest cover more than
#: ``SURFACE_SLICE_MM2`` ends it ``SURFACE_MARGIN_MM`` before that slice.  A wall or a table top
#: fills one slice over the whole region (a fronto-parallel wall about 0.07 m^2); a forearm
#: receding from the hand a strip of it (60 mm wide, 25-50 mm long per 15 mm of depth).  On
#: the first 24 dev and 24 validation mesh renders (automatic calibration) with a wall 50 mm
#: behind the wrist, the wall lay inside the 70 mm window: 16.6 and 16.3 mm mean error
#: (with :data:`~hand_sog_tracker.core.initialise.SURFACE_GAP_SHARES`), 8.0 and 10.9 mm with
#: it; a fixed 35 mm window did as well there (7.0 / 10.9) but moved renders of a rotating hand
#: without a wall both ways (seeds 7000-7095: 5.86 -> 5.94 mm).
SURFACE_SEARCH_MM = 15.0
SURFACE_SLICE_MM = 15.0
SURFACE_SLICE_MM2 = 5000.0
SURFACE_MARGIN_MM = 5.0
#: Bin width (mm) of :func:`before_surface`'s depth histogram.
_SURFACE_BIN_MM = 5.0
#: The initialisation's search window (and its finish's) ends this far behind the hand blob's
#: farthest surface pixel (mm; chosen here: depth noise at the blob's edge), when that is nearer
#: than ``roi_radius_mm`` behind the start poses' centre.
BLOB_BEHIND_MM = 20.0
#: Whether detections of fingers seen end-on (knuckles of a fist look the same) pull
#: fingertips (chosen here: off; they only seed the curled restart candidates).
SALIENT_END_ON = False
#: The refinement of a tracked frame's answer (issue 11; chosen here): when a finger's PIP is
#: flexed over ``REFINE_CURL_RAD`` (rad), the answer is the track's pose refined
#: ``TrackerConfig.refine_iterations`` (2) iterations on the objective of the model with joint
#: Gaussians (:meth:`HandModel.with_joint_gaussians`); the track goes on from its own pose.
#: The tracking model covers a bent joint's outer corner only with the tails of its segments'
#: Gaussians, and its fit opens curled fingers into claws (dev renders: curled MCPs -12.4 deg,
#: curled fingertips 11.3 mm off against 5.4 for open ones); tracking on the joint model
#: removes most of that but loses fingers on the labelled real frames (112 runs: 9.45 -> 14.3
#: mm), where its restarts and initialisation choose worse.  Refining only the answer keeps
#: the track's choices.  From the track's pose, 4 iterations gained as much as 6 on the dev
#: renders (curled fingertips 9.9 mm); from the frame before's correction 2 do
#: (``REFINE_WARM_STEPS``).  Gated on MCP + PIP over 60 deg instead, real frame 3's ring
#: finger (curled toward the camera, MCP 58 and PIP 53 deg) was refined 6 mm further off;
#: without a gate open fingertips lost 0.2 mm.
REFINE_CURL_RAD = math.radians(60.0)
#: When the frame before was refined too and the track went on from its pose (no restart
#: replaced it), the refinement starts from the track's pose plus that frame's correction
#: (answer - track pose), clipped to the limits, with its warm step lengths times this factor
#: (unitless; chosen here, issue 14).  The correction changes little from frame to frame (the
#: joint Gaussians straighten the same claw), so the refinement starts near its end: 2
#: iterations from there do as well as 4 from the track's pose (mesh sets, mean error: dev
#: 5.801 -> 5.790 without 3071, whose automatic fit was no longer accepted, 6.4 -> 11.3 mm;
#: validation 5.913 -> 5.878, further 5.822 -> 5.801 mm) at half the cost.  After a restart won
#: on the frame before, the refinement starts from the fit's pose.
REFINE_WARM_STEPS = 0.5
#: Whether the refinement weights each joint-model Gaussian's overlaps by its visibility at the
#: fit's pose (:func:`~hand_sog_tracker.core.energy.visibility_weights`: the palm behind the
#: fingers and the fingertips tucked behind their middle segments or the thumb count less;
#: issue 11, chosen here).  In a fist facing the camera the hidden palm and fingertips
#: otherwise earn overlap with the fingers' surface in front of them, and the fit settles with
#: the MCPs half flexed and the fingertips 15-20 mm in front of where they are.  Only the
#: answer: with the visibility in the track's own fits (weighted at the start pose, the
#: thumb not an occluder) and in its restarts, the mesh sets scored about as well (dev 5.56,
#: validation 5.65, further 5.71 mm) but the labelled real frames lost 4 runs more (112 runs:
#: 8.30 -> 9.40 mm), where a wrong finger curled over the palm hides the palm's data from it
#: and holds its place.
REFINE_VISIBILITY = True
#: A tracker on its default model (none given, none set since) starts every track by also
#: fitting the initialisation's finalists with the default model scaled to this length factor
#: (unitless; chosen here, issue 11), and tracks with it when its best finalist scores
#: ``SMALL_HAND_GAIN`` higher (:meth:`RestartStrategies._score`, unitless) than the default
#: model's.  The default model's fingers are too long for a small hand, and a too long model
#: finger explains the next longer finger's data better than its own: small hands started with
#: the fingers one place over, for 8-10 frames, until a finger shift caught it.  The scores
#: rise as the model shrinks on most hands (144 mesh dev renders, first frame: the 0.85 model
#: scored 0.069 above the default on average on hands of length 0.79-0.83, 0.068 on 0.83-0.87,
#: 0.044 on 0.87-0.91, 0.025 on 0.91-0.95, 0.003 on 0.95-1.0 and -0.028 on larger ones; over
#: 0.04 on 16 of 17, 19 of 22, 8 of 17, 4 of 25 and none of the 63 others), hence a margin
#: rather than the best score.  (0.03: dev renders 5.79 -> 5.71 mm, but labelled real frame 4,
#: whose objective prefers its fingers one place over, went so in 4 of 14 runs instead of 2:
#: 8.28 -> 8.86 mm over the 112 runs.)  Only between two fits of open fingers (``SMALL_HAND_MAX_FLEX``:
#: mean MCP + PIP flexion of index .. little, rad, as the calibration's open frames): curled
#: fingers do not show their length, and a fist seen from the back (labelled real frame 7) or a
#: hand with a finger curled toward the camera (frame 2) scored 0.04-0.09 higher on the small
#: model with its fingers opened onto the knuckles (the 112 runs of the labelled real frames
#: 8.28 -> 10.58 mm without this rule).  The automatic calibration
#: then starts from the model in use.
SMALL_HAND_LENGTH = 0.85
SMALL_HAND_GAIN = 0.04
SMALL_HAND_MAX_FLEX = 0.6
#: The small model is tried on this many of the finalists, the default model's best by score
#: (count; issue 14: the finalists are 2 or 3, each fit about 6 ms).  On 180 starts of mesh dev
#: renders (frames 0, 20 and 40) where the small model was tried on all, its best was the
#: default's best finalist 127 times and its second 53 times, never the third.
SMALL_HAND_FINALISTS = 2
_INITIAL_STEPS = StepSizes().expand(StepSizes().initial)


def coverage(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ImageSoG,
    centres: NDArray[np.float64] | None = None,
    support: NDArray[np.float64] | None = None,
) -> float:
    """How well the data explain the model at ``theta``, in [0, 1].

    The mean :func:`gaussian_support` over the best-supported two thirds of
    the Gaussians (the rest may be legitimately occluded).  ``support``: that support (m,),
    when already known (:meth:`Objective.support`).
    """
    if support is None:
        support = gaussian_support(model, theta, data, centres)
    support = np.sort(support)[::-1]
    keep = max(1, (2 * support.size) // 3)
    return float(np.add.reduce(support[:keep]) / keep)  # (= .mean(), without its Python layer)


def hand_roi(
    model: HandModel,
    theta: NDArray[np.float64],
    intr: Intrinsics,
    radius_mm: float,
    centres: NDArray[np.float64] | None = None,
) -> tuple[tuple[int, int, int, int], tuple[float, float]]:
    """Pixel box and depth window around the hand at ``theta`` (``centres``: its
    :func:`posed_centres`, shape (m, 3) mm, when already computed).

    Returns
    -------
    roi : (u0, v0, u1, v1)
        End-exclusive pixel box at the resolution of ``intr``.
    window : (near_mm, far_mm)
    """
    P = posed_centres(model, theta) if centres is None else centres
    c = np.add.reduce(P, axis=0) / P.shape[0]  # (= P.mean(axis=0), without its Python layer)
    z = max(c[2], 50.0)
    # The centre's pixel as Intrinsics.project computes it, by Python floats (the same IEEE
    # operations in the same order).
    x, y, zc = c.tolist()
    u, v = intr.fx * x / zc + intr.cx, intr.fy * y / zc + intr.cy
    r_px = radius_mm * max(intr.fx, intr.fy) / max(z - radius_mm * 0.5, 50.0)
    roi = (
        math.floor(u - r_px),
        math.floor(v - r_px),
        math.ceil(u + r_px) + 1,
        math.ceil(v + r_px) + 1,
    )
    return roi, (c[2] - radius_mm, c[2] + radius_mm)


def before_surface(
    depth_mm: NDArray[np.float32], intr: Intrinsics, roi: tuple[int, int, int, int], start_mm: float, end_mm: float
) -> float:
    """Where a depth window ending at ``end_mm`` should end instead, before a surface behind the
    hand (a wall, a table top): see :data:`SURFACE_SLICE_MM2`.

    Parameters
    ----------
    depth_mm : array, shape (H, W), float32
        Depth (mm, 0 invalid) at the resolution of ``intr``.
    intr : Intrinsics
    roi : (u0, v0, u1, v1)
        The hand's pixel box (:func:`hand_roi`; clipped to the image here).
    start_mm, end_mm : float
        The depths searched (mm): from ``start_mm`` (behind the hand) to ``end_mm``.

    Returns
    -------
    float
        ``SURFACE_MARGIN_MM`` before the nearest slice of ``SURFACE_SLICE_MM`` whose pixels (every
        second row and column, counted four times) cover more than ``SURFACE_SLICE_MM2`` at
        their depth, but not before ``start_mm``; ``end_mm`` when there is none.
    """
    h, w = depth_mm.shape
    sub = depth_mm[max(roi[1], 0) : min(roi[3], h) : 2, max(roi[0], 0) : min(roi[2], w) : 2]
    behind = sub[(sub > start_mm) & (sub <= end_mm)]
    if behind.size == 0:
        return end_mm
    per_bin = _SURFACE_BIN_MM
    n_bins = int(math.ceil((end_mm - start_mm) / per_bin))
    counts = np.bincount(
        np.minimum(((behind - start_mm) // per_bin).astype(np.int64), n_bins - 1), minlength=n_bins
    ).astype(np.float64)
    z = start_mm + per_bin * (np.arange(n_bins) + 0.5)
    area = counts * (4.0 * z * z / (intr.fx * intr.fy))  # mm^2 (each counted pixel stands for 4)
    k = int(round(SURFACE_SLICE_MM / per_bin))
    slices = np.convolve(area, np.ones(k))[k - 1 :]  # slices[i]: bins i .. i + k - 1
    hit = np.flatnonzero(slices > SURFACE_SLICE_MM2)
    if hit.size == 0:
        return end_mm
    return max(start_mm, start_mm + per_bin * float(hit[0]) - SURFACE_MARGIN_MM)


def _back_toward(theta: NDArray[np.float64]) -> bool:
    """Whether the back of the hand at ``theta`` faces the camera (the palm normal, hand z,
    points away from it): the side of a start pose (:func:`_balanced`)."""
    return bool(global_rotation(theta)[2, 2] > 0)


def _open(theta: NDArray[np.float64]) -> bool:
    """Whether the fingers (index .. little) at ``theta`` are open enough to tell a hand's size:
    mean MCP + PIP flexion under ``SMALL_HAND_MAX_FLEX``."""
    return float(np.mean(theta[FINGER_MCP] + theta[FINGER_PIP])) < SMALL_HAND_MAX_FLEX


def _size_models(right: bool) -> tuple[HandModel, HandModel]:
    """The default model of this handedness and the same scaled to ``SMALL_HAND_LENGTH``."""
    default = default_hand_model(right)
    return default, default.scaled(HandShape(length=SMALL_HAND_LENGTH))


def _balanced(ranked: list[tuple], n: int) -> list[tuple]:
    """The first ``n`` of ``ranked`` (best first, last item: which way the palm faces), half
    of them from each side while both have enough (the rigid fit's objective prefers the
    back of a hand to a palm it cannot yet articulate: keep both until articulated)."""
    chosen: list[int] = []
    for side in (True, False):
        chosen += [k for k, a in enumerate(ranked) if a[-1] == side][: (n + 1) // 2 if side else n // 2]
    chosen += [k for k in range(len(ranked)) if k not in chosen][: max(0, n - len(chosen))]
    return [ranked[k] for k in sorted(chosen)]


class Tracker(RestartStrategies):
    """Tracks one hand through a depth sequence.

    Parameters
    ----------
    config : TrackerConfig, optional
    model : HandModel, optional
        Hand model (mm), kept as given; default: the default adult hand of
        ``config.right_hand``, on which every new track may start the smaller hand of
        ``SMALL_HAND_LENGTH`` instead (until :meth:`set_model`).
    """

    def __init__(self, config: TrackerConfig | None = None, model: HandModel | None = None) -> None:
        self._config = config or TrackerConfig()
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
        self._frame_count = 0
        self._restart_wait = 0  # frames to skip the detection-triggered restarts
        self._curl_wait = 0  # rounds of the restarts to skip the curl restarts
        self._shift_pending: ShiftCandidate | None = None

    #: (model, low, high) of :meth:`_maximise`: the joint limits as bounds (26,) each, read-only.
    _bounds: tuple[HandModel, NDArray[np.float64], NDArray[np.float64]] | None = None
    #: (tracking model, its :meth:`HandModel.with_joint_gaussians`) of :meth:`_refined`.
    _joint_model: tuple[HandModel, HandModel] | None = None
    #: (track pose, answer) (26,) each of the frame before, when it was refined to its end
    #: (:meth:`_refined`).
    _refine_last: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

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
        """Use another hand model (e.g. after calibration); keeps the track."""
        self._model = model.mirrored(self._config.right_hand)
        self._sizes = None
        self._shift_pending = None

    def set_config(self, config: TrackerConfig) -> None:
        """Change the configuration; a handedness change also resets the track."""
        if config.right_hand != self._config.right_hand:
            self._model = self._model.mirrored(config.right_hand)
            if self._sizes is not None:
                self._sizes = _size_models(config.right_hand)
            self.reset()
        self._config = config

    def reset(self) -> None:
        """Forget the track: the next frame initialises from scratch."""
        self._prev = None
        self._low_frames = 0
        self._status = TrackerStatus.NO_HAND

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
        t0 = time.perf_counter()
        cfg = self._config
        pre = preprocess(depth_mm, intrinsics, cfg)  # raises before any change of this frame's state
        t1 = time.perf_counter()
        if self._prev is not None:
            result = self._track(pre)
        else:
            self._steps = None  # a new track starts with fresh step lengths
            self._shift_pending = None
            self._restart_wait = 0
            self._curl_wait = 0
            if self._sizes is not None:
                self._model = self._sizes[0]  # (a new track on the default model: its size is chosen again)
            result = self._initialise(pre)
        t2 = time.perf_counter()
        result.timings_ms["preprocess"] = (t1 - t0) * 1e3
        result.timings_ms.setdefault("quadtree", 0.0)
        result.timings_ms["optimise"] = (t2 - t1) * 1e3 - result.timings_ms["quadtree"]
        result.timings_ms["total"] = (t2 - t0) * 1e3
        return result

    # -- internals -----------------------------------------------------------
    def _data_near(
        self,
        pre: Preprocessed,
        theta: NDArray[np.float64],
        detect: bool = False,
        outline: bool = True,
        end_mm: float | None = None,
        roi_window: tuple[tuple[int, int, int, int], tuple[float, float]] | None = None,
    ) -> tuple[ImageSoG, Detections, Silhouette | None]:
        """Data Gaussians around the hand at ``theta``, without the forearm.

        Quads beyond the wrist (more than ``WRIST_MARGIN_MM`` on the arm side of
        the plane through the wrist normal to the hand's long axis) are
        dropped: the model has no forearm, and forearm data would pull the palm
        down the arm.  With ``detect``, also the fingertip detections in the same
        region (used by the salient term and the restarts), else none; and with
        ``outline`` the silhouette of the depth in the same depth window (None
        without it or when ``w_sil`` is 0).  With ``end_mm`` the depth window ends there at the
        latest (mm): a wall or a table top behind the hand is then no data, and the silhouette
        of the window is the hand's.  ``roi_window``: :func:`hand_roi` at ``theta`` when already
        computed.
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
            det = detect_fingertips(pre, roi, window)
            if det.n:
                along = (det.points - theta[:3]) @ axis
                det = det.subset(along > -WRIST_MARGIN_MM)
        data = quadtree_sog(pre, self._config.quadtree_threshold_mm, roi, window, leaf)
        if data.n == 0:
            return data, det, sil
        along = (data.points - theta[:3]) @ axis
        keep = along > -WRIST_MARGIN_MM
        return (data if keep.all() else data.subset(keep)), det, sil

    def _targets(self, theta: NDArray[np.float64], det: Detections) -> TipTargets | None:
        """Detections assigned to the fingertips at ``theta`` (seed 001, Table 1)."""
        if det.n == 0:
            return None
        return assigned_targets(fingertips(self._model, theta), det, ASSIGN_LAMBDA_MM, SALIENT_END_ON)

    def _track(self, pre: Preprocessed) -> TrackResult:
        cfg = self._config
        assert self._prev is not None
        p1, p2 = self._prev
        # The paper prints Theta_{t-1} + alpha Theta_{t-2}; we read it as a
        # constant-velocity extrapolation damped by alpha.
        x0 = p1 + ALPHA * (p1 - p2)
        tq = time.perf_counter()
        start_centres = posed_centres(self._model, x0)
        far = float(np.max(start_centres[:, 2]))
        roi_window = hand_roi(self._model, x0, pre.intrinsics, cfg.roi_radius_mm, start_centres)
        end = before_surface(
            pre.depth_mm, pre.intrinsics, roi_window[0], far + SURFACE_SEARCH_MM, far + WINDOW_BEHIND_MM
        )
        data, det, sil = self._data_near(pre, x0, detect=True, end_mm=end, roi_window=roi_window)
        tq2 = time.perf_counter()
        targets = self._targets(x0, det)
        obj = Objective(
            self._model, data, cfg, previous=(p1, p2), targets=targets, silhouette=sil, contact=contact_shares(p1)
        )
        base = _INITIAL_STEPS
        # (np.clip's values by two ufunc calls, without its wrapper.)
        start = base if self._steps is None else np.minimum(np.maximum(self._steps * WARM_GROW, base * WARM_MIN), base)
        res = self._maximise(
            obj, x0, iterations=cfg.iterations, initial_steps=start,
            extra_iterations=EXTRA_ITERATIONS, extra_gain=EXTRA_GAIN,
        )
        self._steps = res.steps if WARM_GROW > 0 else None
        fit = res
        res = run(self._restarts(obj, res, data, det))
        centres = gaussian_centres(self._model, res.x)
        conf = coverage(self._model, res.x, data, centres, obj.support(res.x))
        if conf < cfg.lost_confidence:
            self._low_frames += 1
        else:
            self._low_frames = 0
        if self._low_frames >= cfg.lost_frames or data.n == 0:
            self._prev = None
            self._low_frames = 0
            self._status = TrackerStatus.LOST
            return self._result(None, conf, res.fun, data.n, {"quadtree": (tq2 - tq) * 1e3})
        self._prev = (res.x, p1)
        self._status = TrackerStatus.TRACKING
        answer = self._refined(obj, res, p1)
        if res is not fit:
            # A restart won: the next frame's refinement starts from its fit's pose.
            self._refine_last = None
        if answer is not res.x:
            centres = gaussian_centres(self._model, answer)
        return self._result(answer, conf, res.fun, data.n, {"quadtree": (tq2 - tq) * 1e3}, centres)

    def _refined(self, obj: Objective, res: OptimizeResult, p1: NDArray[np.float64]) -> NDArray[np.float64]:
        """The answer of a tracked frame whose fit is ``res`` on ``obj``: ``res.x`` (26,), or,
        when a finger's PIP is flexed over ``REFINE_CURL_RAD``, ``res.x`` refined
        ``refine_iterations`` iterations on the same frame's objective with the joint model
        (see ``REFINE_CURL_RAD``), from the fit's last step lengths warmed as a tracked
        frame's are; from ``res.x`` plus the frame before's correction when that frame was
        refined and the track went on from its pose ``p1`` (26,) (``REFINE_WARM_STEPS``);
        the overlaps weighted by their visibility at ``res.x`` (``REFINE_VISIBILITY``).
        ``res.x`` also when :attr:`refine_stop` says stop, before or after any iteration of
        the refinement."""
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

    def _fit(self, obj: Objective, x0: NDArray[np.float64], **kwargs: object) -> Steps[OptimizeResult]:
        """:meth:`_maximise` that pauses after every iteration (:func:`maximise_steps`)."""
        return maximise_steps(obj, x0, bounds=self._limits(), **kwargs)  # type: ignore[arg-type]

    def _limits(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The model's joint limits as bounds (low, high), shape (26,) each, read-only
        (computed once per model: several fits per frame)."""
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
        """Find the hand when there is no track (first frame, after a loss): the search
        (:meth:`_init_search`) and its finish (:meth:`_init_finish`) on this frame."""
        found = self._init_search(pre)
        if found is None:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, 0.0, 0.0, 0, {})
        return self._init_finish(pre, found)

    def _init_search(self, pre: Preprocessed) -> InitFinalists | None:
        """First stage: the finalist poses (26,) for the hand in ``pre``, best first, or None.

        One quadtree (coarse) and one detection pass around the palm serve every start pose;
        each pose drops the data beyond its own wrist.  No silhouette term while the poses
        are still far off: it would pull them into the outline before the depth has placed
        them (a hand flipped palm-for-back has the same outline).  When the best start pose
        scores poorly, the curled-finger combinations (:func:`finger_combinations`) are tried
        too (``INIT_SEARCH.combination_below``, about 15 ms more; with
        :attr:`split_initialisation` at the start of the second stage, see
        :attr:`InitFinalists.rest`).
        """
        cfg, eff = self._config, INIT_SEARCH
        blob = find_hand(pre, cfg)
        if blob is None:
            return None
        starts = initial_hypotheses(self._model, blob, cfg.init_hypotheses)
        roi, window = hand_roi(self._model, starts[0], pre.intrinsics, cfg.roi_radius_mm)
        # (The leaves follow the window's centre; the window ends behind the blob: what lies
        # farther was cut off as a body or a wall.)
        fine_px = leaf_px(cfg.min_quad_px, 0.5 * (window[0] + window[1]), pre.intrinsics)
        window = (window[0], min(window[1], blob.far_mm + BLOB_BEHIND_MM))
        coarse = quadtree_sog(pre, cfg.quadtree_threshold_mm, roi, window, max(eff.coarse_quad_px, cfg.min_quad_px))
        # (The coarse data keep their leaves for a far hand too: the search was tuned on them.)
        fine = quadtree_sog(pre, cfg.quadtree_threshold_mm, roi, window, fine_px)
        det = detect_fingertips(pre, roi, window)
        if det.n:
            det = det.subset(self._on_hand_side(det.points, starts[0]))
        n_blob = len(starts)
        # Open hands along the hand end's own axis and toward the detections, palm toward and
        # away (issue 11: a wrist bent sideways turns the blob's axis off the hand's).
        for d in (blob.hand_direction, detection_direction(blob, det.points)):
            if d is not None:
                starts += initial_hypotheses(self._model, HandBlob(blob.palm, [d]), 2)
        rigid = np.zeros(starts[0].size, dtype=bool)
        rigid[:6] = True

        def align(i: int, x0: NDArray[np.float64], data: ImageSoG) -> tuple[float, int, NDArray[np.float64], bool]:
            """Rigid alignment (seed 004's coarse-to-fine: before the articulation)."""
            res = self._maximise(
                Objective(self._model, data, cfg), x0,
                iterations=eff.rigid_iterations, initial_scale=2.0, active=rigid,
            )
            return res.fun, -i, res.x, _back_toward(x0)

        def articulate(kept: list[tuple[float, int, NDArray[np.float64], bool]]) -> list[tuple[float, int, NDArray]]:
            """(score, rank, pose) of each kept pose articulated on the fine data."""
            out = []
            for _, rank, x, _ in kept:
                data = self._hand_side(fine, x)
                if data.n == 0:
                    continue
                obj = Objective(self._model, data, cfg)
                res = self._maximise(obj, x, iterations=eff.full_iterations, initial_scale=2.0)
                # :meth:`_score` without evaluating the objective again (no salient term here).
                out.append((res.fun - cfg.w_sal * self._assignment_cost(res.x, det, hidden_tips=False), rank, res.x))
            return out

        parts = [self._hand_side(coarse, x0) for x0 in starts]
        screened = self._screened(starts[:n_blob], parts[:n_blob], eff.screened)
        aligned = [
            align(i, x0, data)
            for i, (x0, data) in enumerate(zip(starts, parts))
            if (i >= n_blob or i in screened) and data.n
        ]
        # The blob's start poses compete for ``kept``; the best of the hand axis' and the
        # detection direction's is articulated besides them (taking a slot, the detection
        # direction's had displaced the right pose of a far hand whose detections missed two
        # fingers).
        blob_aligned = [a for a in aligned if -a[1] < n_blob]
        kept = _balanced(sorted(blob_aligned, key=lambda a: a[:2], reverse=True), eff.kept)
        if len(blob_aligned) < len(aligned):
            kept.append(max((a for a in aligned if -a[1] >= n_blob), key=lambda a: a[:2]))
        scored = articulate(kept)
        if not scored:
            return None
        scored.sort(key=lambda s: s[:2], reverse=True)

        def finalists() -> list[NDArray[np.float64]]:
            """The finalist poses (26,), best first, after the curled-finger combinations when
            the best pose scores poorly (the search's last step)."""
            ranked = scored
            if ranked[0][0] < eff.combination_below:
                # A poor best: maybe a hand found mid-motion, some fingers curled and others not
                # (issue 11).  From the open hands of the blob's main direction (palm toward and
                # away), the combination of curled fingers that scores best at its start pose on
                # each palm side is aligned and articulated; they replace the others only when the
                # best of them scores higher by ``combination_margin``.
                n = len(starts)
                combos = []
                for k, (x0, part) in enumerate(zip(starts[:2], parts)):
                    if part.n:  # (the start's data serve every combination: the same wrist)
                        screen = Objective(self._model, part, cfg)
                        best = best_combination(x0, lambda c, s=screen: s(c, gradient=False)[0])
                        combos.append(align(n + k, best, part))
                tried = sorted(articulate(combos), key=lambda s: s[:2], reverse=True)
                if tried and tried[0][0] >= ranked[0][0] + eff.combination_margin:
                    ranked = sorted(ranked + tried, key=lambda s: s[:2], reverse=True)
            # The best of the other palm side joins the finalists when none of them has it: the
            # search scores without the silhouette, so a hand flipped palm-for-back can score
            # highest there, and the finish's full objective tells the two apart (issue 11: a
            # finger counting hand found mid-motion, index and thumb out, ended with its thumb on
            # the little finger's side).
            poses = [x for _, _, x in ranked[: eff.finalists]]
            sides = {_back_toward(x) for x in poses}
            return poses + [x for _, _, x in ranked if _back_toward(x) not in sides][:1]

        return InitFinalists(poses=finalists(), end_mm=blob.far_mm + BLOB_BEHIND_MM)

    def _screened(self, starts: list[NDArray[np.float64]], parts: list[ImageSoG], n: int) -> set[int]:
        """Indices of the ``n`` start poses (26,) of ``starts`` with the palm toward the camera
        and the ``n`` with its back toward it that score best by the objective on their data
        ``parts`` (each start's :meth:`_hand_side`) at the start pose itself (one evaluation
        each, no gradient; the first on a tie)."""
        scored = []
        for i, (x0, part) in enumerate(zip(starts, parts)):
            value = Objective(self._model, part, self._config)(x0, gradient=False)[0] if part.n else -np.inf
            scored.append((value, -i, _back_toward(x0)))
        chosen: set[int] = set()
        for side in (True, False):
            chosen.update(-s[1] for s in sorted((s for s in scored if s[2] == side), reverse=True)[:n])
        return chosen

    def _init_finish(self, pre: Preprocessed, found: InitFinalists) -> TrackResult:
        """Second stage: refine the finalists ``found`` on ``pre``; the track starts from the best.

        One data extraction (quadtree, detections, silhouette) around the first finalist serves
        all, in a depth window that ends where the search's did at the latest (behind the hand
        blob: a wall there was data, and the silhouette the whole image); each finalist gets
        ``final_iterations`` with the full objective, the best by score gets the finger and
        (forced) finger-shift restarts, then the lateral restarts (:meth:`_lateral_restarts`,
        about 75 objective evaluations: with :attr:`defer_restarts` after the answer, as a
        tracked frame's restarts).  The detection restarts are left to the tracked frames that
        follow.  On the default model its best ``SMALL_HAND_FINALISTS`` finalists are also refined
        on the small model, which the track starts on when it scores ``SMALL_HAND_GAIN`` higher
        with open fingers.
        """
        cfg = self._config
        poses = found.poses
        tq = time.perf_counter()
        data, det, sil = self._data_near(pre, poses[0], detect=True, end_mm=found.end_mm)
        timings = {"quadtree": (time.perf_counter() - tq) * 1e3}
        if data.n == 0:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, 0.0, 0.0, 0, timings)
        fits = self._finalist_fits(poses, data, det, sil)
        best = fits[0][1] if fits else None
        if best is not None and self._sizes is not None and _open(best[1].x):
            default = self._model
            self._model = self._sizes[1]
            tried = sorted(k for k, _ in fits[:SMALL_HAND_FINALISTS])  # (in the finalists' order)
            small_fits = self._finalist_fits([poses[k] for k in tried], data, det, sil)
            small = small_fits[0][1] if small_fits else None
            if small is not None and small[0] > best[0] + SMALL_HAND_GAIN and _open(small[1].x):
                best = small
            else:
                self._model = default
        if best is None:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, 0.0, 0.0, 0, timings)
        _, res, data, obj = best
        res = run(self._finger_restarts(obj, res, data))
        res = run(self._shift_restarts(obj, res, det, force=True))
        res = run(self._lateral_restarts(obj, res, det))
        conf = coverage(self._model, res.x, data)
        if conf < cfg.lost_confidence:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, conf, res.fun, data.n, timings)
        self._prev = (res.x, res.x)
        self._low_frames = 0
        self._status = TrackerStatus.TRACKING
        return self._result(res.x, conf, res.fun, data.n, timings)

    def _finalist_fits(
        self, poses: list[NDArray[np.float64]], data: ImageSoG, det: Detections, sil: Silhouette | None
    ) -> list[tuple[int, tuple[float, OptimizeResult, ImageSoG, Objective]]]:
        """The initialisation's finalists ``poses`` (26,) each refined ``final_iterations`` on
        the tracker's model with the full objective, best first by :meth:`_score` (the earlier
        finalist first on a tie): (index in ``poses``, (score, fit, its data, its objective));
        the finalists without data on their hand side are left out."""
        fits = []
        for k, x in enumerate(poses):
            data_x = self._hand_side(data, x)
            if data_x.n == 0:
                continue
            obj = Objective(self._model, data_x, self._config, targets=self._targets(x, det), silhouette=sil)
            cand = self._maximise(obj, x, iterations=INIT_SEARCH.final_iterations)
            fits.append((k, (self._score(self._plain(obj), cand.x, det, hidden_tips=False), cand, data_x, obj)))
        fits.sort(key=lambda f: f[1][0], reverse=True)  # (stable: the earlier first on a tie)
        return fits

    def _on_hand_side(self, points: NDArray[np.float64], theta: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which ``points`` (n, 3) mm lie on the hand side of the wrist plane at ``theta``."""
        return (points - theta[:3]) @ global_rotation(theta)[:, 1] > -WRIST_MARGIN_MM

    def _hand_side(self, data: ImageSoG, theta: NDArray[np.float64]) -> ImageSoG:
        """``data`` without the Gaussians beyond the wrist at ``theta`` (see :meth:`_data_near`)."""
        if data.n == 0:
            return data
        keep = self._on_hand_side(data.points, theta)
        return data if keep.all() else data.subset(keep)

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
            return TrackResult(
                status=self._status,
                pose=None,
                fingertips_mm=None,
                skeleton_mm=None,
                confidence=float(conf),
                energy=float(energy),
                n_image_gaussians=n,
                timings_ms=dict(timings),
            )
        # Forward kinematics once: fingertips are the tip Gaussians' centres.
        if centres is None:
            centres = gaussian_centres(self._model, theta)
        return TrackResult(
            status=self._status,
            pose=theta.copy(),
            fingertips_mm=centres[self._model.tip_index],
            skeleton_mm=skeleton_points(self._model, theta),
            confidence=float(conf),
            energy=float(energy),
            n_image_gaussians=n,
            timings_ms=dict(timings),
            gaussians_mm=centres,
            gaussian_radii_mm=self._model.g_sigmas.copy(),
        )
