"""Frame-to-frame hand tracker: depth in, 26-DOF pose and fingertips out.

Units: depth images and every position in millimetres, camera optical frame
(x right, y down, z forward); angles in radians.

Per frame (paper 000, sec. 5): preprocess and cluster the depth near the last
hand position into Gaussians, start from the pose extrapolated from the last
two frames, and run the adaptive gradient ascent on the objective.  When there
is no track yet (first frame, or after a loss) the tracker finds the hand in
the depth by itself and tries several starting poses (see :mod:`.initialise`).
After each frame's fit the restart strategies of :mod:`.restarts` (a mixin of
:class:`Tracker`) try ways out of local optima.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, preprocess, quadtree_sog
from hand_sog_tracker.core.energy import Objective, TipTargets
from hand_sog_tracker.core.hand_model import (
    HandModel,
    default_hand_model,
)
from hand_sog_tracker.core.initialise import find_hand, initial_hypotheses
from hand_sog_tracker.core.kinematics import (
    fingertips,
    gaussian_centres,
    global_rotation,
    skeleton_points,
)
from hand_sog_tracker.core.optimizer import OptimizeResult, maximise
from hand_sog_tracker.core.restarts import ASSIGN_LAMBDA_MM, RestartStrategies
from hand_sog_tracker.core.salient import Detections, assign_detections, detect_fingertips
from hand_sog_tracker.core.silhouette import Silhouette, silhouette
from hand_sog_tracker.core.types import (
    Intrinsics,
    TrackerConfig,
    TrackerStatus,
    TrackResult,
)

__all__ = ["Tracker", "coverage", "hand_roi"]

# Tuning constants.  Each says what it is, its unit and where its value comes from: "paper 000"
# (the tracker's paper), "seed 001/004" (the salient-point and restart papers) or "chosen
# here" (set while developing this package against the synthetic bag sets; commit noted
# where the value was last changed).  They are module constants, not TrackerConfig fields
# (which become ROS parameters), because none is meant to be tuned per camera or user.
# The restarts' constants (RESTART_TIP_MM, ASSIGN_LAMBDA_MM, ...) are in :mod:`.restarts`.

#: Velocity extrapolation factor of the start pose (unitless; paper 000 sec. 5.3: alpha = 0.5).
ALPHA = 0.5
#: Iterations per hypothesis while initialising, and for the best ones after (chosen here,
#: commit 9681579; for comparison seed 001 gives its first frame 50 iterations).
INIT_ITERATIONS = (8, 30)
#: Best-scoring hypotheses refined fully while initialising (count; chosen here, commit 9681579).
INIT_FINALISTS = 2
#: Data farther than this beyond the wrist plane are treated as forearm (mm; chosen here: 0,
#: the model has no forearm).
WRIST_MARGIN_MM = 0.0
#: Whether detections of fingers seen end-on (knuckles of a fist look the same) pull
#: fingertips (chosen here: off; they only seed the curled restart candidates).
SALIENT_END_ON = False


def gaussian_support(model: HandModel, theta: NDArray[np.float64], data: ImageSoG) -> NDArray[np.float64]:
    """How well the data explain each model Gaussian at ``theta``, shape (m,), in [0, 1].

    For Gaussian ``p`` the depth-weighted overlap with the data,
    ``sum_q Delta_pq D_pq``, divided by its value under a gap-free data tiling
    at the right depth (``2 pi^2 sigma_p^2``, px), capped at 1.
    """
    if data.n == 0:
        return np.zeros(model.n_gaussians)
    intr = data.intrinsics
    P = gaussian_centres(model, theta)
    z = np.maximum(P[:, 2], 1.0)
    uv = np.stack([intr.fx * P[:, 0] / z + intr.cx, intr.fy * P[:, 1] / z + intr.cy], 1)
    sp2 = (model.g_sigmas * np.sqrt(intr.fx * intr.fy) / z)[:, None] ** 2
    sq2 = data.sigma[None, :] ** 2
    s2 = sp2 + sq2
    r2 = ((uv[:, None, :] - data.mu[None, :, :]) ** 2).sum(-1)
    D = 2 * np.pi * sp2 * sq2 / s2 * np.exp(-0.5 * r2 / s2)
    dd = np.abs((z - model.g_sigmas)[:, None] - data.depth[None, :])
    delta = np.clip(1.0 - dd / (2.0 * model.g_sigmas[:, None]), 0.0, None)
    support = (delta * D).sum(1) / (2 * np.pi**2 * sp2[:, 0])
    return np.minimum(support, 1.0)


def coverage(model: HandModel, theta: NDArray[np.float64], data: ImageSoG) -> float:
    """How well the data explain the model at ``theta``, in [0, 1].

    The mean :func:`gaussian_support` over the best-supported two thirds of
    the Gaussians (the rest may be legitimately occluded).
    """
    support = np.sort(gaussian_support(model, theta, data))[::-1]
    keep = max(1, (2 * support.size) // 3)
    return float(support[:keep].mean())


def hand_roi(
    model: HandModel, theta: NDArray[np.float64], intr: Intrinsics, radius_mm: float
) -> tuple[tuple[int, int, int, int], tuple[float, float]]:
    """Pixel box and depth window around the hand at ``theta``.

    Returns
    -------
    roi : (u0, v0, u1, v1)
        End-exclusive pixel box at the resolution of ``intr``.
    window : (near_mm, far_mm)
    """
    P = gaussian_centres(model, theta)
    c = P.mean(axis=0)
    z = max(c[2], 50.0)
    uv = intr.project(c[None, :])[0]
    r_px = radius_mm * max(intr.fx, intr.fy) / max(z - radius_mm * 0.5, 50.0)
    roi = (
        int(np.floor(uv[0] - r_px)),
        int(np.floor(uv[1] - r_px)),
        int(np.ceil(uv[0] + r_px)) + 1,
        int(np.ceil(uv[1] + r_px)) + 1,
    )
    return roi, (c[2] - radius_mm, c[2] + radius_mm)


class Tracker(RestartStrategies):
    """Tracks one hand through a depth sequence.

    Parameters
    ----------
    config : TrackerConfig, optional
    model : HandModel, optional
        Hand model (mm); default: the default adult hand of ``config.right_hand``.
    """

    def __init__(self, config: TrackerConfig | None = None, model: HandModel | None = None) -> None:
        self._config = config or TrackerConfig()
        base = model if model is not None else default_hand_model(self._config.right_hand)
        self._model = base.mirrored(self._config.right_hand)
        self._prev: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._low_frames = 0
        self._status = TrackerStatus.NO_HAND
        self._frame_count = 0

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

    def set_config(self, config: TrackerConfig) -> None:
        """Change the configuration; a handedness change also resets the track."""
        if config.right_hand != self._config.right_hand:
            self._model = self._model.mirrored(config.right_hand)
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
        pre = preprocess(depth_mm, intrinsics, cfg)  # raises before any state change
        t1 = time.perf_counter()
        if self._prev is not None:
            result = self._track(pre)
        else:
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
    ) -> tuple[ImageSoG, Detections, Silhouette | None]:
        """Data Gaussians around the hand at ``theta``, without the forearm.

        Quads beyond the wrist (more than ``WRIST_MARGIN_MM`` on the arm side of
        the plane through the wrist normal to the hand's long axis) are
        dropped: the model has no forearm, and forearm data would pull the palm
        down the arm.  With ``detect``, also the fingertip detections in the same
        region (used by the salient term and the restarts), else none; and with
        ``outline`` the silhouette of the depth in the same depth window (None
        without it or when ``w_sil`` is 0).
        """
        roi, window = hand_roi(self._model, theta, pre.intrinsics, self._config.roi_radius_mm)
        sil = silhouette(pre, window, roi) if outline and self._config.w_sil > 0 else None
        det = Detections.empty()
        if detect:
            det = detect_fingertips(pre, roi, window)
            if det.n:
                along = (det.points - theta[:3]) @ global_rotation(theta)[:, 1]
                det = det.subset(along > -WRIST_MARGIN_MM)
        data = quadtree_sog(
            pre, self._config.quadtree_threshold_mm, roi, window, self._config.min_quad_px
        )
        if data.n == 0:
            return data, det, sil
        axis = global_rotation(theta)[:, 1]
        along = (data.points - theta[:3]) @ axis
        keep = along > -WRIST_MARGIN_MM
        return (data if keep.all() else data.subset(keep)), det, sil

    def _targets(self, theta: NDArray[np.float64], det: Detections) -> TipTargets | None:
        """Detections assigned to the fingertips at ``theta`` (seed 001, Table 1)."""
        if det.n == 0:
            return None
        assigned = assign_detections(fingertips(self._model, theta), det, ASSIGN_LAMBDA_MM)
        has = assigned >= 0
        if not SALIENT_END_ON:
            has &= ~det.end_on[np.maximum(assigned, 0)]
        points = np.zeros((5, 3))
        points[has] = det.points[assigned[has]]
        weights = np.where(has, det.confidence[np.maximum(assigned, 0)], 0.0)
        return TipTargets(points=points, weights=weights)

    def _track(self, pre: Preprocessed) -> TrackResult:
        cfg = self._config
        assert self._prev is not None
        p1, p2 = self._prev
        # The paper prints Theta_{t-1} + alpha Theta_{t-2}; we read it as a
        # constant-velocity extrapolation damped by alpha.
        x0 = p1 + ALPHA * (p1 - p2)
        tq = time.perf_counter()
        data, det, sil = self._data_near(pre, x0, detect=True)
        tq2 = time.perf_counter()
        targets = self._targets(x0, det)
        obj = Objective(self._model, data, cfg, previous=(p1, p2), targets=targets, silhouette=sil)
        res = self._maximise(obj, x0, iterations=cfg.iterations)
        res = self._finger_restarts(obj, res, data)
        res = self._shift_restarts(obj, res, det)
        res = self._detection_restarts(obj, res, det)
        conf = coverage(self._model, res.x, data)
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
        return self._result(res.x, conf, res.fun, data.n, {"quadtree": (tq2 - tq) * 1e3})

    def _maximise(self, obj: Objective, x0: NDArray[np.float64], **kwargs: object) -> OptimizeResult:
        """:func:`maximise` with the joint angles projected into the model's limits."""
        m = self._model
        lo = np.concatenate([np.full(6, -np.inf), m.limits_low])
        hi = np.concatenate([np.full(6, np.inf), m.limits_high])
        return maximise(obj, x0, bounds=(lo, hi), **kwargs)  # type: ignore[arg-type]

    def _initialise(self, pre: Preprocessed) -> TrackResult:
        cfg = self._config
        blob = find_hand(pre, cfg)
        if blob is None:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, 0.0, 0.0, 0, {})
        rigid = np.zeros(self._model.limits_low.size + 6, dtype=bool)
        rigid[:6] = True
        scored = []
        det = None
        for x0 in initial_hypotheses(self._model, blob, cfg.init_hypotheses):
            data, det_x, _ = self._data_near(pre, x0, detect=det is None, outline=False)
            det = det_x if det is None else det
            if data.n == 0:
                continue
            # No silhouette term while the hypotheses are still far off: it would pull
            # them into the outline before the depth has placed them (a hand flipped
            # palm-for-back has the same outline).
            obj = Objective(self._model, data, cfg)
            # Rigid alignment first, then articulation (seed 004's coarse-to-fine).
            res = self._maximise(obj, x0, iterations=INIT_ITERATIONS[0], initial_scale=2.0, active=rigid)
            res = self._maximise(obj, res.x, iterations=INIT_ITERATIONS[0], initial_scale=2.0)
            score = self._score(obj, res.x, det)
            scored.append((score, len(scored), res.x))
        if not scored or det is None:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, 0.0, 0.0, 0, {})
        best = None
        for _, _, x in sorted(scored, reverse=True)[:INIT_FINALISTS]:
            data_x, _, sil = self._data_near(pre, x)
            obj = Objective(self._model, data_x, cfg, targets=self._targets(x, det), silhouette=sil)
            cand = self._maximise(obj, x, iterations=INIT_ITERATIONS[1])
            for _ in range(2):
                cand = self._finger_restarts(obj, cand, data_x)
                cand = self._shift_restarts(obj, cand, det, force=True)
                cand = self._detection_restarts(obj, cand, det)
            score = self._score(self._plain(obj), cand.x, det)
            if best is None or score > best[2]:
                best = (cand, data_x, score)
        res, data, _ = best
        conf = coverage(self._model, res.x, data)
        if conf < cfg.lost_confidence:
            self._status = TrackerStatus.NO_HAND
            return self._result(None, conf, res.fun, data.n, {})
        self._prev = (res.x, res.x)
        self._low_frames = 0
        self._status = TrackerStatus.TRACKING
        return self._result(res.x, conf, res.fun, data.n, {})

    def _result(
        self,
        theta: NDArray[np.float64] | None,
        conf: float,
        energy: float,
        n: int,
        timings: dict[str, float],
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
