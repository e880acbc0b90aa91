"""The hand finder: the nearest sizeable depth blob that can be a hand, its palm and directions.

No rest pose is required.  The nearest sizeable blob of in-range depth is the hand (plus
forearm), less what lies too far behind its nearest points (an arm joins hand and body in one
surface).  Its principal axis gives the arm direction; the end that leaves the image as wide as a
forearm, else the side reaching far beyond the palm, is the forearm (undecided: both directions
are tried).  It serves a new track's search (:mod:`hand_sog_tracker.core.search.start`); the
measurements behind the constants: ``doc/design/search.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import Preprocessed
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig

__all__ = [
    "HandBlob", "DETECTION_DIRECTION_MIN_DETECTIONS", "DETECTION_DIRECTION_MIN_DEG", "HAND_AXIS_BEHIND_PALM_MM",
    "MAX_VIEW_SHARE", "detection_direction", "find_hand",
]


# The hand finder's constants, all chosen here (paper 000 has no initialisation, seed 001 starts
# from a manual pose).
MIN_BLOB_AREA_MM2 = 2500.0  #: smallest blob accepted as a hand: mm^2 at its depth (a palm is ~ 6000)
MAX_BLOB_AREA_MM2 = 150_000.0  #: largest (mm^2 at its median depth after the band's cut): else a wall or a table
#: ... and a blob covering more than this share of the image fills the view: its area is only a
#: lower bound (a wall under a focal length 10x too large measures a hand's, issue 50).
MAX_VIEW_SHARE = 0.9
FOREARM_MIN_EXTENT_MM = 150.0  #: reaching this far (mm) beyond the thickest point, 1.4x the other side: a forearm
FOREARM_MIN_WIDTH_MM = 30.0  #: a border run narrower than this (mm) is a finger leaving the view, not a forearm
BORDER_GAP_PX = 1  #: border runs this close (px) count as one: a missing pixel splits no forearm
HAND_DEPTH_BAND_MM = 250.0  #: depth extent (mm) of a hand and wrist behind its nearest point: beyond, arm or body
NARROW_BANDS_MM = (175.0, 120.0)  #: bands (mm) tried while the blob within is too large (a body close behind)
#: ... and last, for a wall or a table 50-120 mm behind the hand, bands (mm) taken only when at
#: most their share in ``SURFACE_GAP_SHARES`` of the pixels lie in the last ``SURFACE_GAP_MM``.
SURFACE_BANDS_MM = (90.0, 60.0)
SURFACE_GAP_MM = 15.0
SURFACE_GAP_SHARES = (0.05, 0.12)
#: The bands :func:`_nearest_blob` tries: (band mm, gap share or None, whether a part failing the
#: gap test is still taken when no narrower band passes).
_BANDS: tuple[tuple[float, float | None, bool], ...] = (
    *((band, None, False) for band in (HAND_DEPTH_BAND_MM, *NARROW_BANDS_MM[:-1])),
    (NARROW_BANDS_MM[-1], SURFACE_GAP_SHARES[0], True),
    *((band, share, False) for band, share in zip(SURFACE_BANDS_MM, SURFACE_GAP_SHARES)),
)
SURFACE_RANGE_MM = 15.0  #: on a surface: a pixel whose 3 x 3 window lies on the blob within this depth range (mm)
HAND_AXIS_BEHIND_PALM_MM = 60.0  #: the hand end's axis: of the blob's points at most this (mm) behind the palm
MAX_HOLE_PX = 4  #: holes up to this size (px) are filled before the palm is searched (dropouts; not finger gaps)
DETECTION_DIRECTION_MIN_DETECTIONS = 3  #: a start direction toward the detections needs this many ...
DETECTION_DIRECTION_MIN_DEG = 10.0  #: ... and must differ from each of the blob's by more than this (degrees)


@dataclass(frozen=True, eq=False)
class HandBlob:
    """A hand candidate in the depth image (mm, camera frame)."""

    palm: NDArray[np.float64]  #: (3,) the centre of the palm's bones (behind the visible surface)
    #: unit vectors (3,) from the wrist toward the fingers, likeliest first, in the image plane but a
    #: last one: the first tilted onto the hand end's plane (depth; :func:`_tilted`)
    directions: list[NDArray[np.float64]]
    #: (3,) the in-plane principal direction of the hand end alone, toward the fingers, when a forearm
    #: was recognised and it lies ``DETECTION_DIRECTION_MIN_DEG`` off ``directions[0]`` (which then
    #: leaves out the most turned ones); else None
    hand_direction: NDArray[np.float64] | None = None
    far_mm: float = np.inf  #: depth (mm) of the farthest pixel on a surface (``SURFACE_RANGE_MM``), inf: unknown



def _nearest_blob(pre: Preprocessed) -> NDArray[np.bool_] | None:
    """The nearest blob of valid depth (8-connected, by median depth) that can be a hand (plus
    forearm): at least ``MIN_BLOB_AREA_MM2``, and within ``MAX_BLOB_AREA_MM2`` and
    ``MAX_VIEW_SHARE`` after the cut at the first of :data:`_BANDS` that passes; or None."""
    depth = pre.depth_mm
    mask = (depth > 0).astype(np.uint8)
    if not mask.any():
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    intr = pre.intrinsics
    candidates: list[tuple[float, int]] = []
    for lab in range(1, n):
        area_px = stats[lab, cv2.CC_STAT_AREA]
        if area_px < 20:
            continue
        x, y, bw, bh = stats[lab, :4]  # (its depths inside its bounding box: no full-image pass)
        box = (slice(y, y + bh), slice(x, x + bw))
        z = float(np.median(depth[box][labels[box] == lab]))
        if _area_mm2(area_px, z, intr) >= MIN_BLOB_AREA_MM2:
            candidates.append((z, lab))
    for _, lab in sorted(candidates):
        component = labels == lab
        near = float(np.percentile(depth[component], 2))
        last_resort = None
        for band_mm, share, keep in _BANDS:
            blob = _hand_part(depth, component, intr, band_mm, near)
            z = depth[blob]
            if z.size > MAX_VIEW_SHARE * depth.size or _area_mm2(z.size, float(np.median(z)), intr) > MAX_BLOB_AREA_MM2:
                continue
            if share is not None and np.count_nonzero(z > near + band_mm - SURFACE_GAP_MM) > share * z.size:
                if keep and last_resort is None:  # (a surface's slice; kept: a hand with its fringe)
                    last_resort = blob
                continue
            return blob
        if last_resort is not None:
            return last_resort
    return None


def _area_mm2(n_px: int, z_mm: float, intr: Intrinsics) -> float:
    """Area (mm^2) of ``n_px`` pixels seen at depth ``z_mm``."""
    return float(n_px) * (z_mm / intr.fx) * (z_mm / intr.fy)


def _hand_part(
    depth: NDArray[np.float32], blob: NDArray[np.bool_], intr: Intrinsics, band_mm: float, near: float
) -> NDArray[np.bool_]:
    """The largest part of ``blob`` within ``band_mm`` behind its nearest points (``near``, mm)
    if that is large enough for a hand, else ``blob`` (an arm joins hand and body in one surface)."""
    band = (blob & (depth <= near + band_mm)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(band, connectivity=8)
    if n <= 1:
        return blob
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == largest if _area_mm2(stats[largest, cv2.CC_STAT_AREA], near, intr) >= MIN_BLOB_AREA_MM2 else blob


def _in_plane(direction: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    """Rotate a direction about the camera z axis by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    d = np.array([c * direction[0] - s * direction[1], s * direction[0] + c * direction[1], direction[2]])
    return d / np.linalg.norm(d)


