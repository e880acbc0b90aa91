"""User-specific hand model: greedy search over four scale factors (paper 000, sec. 5.4).

The user holds an open hand toward the camera (any position and in-plane
orientation).  A pose fit with the current model locates the palm and its
orientation; the fingers are then set open and the global pose refitted.
Candidate shapes are scaled about the fitted palm centre and scored without
further pose changes.  Two rounds of greedy search, each over, in turn, the
overall size (all four factors together), length, width and thickness (sigma
and depth together; the second round also each alone), every value of a grid
about the best so far tried with the others held; before the second round the
global pose is refitted with the model found in the first (a pose fitted with
a wrongly sized model is biased toward that size).

Score.  The tracking objective's similarity term is normalised by the data
alone, so a larger model always covers more data and scores higher; fitting
shape with it drifts to the largest model.  Candidates are therefore scored by
a depth-aware silhouette overlap (:func:`shape_score`), which is largest when
the model's skin and the hand's data cover the same pixels at the same depth.
The skin is drawn with OpenCV (a few ms a candidate and frame at 320 x 240).

Measured on rendered open hands (test_core_calibration.py): length and width
within 3.5% of the truth for hands from 0.85x to 1.15x; one view tells palm
depth and finger thickness apart poorly (errors up to ~10%).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import ImageSoG, Preprocessed, preprocess, quadtree_sog
from hand_sog_tracker.core.energy import Objective
from hand_sog_tracker.core.hand_model import N_PARAMS, HandModel, HandShape
from hand_sog_tracker.core.kinematics import attached_points, gaussian_centres, global_rotation
from hand_sog_tracker.core.optimizer import maximise
from hand_sog_tracker.core.tracker import Tracker, coverage, hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import CalibrationError, HandSogError

__all__ = ["CalibrationResult", "calibrate", "shape_score", "SEARCH_RANGE"]

#: Fixed search range of every scale factor.
SEARCH_RANGE = (0.8, 1.25)
#: Per round: how far (span) and how finely (step) each factor is searched about the best so far.
_ROUNDS = ((0.25, 0.05), (0.06, 0.015))
#: What each round searches, in order: ``size`` scales all four factors together,
#: ``thickness`` sets sigma and depth together (one view hardly tells them apart).
_SEARCH_ORDER = (
    ("size", "length", "width", "thickness"),
    ("size", "length", "width", "thickness", "sigma", "depth"),
)
_TOLERANCE_MM = 12.0
_SCORE_MARGIN_PX = 12
_REFIT_ITERATIONS = 15
_OPEN_JOINTS = np.array([0.1, 0.0, 0.1, 0.1] + [0.05, 0.0, 0.05, 0.05] * 4)


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
    if abs(offset) < 1e-9 or np.any(values < lo - 1e-9) or np.any(values > hi + 1e-9):
        return None
    return HandShape(*(float(v) for v in values))


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


def _skin(model: HandModel, theta: NDArray[np.float64]):
    """Capsules of the model's skin: centres (k, 3) mm, radii (k,) mm, index pairs (a, b).

    Consecutive Gaussians along each chain are joined, starting at the chain's
    first joint (spheres alone leave gaps along a finger); neighbouring palm
    Gaussians are joined too, so the palm is a filled plate.
    """
    m = model.n_gaussians
    centres = gaussian_centres(model, theta)
    bases = attached_points(model, theta, np.arange(5), np.zeros(5, np.int64), np.zeros((5, 3)))
    radii = np.concatenate([model.g_sigmas, np.zeros(5)])
    a_idx, b_idx = [], []
    palm = np.flatnonzero(model.g_chain < 0)
    off = model.g_offsets[palm]
    near = np.linalg.norm(off[:, None, :] - off[None, :, :], axis=-1)
    spacing = np.sort(near + np.eye(palm.size) * 1e9, axis=1)[:, 0].max() * 1.5
    for i in range(palm.size):
        for j in range(i, palm.size):
            if near[i, j] <= spacing:
                a_idx.append(palm[i]), b_idx.append(palm[j])
    for c in range(5):
        ks = np.flatnonzero(model.g_chain == c)
        order = ks[np.lexsort((model.g_offsets[ks, 1], model.g_segment[ks]))]
        radii[m + c] = model.g_sigmas[order[0]]
        chain = [m + c, *order]
        for k0, k1 in zip(chain[:-1], chain[1:]):
            a_idx.append(k0), b_idx.append(k1)
    return np.concatenate([centres, bases]), radii, np.array(a_idx), np.array(b_idx)


_SUBPIXEL_BITS = 3
_SUB = float(1 << _SUBPIXEL_BITS)


def _draw_skin(
    model: HandModel, theta: NDArray[np.float64], intr: Intrinsics, roi: tuple[int, int, int, int]
) -> NDArray[np.float32]:
    """Front depth (mm) of the model's skin over ``roi``; ``inf`` where the skin is absent.

    Each capsule of :func:`_skin` is drawn with OpenCV (two end discs and the
    quad between them, subpixel precision) at one depth, its front surface at
    its middle, far capsules first so that near ones cover them.
    """
    u0, v0, u1, v1 = roi
    out = np.full((v1 - v0, u1 - u0), np.inf, dtype=np.float32)
    P, radii, ia, ib = _skin(model, theta)
    z = np.maximum(P[:, 2], 1.0)
    uv = intr.project(P) - np.array([u0, v0])
    # OpenCV fills every pixel a shape's outline touches: half a pixel wider all round.
    r_px = np.maximum(radii * intr.fx / z - 0.5, 0.0)
    front = 0.5 * (z[ia] + z[ib]) - 0.5 * (radii[ia] + radii[ib])
    ab = uv[ib] - uv[ia]
    normal = np.stack([-ab[:, 1], ab[:, 0]], 1) / np.maximum(np.linalg.norm(ab, axis=1), 1e-9)[:, None]
    for k in np.argsort(-front):
        a, b, value = ia[k], ib[k], float(front[k])
        quad = np.array(
            [uv[a] + r_px[a] * normal[k], uv[b] + r_px[b] * normal[k],
             uv[b] - r_px[b] * normal[k], uv[a] - r_px[a] * normal[k]]
        )
        cv2.fillConvexPoly(out, np.round(quad * _SUB).astype(np.int32), value, cv2.LINE_8, _SUBPIXEL_BITS)
        for e in (a, b):
            if radii[e] > 0:
                centre = (int(round(uv[e, 0] * _SUB)), int(round(uv[e, 1] * _SUB)))
                cv2.circle(out, centre, int(round(r_px[e] * _SUB)), value, -1, cv2.LINE_8, _SUBPIXEL_BITS)
    return out


@dataclass(frozen=True, eq=False)
class _ScoreData:
    """One frame's data inside the scoring box (see :func:`shape_score`)."""

    roi: tuple[int, int, int, int]
    depth: NDArray[np.float32]  # (h, w) mm, 0 = none
    points: NDArray[np.float64]  # (h, w, 3) back-projected pixels, mm


