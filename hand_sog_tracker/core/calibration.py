"""User-specific hand model: greedy search over four scale factors (paper 000, sec. 5.4).

The user holds an open hand toward the camera (any position and in-plane
orientation; the pose is found automatically and refined during the fit).  For
each scale factor in turn (length, width, sigma, depth) every value of a fixed
grid is tried with the others held at their best so far; the pose is refined by
a few optimiser iterations for every candidate and the candidate with the best
score is kept.  Two passes, the second on a finer grid around the first result.

Score.  The tracking objective's similarity term is normalised by the data
alone, so a larger model always covers more data and scores higher; fitting
shape with it drifts to the largest model.  The fit therefore scores a
candidate by the symmetric, depth-weighted overlap

``S = 2 sum_pq Delta_pq D_pq / (E(C_p, C_p) + E(C_I, C_I)) - w_c E_col - w_l E_lim``

which is largest when the projected model and the data cover the same area at
the same depth.  ``E(C_p, C_p)`` is the projected model's overlap with itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, preprocess, quadtree_sog
from hand_sog_tracker.core.energy import Objective
from hand_sog_tracker.core.hand_model import HandModel, HandShape
from hand_sog_tracker.core.kinematics import gaussian_centres, global_rotation
from hand_sog_tracker.core.optimizer import maximise
from hand_sog_tracker.core.tracker import Tracker, coverage, hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import CalibrationError, HandSogError

__all__ = ["CalibrationResult", "calibrate", "shape_score", "SEARCH_RANGE"]

#: Fixed search range of every scale factor.
SEARCH_RANGE = (0.8, 1.25)
_ORDER = ("length", "width", "sigma", "depth")
_COARSE = 10
_FINE_STEP = 0.01
_POSE_ITERATIONS = 4


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
        Refined pose on the first frame (mm, rad).
    energy_before, energy_after : float
        Fit score of the starting model and of the fitted one (higher is better).
    seconds : float
        Wall time of the fit.
    """

    shape: HandShape
    model: HandModel
    pose: NDArray[np.float64]
    energy_before: float
    energy_after: float
    seconds: float


def shape_score(
    model: HandModel,
    theta: NDArray[np.float64],
    pre: Preprocessed,
    roi: tuple[int, int, int, int],
    tolerance_mm: float = 12.0,
) -> float:
    """Depth-aware overlap of the model's silhouette with the hand's, in [0, 1].

    The model is drawn as the union of its Gaussians' 1-sigma spheres (the
    skin), exactly: a pixel is covered when its ray meets a sphere, with the
    front depth of the nearest one.  Data pixels count if they lie inside
    ``roi`` and on the finger side of the wrist (the forearm is not part of
    the model).  Score = pixels covered by both with depths within
    ``tolerance_mm``, divided by pixels covered by either.
    """
    intr = pre.intrinsics
    u0, v0, u1, v1 = (max(0, roi[0]), max(0, roi[1]), min(intr.width, roi[2]), min(intr.height, roi[3]))
    if u1 <= u0 or v1 <= v0:
        return 0.0
    depth = pre.depth_mm[v0:v1, u0:u1].astype(np.float64)
    vv, uu = np.mgrid[v0:v1, u0:u1]
    P = gaussian_centres(model, theta)
    sig = model.g_sigmas
    z = np.maximum(P[:, 2], 1.0)
    uv = intr.project(P)
    # Lateral distance (mm, at each sphere's depth) between a pixel ray and a centre.
    du = (uu.reshape(-1)[None, :] - uv[:, 0:1]) * (z[:, None] / intr.fx)
    dv = (vv.reshape(-1)[None, :] - uv[:, 1:2]) * (z[:, None] / intr.fy)
    rho2 = du * du + dv * dv
    inside = rho2 < sig[:, None] ** 2
    front = np.where(inside, z[:, None] - np.sqrt(np.maximum(sig[:, None] ** 2 - rho2, 0.0)), np.inf)
    model_depth = front.min(axis=0)
    covered = np.isfinite(model_depth)
    d = depth.reshape(-1)
    data_pts = intr.backproject(np.stack([uu.reshape(-1), vv.reshape(-1)], 1).astype(np.float64), d)
    R = global_rotation(theta)
    beyond_wrist = (data_pts - theta[:3]) @ R[:, 1] > 0.0
    data = (d > 0) & beyond_wrist
    both = covered & data & (np.abs(model_depth - d) < tolerance_mm)
    union = covered | data
    return float(both.sum() / max(union.sum(), 1))