def _without_holes(blob: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``blob`` (H, W) with its holes of up to ``MAX_HOLE_PX`` (off the image border) filled."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~blob).astype(np.uint8), connectivity=4)
    h, w = blob.shape
    x, y, bw, bh, area = (stats[:, k] for k in range(5))
    small = (area <= MAX_HOLE_PX) & (x > 0) & (y > 0) & (x + bw < w) & (y + bh < h)
    small[0] = False  # label 0: the blob itself
    return blob | small[labels]


def find_hand(pre: Preprocessed, config: TrackerConfig) -> HandBlob | None:
    """The nearest sizeable depth blob, its palm and candidate hand directions, or None.

    The palm centre is the point of the blob farthest from its outline (distance-transform
    maximum, small holes filled), at the hand end when a forearm is recognised.
    """
    blob = _nearest_blob(pre)
    if blob is None:
        return None
    depth = pre.depth_mm
    intr = pre.intrinsics
    vs, us = np.nonzero(blob)
    zs = depth[vs, us].astype(np.float64)
    pts = intr.backproject(np.stack([us, vs], 1).astype(np.float64), zs)
    axis = _principal(pts)
    if axis is None:
        axis = np.array([0.0, -1.0, 0.0])
    t = (pts - pts.mean(axis=0)) @ axis
    dist = cv2.distanceTransform(_without_holes(blob).astype(np.uint8), cv2.DIST_L2, 5)
    # The blob's extent on either side of its thickest point: fingers reach about a hand length
    # from the palm, a forearm much farther (and it usually leaves the image).
    k0 = int(np.argmax(dist[vs, us]))
    t0 = t[k0]
    ext_pos = float(np.percentile(t, 99) - t0)
    ext_neg = float(t0 - np.percentile(t, 1))
    sign = _forearm_side(blob, depth, intr, vs, us, t)
    if sign is None:  # (the blob leaves the view at both ends: both directions are tried)
        sign = 0.0
    elif sign == 0.0 and max(ext_pos, ext_neg) > max(FOREARM_MIN_EXTENT_MM, 1.4 * min(ext_pos, ext_neg)):
        sign = 1.0 if ext_pos < ext_neg else -1.0
    if sign != 0.0:  # the hand end is the far side from the forearm
        hand_end = sign * t > np.percentile(sign * t, 40)
        main = sign * axis
        angles = (0.0, 0.6, -0.6, 1.2, -1.2)
    else:
        hand_end = np.ones_like(t, dtype=bool)
        main = axis if -axis[1] >= 0 else -axis  # prefer fingers up in the image
        angles = (0.0, np.pi, np.pi / 2, -np.pi / 2, np.pi / 4, -np.pi / 4, 3 * np.pi / 4, -3 * np.pi / 4)
    dvals = dist[vs, us] * hand_end
    k = int(np.argmax(dvals))
    near = (np.abs(us - us[k]) <= 3) & (np.abs(vs - vs[k]) <= 3)
    palm_surface = intr.backproject(np.array([[us[k], vs[k]]], dtype=np.float64), np.array([np.median(zs[near])]))[0]
    palm = palm_surface + np.array([0.0, 0.0, 12.0])  # bones lie behind the skin
    hand_direction = _hand_axis(pts, palm_surface, main) if sign != 0.0 else None
    if hand_direction is not None and float(hand_direction @ main) > np.cos(np.deg2rad(DETECTION_DIRECTION_MIN_DEG)):
        hand_direction = None  # (the blob's own direction already)
    if hand_direction is not None:
        angles = angles[:3]  # (its two start poses replace the four of the most turned directions)
    directions = [_in_plane(main, a) for a in angles] + [_tilted(pts[hand_end], main)]
    return HandBlob(palm=palm, directions=directions, hand_direction=hand_direction, far_mm=_surface_far(depth, blob))


def _tilted(pts: NDArray[np.float64], d: NDArray[np.float64]) -> NDArray[np.float64]:
    """The in-plane unit direction ``d`` (3,) tilted onto the plane fitted to ``pts`` (n, 3) mm
    (depth against image position, least squares), unit: a hand seen from above and behind lies
    tilted in depth, its wrist behind its palm, which the in-plane start poses cannot reach."""
    xy = np.column_stack([pts[:, :2] - pts[:, :2].mean(axis=0), np.ones(pts.shape[0])])
    grad = np.linalg.lstsq(xy, pts[:, 2], rcond=None)[0][:2]  # (dz / dx, dz / dy)
    v = np.array([d[0], d[1], float(grad @ d[:2])])
    return v / np.linalg.norm(v)


def _surface_far(depth: NDArray[np.float32], blob: NDArray[np.bool_]) -> float:
    """Depth (mm) of the farthest pixel of ``blob`` (H, W) on a surface (``SURFACE_RANGE_MM``),
    else its farthest pixel."""
    square = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))
    inner = cv2.erode(blob.astype(np.uint8), square).astype(bool)
    # (An inner pixel's 3 x 3 window lies on the blob: there the depth's own range is the blob's.)
    spread = cv2.dilate(depth, square) - cv2.erode(depth, square)
    surface = inner & (spread < SURFACE_RANGE_MM)
    return float(depth[surface if surface.any() else blob].max())


