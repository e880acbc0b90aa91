"""Depth image to a 2D Sum of Gaussians (paper 000, sec. 4.1 and 5.1).

Pipeline: validate, decimate wide images, near/far range filter, median filter
against flying pixels, optional region of interest, then a quadtree over an
image pyramid: a block becomes a leaf when all of its pixels are valid and the
spread of their depths (max - min) is below the homogeneity threshold.  Every
leaf is one Gaussian: mean at the block centre, ``sigma = side / sqrt(2)``,
depth = mean depth of the block, unit weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import DepthImageError, IntrinsicsError

__all__ = [
    "ImageSoG",
    "Preprocessed",
    "check_depth",
    "preprocess",
    "quadtree_sog",
    "self_overlap_2d",
]

MAX_QUAD_PX = 16  #: largest quad side (px) at the processing resolution (chosen here)
MIN_QUAD_PX = 4  #: default smallest quad side (px; chosen here)


def _raise_malloc_thresholds(nbytes: int = 16 << 20) -> None:
    """Allocate and free one large block, once, at import.

    glibc serves blocks above its mmap threshold (initially 128 KiB) by mmap and gives the
    top of the heap back to the system when more than its trim threshold is free there.
    Freeing an mmapped block raises both thresholds (to its size and twice that), so that
    the tracker's per-frame working set (a few depth-sized arrays, about 0.3 MiB each at
    320x240) then stays in the heap instead of being returned and page-faulted back every
    frame (measured: up to 280 page faults and 0.3-0.5 ms per frame).  Harmless elsewhere.
    """
    block = np.empty(nbytes, dtype=np.uint8)
    block[:: 1 << 12] = 0  # touch it so that the allocation is real
    del block


_raise_malloc_thresholds()


@dataclass(frozen=True, eq=False)
class Preprocessed:
    """A range-filtered, median-filtered depth image at processing resolution.

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
    arr = np.asarray(depth_mm)
    if arr.ndim != 2 or arr.size == 0:
        raise DepthImageError(f"depth image must be a non-empty 2D array, got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise DepthImageError(f"depth image must be numeric, got dtype {arr.dtype}")
    if arr.shape != (intrinsics.height, intrinsics.width):
        raise IntrinsicsError(
            f"depth image is {arr.shape[1]}x{arr.shape[0]} but the intrinsics are for "
            f"{intrinsics.width}x{intrinsics.height}"
        )
    out = arr.astype(np.float32, copy=True)
    out[~np.isfinite(out) | (out < 0)] = 0.0
    return out


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
        Uses ``near_mm``, ``far_mm``, ``median_kernel`` and ``max_width_px``.
    """
    depth = check_depth(depth_mm, intrinsics)
    k = max(1, int(np.ceil(depth.shape[1] / config.max_width_px)))
    if k > 1:
        # Decimation keeps every k-th pixel: pixel u' sits at input pixel k * u'.
        depth = np.ascontiguousarray(depth[::k, ::k])
        intrinsics = Intrinsics(
            fx=intrinsics.fx / k,
            fy=intrinsics.fy / k,
            cx=intrinsics.cx / k,
            cy=intrinsics.cy / k,
            width=depth.shape[1],
            height=depth.shape[0],
        )
    if config.near_mm >= 0:
        # In range <=> nonzero after the window (a value > near >= 0 is positive).
        depth = _in_window(depth, config.near_mm, config.far_mm)
        in_range = depth > 0
    else:
        in_range = (depth > config.near_mm) & (depth < config.far_mm)
        depth = np.where(in_range, depth, np.float32(0.0))
    if config.median_kernel >= 3:
        med = cv2.medianBlur(depth, config.median_kernel)
        # Keep a pixel only where it and its median agree: removes flying pixels
        # and isolated speckles without inventing depth in holes.
        keep = in_range & (med > 0) & (np.abs(med - depth) < config.quadtree_threshold_mm)
        depth = np.where(keep, med, np.float32(0.0))
    return Preprocessed(depth_mm=depth, intrinsics=intrinsics, decimation=k)


def _in_window(a: NDArray, lo: float, hi: float) -> NDArray:
    """``np.where((a > lo) & (a < hi), a, 0)``, for float32 images by two OpenCV thresholds.

    The float32 thresholds are chosen with NumPy's own comparison (so its promotion rules
    for ``lo`` and ``hi`` are kept): ``t_lo`` is the largest float32 that is not ``> lo``,
    ``t_hi`` the largest that is ``< hi``; then for every float32 pixel ``x``,
    ``x > t_lo <=> x > lo`` and ``x > t_hi <=> not x < hi``.  Bit-identical to the NumPy
    expression and about ten times faster.
    """
    r_lo, r_hi = np.float32(lo), np.float32(hi)
    if (
        a.dtype != np.float32
        or a.ndim != 2
        or a.size == 0
        or not (np.isfinite(r_lo) and np.isfinite(r_hi))
        or np.isnan(a).any()
    ):
        return np.where((a > lo) & (a < hi), a, np.float32(0.0))
    down, up = np.float32(-np.inf), np.float32(np.inf)
    cand = np.array([np.nextafter(r_lo, down), r_lo, np.nextafter(r_lo, up)], dtype=np.float32)
    t_lo = float(cand[~(cand > lo)].max())
    cand = np.array([np.nextafter(r_hi, down), r_hi, np.nextafter(r_hi, up)], dtype=np.float32)
    t_hi = float(cand[cand < hi].max())
    out = cv2.threshold(np.ascontiguousarray(a), t_lo, 0.0, cv2.THRESH_TOZERO)[1]
    return cv2.threshold(out, t_hi, 0.0, cv2.THRESH_TOZERO_INV)[1]


def _block_reduce(
    vmin: NDArray, vmax: NDArray, vsum: NDArray, cnt: NDArray
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Merge 2x2 children into parents (arrays of even shape (h, w) -> (h/2, w/2)).

    Row pairs first (contiguous rows), then column pairs: the sums are
    ``(top-left + bottom-left) + (top-right + bottom-right)``, in this order.
    """
    t = np.minimum(vmin[0::2], vmin[1::2])
    mn = np.minimum(t[:, 0::2], t[:, 1::2])
    t = np.maximum(vmax[0::2], vmax[1::2])
    mx = np.maximum(t[:, 0::2], t[:, 1::2])
    t = vsum[0::2] + vsum[1::2]
    sm = t[:, 0::2] + t[:, 1::2]
    t = cnt[0::2] + cnt[1::2]
    return mn, mx, sm, t[:, 0::2] + t[:, 1::2]