def _score_data(pre: Preprocessed, roi: tuple[int, int, int, int]) -> _ScoreData:
    intr = pre.intrinsics
    u0, v0, u1, v1 = (max(0, roi[0]), max(0, roi[1]), min(intr.width, roi[2]), min(intr.height, roi[3]))
    u1, v1 = max(u1, u0), max(v1, v0)
    depth = pre.depth_mm[v0:v1, u0:u1].astype(np.float32)
    vv, uu = np.mgrid[v0:v1, u0:u1]
    pts = intr.backproject(np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64), depth.ravel().astype(np.float64))
    return _ScoreData((u0, v0, u1, v1), depth, pts.reshape(depth.shape + (3,)))


def _score(model: HandModel, theta: NDArray[np.float64], data: _ScoreData, intr: Intrinsics, tolerance_mm: float) -> float:
    if data.depth.size == 0:
        return 0.0
    model_depth = _draw_skin(model, theta, intr, data.roi)
    covered = np.isfinite(model_depth)
    beyond_wrist = (data.points - theta[:3]) @ global_rotation(theta)[:, 1] > 0.0
    hand = (data.depth > 0) & beyond_wrist
    both = covered & hand & (np.abs(model_depth - data.depth) < tolerance_mm)
    return float(both.sum() / max((covered | hand).sum(), 1))


