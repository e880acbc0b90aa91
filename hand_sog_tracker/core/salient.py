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

from hand_sog_tracker.core.depth_sog import Preprocessed, _in_window

# The detector is this package's own (seed 001 trains one): every constant below is chosen
# here from the default hand's sizes, the reason beside it.

__all__ = [
    "Detections",
    "RING_RADIUS_MM",
    "detect_fingertips",
    "assign_detections",
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


_RING_ANGLES = 2.0 * np.pi * np.arange(RING_SAMPLES) / RING_SAMPLES
_RING_UNIT = np.stack([np.cos(_RING_ANGLES), np.sin(_RING_ANGLES)], 1)  # (RING_SAMPLES, 2)


def _ring_offsets(radius_px: float) -> NDArray[np.int64]:
    return np.round(_RING_UNIT * radius_px).astype(np.int64)


def detect_fingertips(
    pre: Preprocessed,
    roi: tuple[int, int, int, int],
    window_mm: tuple[float, float],
    max_detections: int = 8,
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
    max_detections : int
        Keep at most this many, the most confident first.

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
    d = _in_window(depth[v0:v1, u0:u1], near, far)
    valid = d > 0
    vals = d[valid]
    if vals.size < 20:
        return Detections.empty()
    intr = pre.intrinsics
    f = float(np.sqrt(intr.fx * intr.fy))
    z_ref = float(np.median(vals, overwrite_input=True))
    r_px = max(RING_RADIUS_MM * f / z_ref, 3.0)
    offsets = _ring_offsets(r_px)
    pad = int(np.abs(offsets).max()) + 1
    # The ROI padded by the ring: outside the image is "unknown" (-1), invalid is 0.  The
    # ROI itself is ``d``; only the strips around it are windowed here.
    hh, ww = v1 - v0, u1 - u0
    big = np.full((hh + 2 * pad, ww + 2 * pad), -1.0, np.float32)
    bu0, bv0 = max(u0 - pad, 0), max(v0 - pad, 0)
    bu1, bv1 = min(u1 + pad, w), min(v1 + pad, h)
    big[pad : pad + hh, pad : pad + ww] = d
    for r0, r1, c0, c1 in ((bv0, v0, bu0, bu1), (v1, bv1, bu0, bu1), (v0, v1, bu0, u0), (v0, v1, u1, bu1)):
        if r1 > r0 and c1 > c0:
            src = depth[r0:r1, c0:c1]
            big[r0 - v0 + pad : r1 - v0 + pad, c0 - u0 + pad : c1 - u0 + pad] = np.where(
                (src > near) & (src < far), src, np.float32(0.0)
            )
    # Candidates: valid pixels on a 2-pixel grid (a tip region is several pixels wide).
    grid_valid = valid[::2, ::2]
    vv, uu = np.divmod(np.flatnonzero(grid_valid), grid_valid.shape[1])
    vv, uu = vv * 2, uu * 2
    stride = big.shape[1]
    flat = big.ravel()
    centre = (vv + pad) * stride + (uu + pad)
    dc = flat[centre]
    # All ring samples of all candidates at once, shape (RING_SAMPLES, candidates).
    s = flat[centre[None, :] + (offsets[:, 1] * stride + offsets[:, 0])[:, None]]
    diff = s - dc
    on_surface = s > 0
    same = on_surface & (np.abs(diff) < SAME_SURFACE_MM)
    blocked = ((s < 0) | (on_surface & (diff < -SAME_SURFACE_MM))).any(axis=0)
    behind = ((s == 0) | (diff > END_ON_MM)).sum(axis=0)
    n_same = same.sum(0)
    # Changes between neighbouring ring samples, the ring closed (last to first).
    transitions = (same[1:] != same[:-1]).sum(0) + (same[0] != same[-1])
    side_tip = (n_same >= 1) & (n_same <= RING_SAMPLES // 4) & (transitions == 2)
    end_on = (n_same == 0) & (behind >= RING_SAMPLES - 2)
    keep = ~blocked & (side_tip | end_on)
    if not keep.any():
        return Detections.empty()
    grid = np.zeros(((hh + 1) // 2, (ww + 1) // 2), np.uint8)
    gv, gu = vv[keep] // 2, uu[keep] // 2
    grid[gv, gu] = 1
    # Labels only (the statistics of connectedComponentsWithStats cost several times more);
    # areas and centroids from the candidate cells, each cell once: integer sums, exact.
    n_lab, labels = cv2.connectedComponents(grid, connectivity=8)
    lab = labels[gv, gu] - 1
    n_reg = n_lab - 1
    cnt = np.bincount(lab, minlength=n_reg)
    expected = np.pi * (0.5 * r_px) ** 2 / 4.0  # in grid cells
    area = cnt.astype(np.float64)
    big = np.flatnonzero(area >= MIN_REGION_SHARE * expected)
    if big.size == 0:
        return Detections.empty()
    # Per region: mean depth and share of end-on cells, from the candidate cells' labels.
    z_sum = np.bincount(lab, weights=dc[keep], minlength=n_reg)
    end_sum = np.bincount(lab, weights=end_on[keep].astype(np.float64), minlength=n_reg)
    cents = np.stack(
        [np.bincount(lab, weights=gu.astype(np.float64), minlength=n_reg),
         np.bincount(lab, weights=gv.astype(np.float64), minlength=n_reg)], axis=1,
    ) / area[:, None]
    cnt = np.maximum(cnt, 1)
    uv_all = 2.0 * cents + np.array([u0, v0], dtype=np.float64)
    z_all = z_sum / cnt + TIP_DEPTH_OFFSET_MM
    uvs = uv_all[big]
    pts = intr.backproject(uvs, z_all[big])
    conf = np.minimum(1.0, area[big] / expected)
    ends = end_sum[big] / cnt[big] > 0.5
    order = np.argsort(conf)[::-1][:max_detections]
    return Detections(points=pts[order], uv=uvs[order], confidence=conf[order], end_on=ends[order])


_SUBSETS: dict[int, tuple[NDArray[np.int64], NDArray[np.int64]]] = {}


def _subset_tables(S: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``bits[D, s]`` (detection ``s`` in subset ``D``) and ``prev[D, s] = D - {s}``, (2^S, S)."""
    hit = _SUBSETS.get(S)
    if hit is None:
        masks = np.arange(1 << S)
        bits = (masks[:, None] >> np.arange(S)[None, :]) & 1
        prev = masks[:, None] & ~(1 << np.arange(S))[None, :]
        hit = (bits, prev)
        _SUBSETS[S] = hit
    return hit


def assign_detections(
    tips_mm: NDArray[np.float64],
    det: Detections,
    lam_mm: float,
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
    cost = np.linalg.norm(tips_mm[:, None, :] - det.points[None, :, :], axis=-1)  # (T, S)
    bits, prev = _subset_tables(S)
    n_masks = 1 << S
    best = np.full((T + 1, n_masks), np.inf)
    choice = np.full((T + 1, n_masks), -1, dtype=np.int64)
    best[0, 0] = 0.0
    cand = np.empty((n_masks, S + 1))
    for t in range(T):
        # Set D of used detections after fingertip t: fingertip t without a detection
        # (column 0), or with detection s of D (column s + 1) after the set D - {s}.  The
        # first minimum wins, as "none" and then s = 0, 1, ... would in a sequential update.
        cand[:, 0] = best[t] + lam_mm
        cand[:, 1:] = np.where(bits, best[t][prev] + cost[t], np.inf)
        pick = cand.argmin(axis=1)
        best[t + 1] = cand[np.arange(n_masks), pick]
        choice[t + 1] = pick - 1
    # Detections left unused are false positives.
    unused = (1 - bits) @ (lam_mm * det.confidence)
    mask = int(np.argmin(best[T] + unused))
    for t in range(T, 0, -1):
        s = int(choice[t, mask])
        out[t - 1] = s
        if s >= 0:
            mask &= ~(1 << s)
    return out
