"""Depth image to a 2D Sum of Gaussians (paper 000, sec. 4.1 and 5.1).

One job: a frame's depth to the data the objective sees; kept together because the
preprocessing, the shared hand window and the quadtree read the same arrays in one pass.

Pipeline: validate, decimate wide images, near/far range filter, median filter
against flying pixels (blind to what lies behind a depth edge), optional region of
interest, then a quadtree over an image pyramid: a block becomes a leaf when all of
its pixels are valid and the spread of their depths (max - min) is below the
homogeneity threshold.  Every leaf is one Gaussian: mean at the block centre,
``sigma = side / sqrt(2)``, depth = mean depth of the block, unit weight.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import DepthImageError, IntrinsicsError

__all__ = [
    "HandWindow",
    "ImageSoG",
    "Preprocessed",
    "EDGE_BEHIND_MM",
    "SHARED_MARGIN_PX",
    "check_depth",
    "decimation_offset",
    "hand_window",
    "lattice_anchor",
    "leaf_px",
    "preprocess",
    "quadtree_sog",
    "self_overlap_2d",
]

MAX_QUAD_PX = 16  #: largest quad side (px) at the processing resolution (chosen here)
#: Most data Gaussians of one quadtree: the energy's cost grows with their number, and no input
#: may make a frame unboundedly dear.  A near hand (200 mm, 2 px leaves) gives about 1100,
#: 400 mm about 700; an image textured finer than the leaves (2 px at 640x480: 77 000) would
#: give thousands.  Beyond it the leaves are thinned (:func:`quadtree_sog`).
MAX_DATA_GAUSSIANS = 1536
MIN_QUAD_PX = 4  #: default smallest quad side (px; chosen here)
#: A hand farther than this many focal lengths (f in processing pixels, so mm per px) gets
#: leaves half as wide (:func:`leaf_px`), again beyond twice that: 2 f is 575 mm for a 58 deg
#: camera (a far hand has few pixels per finger; measurement: design notes, "Constants").
FAR_LEAF_DEPTH_F = 2.0
#: A pixel more than this (mm) behind the nearest valid pixel of its median filter window lies
#: behind a depth edge (a wall, a table or the body behind the hand): the tracker's median
#: counts it as no data there, so that a hand pixel's median does not depend on what lies
#: behind the hand (:func:`_median_blind_behind_edges`): with a wall, a hand edge pixel's median
#: took values from the wall and the fit turned about the palm normal.  150 mm leaves the
#: self-occlusion edge of a finger in front of the palm alone (measurements: design notes,
#: "Constants").
EDGE_BEHIND_MM = 150.0


def _raise_malloc_thresholds(nbytes: int = 16 << 20) -> None:
    """Allocate and free one large block, once, at import.

    glibc serves blocks above its mmap threshold (initially 128 KiB) by mmap and gives the
    top of the heap back to the system when more than its trim threshold is free there.
    Freeing an mmapped block raises both thresholds (to its size and twice that), so that
    the tracker's per-frame working set (a few depth-sized arrays, about 0.3 MiB each at
    320x240) then stays in the heap instead of being returned and page-faulted back every
    frame (page faults cost 0.3-0.5 ms per frame).  Harmless elsewhere.
    """
    block = np.empty(nbytes, dtype=np.uint8)
    block[:: 1 << 12] = 0  # touch it so that the allocation is real
    del block


_raise_malloc_thresholds()


@dataclass(frozen=True, eq=False)
class Preprocessed:
    """A range-filtered, median-filtered depth image at processing resolution.

    The data stages share windowed boxes of ``depth_mm`` through a cache on the object
    (:func:`hand_window`): do not modify ``depth_mm`` in place after the first stage ran.

    Attributes
    ----------
    depth_mm : array, shape (h, w), float32
        Depth in mm, 0 where invalid or out of range.
    intrinsics : Intrinsics
        Intrinsics of ``depth_mm`` (decimation applied).
    decimation : int
        Input pixels per processing pixel along each axis.
    """

    depth_mm: NDArray[np.float32]
    intrinsics: Intrinsics
    decimation: int
    #: Windowed boxes shared by the data stages of this frame (see :func:`hand_window`).
    _windows: dict = field(default_factory=dict, init=False, repr=False, compare=False)


@dataclass(frozen=True, eq=False)
class ImageSoG:
    """The input depth as a 2D Gaussian mixture.

    Attributes
    ----------
    mu : array, shape (n, 2)
        Gaussian means, pixels of the processing image (u right, v down).
    sigma : array, shape (n,)
        Standard deviations, pixels.
    depth : array, shape (n,)
        Mean depth of each quad, mm.
    points : array, shape (n, 3)
        Back-projected means, mm, camera frame.
    intrinsics : Intrinsics
        Intrinsics of the processing image.
    norm : float
        Normaliser of ``E_sim``: ``E(C_I, C_I)``, the overlap of the mixture with
        itself, approximated in O(n) by its value for a gap-free tiling of the
        same quads, ``2 pi^2 sum_q sigma_q^2`` (within 10-20 % of the exact
        :func:`self_overlap_2d` on hand images, and constant within a frame).
    """

    mu: NDArray[np.float64]
    sigma: NDArray[np.float64]
    depth: NDArray[np.float64]
    points: NDArray[np.float64]
    intrinsics: Intrinsics
    norm: float

    @property
    def n(self) -> int:
        """Number of Gaussians."""
        return int(self.sigma.shape[0])

    def subset(self, keep: NDArray[np.bool_]) -> "ImageSoG":
        """The mixture of the Gaussians where ``keep`` (shape (n,)) is True."""
        sigma = self.sigma[keep]
        return ImageSoG(
            mu=self.mu[keep],
            sigma=sigma,
            depth=self.depth[keep],
            points=self.points[keep],
            intrinsics=self.intrinsics,
            norm=float(2.0 * np.pi**2 * (sigma**2).sum()),
        )


def check_depth(depth_mm: NDArray, intrinsics: Intrinsics) -> NDArray[np.float32]:
    """Validate a depth image against its intrinsics.

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        Millimetres; 0, NaN, Inf or negative mean invalid.
    intrinsics : Intrinsics
        Must describe an image of the same size.

    Returns
    -------
    array, shape (H, W), float32
        Depth with every invalid pixel set to 0.
    """
    out = _validated(depth_mm, intrinsics).astype(np.float32, copy=True)
    out[~np.isfinite(out) | (out < 0)] = 0.0
    return out


def _validated(depth_mm: NDArray, intrinsics: Intrinsics) -> NDArray:
    """``depth_mm`` as an array, after :func:`check_depth`'s checks (raises as it does)."""
    arr = np.asarray(depth_mm)
    if arr.ndim != 2 or arr.size == 0:
        raise DepthImageError(f"depth image must be a non-empty 2D array, got shape {arr.shape}")
    # (The kinds of np.floating and np.integer: np.issubdtype costs several microseconds.)
    if arr.dtype.kind not in "fiu":
        raise DepthImageError(f"depth image must be numeric, got dtype {arr.dtype}")
    if arr.shape != (intrinsics.height, intrinsics.width):
        raise IntrinsicsError(
            f"depth image is {arr.shape[1]}x{arr.shape[0]} but the intrinsics are for "
            f"{intrinsics.width}x{intrinsics.height}"
        )
    return arr