def shape_score(
    model: HandModel,
    theta: NDArray[np.float64],
    pre: Preprocessed,
    roi: tuple[int, int, int, int],
    tolerance_mm: float = _TOLERANCE_MM,
) -> float:
    """Depth-aware overlap of the model's silhouette with the hand's, in [0, 1].

    The model's skin is drawn as capsules joining consecutive Gaussians of each
    chain and neighbouring palm Gaussians (radii = their sigmas, mm), projected
    into the image at the resolution of ``pre``.  Data pixels count if they lie
    inside ``roi`` (u0, v0, u1, v1, px, end-exclusive) and on the finger side
    of the wrist (the forearm is not part of the model).  Score = pixels
    covered by both with depths within ``tolerance_mm`` (mm), divided by pixels
    covered by either.
    """
    return _score(model, theta, _score_data(pre, roi), pre.intrinsics, tolerance_mm)


def _keep_palm_centre(theta: NDArray[np.float64], old: HandModel, new: HandModel) -> NDArray[np.float64]:
    """Move the wrist so that the palm centre stays put when the model is rescaled."""
    palm = old.g_chain < 0
    c_old = gaussian_centres(old, theta)[palm].mean(axis=0)
    c_new = gaussian_centres(new, theta)[palm].mean(axis=0)
    out = theta.copy()
    out[:3] += c_old - c_new
    return out


_RIGID = np.arange(N_PARAMS) < 6


def _refine(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ImageSoG,
    config: TrackerConfig,
    iters: int,
    rigid: bool = False,
) -> NDArray[np.float64]:
    """``theta`` (26,) refined by the tracking objective; only the global pose when ``rigid``."""
    res = maximise(Objective(model, data, config), theta, iterations=iters, active=_RIGID if rigid else None)
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
    if datas[0].n:
        # Score only around the hand's data (plus a margin for a model too large).
        lo = np.floor((datas[0].mu - datas[0].sigma[:, None]).min(axis=0)) - _SCORE_MARGIN_PX
        hi = np.ceil((datas[0].mu + datas[0].sigma[:, None]).max(axis=0)) + _SCORE_MARGIN_PX
        roi = (int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1)
    if datas[0].n == 0 or coverage(mirrored, pose, datas[0]) < config.lost_confidence:
        raise CalibrationError("no hand in view (hold an open hand toward the camera)")

    scoring = [_score_data(p, roi) for p in pres]
    intr = pres[0].intrinsics

    def evaluate(
        shape: HandShape, start: NDArray[np.float64], start_model: HandModel
    ) -> tuple[float, NDArray[np.float64]]:
        """Score ``shape`` scaled about the palm centre of ``start`` (a pose of ``start_model``)."""
        m = mirrored.scaled(shape)
        th = _keep_palm_centre(start, start_model, m)
        return sum(_score(m, th, sd, intr, _TOLERANCE_MM) for sd in scoring) / len(scoring), th

    best_shape = model.shape
    pose_model = mirrored.scaled(best_shape)
    # The user holds an open hand: after one pose fit with the starting model the
    # fingers are set open (a wrongly sized model bends them to make up for it).
    start = _refine(pose_model, pose, datas[0], config, _REFIT_ITERATIONS)
    start[6:] = _OPEN_JOINTS
    start = _refine(pose_model, start, datas[0], config, _REFIT_ITERATIONS, rigid=True)
    before, best_pose = evaluate(best_shape, start, pose_model)
    best_val = before
    for round_no, (span, step) in enumerate(_ROUNDS):
        if round_no > 0:
            # Refit the pose with the model found so far: a pose fitted with a
            # wrongly sized model is biased toward that size.
            pose_model = mirrored.scaled(best_shape)
            start = _refine(pose_model, best_pose, datas[0], config, _REFIT_ITERATIONS, rigid=True)
            val, th = evaluate(best_shape, start, pose_model)
            if val > best_val:
                best_val, best_pose = val, th
            else:
                start = best_pose
        for name in _SEARCH_ORDER[round_no]:
            for offset in np.arange(-span, span + 1e-9, step):
                cand = _candidate(best_shape, name, offset)
                if cand is None:
                    continue
                val, th = evaluate(cand, start, pose_model)
                if val > best_val:
                    best_val, best_shape, best_pose = val, cand, th
    fitted = mirrored.scaled(best_shape)
    after = best_val
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
