"""Finger widths, knuckle span and palm width measured in depth images at known poses (calibration's data check).

The pose tells where each finger's axis and the knuckle (MCP) row lie in the image; the
widths come from the depth data alone:

* finger width: at :data:`FINGER_FRACTIONS` (15 positions, 0.15-0.85) of the proximal and
  middle segment of each finger (index .. little) the depth is sampled on the image line
  through the axis point perpendicular to the projected axis (steps of :data:`STEP_PX`,
  nearest pixel); the finger is the run of samples around the axis whose depth stays within
  the hand's depth band, ending
  where the data end, where the depth jumps (:data:`JUMP_MM`) or where it passes a crest (the
  fold between two touching fingers: the depth rises toward a finger's edge and falls again on
  its neighbour).  The profiles are then taken again across the line through the runs'
  centres (the finger's axis in the data: a pose whose finger is turned or spread would cut
  it obliquely).  Width (mm) = run length in pixels plus :data:`EDGE_ALLOWANCE_PX` at each end,
  times the axis depth over the focal length; runs cut off by the scan, shorter than 2 px or
  merged with a neighbour are dropped; each finger's width is a robust mean over its profiles
  and frames (a median would stick to whole pixels).
* knuckle span: the distance along the hand's x axis between the index and the little
  finger's axis lines (through their runs' centres), each taken at the point nearest its MCP
  joint and intersected with the plane through the joint normal to the palm.
* palm width (reported; the factor uses it only without a knuckle span): on lines across the
  palm (hand x) at :data:`PALM_ROWS`, the run from the palm centre outward, its ends
  intersected with the palm plane (a tilted palm is not measured foreshortened).

:func:`shape_from_widths` maps the measured widths to the model's factors relative to the
default model (:mod:`.hand_model`, :func:`reference_widths`): a finger of the model at
``sigma = 1`` is twice the mean sigma of its proximal and middle segment Gaussians wide, the
knuckle span at ``width = 1`` is the hand-x distance of the index and little MCP joints
(57 mm), the palm at ``width = depth = 1`` that plus twice the palm Gaussians' sigma.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel, HandShape, default_hand_model
from hand_sog_tracker.core.kinematics import attached_points, global_rotation
from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import CalibrationError

__all__ = [
    "STEP_PX",
    "JUMP_MM",
    "CREST_MM",
    "EDGE_ALLOWANCE_PX",
    "FINGER_FRACTIONS",
    "PALM_ROWS",
    "WidthMeasurement",
    "measure_widths",
    "reference_widths",
    "shape_from_widths",
]

#: Sampling step along a profile (px).
STEP_PX = 0.25
#: A depth change between neighbouring samples larger than this (mm) ends a run.
JUMP_MM = 8.0
#: A run ends where the depth falls this much (mm) below its highest value since the axis,
#: after rising at least this much: the crest between two touching fingers.
CREST_MM = 2.0
#: Added to a run's length (px) at each of its two ends: a depth sensor loses about half of a
#: silhouette's boundary pixels (mixed "flying" returns, dropout at grazing angles; both
#: synthetic sensors of :mod:`hand_sog_tracker.synth` do).  On artefact-free depth this reads a
#: finger about 1 px (6-9% at 350-450 mm) too wide.
EDGE_ALLOWANCE_PX = 0.5
#: A finger profile wider than this many times the model finger's width is two fingers merged.
_MAX_FINGER_RATIO = 1.6
#: Positions along the proximal and middle segments (fractions of the segment length): 15 a
#: segment, 30 profiles a finger and frame.  Each profile's run ends snap to whole samples and
#: the crest between touching fingers wanders along the finger, so the knuckle span (the line
#: through the runs' centres) and the widths are averages over many profiles; with 3 a segment
#: (0.3, 0.5, 0.7; before 2026-11-23) the width factor of the 12 mesh dev hands was off by up
#: to 7.4% (sd 2.5%), with 15 by up to 4.1% (sd 1.7%); about 15 ms a frame.
FINGER_FRACTIONS = tuple(round(0.15 + 0.05 * k, 2) for k in range(15))
#: Palm rows, as fractions of the way from the wrist (y = 0) to the lowest MCP joint.
PALM_ROWS = (0.88, 0.91, 0.94, 0.97, 1.0)
#: Depth band of the hand around an axis point (mm): data nearer or farther are not the hand.
_BAND_MM = 30.0
#: A finger profile is scanned over this many expected finger widths each side of the axis.
_FINGER_SCAN = 1.6


@dataclass(frozen=True)
class WidthMeasurement:
    """Widths measured in depth frames (mm; NaN where nothing was measured).

    Attributes
    ----------
    finger_mm : array, shape (4,)
        Width of the index .. little finger across its axis (robust mean over profiles), mm.
    finger_profiles : int array, shape (4,)
        Profiles each finger width is measured on.
    palm_mm : float
        Width of the palm across the hand axis between the thumb's web and the MCP row (robust
        mean over profiles), mm.
    palm_profiles : int
        Profiles the palm width is measured on.
    knuckle_mm : float
        Knuckle span: hand-x distance of the index and little finger axes at their MCP
        joints (median over frames), mm.
    knuckle_frames : int
        Frames the knuckle span is the median of.
    """

    finger_mm: NDArray[np.float64]
    finger_profiles: NDArray[np.int64]
    palm_mm: float
    palm_profiles: int
    knuckle_mm: float = float("nan")
    knuckle_frames: int = 0


def _project(points: NDArray[np.float64], intr: Intrinsics) -> NDArray[np.float64]:
    """Pixel coordinates (k, 2) of camera-frame points (k, 3) mm."""
    z = points[:, 2]
    return np.stack([intr.fx * points[:, 0] / z + intr.cx, intr.fy * points[:, 1] / z + intr.cy], axis=1)


def _profile(
    depth: NDArray[np.floating], centre: NDArray[np.float64], normal: NDArray[np.float64], half_px: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Depth (n,) mm (0 = none) sampled nearest-neighbour at offsets s (n,) px along ``normal``."""
    s = np.arange(-half_px, half_px + 1e-9, STEP_PX)
    uv = centre[None, :] + s[:, None] * normal[None, :]
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    h, w = depth.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = np.zeros(s.size)
    z[inside] = depth[v[inside], u[inside]]
    return s, z