def preprocess(
    depth_mm: NDArray, intrinsics: Intrinsics, config: TrackerConfig
) -> Preprocessed:
    """Validate, decimate, range-filter and median-filter a depth image (sec. 5.1).

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        Depth in mm (0/NaN invalid).
    intrinsics : Intrinsics
        Intrinsics of ``depth_mm``.
    config : TrackerConfig
        Uses ``near_mm``, ``far_mm``, ``median_kernel``, ``max_width_px`` and ``min_focal_px``.
    """
    arr = _validated(depth_mm, intrinsics)
    k = max(1, int(np.ceil(arr.shape[1] / config.max_width_px)))
    f = float(np.sqrt(intrinsics.fx * intrinsics.fy))  # (tuned at 287 px; see min_focal_px)
    while k > 1 and f / k < config.min_focal_px:
        k -= 1
    if k > 1:
        # Decimation keeps every k-th pixel, on the lattice through the pixel nearest the
        # principal point: pixel u' sits at input pixel k * u' + ou.  Anchored there, the
        # mirror image (u -> W - 1 - u, cx -> W - 1 - cx) keeps the mirrored pixels.
        ou = decimation_offset(intrinsics.cx, k)
        ov = decimation_offset(intrinsics.cy, k)
        arr = arr[ov::k, ou::k]
        intrinsics = Intrinsics(
            fx=intrinsics.fx / k,
            fy=intrinsics.fy / k,
            cx=(intrinsics.cx - ou) / k,
            cy=(intrinsics.cy - ov) / k,
            width=arr.shape[1],
            height=arr.shape[0],
        )
    if config.near_mm >= 0:
        # The window is also the validity test: 0, negative, NaN and infinite depths all
        # fall outside (near, far) with near >= 0, as after check_depth's cleaning.
        # In range <=> nonzero after the window (a value > near >= 0 is positive).
        nan_free = arr.dtype.kind != "f"  # (= not np.issubdtype(arr.dtype, np.floating))
        depth = _in_window(
            np.ascontiguousarray(arr, dtype=np.float32), config.near_mm, config.far_mm, nan_free
        )
        in_range = None
    else:
        depth = check_depth(arr, Intrinsics(1.0, 1.0, 0.0, 0.0, arr.shape[1], arr.shape[0]))
        in_range = (depth > config.near_mm) & (depth < config.far_mm)
        depth = np.where(in_range, depth, np.float32(0.0))
    if config.median_kernel >= 3:
        med = _median_blind_behind_edges(depth, config.median_kernel)
        # Keep a pixel only where it and its median agree: removes flying pixels
        # and isolated speckles without inventing depth in holes.
        thr = config.quadtree_threshold_mm
        if in_range is None and config.near_mm >= thr:
            # Both images are 0 or in (near, far), so where exactly one of them is 0 they
            # differ by more than near >= thr: "agree" alone decides (bit-identical to the
            # expression below, by OpenCV: about five times faster).
            # (In place: the windowed depth becomes the difference, then the agreement, and
            # the median the result; fewer depth-sized temporaries.)
            diff = cv2.absdiff(med, depth, dst=depth)
            agree = cv2.threshold(diff, _below_cached(thr), 1.0, cv2.THRESH_BINARY_INV, dst=diff)[1]
            depth = cv2.multiply(med, agree, dst=med)
        else:
            if in_range is None:
                in_range = depth > 0
            keep = in_range & (med > 0) & (np.abs(med - depth) < thr)
            depth = np.where(keep, med, np.float32(0.0))
    return Preprocessed(depth_mm=depth, intrinsics=intrinsics, decimation=k)


