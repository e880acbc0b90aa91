"""Salient points: fingertip detections on the depth and their assignment to the model's fingertips.

Seed 001 (sec. 3.2.5, Table 1) adds fingertip detections to a generative tracker: each frame
the detections are assigned to model fingertips by an optimal assignment in which a detection
may be declared a false positive (cost ``lambda * w_s``) and a fingertip may stay without a
detection (cost ``lambda``); the assigned pairs pull the model's fingertips towards the
detections.  The detector here needs no training data: a fingertip is where the hand surface
ends in a finger-wide tube (see :func:`detect_fingertips`).

Units: millimetres in the camera optical frame, pixels of the processing image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import SHARED_MARGIN_PX, Preprocessed, _in_window, hand_window
from hand_sog_tracker.core.objective import TipTargets

# The detector is this package's own (seed 001 trains one): every constant below is chosen
# here from the default hand's sizes, the reason beside it.

__all__ = [
    "Detections",
    "MAX_DETECTIONS",
    "RING_RADIUS_MM",
    "detect_fingertips",
    "assign_detections",
    "assigned_targets",
]

#: Radius of the sampling ring around a candidate pixel (mm at the hand's depth): larger than a
#: finger's half-width (7-10 mm) so that the ring leaves the finger sideways, smaller than a
#: finger segment.
RING_RADIUS_MM: Final[float] = 17.0
#: Ring samples around a pixel.
RING_SAMPLES: Final[int] = 16
#: Two depths within this (mm) belong to the same surface.
SAME_SURFACE_MM: Final[float] = 14.0
#: A finger seen end-on is nearer than the ring around it by at least this (mm).
END_ON_MM: Final[float] = 18.0
#: Fingertip detections sit this far behind the surface (mm): the centre of the model's
#: fingertip sphere is one finger radius inside the skin.
TIP_DEPTH_OFFSET_MM: Final[float] = 8.0
#: Smallest candidate region kept, as a share of the expected tip region's area.
MIN_REGION_SHARE: Final[float] = 0.15
#: Most detections kept in a region of interest (most confident first).
MAX_DETECTIONS: Final[int] = 8


@dataclass(frozen=True, eq=False)
class Detections:
    """Fingertip detections of one frame.

    Attributes
    ----------
    points : array, shape (S, 3), mm
        Detected fingertip centres, camera optical frame (one finger radius behind the skin).
    uv : array, shape (S, 2), px
        Their pixels in the processing image.
    confidence : array, shape (S,)
        In (0, 1]: how tip-like the region is (its size against the expected size).
    end_on : bool array, shape (S,)
        True for fingers seen end-on (pointing at the camera).
    """

    points: NDArray[np.float64]
    uv: NDArray[np.float64]
    confidence: NDArray[np.float64]
    end_on: NDArray[np.bool_]

    @property
    def n(self) -> int:
        """Number of detections ``S``."""
        return int(self.confidence.shape[0])

    def subset(self, keep: NDArray[np.bool_]) -> "Detections":
        """The detections where ``keep`` (shape (S,)) is True."""
        return Detections(self.points[keep], self.uv[keep], self.confidence[keep], self.end_on[keep])

    @staticmethod
    def empty() -> "Detections":
        """No detections."""
        return Detections(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool))


_QUARTER = RING_SAMPLES // 4
_RING_ANGLES = 2.0 * np.pi * np.arange(_QUARTER + 1) / RING_SAMPLES  # first quadrant
_RING_COS = np.cos(_RING_ANGLES)


def _reflected(q: NDArray[np.int64]) -> NDArray[np.int64]:
    """The ring offsets (du, dv), shape (RING_SAMPLES, 2), from their first-quadrant values
    ``q`` (QUARTER + 1,): reflected into the other quadrants, counter-clockwise from +u."""
    du = np.concatenate([q, -q[-2::-1], -q[1:], q[-2:0:-1]])
    dv = np.concatenate([q[::-1], q[1:], -q[-2::-1], -q[1:-1]])
    return np.stack([du, dv], 1)


# The reflection as a gather: offsets = _RING_SIGN * q[_RING_INDEX] (from 1-based q, whose
# signs survive the reflection).
_RING_CODE = _reflected(np.arange(1, _QUARTER + 2))
_RING_INDEX, _RING_SIGN = np.abs(_RING_CODE) - 1, np.sign(_RING_CODE)


def _ring_offsets(radius_px: float) -> NDArray[np.int64]:
    """Ring sample offsets (du, dv), shape (RING_SAMPLES, 2), px, counter-clockwise from +u.

    Rounded in the first quadrant and reflected into the others (:func:`_reflected`), so that
    the ring is exactly symmetric under u -> -u, v -> -v and u <-> v (a mirrored image sees
    the mirrored ring).
    """
    q = np.round(_RING_COS * radius_px).astype(np.int64)  # du of angles 0..90 deg
    return q.take(_RING_INDEX) * _RING_SIGN  # (= _reflected(q), one gather)


def detect_fingertips(
    pre: Preprocessed,
    roi: tuple[int, int, int, int],
    window_mm: tuple[float, float],
    max_detections: int | None = MAX_DETECTIONS,
) -> Detections:
    """Detect fingertips in the depth inside a region of interest.

    A pixel is a fingertip candidate when a ring of radius :data:`RING_RADIUS_MM` around it
    meets the pixel's own surface in one short arc only (a finger-wide tube that ends here,
    seen from the side), or not at all while the ring lies behind the pixel by
    :data:`END_ON_MM` (a finger pointing at the camera).  Rings that leave the image, or meet
    a surface in front of the pixel (an occluder), disqualify it.  Connected candidate
    regions become detections at their centroid.

    Parameters
    ----------
    pre : Preprocessed
        The frame at processing resolution (mm, 0 = invalid).
    roi : (u0, v0, u1, v1)
        End-exclusive pixel box to search (clipped to the image).
    window_mm : (near, far)
        Depth window of the hand (mm); depth outside it counts as no data.
    max_detections : int or None
        Keep at most this many, the most confident first (None: all).

    Returns
    -------
    Detections
    """
    depth = pre.depth_mm
    h, w = depth.shape
    u0, v0, u1, v1 = max(roi[0], 0), max(roi[1], 0), min(roi[2], w), min(roi[3], h)
    if u1 - u0 < 8 or v1 - v0 < 8:
        return Detections.empty()
    near, far = window_mm
    # The windowed depth around the ROI, shared with the quadtree and the silhouette.
    hw = hand_window(pre, roi, window_mm)
    d = hw.view(u0, v0, u1, v1)
    intr = pre.intrinsics
    # Candidates: valid pixels on a 2-pixel grid (a tip region is several pixels wide),
    # anchored on the pixel nearest the principal point (not on the ROI): the mirror image
    # (u -> W - 1 - u, cx -> W - 1 - cx) samples the mirrored pixels, and a ROI moving by a
    # pixel samples the same ones.  (cu, cv): first grid pixel in the ROI.
    cu = int(np.floor(intr.cx + 0.5) - u0) % 2
    cv = int(np.floor(intr.cy + 0.5) - v0) % 2
    grid_valid = d[cv::2, cu::2] > 0  # (a quarter of the comparisons; contiguous)
    gw = grid_valid.shape[1]
    cell = grid_valid.ravel().nonzero()[0]
    # Fewer than 20 valid pixels in the ROI: no detections.  The grid's valid pixels are some
    # of them: only with fewer than 20 on the grid are all counted.  (Inside the image the
    # window holds no negative values: its nonzero pixels are the valid ones, counted by
    # OpenCV without a boolean image.)
    if cell.size < 20 and cv2.countNonZero(d) < 20:
        return Detections.empty()
    gv = cell // gw  # (row and column of the grid cells: cheaper than np.divmod and 2-d nonzero)
    gu = cell - gv * gw
    # The candidates' depths, gathered from the shared window (flat indices ``centre`` of the
    # pixels (v0 + cv + 2 gv, u0 + cu + 2 gu)).
    stride = hw.depth.shape[1]
    flat = hw.depth.ravel()
    centre = gv * (2 * stride) + gu * 2
    centre += (v0 + cv - hw.v0) * stride + (u0 + cu - hw.u0)
    dc = flat.take(centre)
    # The hand's depth: the median over the candidates (a quarter of the pixels).
    z_ref = _median(dc if dc.size else d[d > 0])
    f = float(np.sqrt(intr.fx * intr.fy))
    r_px = max(RING_RADIUS_MM * f / z_ref, 3.0)
    offsets = _ring_offsets(r_px)
    pad = int(np.abs(offsets).max()) + 1
    # Ring samples read the ROI padded by the ring: outside the image is "unknown" (-1),
    # invalid is 0.  The shared window is exactly that when the ring fits in its margin.
    if pad > SHARED_MARGIN_PX:  # a ring wider than the shared margin (a hand nearer than 200 mm)
        hh, ww = v1 - v0, u1 - u0
        big = np.full((hh + 2 * pad, ww + 2 * pad), -1.0, np.float32)
        cu0, cv0 = max(u0 - pad, 0), max(v0 - pad, 0)
        cu1, cv1 = min(u1 + pad, w), min(v1 + pad, h)
        big[cv0 - v0 + pad : cv1 - v0 + pad, cu0 - u0 + pad : cu1 - u0 + pad] = _in_window(
            depth[cv0:cv1, cu0:cu1], near, far, nan_free=True
        )
        stride = big.shape[1]
        flat = big.ravel()
        centre = gv * (2 * stride) + gu * 2
        centre += (cv + pad) * stride + (cu + pad)
    step = offsets[:, 1] * stride + offsets[:, 0]  # flat offsets of the ring samples
    # First the four samples on the axes (every quarter of the ring): a fingertip seen from
    # the side meets its own surface in one arc of at most a quarter of the ring, and any
    # quarter-long arc holds exactly one axis sample; end-on, none.  So two or more axis
    # samples on the pixel's surface, or one blocked, rule a candidate out exactly, and the
    # full ring is sampled only for the rest (most of the hand's inside goes here).
    q = RING_SAMPLES // 4
    # (Gathers by ``take``, cheaper than indexing; counts of booleans summed as uint8, exact
    # up to 255, cheaper than the default int64 sums.)
    s = flat.take(centre[None, :] + step[::q, None])
    diff = s - dc
    on_surface = s > 0
    n_axis = _count(on_surface & (np.abs(diff) < SAME_SURFACE_MM))
    axis_blocked = _any(np.logical_or(s < 0, on_surface & (diff < -SAME_SURFACE_MM)))
    cand = np.flatnonzero((n_axis <= 1) & ~axis_blocked)
    dcc = dc.take(cand)
    # All ring samples of the remaining candidates at once, shape (RING_SAMPLES, candidates).
    s = flat.take(centre.take(cand)[None, :] + step[:, None])
    diff = s - dcc
    on_surface = s > 0
    same = on_surface & (np.abs(diff) < SAME_SURFACE_MM)
    blocked = _any(np.logical_or(s < 0, on_surface & (diff < -SAME_SURFACE_MM)))
    behind = _count(np.logical_or(s == 0, diff > END_ON_MM))
    n_same = _count(same)
    # Changes between neighbouring ring samples, the ring closed (last to first).
    transitions = _count(same[1:] != same[:-1]) + (same[0] != same[-1])
    side_tip = (n_same >= 1) & (n_same <= RING_SAMPLES // 4) & (transitions == 2)
    end_on = (n_same == 0) & (behind >= RING_SAMPLES - 2)
    keep = ~blocked & (side_tip | end_on)
    if not keep.any():
        return Detections.empty()
    sel = cand[keep]  # increasing, like the candidates
    grid = np.zeros(grid_valid.shape, np.uint8)
    gcell = cell[sel]  # flat index in the grid (of row gv, column gu)
    gv, gu = gv.take(sel), gu.take(sel)
    grid.reshape(-1)[gcell] = 1
    # Labels only (the statistics of connectedComponentsWithStats cost several times more);
    # areas and centroids from the candidate cells, each cell once: integer sums, exact.
    n_lab, labels = cv2.connectedComponents(grid, connectivity=8)
    lab = labels.reshape(-1).take(gcell) - 1
    n_reg = n_lab - 1
    cnt = np.bincount(lab, minlength=n_reg)
    expected = np.pi * (0.5 * r_px) ** 2 / 4.0  # in grid cells
    area = cnt.astype(np.float64)
    big = np.flatnonzero(area >= MIN_REGION_SHARE * expected)
    if big.size == 0:
        return Detections.empty()
    # Per region: mean depth and share of end-on cells, from the candidate cells' labels.
    z_sum = np.bincount(lab, weights=dcc[keep], minlength=n_reg)
    end_sum = np.bincount(lab, weights=end_on[keep].astype(np.float64), minlength=n_reg)
    cents = np.empty((n_reg, 2))
    cents[:, 0] = np.bincount(lab, weights=gu.astype(np.float64), minlength=n_reg)
    cents[:, 1] = np.bincount(lab, weights=gv.astype(np.float64), minlength=n_reg)
    cents /= area[:, None]
    cnt = np.maximum(cnt, 1)
    uv_all = 2.0 * cents + np.array([u0 + cu, v0 + cv], dtype=np.float64)
    z_all = z_sum / cnt + TIP_DEPTH_OFFSET_MM
    uvs = uv_all[big]
    pts = intr.backproject(uvs, z_all[big])
    conf = np.minimum(1.0, area[big] / expected)
    ends = end_sum[big] / cnt[big] > 0.5
    # Most confident first; ties (many regions have confidence 1) by row, then by distance
    # from the principal point's column, then depth: an order the mirror image keeps.
    order = np.lexsort((pts[:, 2], np.abs(uvs[:, 0] - intr.cx), uvs[:, 1], -conf))[:max_detections]
    return Detections(points=pts[order], uv=uvs[order], confidence=conf[order], end_on=ends[order])


def _count(flags: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """``flags.sum(axis=0)`` of a (k, n) boolean array with ``k <= 255``, as uint8 (exact)."""
    return np.add.reduce(flags.view(np.uint8), axis=0, dtype=np.uint8)


def _any(flags: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``flags.any(axis=0)`` without the method's Python layer."""
    return np.logical_or.reduce(flags, axis=0)