def _run(
    z: NDArray[np.float64], start: int, near: float, far: float, crest: bool
) -> tuple[int, int, int] | None:
    """First and last sample index of the run through ``start`` and how many of its two ends are
    where the data end (not at a crest); None when ``start`` is not on the hand."""
    z = z.tolist()  # (the walk below reads single samples: Python floats are read fastest)
    n = len(z)
    z0 = z[start]
    if not near <= z0 <= far:
        return None
    ends, lost = [], 0
    for step in (-1, 1):
        i, zi, top, top_i = start, z0, z0, start
        while True:
            j = i + step
            if j < 0 or j >= n:
                ends.append(i)
                lost += 1
                break
            zj = z[j]
            if not near <= zj <= far or abs(zj - zi) > JUMP_MM:
                ends.append(i)
                lost += 1
                break
            if crest:
                if zj > top:
                    top, top_i = zj, j
                if top - z0 >= CREST_MM and top - zj >= CREST_MM:
                    ends.append(top_i)
                    break
            i, zi = j, zj
    return ends[0], ends[1], lost


def _finger_profile(
    depth: NDArray[np.floating],
    intr: Intrinsics,
    uv: NDArray[np.float64],
    normal: NDArray[np.float64],
    axis_z: float,
    sigma: float,
) -> tuple[float, NDArray[np.float64]] | None:
    """Width (mm) and centre (pixel (2,)) of the finger run on the profile through ``uv`` along
    ``normal`` (unit, px); ``axis_z`` and ``sigma`` (mm) are the model's axis depth and radius
    there; None when the profile is unusable."""
    half = _FINGER_SCAN * 2.0 * sigma * intr.fx / axis_z
    s, z = _profile(depth, uv, normal, half)
    run = _run(z, int(np.argmin(np.abs(s))), axis_z - sigma - _BAND_MM, axis_z + _BAND_MM, crest=True)
    if run is None or run[0] == 0 or run[1] == z.size - 1:
        return None
    width_px = (run[1] - run[0] + 1) * STEP_PX + 2 * EDGE_ALLOWANCE_PX
    if width_px < 2.0 or width_px > _MAX_FINGER_RATIO * 2.0 * sigma * intr.fx / axis_z:
        return None
    front = _median(z[run[0] : run[1] + 1].tolist())
    # The silhouette of a round finger is its diameter at the depth of its axis, about
    # pi/4 radii behind the mean depth of its front.
    radius = 0.5 * width_px * front / intr.fx
    return width_px * (front + radius * np.pi / 4) / intr.fx, uv + 0.5 * (s[run[0]] + s[run[1]]) * normal