def _median_blind_behind_edges(depth: NDArray[np.float32], k: int) -> NDArray[np.float32]:
    """The ``k`` x ``k`` median of ``depth`` (H, W) mm, blind to what lies behind a depth edge.

    A pixel's median is taken over its window with the pixels that lie more than
    :data:`EDGE_BEHIND_MM` behind the window's nearest valid pixel counted as no data (0):
    a hand pixel's median then does not depend on what is behind the hand.  Those pixels
    themselves (the wall or body next to the hand) get the plain median of their window: what
    lies behind a hand stays connected as before (without it, a forearm in front of the body
    in the NYU Kinect frame came apart from it along a 1 px seam, and the hand finder's
    changed blob turned the initialisation palm-for-back on 13 of 63 shifted copies of the
    frame against 3 of 63, with a 50 mm edge; with it, 4, and 3 with 150 mm as without this
    filter).  About 0.1 ms at 320 x 240 without such an edge, 0.18 ms with (the plain median
    alone: 0.04 ms).
    """
    # Invalid pixels (0) as a depth no valid one reaches, so that they are never the nearest.
    nearest = cv2.threshold(depth, 0.0, _NO_DEPTH_MM, cv2.THRESH_BINARY_INV)[1]
    cv2.add(nearest, depth, dst=nearest)
    cv2.erode(nearest, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)), dst=nearest)
    cv2.add(nearest, EDGE_BEHIND_MM, dst=nearest)
    behind = cv2.compare(depth, nearest, cv2.CMP_GT)  # 255 where behind an edge, else 0
    plain = cv2.medianBlur(depth, k)
    if not cv2.countNonZero(behind):  # (no such edge, e.g. nothing within the depth window behind)
        return plain
    src = depth.copy()
    src[behind > 0] = 0.0
    blind = cv2.medianBlur(src, k)
    cv2.copyTo(plain, behind, blind)  # the pixels behind an edge: their plain median
    return blind