def _median(a: NDArray[np.float32]) -> float:
    """``float(np.median(a))`` of a non-empty 1D array, by one partition (several times faster)."""
    n = a.size
    k = n // 2
    part = np.partition(a, k)
    if n % 2:
        return float(part[k])
    # The lower middle value is the largest of the first k after the partition; the mean of
    # the two as np.median takes it.
    lo, hi = part[:k].max(), part[k]
    if a.dtype == np.float32:
        # (np.mean of two float32 values: their float32 sum, halved; halving is exact.)
        return float(lo + hi) / 2.0
    return float(np.mean(np.array([lo, hi], dtype=a.dtype)))


_SUBSETS: dict[int, tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]] = {}


def _subset_tables(S: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Tables of the subsets ``D`` of ``S`` detections: ``bits[D, s]`` (2^S, S) (1 when
    detection ``s`` is in ``D``), ``prev[s, D] = D - {s}`` (S, 2^S) where ``s`` is in ``D`` and
    ``2^S`` (one past the last subset: an infinite cost there) where it is not, and
    ``1 - bits`` (2^S, S) as floats."""
    hit = _SUBSETS.get(S)
    if hit is None:
        masks = np.arange(1 << S)
        bits = (masks[:, None] >> np.arange(S)[None, :]) & 1
        prev = np.where(bits > 0, masks[:, None] & ~(1 << np.arange(S))[None, :], 1 << S)
        hit = (bits, np.ascontiguousarray(prev.T), (1 - bits).astype(np.float64))
        _SUBSETS[S] = hit
    return hit


def assign_detections(
    tips_mm: NDArray[np.float64],
    det: Detections,
    lam_mm: float,
    tip_lam_mm: NDArray[np.float64] | None = None,
) -> NDArray[np.int64]:
    """Optimal assignment of detections to model fingertips (seed 001, eq. 11, Table 1).

    Minimises ``sum_assigned |tip_t - det_s| + lam sum_unassigned_s w_s + lam
    sum_unassigned_t 1`` with ``w_s`` the detection confidence, each detection and each
    fingertip used at most once.  Solved exactly by dynamic programming over the fingertips
    with the set of used detections as state (``T * 2^S * S`` steps; ``S <= 10``).

    Parameters
    ----------
    tips_mm : array, shape (T, 3)
        Model fingertips (mm).
    det : Detections
    lam_mm : float
        The cost ``lambda`` of a fingertip without a detection (mm); a detection declared a
        false positive costs ``lambda * confidence``.
    tip_lam_mm : array, shape (T,), optional
        Per fingertip, the cost of leaving it without a detection (mm) instead of ``lam_mm``.

    Returns
    -------
    int array, shape (T,)
        Index of the detection assigned to each fingertip, -1 for none.
    """
    T, S = tips_mm.shape[0], det.n
    out = np.full(T, -1, dtype=np.int64)
    if S == 0:
        return out
    if S > 10:
        raise ValueError(f"at most 10 detections can be assigned, got {S}")
    diff = tips_mm[:, None, :] - det.points[None, :, :]
    cost = np.sqrt(np.add.reduce(diff * diff, axis=-1))  # (T, S), = np.linalg.norm(diff, axis=-1)
    _, prev, not_bits = _subset_tables(S)
    n_masks = 1 << S
    # best[t, D]: the least cost of fingertips 0 .. t-1 using the detections D; one column
    # more, always infinite, that prev points to for a detection not in D.
    best = np.full((T + 1, n_masks + 1), np.inf)
    best[0, 0] = 0.0
    # cand[t, c, D]: the cost of the set D of used detections after fingertip t with choice
    # c: fingertip t without a detection (c = 0), or with detection s of D (c = s + 1) after
    # the set D - {s}.  One row per choice: the minimum over the choices runs along
    # contiguous rows; the choice itself is read only along the path the backtracking takes.
    cand = np.empty((T, S + 1, n_masks))
    for t in range(T):
        np.add(best[t, :n_masks], lam_mm if tip_lam_mm is None else tip_lam_mm[t], out=cand[t, 0])
        np.add(best[t].take(prev), cost[t][:, None], out=cand[t, 1:])  # (inf + cost = inf off D)
        np.minimum.reduce(cand[t], axis=0, out=best[t + 1, :n_masks])
    # Detections left unused are false positives.
    unused = not_bits @ (lam_mm * det.confidence)
    mask = int(np.argmin(best[T, :n_masks] + unused))
    for t in range(T, 0, -1):
        # The first minimum wins, as "none" and then s = 0, 1, ... would in a sequential update.
        s = int(cand[t - 1, :, mask].argmin()) - 1
        out[t - 1] = s
        if s >= 0:
            mask &= ~(1 << s)
    return out


def assigned_targets(
    tips_mm: NDArray[np.float64], det: Detections, lam_mm: float, end_on: bool
) -> TipTargets | None:
    """The detections :func:`assign_detections` gives the fingertips, as the salient term's
    targets (weight = the detection's confidence, 0 for a fingertip without one); None
    without detections.  ``end_on``: whether detections of fingers seen end-on count."""
    if det.n == 0:
        return None
    assigned = assign_detections(tips_mm, det, lam_mm)
    has = assigned >= 0
    if not end_on:
        has &= ~det.end_on[np.maximum(assigned, 0)]
    points = np.zeros((5, 3))
    points[has] = det.points[assigned[has]]
    return TipTargets(points=points, weights=np.where(has, det.confidence[np.maximum(assigned, 0)], 0.0))