def _forearm_side(
    blob: NDArray[np.bool_], depth: NDArray[np.float32], intr: Intrinsics, vs: NDArray[np.int64], us: NDArray[np.int64],
    t: NDArray[np.float64],
) -> float | None:
    """Where the blob leaves the image along its axis (``t``: mm along it per blob pixel ``vs,
    us``): ``s`` = +-1.0 when a forearm leaves it where ``s t < 0``, 0.0 when nothing arm-like
    does, None when the blob leaves it at both ends (undecided).  Only border runs at least
    ``FOREARM_MIN_WIDTH_MM`` wide are arm-like; fingers count only toward "both ends"."""
    h, w = blob.shape
    arm = np.zeros(blob.shape, dtype=bool)
    # Each border's two outermost lines together, runs up to BORDER_GAP_PX apart joined.
    lines = (
        (np.s_[0, :], np.s_[1, :], intr.fx),
        (np.s_[h - 1, :], np.s_[h - 2, :], intr.fx),
        (np.s_[:, 0], np.s_[:, 1], intr.fy),
        (np.s_[:, w - 1], np.s_[:, w - 2], intr.fy),
    )
    for line, inner, f in lines:
        inside = blob[line] | blob[inner]
        if not inside.any():
            continue
        edges = np.flatnonzero(np.diff(np.concatenate(([0], inside.astype(np.int8), [0]))))
        starts, ends = edges[0::2], edges[1::2]
        joined = np.concatenate(([True], starts[1:] - ends[:-1] > BORDER_GAP_PX))
        for a, b in zip(starts[joined], np.append(ends[:-1][joined[1:]], ends[-1])):
            on = (blob[line][a:b], blob[inner][a:b])
            z = np.concatenate((depth[line][a:b][on[0]], depth[inner][a:b][on[1]]))
            if (b - a) * float(np.median(z)) / f >= FOREARM_MIN_WIDTH_MM:
                arm[line][a:b] = blob[line][a:b]
    near_border = (us <= 1) | (vs <= 1) | (us >= w - 2) | (vs >= h - 2)
    both_ends = (near_border & (t > 30.0)).sum() >= 3 and (near_border & (t < -30.0)).sum() >= 3
    on_arm = arm[vs, us]
    if on_arm.sum() < 3:
        return None if both_ends else 0.0
    ta = t[on_arm]
    if (ta > 30.0).sum() >= 3 and (ta < -30.0).sum() >= 3:
        return None
    mean = float(ta.mean())
    if abs(mean) > 30.0:
        return -float(np.sign(mean))
    return None if both_ends else 0.0


