"""Value types shared by the core, the ROS layer and the tools."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.errors import InputError, IntrinsicsError

__all__ = ["HandDecision", "HandEvidence", "Intrinsics", "TrackerConfig", "TrackerStatus", "TrackResult"]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth image (pixels).

    ``fx, fy`` focal lengths, ``cx, cy`` principal point, ``width, height``
    image size the intrinsics belong to.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals) or self.fx <= 0 or self.fy <= 0:
            raise IntrinsicsError(
                f"focal lengths must be finite and positive, got fx={self.fx}, fy={self.fy}"
            )
        if self.width <= 0 or self.height <= 0:
            raise IntrinsicsError(f"image size must be positive, got {self.width}x{self.height}")

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the image resized by ``factor`` (pixel centres kept aligned)."""
        return Intrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
        )

    def project(self, points_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Project camera-frame points, shape (k, 3) mm, to pixels, shape (k, 2)."""
        p = np.asarray(points_mm, dtype=np.float64)
        z = p[:, 2]
        return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=1)

    def backproject(self, uv: NDArray[np.float64], z_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Back-project pixels (k, 2) at depths (k,) mm to camera points (k, 3) mm."""
        uv = np.asarray(uv, dtype=np.float64)
        z = np.asarray(z_mm, dtype=np.float64)
        # (u - cx) z / fx, (v - cy) z / fy, z, written into the columns of the result (the same
        # operations as separate arrays stacked; fewer temporaries).
        out = np.empty((uv.shape[0], 3))
        x = np.subtract(uv[:, 0], self.cx, out=out[:, 0])
        x *= z
        x /= self.fx
        y = np.subtract(uv[:, 1], self.cy, out=out[:, 1])
        y *= z
        y /= self.fy
        out[:, 2] = z
        return out


class TrackerStatus(enum.Enum):
    """Per-frame state of the tracker."""

    NO_HAND = "no_hand"  #: nothing hand-like in range; no pose output
    TRACKING = "tracking"  #: pose valid
    LOST = "lost"  #: the model no longer explains the data; re-initialising


@dataclass(frozen=True)
class TrackerConfig:
    """Every tunable of the core tracker (units in the names)."""

    near_mm: float = 150.0
    #: 1 m: a hand at arm's length from a Kinect-class camera (0.7-0.9 m) is in range; a body or
    #: wall behind the hand is cut off by the hand finder and the tracking window (issue notes:
    #: 600 mm saw no hand in the labelled NYU frame at 0.74 m; no change on the renders).
    far_mm: float = 1000.0
    quadtree_threshold_mm: float = 20.0
    min_quad_px: int = 4  #: smallest quadtree leaf side at processing resolution: 2, 4 or 8 (see leaf_px)
    median_kernel: int = 3  #: 0 or 1 disables the median filter; else odd 3 or 5
    max_width_px: int = 320  #: images wider than this are decimated first ...
    #: ... but not below this focal length (px) at the processing resolution: a wide-angle camera
    #: keeps more pixels (a D435-like 640x480, fx = 385, is processed at 640x480; 0: off)
    min_focal_px: float = 240.0
    iterations: int = 7
    #: A frame with a curled finger answers with its fit refined this many iterations on the
    #: model with joint Gaussians (0: off; issue 11, see tracker.REFINE_CURL_RAD)
    refine_iterations: int = 2
    w_col: float = 1.0
    w_dan: float = 0.1
    w_lim: float = 0.2
    w_smo: float = 0.0  #: paper: 1.0; see core/objective for why the default is 0
    w_ord: float = 1.0  #: finger order across the palm (not in the paper; core/objective)
    w_sal: float = 0.15  #: salient points (fingertip detections; seed 001; measured here)
    w_sil: float = 1.0  #: silhouette: model Gaussians outside the hand's pixels (silhouette.py)
    w_cpl: float = 0.0  #: DIP flexed beyond 2/3 of its PIP (seed 004; opt-in, see core/objective)
    w_curl: float = 0.5  #: PIP + DIP flexed beyond 165 deg (issue 11; measured here, core/objective)
    right_hand: bool = True
    roi_radius_mm: float = 160.0  #: data farther than this from the last hand centre is ignored
    lost_confidence: float = 0.2  #: confidence below this for ``lost_frames`` frames means LOST
    lost_frames: int = 3
    init_hypotheses: int = 16  #: starting poses tried when (re)initialising

    def __post_init__(self) -> None:
        if not (0.0 < self.near_mm < self.far_mm):
            raise InputError(f"need 0 < near_mm < far_mm, got {self.near_mm}, {self.far_mm}")
        if self.quadtree_threshold_mm <= 0:
            raise InputError("quadtree_threshold_mm must be positive")
        if self.min_quad_px not in (2, 4, 8):
            raise InputError(f"min_quad_px must be 2, 4 or 8, got {self.min_quad_px}")
        if self.median_kernel not in (0, 1, 3, 5):
            raise InputError(f"median_kernel must be 0, 1, 3 or 5, got {self.median_kernel}")
        if self.max_width_px < 80:
            raise InputError("max_width_px must be at least 80")
        if not (0.0 <= self.min_focal_px <= 10000.0):
            raise InputError("min_focal_px must be in [0, 10000]")
        if not (1 <= self.iterations <= 200):
            raise InputError("iterations must be in [1, 200]")
        if not (0 <= self.refine_iterations <= 50):
            raise InputError("refine_iterations must be in [0, 50]")
        for w in ("w_col", "w_dan", "w_lim", "w_smo", "w_ord", "w_sal", "w_sil", "w_cpl", "w_curl"):
            if getattr(self, w) < 0:
                raise InputError(f"{w} must be >= 0")
        if self.roi_radius_mm <= 0:
            raise InputError("roi_radius_mm must be positive")
        if not (0.0 <= self.lost_confidence <= 1.0):
            raise InputError("lost_confidence must be in [0, 1]")
        if self.lost_frames < 1 or self.init_hypotheses < 1:
            raise InputError("lost_frames and init_hypotheses must be >= 1")


@dataclass(frozen=True)
class HandEvidence:
    """The measured evidence of :func:`~hand_sog_tracker.core.handcheck.check_hand` (all in [0, 1], NaN
    when not measured).

    Attributes
    ----------
    on : float
        Share of the model's visible silhouette lying on data.
    explained : float
        Share of the foreground data around the model covered by its silhouette.
    fingers_on : float
        Mean over the five fingers of the share of each finger's visible silhouette on data.
    ends : float
        Share of the checked fingers (straight, seen from the side, on the data) whose data
        end past the fingertip (NaN: none checked).
    in_view : float
        Share of the model's silhouette inside the image.
    outline : float
        Share of the ring just outside the silhouette (hand side of the wrist) where the depth
        steps back from the model's data or has none: the hand's outline is a depth edge.
    finger_edges : float
        The same share over the part of the ring next to the model's fingers: a finger has a
        depth edge on both sides, a model finger lying on a head or a torso has none (NaN: no
        finger next to the ring).
    steep : float
        Of the outline's depth edges, the share that are steps, not a surface curving away: an
        edge less than ``STEEP_MM`` behind whose surface keeps receding (or ends) one ring
        width further out is the side of a head or a ball, not a hand's outline (NaN: no edge).
    """

    on: float
    explained: float
    fingers_on: float
    ends: float
    in_view: float
    outline: float
    finger_edges: float = math.nan
    steep: float = math.nan


@dataclass(frozen=True, eq=False)
class HandDecision:
    """The hand decision of one frame.

    Attributes
    ----------
    present : bool
        A hand is reported (tracked, its confidence at least the threshold, a new track
        confirmed; see :class:`~hand_sog_tracker.core.handcheck.HandGate`).
    confidence : float
        In [0, 1]; 0 when nothing was tracked.
    fingers : array, shape (5,)
        Per finger (thumb .. little) in [0, 1]: how much of it the data show.
    evidence : HandEvidence or None
        None when nothing was tracked.
    """

    present: bool
    confidence: float
    fingers: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))
    evidence: HandEvidence | None = None