def _finger_widths(
    depth: NDArray[np.floating], intr: Intrinsics, model: HandModel, theta: NDArray[np.float64]
) -> tuple[list[list[float]], list[list[NDArray[np.float64]]]]:
    """Per finger (index .. little) the widths (mm) of its usable profiles and their centres
    (pixel coordinates (2,): the middle of each run).

    Two passes: profiles across the pose's finger axes find the finger; then the finger's axis
    in the image is the line through their centres, and the profiles are taken again across
    that line (a pose whose finger is turned or spread otherwise cuts the finger obliquely).
    """
    chains, segs, offs, nxt = [], [], [], []
    for c in range(1, 5):
        for s in (0, 1):
            for f in FINGER_FRACTIONS:
                y = f * model.lengths[c, s]
                chains.append(c), segs.append(s), offs.append([0.0, y, 0.0]), nxt.append([0.0, y + 5.0, 0.0])
    ch = np.array(chains, dtype=np.int64)
    sg = np.array(segs, dtype=np.int64)
    p = attached_points(model, theta, ch, sg, np.array(offs))
    q = attached_points(model, theta, ch, sg, np.array(nxt))
    puv, quv = _project(p, intr), _project(q, intr)
    seg_sigma = {
        (c, g): float(np.median(model.g_sigmas[(model.g_chain == c) & (model.g_segment == g)]))
        for c in range(1, 5)
        for g in (0, 1)
    }
    sigmas = [seg_sigma[c, g] for c, g in zip(chains, segs)]
    out: list[list[float]] = [[] for _ in range(4)]
    centres: list[list[NDArray[np.float64]]] = [[] for _ in range(4)]
    for c in range(1, 5):
        ks = [k for k in np.flatnonzero(ch == c) if p[k, 2] > 0 and np.hypot(*(quv[k] - puv[k])) > 1e-6]
        first = {}
        for k in ks:
            axis = (quv[k] - puv[k]) / np.hypot(*(quv[k] - puv[k]))
            got = _finger_profile(depth, intr, puv[k], np.array([-axis[1], axis[0]]), p[k, 2], sigmas[k])
            if got is not None:
                first[k] = got[1]
        if len(first) < 3:
            continue
        pts = np.array(list(first.values()))
        mean = pts.mean(axis=0)
        d = np.linalg.svd(pts - mean)[2][0]
        normal = np.array([-d[1], d[0]])
        for k, centre in first.items():
            on_line = mean + d * float((centre - mean) @ d)
            got = _finger_profile(depth, intr, on_line, normal, p[k, 2], sigmas[k])
            if got is not None:
                out[c - 1].append(got[0])
                centres[c - 1].append(got[1])
    return out, centres


