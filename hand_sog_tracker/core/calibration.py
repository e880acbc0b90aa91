"""User-specific hand model: greedy search over four scale factors (paper 000, sec. 5.4).

The user holds an open hand toward the camera (any position and in-plane
orientation).  One pose fit with the current model locates the palm and its
orientation; the fingers are then set open.  For each scale factor in turn
(length, width, sigma, depth) every value of a fixed grid is tried with the
others held at their best so far; each candidate model is scaled about the
fitted palm centre and scored.  Two passes, the second on a finer grid around
the first result.

Score.  The tracking objective's similarity term is normalised by the data
alone, so a larger model always covers more data and scores higher; fitting
shape with it drifts to the largest model.  Candidates are therefore scored by
a depth-aware silhouette overlap (:func:`shape_score`), which is largest when
the model's skin and the hand's data cover the same pixels at the same depth.

Known limitation: the pose is fitted once with the *starting* model, and that
pose is biased toward the starting size, so the fitted factors are pulled
toward the starting ones (see the README's calibration section for numbers).
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
from hand_sog_tracker.core.kinematics import attached_points, gaussian_centres, global_rotation
from hand_sog_tracker.core.optimizer import maximise
from hand_sog_tracker.core.tracker import Tracker, coverage, hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import CalibrationError, HandSogError

__all__ = ["CalibrationResult", "calibrate", "shape_score", "SEARCH_RANGE"]

#: Fixed search range of every scale factor.
SEARCH_RANGE = (0.8, 1.25)
_ORDER = ("length", "width", "sigma", "depth")
_COARSE = 7
_FINE_STEP = 0.015
_SCORE_MARGIN_PX = 12
_REFIT_ITERATIONS = 15
_OPEN_JOINTS = np.array([0.1, 0.0, 0.1, 0.1] + [0.05, 0.0, 0.05, 0.05] * 4)
_STRIDE = 3


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


def shape_score(
    model: HandModel,
    theta: NDArray[np.float64],
    pre: Preprocessed,
    roi: tuple[int, int, int, int],
    tolerance_mm: float = 12.0,
    stride: int = 2,
) -> float:
    """Depth-aware overlap of the model's silhouette with the hand's, in [0, 1].

    The model's skin is drawn as capsules joining consecutive Gaussians of each
    chain and neighbouring palm Gaussians (radii = their sigmas), projected
    into the image; each covered pixel gets the capsule's front depth.  Data
    pixels count if they lie inside ``roi`` and on the finger side of the
    wrist (the forearm is not part of the model).  Score = pixels covered by
    both with depths within ``tolerance_mm``, divided by pixels covered by
    either, on every ``stride``-th pixel.
    """
    intr = pre.intrinsics
    u0, v0, u1, v1 = (max(0, roi[0]), max(0, roi[1]), min(intr.width, roi[2]), min(intr.height, roi[3]))
    if u1 <= u0 or v1 <= v0:
        return 0.0
    vv, uu = np.mgrid[v0:v1:stride, u0:u1:stride]
    pix = np.stack([uu.reshape(-1), vv.reshape(-1)], 1).astype(np.float64)  # (k, 2)
    d = pre.depth_mm[v0:v1:stride, u0:u1:stride].astype(np.float64).reshape(-1)
    P, radii, ia, ib = _skin(model, theta)
    z = np.maximum(P[:, 2], 1.0)
    uv = intr.project(P)
    rad = radii * intr.fx / z
    a, b = uv[ia], uv[ib]  # (c, 2)
    ab = b - a
    len2 = np.maximum((ab * ab).sum(1), 1e-9)
    t = np.clip(((pix[None, :, :] - a[:, None, :]) * ab[:, None, :]).sum(-1) / len2[:, None], 0.0, 1.0)
    closest = a[:, None, :] + t[:, :, None] * ab[:, None, :]
    dist2 = ((pix[None, :, :] - closest) ** 2).sum(-1)
    r_px = rad[ia][:, None] + t * (rad[ib] - rad[ia])[:, None]
    inside = dist2 < r_px * r_px
    r_mm = radii[ia][:, None] + t * (radii[ib] - radii[ia])[:, None]
    z_c = z[ia][:, None] + t * (z[ib] - z[ia])[:, None]
    bulge = np.sqrt(np.maximum(1.0 - dist2 / np.maximum(r_px * r_px, 1e-9), 0.0))
    front = np.where(inside, z_c - r_mm * bulge, np.inf)
    model_depth = front.min(axis=0)
    covered = np.isfinite(model_depth)
    data_pts = intr.backproject(pix, d)
    R = global_rotation(theta)
    beyond_wrist = (data_pts - theta[:3]) @ R[:, 1] > 0.0
    data = (d > 0) & beyond_wrist
    both = covered & data & (np.abs(model_depth - d) < tolerance_mm)
    union = covered | data
    return float(both.sum() / max(union.sum(), 1))


def _keep_palm_centre(theta: NDArray[np.float64], old: HandModel, new: HandModel) -> NDArray[np.float64]:
    """Move the wrist so that the palm centre stays put when the model is rescaled."""
    palm = old.g_chain < 0
    c_old = gaussian_centres(old, theta)[palm].mean(axis=0)
    c_new = gaussian_centres(new, theta)[palm].mean(axis=0)
    out = theta.copy()
    out[:3] += c_old - c_new
    return out


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
    if datas[0].n:
        # Score only around the hand's data (plus a margin for a model too large).
        lo = np.floor((datas[0].mu - datas[0].sigma[:, None]).min(axis=0)) - _SCORE_MARGIN_PX
        hi = np.ceil((datas[0].mu + datas[0].sigma[:, None]).max(axis=0)) + _SCORE_MARGIN_PX
        roi = (int(lo[0]), int(lo[1]), int(hi[0]) + 1, int(hi[1]) + 1)
    if datas[0].n == 0 or coverage(mirrored, pose, datas[0]) < config.lost_confidence:
        raise CalibrationError("no hand in view (hold an open hand toward the camera)")

    def evaluate(
        shape: HandShape, start: NDArray[np.float64], start_model: HandModel
    ) -> tuple[float, NDArray[np.float64]]:
        """Score ``shape`` from a pose fitted with ``start_model``."""
        m = mirrored.scaled(shape)
        th = _keep_palm_centre(start, start_model, m)
        return sum(shape_score(m, th, p, roi, stride=_STRIDE) for p in pres) / len(pres), th

    best_shape = model.shape
    best_model = mirrored.scaled(best_shape)
    # One pose fit locates the palm and its orientation; the user holds an open
    # hand, so the fingers are then set open and every candidate is scaled
    # about that palm centre and scored without further pose changes (a pose
    # refitted with a wrongly sized model is biased toward that size).
    start = _refine(best_model, pose, datas[0], config, _REFIT_ITERATIONS)
    start[6:] = _OPEN_JOINTS
    before, best_pose = evaluate(best_shape, start, best_model)
    best_val = before
    for pass_no in range(2):
        for name in _ORDER:
            if pass_no == 0:
                grid = np.linspace(*SEARCH_RANGE, _COARSE)
            else:
                c = getattr(best_shape, name)
                grid = np.clip(c + _FINE_STEP * np.arange(-3, 4), *SEARCH_RANGE)
            for value in grid:
                cand = HandShape(**{**best_shape.__dict__, name: float(value)})
                val, th = evaluate(cand, start, best_model)
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