def _hand_axis(
    pts: NDArray[np.float64], palm_surface: NDArray[np.float64], main: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """The in-plane principal direction (3,), signed like ``main`` (the blob's unit direction
    toward the fingers), of the points ``pts`` (n, 3) mm less than ``HAND_AXIS_BEHIND_PALM_MM``
    behind ``palm_surface``; None with too few.  (A forearm tilts the whole blob's axis.)"""
    hand = pts[(pts - palm_surface) @ main > -HAND_AXIS_BEHIND_PALM_MM]
    axis = _principal(hand) if hand.shape[0] >= 20 else None
    if axis is None:
        return None
    return axis if float(axis @ main) >= 0.0 else -axis


def _principal(pts: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The in-plane principal direction (3,) of ``pts`` (n, 3) (:func:`_in_plane_unit`)."""
    _, V = np.linalg.eigh(np.cov((pts - pts.mean(axis=0)).T))
    return _in_plane_unit(V[:, -1])


def _in_plane_unit(v: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """``v`` (3,) with z = 0, normalised; None when that is (nearly) zero."""
    v = v.copy()
    v[2] = 0.0
    norm = float(np.linalg.norm(v))
    return None if norm < 1e-6 else v / norm


def detection_direction(blob: HandBlob, points: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The in-plane unit direction (3,) from the palm to the mean of the fingertip detections
    ``points`` (n, 3) mm, or None (too few, or a direction the blob offers already): seen
    fingertips point along the hand whatever the forearm does."""
    if points.shape[0] < DETECTION_DIRECTION_MIN_DETECTIONS:
        return None
    toward = _in_plane_unit(points.mean(axis=0) - blob.palm)
    cos_min = np.cos(np.deg2rad(DETECTION_DIRECTION_MIN_DEG))
    if toward is None or any(float(toward @ _in_plane_unit(d)) > cos_min for d in blob.directions):
        return None
    return toward