def _knuckle_span(
    centres: list[list[NDArray[np.float64]]], intr: Intrinsics, model: HandModel, theta: NDArray[np.float64]
) -> float:
    """Hand-x distance (mm) of the index and little finger axes at their MCP joints; NaN if unseen.

    Each finger's axis is the line through its profiles' centres (image); its knuckle is the
    point of that line nearest the pose's MCP joint, intersected with the plane through the MCP
    joints normal to the palm.
    """
    if len(centres[0]) < 3 or len(centres[3]) < 3:
        return float("nan")
    rot = global_rotation(theta)
    x_axis = rot[:, 0]  # (up to its sign, which the distance ignores)
    mcp = attached_points(model, theta, np.array([1, 4]), np.zeros(2, np.int64), np.zeros((2, 3)))
    mcp_uv = _project(mcp, intr)
    knuckles = []
    for f in (0, 3):
        pts = np.array(centres[f])
        mean = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - mean)
        d = vt[0]
        uv = mean + d * float((mcp_uv[f // 3] - mean) @ d)
        ray = np.array([(uv[0] - intr.cx) / intr.fx, (uv[1] - intr.cy) / intr.fy, 1.0])
        denom = float(ray @ rot[:, 2])
        if abs(denom) < 1e-6:
            return float("nan")
        knuckles.append(ray * (float(mcp[f // 3] @ rot[:, 2]) / denom))
    return abs(float((knuckles[0] - knuckles[1]) @ x_axis))


def _palm_widths(
    depth: NDArray[np.floating], intr: Intrinsics, model: HandModel, theta: NDArray[np.float64]
) -> list[float]:
    """Widths (mm) of the usable palm profiles (hand x) at :data:`PALM_ROWS`."""
    rot = global_rotation(theta)
    normal3 = rot[:, 2]
    palm = model.g_chain < 0
    mcp_y = float(model.bases[1:, 1].min())
    x_mid = 0.5 * float(model.bases[1, 0] + model.bases[4, 0])
    half_mm = 0.5 * (model.bases[1, 0] - model.bases[4, 0]) + 2.0 * float(model.g_sigmas[palm].max())
    out: list[float] = []
    for frac in PALM_ROWS:
        y = frac * mcp_y
        offs = np.array([[x_mid, y, 0.0], [x_mid + 1.0, y, 0.0]])
        pts = attached_points(model, theta, np.array([-1, -1]), np.zeros(2, np.int64), offs)
        uv = _project(pts, intr)
        axis = uv[1] - uv[0]
        norm = float(np.hypot(*axis))
        if norm < 1e-6 or pts[0, 2] <= 0:
            continue
        # Scan 1.6x the model's palm half width each side.
        s, z = _profile(depth, uv[0], axis / norm, 1.6 * half_mm * norm)
        centre = int(np.argmin(np.abs(s)))
        sigma = float(model.g_sigmas[palm].max())
        run = _run(z, centre, pts[0, 2] - sigma - _BAND_MM, pts[0, 2] + _BAND_MM, crest=False)
        if run is None or run[0] == 0 or run[1] == z.size - 1:
            continue
        ends_uv = uv[0][None, :] + s[list(run[:2])][:, None] * (axis / norm)[None, :]
        rays = np.stack(
            [(ends_uv[:, 0] - intr.cx) / intr.fx, (ends_uv[:, 1] - intr.cy) / intr.fy, np.ones(2)], axis=1
        )
        denom = rays @ normal3
        if np.any(np.abs(denom) < 1e-6):
            continue
        hits = rays * ((pts[0] @ normal3) / denom)[:, None]
        # The run counts whole samples: add one step's length and the lost edges.
        px_mm = pts[0, 2] / intr.fx
        out.append(float(np.linalg.norm(hits[1] - hits[0])) + (STEP_PX + run[2] * EDGE_ALLOWANCE_PX) * px_mm)
    return out


def _median(values: list[float]) -> float:
    """``np.median`` of finite ``values`` (the same value; sorting a short Python list is
    several times cheaper than NumPy's call, and a fit measures hundreds of profiles)."""
    s = sorted(values)
    mid = len(s) // 2
    return s[mid] if len(s) % 2 else (s[mid - 1] + s[mid]) / 2


def _robust_mean(values: Sequence[float]) -> float:
    """Mean of the values within [0.75, 1.33] times their median (NaN if none).

    Run lengths come in whole pixels along a profile that follows an image row or column, so a
    median would be one of a few quantised values; the mean over profiles at different
    sub-pixel phases is not.  Merged fingers and cut-off runs are left out.
    """
    if not len(values):
        return float("nan")
    v = np.asarray(values, dtype=np.float64)
    med = float(np.median(v))
    keep = v[(v >= 0.75 * med) & (v <= 1.33 * med)]  # (empty for a median <= 0)
    return float(keep.mean()) if keep.size else float("nan")


def measure_widths(
    depths: Sequence[NDArray[np.floating]],
    intrinsics: Sequence[Intrinsics] | Intrinsics,
    model: HandModel,
    poses: Sequence[NDArray[np.float64]],
) -> WidthMeasurement:
    """Measure finger widths and the palm width in depth frames at known poses.

    Parameters
    ----------
    depths : sequence of arrays, shape (H, W)
        Depth images (mm, 0 = no data), e.g. :attr:`~.depth_sog.Preprocessed.depth_mm`.
    intrinsics : Intrinsics or sequence of Intrinsics
        Camera of each image (one for all).
    model : HandModel
        Model the poses were fitted with (its handedness and bone lengths place the axes).
    poses : sequence of arrays, shape (26,)
        Pose of the hand in each image (mm, rad).

    Returns
    -------
    WidthMeasurement
        Medians over all profiles of all frames.
    """
    if len(depths) != len(poses):
        raise CalibrationError(f"got {len(poses)} poses for {len(depths)} depth frames")
    intrs = list(intrinsics) if isinstance(intrinsics, (list, tuple)) else [intrinsics] * len(depths)
    fingers: list[list[float]] = [[] for _ in range(4)]
    palms: list[float] = []
    spans: list[float] = []
    for depth, intr, theta in zip(depths, intrs, poses):
        th = np.asarray(theta, dtype=np.float64)
        widths, centres = _finger_widths(depth, intr, model, th)
        for c in range(4):
            fingers[c] += widths[c]
        span = _knuckle_span(centres, intr, model, th)
        if np.isfinite(span):
            spans.append(span)
        palms += _palm_widths(depth, intr, model, th)
    return WidthMeasurement(
        finger_mm=np.array([_robust_mean(w) for w in fingers]),
        finger_profiles=np.array([len(w) for w in fingers], dtype=np.int64),
        palm_mm=_robust_mean(palms),
        palm_profiles=len(palms),
        knuckle_mm=float(np.median(spans)) if spans else float("nan"),
        knuckle_frames=len(spans),
    )


def reference_widths(model: HandModel | None = None) -> tuple[NDArray[np.float64], float, float]:
    """The default model's widths the factors are relative to.

    Returns
    -------
    finger_mm : array, shape (4,)
        Index .. little: twice the mean sigma of the finger's proximal and middle segment
        Gaussians at ``sigma = 1`` (mm).
    knuckle_mm : float
        Knuckle span at ``width = 1``: hand-x distance of the index and little MCP joints (mm).
    palm_rim_mm : float
        Twice the palm Gaussians' sigma at ``depth = 1`` (mm): the palm's width is
        ``knuckle_mm * width + palm_rim_mm * depth``.
    """
    base = default_hand_model(True) if model is None else model.scaled(HandShape())
    fingers = np.array(
        [
            2.0 * float(base.g_sigmas[(base.g_chain == c) & (base.g_segment <= 1)].mean())
            for c in range(1, 5)
        ]
    )
    knuckle = float(base.bases[1, 0] - base.bases[4, 0])
    rim = 2.0 * float(base.g_sigmas[base.g_chain < 0].mean())
    return fingers, knuckle, rim


def shape_from_widths(measured: WidthMeasurement) -> tuple[float, float]:
    """The model's ``sigma`` and ``width`` factors that reproduce the measured widths.

    ``sigma``: the profile-weighted mean over fingers of measured / reference width;
    ``width``: measured / reference knuckle span (the MCP joints' spread does not depend on
    how thick the hand is); without a knuckle span, ``(palm_mm - palm_rim_mm * sigma) /
    knuckle_mm`` from the palm's outline (its rim taken as thick as the fingers, as calibration
    ties palm depth to finger thickness; a hand whose palm is not thicker with thicker fingers
    is then fitted wrong by ``palm_rim_mm / knuckle_mm`` (0.44) times the thickness error).

    Returns
    -------
    sigma, width : float
        NaN where the measurement has no profiles.
    """
    ref, knuckle, rim = reference_widths()
    ok = np.isfinite(measured.finger_mm) & (measured.finger_profiles > 0)
    if not ok.any():
        return float("nan"), float("nan")
    ratio = measured.finger_mm[ok] / ref[ok]
    sigma = float(np.average(ratio, weights=measured.finger_profiles[ok]))
    if np.isfinite(measured.knuckle_mm):
        width = measured.knuckle_mm / knuckle
    elif np.isfinite(measured.palm_mm):
        width = (measured.palm_mm - rim * sigma) / knuckle
    else:
        width = float("nan")
    return sigma, float(width)