def quadtree_sog(
    pre: Preprocessed,
    threshold_mm: float,
    roi: tuple[int, int, int, int] | None = None,
    depth_window_mm: tuple[float, float] | None = None,
    min_quad_px: int = MIN_QUAD_PX,
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
    """
    depth = pre.depth_mm
    h, w = depth.shape
    u0, v0, u1, v1 = roi if roi is not None else (0, 0, w, h)
    u0, v0 = max(0, int(u0)), max(0, int(v0))
    u1, v1 = min(w, int(u1)), min(h, int(v1))
    if u1 - u0 < 1 or v1 - v0 < 1:
        return _empty(pre.intrinsics)
    crop = depth[v0:v1, u0:u1]
    if depth_window_mm is not None:
        lo, hi = depth_window_mm
        crop = _in_window(crop, lo, hi)
    S = MAX_QUAD_PX
    # Only blocks with valid pixels can become leaves: cluster the box around the valid
    # pixels, its corner moved back onto the block grid (same blocks, same leaf order).
    has = crop > 0
    rows = np.flatnonzero(has.any(axis=1))
    if rows.size == 0:
        return _empty(pre.intrinsics)
    cols = np.flatnonzero(has.any(axis=0))
    r0, c0 = (int(rows[0]) // S) * S, (int(cols[0]) // S) * S
    crop = crop[r0 : int(rows[-1]) + 1, c0 : int(cols[-1]) + 1]
    u0, v0 = u0 + c0, v0 + r0
    ph = -(-crop.shape[0] // S) * S
    pw = -(-crop.shape[1] // S) * S
    img = np.empty((ph, pw), dtype=np.float32)  # written in full (np.zeros may leave pages
    img[: crop.shape[0], : crop.shape[1]] = crop  # untouched, to be page-faulted on reading)
    img[crop.shape[0] :, :] = 0.0
    img[: crop.shape[0], crop.shape[1] :] = 0.0
    valid = img > 0
    if not valid.any():
        return _empty(pre.intrinsics)
    # Finest level: the pixels themselves.  Invalid pixels are +inf for the minimum; for
    # the maximum they may stay 0 (valid depths are > 0, and a block without any valid
    # pixel never becomes a leaf).
    levels = []
    if img.dtype == np.float32:
        vmin = img + cv2.threshold(img, 0.0, np.inf, cv2.THRESH_BINARY_INV)[1]
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
    mus, sigmas, depths = [], [], []
    taken_parent: NDArray[np.bool_] | None = None
    for size, vmin, vmax, vsum, cnt in reversed(levels):
        full = cnt == size * size
        if size == min_quad_px:
            # Smallest blocks may be partly valid (object edges, holes).
            full = cnt * 2 >= size * size
        homog = full & ((vmax - vmin) < threshold_mm)
        if taken_parent is not None:
            covered = np.repeat(np.repeat(taken_parent, 2, axis=0), 2, axis=1)
            leaf = homog & ~covered
            taken = covered | leaf
        else:
            leaf = homog
            taken = leaf
        taken_parent = taken
        bv, bu = np.nonzero(leaf)
        if bv.size:
            mus.append(
                np.stack([u0 + (bu + 0.5) * size - 0.5, v0 + (bv + 0.5) * size - 0.5], axis=1)
            )
            sigmas.append(np.full(bv.size, size / np.sqrt(2.0)))
            depths.append(vsum[bv, bu].astype(np.float64) / cnt[bv, bu])
    if not mus:
        return _empty(pre.intrinsics)
    mu = np.concatenate(mus)
    sigma = np.concatenate(sigmas)
    dq = np.concatenate(depths)
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