def _refine(model: HandModel, theta: NDArray[np.float64], data: ImageSoG, config: TrackerConfig, iters: int):
    res = maximise(Objective(model, data, config), theta, iterations=iters)
    return res.x


def calibrate(
    frames: Sequence[NDArray],
    intrinsics: Intrinsics,
    config: TrackerConfig,
    model: HandModel,
    start_pose: NDArray[np.float64] | None = None,
) -> CalibrationResult:
    """Fit the four scale factors of ``model`` to frames of an open hand.

    Parameters
    ----------
    frames : sequence of arrays, shape (H, W)
        One to three depth images (mm) of the open hand; the first is used for
        the pose search, all for scoring.
    intrinsics : Intrinsics
    config : TrackerConfig
    model : HandModel
        Current model; its handedness is kept, its shape is the starting point.
    start_pose : array, shape (26,), optional
        Pose of the hand in the first frame; found automatically when None.

    Raises
    ------
    CalibrationError
        No frames, no hand in view, or no candidate scored better than the
        starting model.
    """
    t0 = time.perf_counter()
    if len(frames) == 0:
        raise CalibrationError("no depth frames to calibrate on")
    frames = list(frames)[:3]
    try:
        pres = [preprocess(f, intrinsics, config) for f in frames]
    except HandSogError as err:
        raise CalibrationError(f"unusable depth frame: {err}") from err
    if start_pose is None:
        tracker = Tracker(config, model)
        res = tracker.process(frames[0], intrinsics)
        if res.pose is None:
            raise CalibrationError("no hand in view (hold an open hand toward the camera)")
        pose = res.pose
    else:
        pose = np.asarray(start_pose, dtype=np.float64)
    mirrored = model.mirrored(config.right_hand)
    roi, window = hand_roi(mirrored, pose, pres[0].intrinsics, config.roi_radius_mm)
    datas = [quadtree_sog(p, config.quadtree_threshold_mm, roi, window, config.min_quad_px) for p in pres]
    if datas[0].n == 0 or coverage(mirrored, pose, datas[0]) < config.lost_confidence:
        raise CalibrationError("no hand in view (hold an open hand toward the camera)")

    def evaluate(shape: HandShape, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        m = mirrored.scaled(shape)
        th = _refine(m, theta, datas[0], config, _POSE_ITERATIONS)
        return sum(shape_score(m, th, p, roi) for p in pres) / len(pres), th

    current = model.shape
    pose = _refine(mirrored.scaled(current), pose, datas[0], config, 15)
    before, _ = evaluate(current, pose)
    best_val, best_shape, best_pose = before, current, pose
    grids = [np.linspace(*SEARCH_RANGE, _COARSE)]
    for pass_no in range(2):
        for name in _ORDER:
            if pass_no == 0:
                grid = grids[0]
            else:
                c = getattr(best_shape, name)
                grid = np.clip(c + _FINE_STEP * np.arange(-3, 4), *SEARCH_RANGE)
            for value in grid:
                cand = HandShape(**{**best_shape.__dict__, name: float(value)})
                val, th = evaluate(cand, best_pose)
                if val > best_val:
                    best_val, best_shape, best_pose = val, cand, th
    fitted = mirrored.scaled(best_shape)
    best_pose = _refine(fitted, best_pose, datas[0], config, 15)
    after = sum(shape_score(fitted, best_pose, p, roi) for p in pres) / len(pres)
    if not after > before:
        raise CalibrationError(
            f"fit not better than the current model (score {after:.4f} <= {before:.4f})"
        )
    return CalibrationResult(
        shape=best_shape,
        model=fitted,
        pose=best_pose,
        energy_before=float(before),
        energy_after=float(after),
        seconds=time.perf_counter() - t0,
    )
