"""Frame-to-frame hand tracker: depth in, 26-DOF pose and fingertips out.

Units: depth images and every position in millimetres, camera optical frame
(x right, y down, z forward); angles in radians.

Per frame (paper 000, sec. 5): preprocess and cluster the depth near the last
hand position into Gaussians, start from the pose extrapolated from the last
two frames, and run the adaptive gradient ascent on the objective.  When there
is no track yet (first frame, or after a loss) the tracker finds the hand in
the depth by itself and tries several starting poses (see :mod:`.initialise`).
"""

from __future__ import annotations

import time
from dataclasses import replace as replace_config

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.articulations import FINGER_CURLED, FINGER_EXTENDED
from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, preprocess, quadtree_sog
from hand_sog_tracker.core.energy import SALIENT_SCALE_MM, Objective, TipTargets
from hand_sog_tracker.core.hand_model import (
    CHAIN_JOINTS,
    JOINTS,
    HandModel,
    chain_slice,
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

#: Velocity extrapolation factor of the start pose (unitless; paper 000 sec. 5.3: alpha = 0.5).
ALPHA = 0.5
#: Iterations per hypothesis while initialising, and for the best ones after (chosen here,
#: commit 9681579; for comparison seed 001 gives its first frame 50 iterations).
INIT_ITERATIONS = (8, 30)
#: Best-scoring hypotheses refined fully while initialising (count; chosen here, commit 9681579).
INIT_FINALISTS = 2
#: A fingertip this far from all data (mm) triggers a restart of its finger (seed 004's
#: restarts; the distance is chosen here).
RESTART_TIP_MM = 25.0
#: Iterations each restart candidate gets (count; chosen here, raised to 12 in commit f16019d).
RESTART_ITERATIONS = 12
#: Data farther than this beyond the wrist plane are treated as forearm (mm; chosen here: 0,
#: the model has no forearm).
WRIST_MARGIN_MM = 0.0
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
#: Whether detections of fingers seen end-on (knuckles of a fist look the same) pull
#: fingertips (chosen here: off; they only seed the curled restart candidates).
SALIENT_END_ON = False
#: Without an unexplained detection, finger-shifted restarts (seed 004) are tried every this
#: many frames (count; chosen here, commit 0e963cc).
SHIFT_EVERY = 6


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


class Tracker:
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
        self, pre: Preprocessed, theta: NDArray[np.float64], detect: bool = False
    ) -> tuple[ImageSoG, Detections, Silhouette | None]:
        """Data Gaussians around the hand at ``theta``, without the forearm.

        Quads beyond the wrist (more than ``WRIST_MARGIN_MM`` on the arm side of
        the plane through the wrist normal to the hand's long axis) are
        dropped: the model has no forearm, and forearm data would pull the palm
        down the arm.  With ``detect``, also the fingertip detections in the same
        region (used by the salient term and the restarts), else none; and the
        silhouette of the depth in the same depth window (None when ``w_sil`` is 0).
        """
        roi, window = hand_roi(self._model, theta, pre.intrinsics, self._config.roi_radius_mm)
        sil = silhouette(pre, window, roi) if self._config.w_sil > 0 else None
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

    def _assignment_cost(self, theta: NDArray[np.float64], det: Detections) -> float:
        """Seed 001's assignment cost (eq. 11) at ``theta``, in units of ``SALIENT_SCALE_MM``.

        Assigned pairs cost their distance, detections left over ``lambda * confidence``,
        fingertips without a detection ``lambda``: a hypothesis whose fingertips are not
        where the fingertips are seen (a hand flipped palm-for-back, fingers swapped) scores
        worse even where the depth overlap cannot tell.
        """
        if det.n == 0:
            return 0.0
        tips = fingertips(self._model, theta)
        assigned = assign_detections(tips, det, ASSIGN_LAMBDA_MM)
        has = assigned >= 0
        d = np.linalg.norm(tips[has] - det.points[assigned[has]], axis=1).sum()
        unused = np.ones(det.n, bool)
        unused[assigned[has]] = False
        cost = d + ASSIGN_LAMBDA_MM * ((~has).sum() + det.confidence[unused].sum())
        return float(cost / SALIENT_SCALE_MM)

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

    def _finger_restarts(self, obj: Objective, res: OptimizeResult, data: ImageSoG) -> OptimizeResult:
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
        d2 = ((tips[:, None, :] - data.points[None, :, :]) ** 2).sum(-1)
        far = np.sqrt(d2.min(axis=1))
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
            cand = self._maximise(obj, x0, iterations=RESTART_ITERATIONS)
            if cand.fun > best.fun:
                best = cand
        return best

    def _maximise(self, obj: Objective, x0: NDArray[np.float64], **kwargs: object) -> OptimizeResult:
        """:func:`maximise` with the joint angles projected into the model's limits."""
        m = self._model
        lo = np.concatenate([np.full(6, -np.inf), m.limits_low])
        hi = np.concatenate([np.full(6, np.inf), m.limits_high])
        return maximise(obj, x0, bounds=(lo, hi), **kwargs)  # type: ignore[arg-type]

    def _shift_restarts(
        self, obj: Objective, res: OptimizeResult, det: Detections, force: bool = False
    ) -> OptimizeResult:
        """Move every finger's articulation to its neighbour (seed 004's finger-shifted restarts).

        A model whose fingers each lie on their neighbour's data (one curled into the palm,
        the others spread over its place) is a deep local optimum: every finger explains
        data.  The candidate gives index .. little the flexions of their neighbour on one
        side (the last finger keeps its own) and neutral abductions, is refined for
        ``RESTART_ITERATIONS`` and is kept only if its :meth:`_score` is higher.  Tried in
        both directions when a confident detection is unexplained (see
        :meth:`_detection_restarts`) or with ``force`` (initialisation), otherwise one
        direction every ``SHIFT_EVERY`` frames.
        """
        if not force:
            self._frame_count += 1
        if force or self._lonely(res.x, det).size:
            sides = (1, -1)
        elif self._frame_count % SHIFT_EVERY == 0:
            sides = (1 if (self._frame_count // SHIFT_EVERY) % 2 else -1,)
        else:
            return res
        plain = self._plain(obj)
        best, best_val = res, self._score(plain, res.x, det)
        q = res.x[JOINTS].reshape(5, CHAIN_JOINTS)
        for side in sides:
            # Each finger takes its neighbour's flexions, with the abductions neutral: the
            # neighbour's abduction is what carried it over onto this finger's data.
            shifted = q[np.clip(np.arange(1, 5) + side, 1, 4)].copy()
            shifted[:, 1] = 0.0
            x0 = res.x.copy()
            x0[chain_slice(1).start :] = shifted.ravel()
            cand = self._maximise(plain, x0, iterations=RESTART_ITERATIONS)
            val = self._score(plain, cand.x, det)
            if val > best_val:
                best, best_val = cand, val
        return best

    def _score(self, plain: Objective, theta: NDArray[np.float64], det: Detections) -> float:
        """How well ``theta`` explains the frame: the objective without the salient term,
        minus the assignment cost of the detections at ``theta`` (fresh, not the one the
        frame started with), weighted like the salient term."""
        return plain(theta, gradient=False)[0] - self._config.w_sal * self._assignment_cost(theta, det)

    def _plain(self, obj: Objective) -> Objective:
        """``obj`` without the salient term (to judge candidates built from detections)."""
        if obj.targets is None or self._config.w_sal == 0:
            return obj
        return Objective(
            self._model,
            obj.data,
            replace_config(self._config, w_sal=0.0),
            previous=obj.previous,
            silhouette=obj.silhouette,
        )

    def _lonely(self, theta: NDArray[np.float64], det: Detections) -> NDArray[np.int64]:
        """Confident detections farther than ``UNEXPLAINED_DETECTION_MM`` from every fingertip."""
        if det.n == 0:
            return np.zeros(0, dtype=np.int64)
        tips = fingertips(self._model, theta)
        dist = np.linalg.norm(det.points[:, None, :] - tips[None, :, :], axis=-1).min(axis=1)
        return np.flatnonzero(
            (dist > UNEXPLAINED_DETECTION_MM) & (det.confidence >= UNEXPLAINED_CONFIDENCE)
        )

    def _detection_restarts(
        self, obj: Objective, res: OptimizeResult, det: Detections
    ) -> OptimizeResult:
        """Put a finger onto a detection that no model finger explains (seed 001 + 004).

        A confident detection farther than ``UNEXPLAINED_DETECTION_MM`` from every model
        fingertip is a finger the model has missed (typically one curled toward the camera
        while the model finger lies on its neighbour).  Each of the two model fingers
        nearest to it is pulled onto it (the salient term alone, strongly weighted, for
        ``RESTART_ITERATIONS``), then released into the objective without the salient term
        (which would favour the assignment the frame started with); a candidate is kept only
        if its :meth:`_score` is higher than before.
        """
        lonely = self._lonely(res.x, det)
        if lonely.size == 0:
            return res
        s = int(lonely[np.argmax(det.confidence[lonely])])
        dist = np.linalg.norm(det.points[s] - fingertips(self._model, res.x), axis=1)
        cfg = self._config
        plain = self._plain(obj)
        best, best_val = res, self._score(plain, res.x, det)
        for c in np.argsort(dist)[:2]:
            w = np.zeros(5)
            w[c] = 1.0
            pts = np.zeros((5, 3))
            pts[c] = det.points[s]
            pull = Objective(
                self._model, obj.data, replace_config(cfg, w_sal=max(cfg.w_sal, 1.0) * 20.0),
                previous=obj.previous, targets=TipTargets(pts, w), silhouette=obj.silhouette,
            )
            starts = [self._maximise(pull, res.x, iterations=RESTART_ITERATIONS).x]
            if det.end_on[s] and c > 0:
                # A finger seen end-on is curled toward the camera: also try it curled.
                curled = res.x.copy()
                curled[chain_slice(c)] = FINGER_CURLED
                starts.append(curled)
            for x0 in starts:
                cand = self._maximise(plain, x0, iterations=RESTART_ITERATIONS)
                val = self._score(plain, cand.x, det)
                if val > best_val:
                    best, best_val = cand, val
        return best

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
            data, det_x, _ = self._data_near(pre, x0, detect=det is None)
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