#: A depth "no valid pixel reaches" for :func:`_median_blind_behind_edges` (mm).
_NO_DEPTH_MM = 1e9


#: Margin (px) around the region of interest of the windowed depth that the data stages
#: share (:func:`hand_window`): covers the silhouette's margin (16 px, plus one for its
#: cells) and the detector's ring (13 px at 400 mm, 24 px at 200 mm).
SHARED_MARGIN_PX = 24


@dataclass(frozen=True, eq=False)
class HandWindow:
    """The depth inside the hand's depth window around a region of interest (shared, read-only).

    Attributes
    ----------
    depth : array, shape (h, w), float32
        Over the ROI plus :data:`SHARED_MARGIN_PX` on every side: the depth (mm) where inside
        the window, 0 where not (or invalid), -1 outside the image.
    u0, v0 : int
        Image pixel of ``depth[0, 0]`` (negative when the box starts outside the image).
    valid_box : (u0, v0, u1, v1) or None
        End-exclusive image box of the pixels with depth inside the ROI (clipped to the
        image); None when there are none.
    """

    depth: NDArray[np.float32]
    u0: int
    v0: int
    valid_box: tuple[int, int, int, int] | None

    def contains(self, u0: int, v0: int, u1: int, v1: int) -> bool:
        """Whether the image box ``[u0, u1) x [v0, v1)`` lies inside this window."""
        h, w = self.depth.shape
        return u0 >= self.u0 and v0 >= self.v0 and u1 <= self.u0 + w and v1 <= self.v0 + h

    def view(self, u0: int, v0: int, u1: int, v1: int) -> NDArray[np.float32]:
        """``depth`` over the image box ``[u0, u1) x [v0, v1)`` (inside this window)."""
        return self.depth[v0 - self.v0 : v1 - self.v0, u0 - self.u0 : u1 - self.u0]


def hand_window(
    pre: Preprocessed, roi: tuple[int, int, int, int], window_mm: tuple[float, float]
) -> HandWindow:
    """The depth inside ``window_mm`` over the ROI plus :data:`SHARED_MARGIN_PX`.

    The quadtree, the fingertip detector and the silhouette of one frame all start from the
    same box and depth window: it is computed once per ``pre`` (the last four pairs of
    ``roi`` and ``window_mm`` are kept on it).

    Parameters
    ----------
    pre : Preprocessed
    roi : (u0, v0, u1, v1)
        End-exclusive pixel box (may reach beyond the image).
    window_mm : (near, far)
        Depth window, mm (compared as NumPy compares them with a float32 image).
    """
    lo, hi = window_mm
    key = (tuple(int(x) for x in roi), lo, hi, type(lo), type(hi))
    hit = pre._windows.get(key)
    if hit is not None:
        return hit
    h, w = pre.depth_mm.shape
    m = SHARED_MARGIN_PX
    bu0, bv0 = int(roi[0]) - m, int(roi[1]) - m
    bu1, bv1 = max(int(roi[2]) + m, bu0), max(int(roi[3]) + m, bv0)
    arr = np.empty((bv1 - bv0, bu1 - bu0), np.float32)
    cu0, cv0 = min(max(bu0, 0), w), min(max(bv0, 0), h)
    cu1, cv1 = max(min(bu1, w), cu0), max(min(bv1, h), cv0)
    if cu1 > cu0 and cv1 > cv0:
        # -1 on the strips outside the image, the windowed depth inside.
        arr[: cv0 - bv0] = -1.0
        arr[cv1 - bv0 :] = -1.0
        arr[cv0 - bv0 : cv1 - bv0, : cu0 - bu0] = -1.0
        arr[cv0 - bv0 : cv1 - bv0, cu1 - bu0 :] = -1.0
        _in_window(
            pre.depth_mm[cv0:cv1, cu0:cu1], lo, hi, nan_free=True,
            out=arr[cv0 - bv0 : cv1 - bv0, cu0 - bu0 : cu1 - bu0],
        )
    else:
        arr.fill(-1.0)
    arr.flags.writeable = False
    # The box of the pixels with data inside the (clipped) ROI.
    ru0, rv0 = max(int(roi[0]), 0), max(int(roi[1]), 0)
    ru1, rv1 = min(int(roi[2]), w), min(int(roi[3]), h)
    box = None
    if ru1 > ru0 and rv1 > rv0:
        has = (arr[rv0 - bv0 : rv1 - bv0, ru0 - bu0 : ru1 - bu0] > 0).view(np.uint8)
        x, y, bw, bh = cv2.boundingRect(has)  # of the nonzero pixels; (0, 0, 0, 0) if none
        if bw > 0:
            box = (ru0 + x, rv0 + y, ru0 + x + bw, rv0 + y + bh)
    if len(pre._windows) >= 4:
        pre._windows.clear()
    hit = pre._windows[key] = HandWindow(arr, bu0, bv0, box)
    return hit