@dataclass(frozen=True, eq=False)
class TrackResult:
    """Output of :meth:`Tracker.process` for one frame.

    Attributes
    ----------
    status : TrackerStatus
    pose : array, shape (26,) or None
        Pose vector (mm, rad); ``None`` unless ``status`` is TRACKING.
    fingertips_mm : array, shape (5, 3) or None
        Fingertip centres, camera optical frame, mm (thumb .. little).
    skeleton_mm : array, shape (21, 3) or None
        The published keypoints' skeleton (:func:`kinematics.keypoint_skeleton`: the
        kinematic skeleton with the wrist, thumb CMC and MCPs at the joint centres), mm.
    confidence : float
        In [0, 1]: how well the model explains the data near the hand.
    energy : float
        Objective value E of the frame's fit (the track's pose; ``pose`` is that pose refined
        when a finger is curled, see ``tracker.REFINE_CURL_RAD``).
    n_image_gaussians : int
        Quadtree leaves used as data.
    timings_ms : dict
        Wall time per stage: ``preprocess``, ``quadtree``, ``optimise``, ``total``.
    gaussians_mm : array, shape (m, 3) or None
        Model Gaussian centres at ``pose``, camera optical frame, mm (``HandModel`` order;
        ``fingertips_mm`` is its rows ``HandModel.tip_index``).
    gaussian_radii_mm : array, shape (m,) or None
        Their standard deviations (the skin radius), mm.
    hand : HandDecision or None
        The frame's hand decision (:mod:`hand_sog_tracker.core.handcheck`): ``pose`` is given
        only when ``hand.present``.  None from producers without the check (test doubles).
    """

    status: TrackerStatus
    pose: NDArray[np.float64] | None
    fingertips_mm: NDArray[np.float64] | None
    skeleton_mm: NDArray[np.float64] | None
    confidence: float
    energy: float
    n_image_gaussians: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    gaussians_mm: NDArray[np.float64] | None = None
    gaussian_radii_mm: NDArray[np.float64] | None = None
    hand: HandDecision | None = None