def decimation_offset(c: float, k: int) -> int:
    """First input pixel (0 <= ou < k) of the decimation lattice through ``round(c)``.

    ``c`` is the principal point's coordinate (px).  Mirror-symmetric: for ``c' = W - 1 - c``
    the kept pixels are the mirror images of those kept for ``c`` (unless ``c`` lies exactly
    half-way between two pixels, where no lattice of step ``k > 1`` can be).
    """
    return int(np.floor(c + 0.5)) % k


def lattice_anchor(n: int, step: int) -> int:
    """Offset (px) of a lattice of ``step``-pixel blocks that is symmetric in an image ``n`` wide.

    Blocks start at ``anchor + step * j``; for even ``n`` the mirror image (u -> n - 1 - u) of
    every block is again a block (the lattice is centred on the image).
    """
    return (n // 2) % step


def _largest_below(hi: float) -> float:
    """The largest float32 ``t`` with ``t < hi`` (NumPy's comparison of a float32 with ``hi``)."""
    r = np.float32(hi)
    down, up = np.float32(-np.inf), np.float32(np.inf)
    cand = np.array([np.nextafter(r, down), r, np.nextafter(r, up)], dtype=np.float32)
    return float(cand[cand < hi].max())


_BELOW: dict[tuple, float] = {}


def _below_cached(hi: float) -> float:
    """:func:`_largest_below` cached per value and type (every frame asks for the same one)."""
    key = (hi, type(hi))
    hit = _BELOW.get(key)
    if hit is None:
        if len(_BELOW) >= 16:
            _BELOW.clear()
        hit = _BELOW[key] = _largest_below(hi)
    return hit


_THRESHOLDS: dict[tuple, tuple[float, float] | None] = {}


def _window_thresholds(lo: float, hi: float) -> tuple[float, float] | None:
    """The float32 thresholds ``(t_lo, t_hi)`` of :func:`_in_window` for ``lo``, ``hi`` (None
    when either is not finite as a float32); cached per value and type (a frame asks for the
    same window several times, and the arithmetic costs more than the thresholding)."""
    key = (lo, hi, type(lo), type(hi))
    try:
        return _THRESHOLDS[key]
    except KeyError:
        pass
    except TypeError:  # (an unhashable value: not cached)
        key = None
    r_lo, r_hi = np.float32(lo), np.float32(hi)
    res = None
    if np.isfinite(r_lo) and np.isfinite(r_hi):
        down, up = np.float32(-np.inf), np.float32(np.inf)
        cand = np.array([np.nextafter(r_lo, down), r_lo, np.nextafter(r_lo, up)], dtype=np.float32)
        res = (float(cand[~(cand > lo)].max()), _largest_below(hi))
    if key is not None:
        if len(_THRESHOLDS) >= 64:  # (the hand's window moves every frame)
            _THRESHOLDS.clear()
        _THRESHOLDS[key] = res
    return res


def _in_window(
    a: NDArray, lo: float, hi: float, nan_free: bool = False, out: NDArray | None = None
) -> NDArray:
    """``np.where((a > lo) & (a < hi), a, 0)``, for float32 images by two OpenCV thresholds.

    The float32 thresholds are chosen with NumPy's own comparison (so its promotion rules
    for ``lo`` and ``hi`` are kept): ``t_lo`` is the largest float32 that is not ``> lo``,
    ``t_hi`` the largest that is ``< hi``; then for every float32 pixel ``x``,
    ``x > t_lo <=> x > lo`` and ``x > t_hi <=> not x < hi``.  Bit-identical to the NumPy
    expression and about ten times faster.  ``nan_free`` skips the NaN test (the caller
    knows there is none).  ``out``: a float32 array (or view) of ``a``'s shape to write
    the result into (returned).
    """
    thresholds = _window_thresholds(lo, hi)
    if (
        a.dtype != np.float32
        or a.ndim != 2
        or a.size == 0
        or thresholds is None
        or (not nan_free and np.isnan(a).any())
    ):
        res = np.where((a > lo) & (a < hi), a, np.float32(0.0))
        if out is None:
            return res
        out[...] = res
        return out
    t_lo, t_hi = thresholds
    # (OpenCV reads and writes rows of strided views in place: no copies.)
    res = cv2.threshold(a, t_lo, 0.0, cv2.THRESH_TOZERO, dst=out)[1]
    res = cv2.threshold(res, t_hi, 0.0, cv2.THRESH_TOZERO_INV, dst=res)[1]
    if out is not None and res is not out:  # (not expected: OpenCV allocated another array)
        out[...] = res
        return out
    return res


def _block_reduce(
    vmin: NDArray, vmax: NDArray, vsum: NDArray, cnt: NDArray
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Merge 2x2 children into parents (arrays of even shape (h, w) -> (h/2, w/2)).

    Row pairs first (contiguous rows), then column pairs: the sums are
    ``(top-left + bottom-left) + (top-right + bottom-right)``, in this order.  The row pairs
    of float32 images and int16 counts by OpenCV (the same IEEE minimum, maximum and sums,
    several times faster than NumPy on these row-strided views; the counts, at most
    ``MAX_QUAD_PX^2``, never saturate int16).
    """
    if vmin.dtype == vmax.dtype == vsum.dtype == np.float32 and cnt.dtype == np.int16:
        rmin, rmax = cv2.min(vmin[0::2], vmin[1::2]), cv2.max(vmax[0::2], vmax[1::2])
        rsum, rcnt = cv2.add(vsum[0::2], vsum[1::2]), cv2.add(cnt[0::2], cnt[1::2])
    else:
        rmin, rmax = np.minimum(vmin[0::2], vmin[1::2]), np.maximum(vmax[0::2], vmax[1::2])
        rsum, rcnt = vsum[0::2] + vsum[1::2], cnt[0::2] + cnt[1::2]
    mn = np.minimum(rmin[:, 0::2], rmin[:, 1::2])
    mx = np.maximum(rmax[:, 0::2], rmax[:, 1::2])
    sm = rsum[:, 0::2] + rsum[:, 1::2]
    return mn, mx, sm, rcnt[:, 0::2] + rcnt[:, 1::2]


def leaf_px(min_quad_px: int, depth_mm: float, intrinsics: Intrinsics) -> int:
    """The smallest quadtree leaf (px) for a hand at ``depth_mm``: ``min_quad_px`` for a hand
    nearer than :data:`FAR_LEAF_DEPTH_F` focal lengths, halved beyond (and again beyond twice
    that), not below 2 px: a far hand keeps about the leaf size in mm of a near one.

    ``intrinsics`` are those of the processing resolution (:attr:`Preprocessed.intrinsics`).
    """
    f = float(np.sqrt(intrinsics.fx * intrinsics.fy))
    px, limit = int(min_quad_px), FAR_LEAF_DEPTH_F * f
    while px > 2 and depth_mm > limit:
        px //= 2
        limit *= 2.0
    return px


def quadtree_sog(
    pre: Preprocessed,
    threshold_mm: float,
    roi: tuple[int, int, int, int] | None = None,
    depth_window_mm: tuple[float, float] | None = None,
    min_quad_px: int = MIN_QUAD_PX,
    max_gaussians: int = MAX_DATA_GAUSSIANS,
) -> ImageSoG:
    """Cluster a preprocessed depth image into quadtree leaves, one Gaussian each.

    Parameters
    ----------
    pre : Preprocessed
    threshold_mm : float
        Depth homogeneity threshold epsilon_c (max - min within a leaf), mm.
    roi : (u0, v0, u1, v1) or None
        Pixel box (processing resolution, end-exclusive) to cluster; None = all.
    depth_window_mm : (near, far) or None
        Extra depth window applied inside the ROI, mm.
    min_quad_px : int
        Side of the smallest leaves (a power of two up to ``MAX_QUAD_PX``);
        these may be partly valid (at least half their pixels).
    max_gaussians : int
        At most this many Gaussians: more leaves are thinned to an evenly spread subset (every
        k-th leaf of each level).  (Coarser leaves instead would leave nothing of a texture
        finer than them.)
    """
    depth = pre.depth_mm
    h, w = depth.shape
    u0, v0, u1, v1 = roi if roi is not None else (0, 0, w, h)
    u0, v0 = max(0, int(u0)), max(0, int(v0))
    u1, v1 = min(w, int(u1)), min(h, int(v1))
    if u1 - u0 < 1 or v1 - v0 < 1:
        return _empty(pre.intrinsics)
    S = MAX_QUAD_PX
    if depth_window_mm is not None and roi is not None:
        hw = hand_window(pre, roi, depth_window_mm)  # shared with the other data stages
        if hw.valid_box is None:
            return _empty(pre.intrinsics)
        crop = hw.view(u0, v0, u1, v1)
        c_first, r_first, c_end, r_end = hw.valid_box
    else:
        crop = depth[v0:v1, u0:u1]
        if depth_window_mm is not None:
            lo, hi = depth_window_mm
            crop = _in_window(crop, lo, hi)
        has = crop > 0
        rows = np.flatnonzero(has.any(axis=1))
        if rows.size == 0:
            return _empty(pre.intrinsics)
        cols = np.flatnonzero(has.any(axis=0))
        c_first, r_first = u0 + int(cols[0]), v0 + int(rows[0])
        c_end, r_end = u0 + int(cols[-1]) + 1, v0 + int(rows[-1]) + 1
    # Only blocks with valid pixels can become leaves: cluster the box around the valid
    # pixels (image box [c_first, c_end) x [r_first, r_end)), widened to the block lattice.
    # The lattice's columns are anchored on the image (centred, :func:`lattice_anchor`), not
    # on the ROI, so that the mirror image (u -> W - 1 - u) is cut into the mirrored blocks;
    # its rows start on the ROI's first row (a left-right mirror keeps them, and of the
    # variants measured on the dev bags this one tracked best).
    au, av = lattice_anchor(w, S), v0
    bu0 = au + ((c_first - au) // S) * S  # image pixel of the first block
    bv0 = av + ((r_first - av) // S) * S
    pw = -(-(c_end - bu0) // S) * S
    ph = -(-(r_end - bv0) // S) * S
    # The crop's part inside the blocks (the blocks may reach beyond the ROI: no data there).
    cr0, cc0 = max(bv0 - v0, 0), max(bu0 - u0, 0)
    cr1, cc1 = min(bv0 + ph - v0, crop.shape[0]), min(bu0 + pw - u0, crop.shape[1])
    img = np.empty((ph, pw), dtype=np.float32)  # written in full (np.zeros may leave pages
    img.fill(0.0)  # untouched, to be page-faulted on reading)
    img[v0 + cr0 - bv0 : v0 + cr1 - bv0, u0 + cc0 - bu0 : u0 + cc1 - bu0] = crop[cr0:cr1, cc0:cc1]
    u0, v0 = bu0, bv0
    # (The blocks hold the valid pixels found above: at least one.)
    valid = img > 0
    # Finest level: the pixels themselves.  Invalid pixels are +inf for the minimum; for
    # the maximum they may stay 0 (valid depths are > 0, and a block without any valid
    # pixel never becomes a leaf).
    levels = []
    if img.dtype == np.float32:
        vmin = cv2.threshold(img, 0.0, np.inf, cv2.THRESH_BINARY_INV)[1]
        vmin += img  # (in place: one depth-sized temporary fewer)
    else:
        vmin = np.where(valid, img, np.inf)
    vmax = img
    vsum = img
    cnt = valid.astype(np.int16)
    size = 1
    while size < S:
        vmin, vmax, vsum, cnt = _block_reduce(vmin, vmax, vsum, cnt)
        size *= 2
        if size >= min_quad_px:
            levels.append((size, vmin, vmax, vsum, cnt))
    # Per level (coarse to fine): its leaves' flat cells, their depth sums and pixel counts,
    # its width (blocks) and block side (px).
    found: list[tuple[NDArray, NDArray, NDArray, int, int]] = []
    taken_parent: NDArray[np.bool_] | None = None
    for size, vmin, vmax, vsum, cnt in reversed(levels):
        if size == min_quad_px:
            # Smallest blocks may be partly valid (object edges, holes).
            full = cnt * 2 >= size * size
        else:
            full = cnt == size * size
        homog = full & ((vmax - vmin) < threshold_mm)
        if taken_parent is not None:
            # A block is covered when its parent is taken: the parent's flag seen on each of
            # its 2x2 children by broadcasting (no repeated copies).
            ph_, pw_ = taken_parent.shape
            parent = taken_parent[:, None, :, None]
            children = homog.reshape(ph_, 2, pw_, 2)
            leaf = (children & ~parent).reshape(homog.shape)
            if size > min_quad_px:
                taken_parent = (children | parent).reshape(homog.shape)
        else:
            leaf = homog
            taken_parent = leaf
        cells = leaf.ravel().nonzero()[0]
        if cells.size:
            found.append((cells, vsum.ravel().take(cells), cnt.ravel().take(cells), leaf.shape[1], size))
    if not found:
        return _empty(pre.intrinsics)
    n_leaves = sum(f[0].size for f in found)
    # Every level's leaves at once (the same operations per leaf as level by level, with the
    # level's width and block side per leaf: a few calls instead of a dozen per level).
    cells, sums, counts, widths, sizes = zip(*found)
    per_level = [c.size for c in cells]
    cells = np.concatenate(cells)
    width = np.repeat(widths, per_level)
    side = np.repeat(np.array(sizes, dtype=np.float64), per_level)
    sums, counts = np.concatenate(sums), np.concatenate(counts)
    if n_leaves > max_gaussians:  # an evenly spread subset, the same share of every level
        keep = np.linspace(0, n_leaves - 1, max_gaussians).astype(np.int64)
        cells, width, side, sums, counts = cells[keep], width[keep], side[keep], sums[keep], counts[keep]
    bv = cells // width  # (row and column by division: cheaper than 2-d nonzero)
    bu = cells - bv * width
    mu = np.empty((cells.size, 2))
    mu[:, 0] = u0 + (bu + 0.5) * side - 0.5
    mu[:, 1] = v0 + (bv + 0.5) * side - 0.5
    sigma = side / np.sqrt(2.0)
    dq = sums.astype(np.float64) / counts
    pts = pre.intrinsics.backproject(mu, dq)
    return ImageSoG(
        mu=mu,
        sigma=sigma,
        depth=dq,
        points=pts,
        intrinsics=pre.intrinsics,
        norm=float(2.0 * np.pi**2 * (sigma**2).sum()),
    )


def _empty(intr: Intrinsics) -> ImageSoG:
    return ImageSoG(
        mu=np.zeros((0, 2)),
        sigma=np.zeros(0),
        depth=np.zeros(0),
        points=np.zeros((0, 3)),
        intrinsics=intr,
        norm=0.0,
    )


def self_overlap_2d(mu: NDArray[np.float64], sigma: NDArray[np.float64], chunk: int = 2048) -> float:
    """``E(C, C) = sum_p sum_q D_pq`` of a 2D unit-weight mixture (eq. 4).

    Exact, computed in row chunks of ``chunk`` to bound memory: O(n^2) time,
    which is why the tracker clusters only a region of interest around the hand.

    Parameters
    ----------
    mu : array, shape (n, 2), px
    sigma : array, shape (n,), px
    """
    n = sigma.shape[0]
    if n == 0:
        return 0.0
    total = 0.0
    s2 = sigma**2
    for a in range(0, n, chunk):
        d2 = ((mu[a : a + chunk, None, :] - mu[None, :, :]) ** 2).sum(-1)
        ss = s2[a : a + chunk, None] + s2[None, :]
        total += float((2 * np.pi * s2[a : a + chunk, None] * s2[None, :] / ss * np.exp(-0.5 * d2 / ss)).sum())
    return total
