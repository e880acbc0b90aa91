"""Is it a hand?  Evidence from one frame's depth against the tracked model (issue 46).

One job: the per-frame hand check and the gate that acts on it; kept together because the
gate's threshold is the check's confidence scale.

The tracker fits its model to whatever lies near the last hand: a forearm at the image
border, a head, a cup.  :func:`check_hand` compares the fitted model with the depth image on a
coarse pixel grid (about 160 px wide) and measures what a hand gives and those do not:

* **model on data** (``on``): of the cores of the model's projected Gaussians (each a disc of
  ``ON_CORE`` times its skin radius, with its front surface depth: the model's spheres overflow
  a flat palm or finger seen edge-on), the share whose pixels hold data at the model's depth
  (within ``DEPTH_TOL_MM``).  Pixels whose data lie in front of the model are *occluded*
  (an object in the hand, another finger) and count neither way; pixels with no data, data
  behind the model or outside the image count against.
* **data explained** (``explained``): of the foreground data around the model (within
  ``MARGIN_MM`` of its silhouette, on the hand side of the wrist plane, not behind the nearest
  model surface by more than ``DEPTH_TOL_MM``: a table or a wall behind the hand is background),
  the share the silhouette covers.  A head, a torso or a table edge the model sits on leaves
  much of it unexplained; a hand does not.
* **fingers on data** (``fingers_on``): the same share per finger (thumb .. little), averaged
  over the five.  The palm alone lying on a forearm stump, its fingers in the air, gives a high
  ``on`` but a low ``fingers_on``.
* **outline** (``outline``): in a ring just outside the silhouette (hand side of the wrist), the
  share where the depth steps back by more than ``EDGE_MM`` from the data of the nearest model
  pixel, or has none: a hand's outline is a depth edge, also on a table; a model lying on a
  head, a box or a table top has the same surface on both sides of its outline.
* **finger edges** (``finger_edges``, reported, not used): the outline share over the part of
  the ring next to the model's fingers (their nearest model pixel is a finger's).  Model
  fingers spread over a head lie on one surface; but a real hand's or an adducted hand's
  finger outline is also partly on its own data.
* **steep edges** (``steep``): of the outline ring's depth edges, the share that are steps: a
  hand's outline drops to what lies behind it (far, or a wall or a table close behind, flat
  beyond the step), while a head's surface curves away, so a model lying on a head has edges
  of 10-30 mm that keep receding one ring width further out.
* **finger ends** (``ends``): past each fingertip, along the finger in the image, the data must
  end or step back by more than ``EDGE_MM`` (a finger-like extremity): a model finger lying on
  a forearm, a head or a box runs into more surface there.  Fingers seen end-on are left out,
  and so are fingers off the data (their ``fingers_on`` share below ``FINGERS_LOW``): a model
  finger hanging in the air beside a forearm has no data past its tip either.

The confidence is the product of six of them, each mapped linearly onto [0, 1]: ``on`` from
``ON_LOW`` to ``ON_HIGH``, ``fingers_on`` from ``FINGERS_LOW`` to ``FINGERS_HIGH``,
``explained`` from ``EXPLAINED_LOW`` to ``EXPLAINED_HIGH``, ``outline`` from ``OUTLINE_LOW`` to
``OUTLINE_HIGH``, ``steep`` from ``STEEP_LOW`` to ``STEEP_HIGH`` (no edge: 1), ``ends`` from
``ENDS_LOW`` to 1 (no finger checked: 1); ``finger_edges`` is
measured and reported but not in the product (see the design note: it separates a synthetic
head from synthetic hands, not from real hands or fingers held together).  A product, because
each failure alone means "no hand": a model on a head or among cups lies on data but explains
little of it and has no outline, a model on a forearm stump explains it but its fingers hang off
it, a model flat on a table top does both but has no outline, a model on a head passes all of
those on some frames (on data, covering it, fingers ending at the head's rim) but its outline
is the head's surface curving away.

Per finger: the share of that finger's
silhouette on data (occluded pixels count against: a finger the data cannot show is reported
with a low confidence).

:class:`HandGate` applies it, inside :class:`~hand_sog_tracker.core.tracker.Tracker` (every
result carries its decision, so the node, the tools and the core answer alike): below its
threshold the frame is "no hand" (no pose is reported);
below ``RESET_BELOW``, or after ``RESET_FRAMES`` frames in a row below the threshold, the
tracker is reset, so that the next frame searches the whole image afresh instead of keeping a
wrong lock.  A new track is reported only from its first frame with a finger seen to end
(``ends`` at least ``ENDS_CONFIRM``; until then its confidence is multiplied by the ``ends``
ramp, a frame with no finger seen counting as none ending): a model curled into a fist fits a head or a ball as well
as a fist, and the fingers are what a hand has and they do not (a fist that enters the view is
reported once it opens a finger; a tracked hand that closes into a fist stays reported).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Callable, Final, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import skeleton_points
from hand_sog_tracker.core.types import HandDecision, HandEvidence, Intrinsics, TrackerStatus, TrackResult

__all__ = [
    "DEPTH_TOL_MM",
    "MARGIN_MM",
    "HAND_THRESHOLD",
    "HandEvidence",
    "HandDecision",
    "check_hand",
    "HandGate",
]

DEPTH_TOL_MM: Final = 20.0  #: data within this of the model's front surface lie on it (chosen here)
MARGIN_MM: Final = 35.0  #: foreground data this close to the silhouette must be explained (chosen here)
ON_CORE: Final = 0.6  #: ``on`` looks at discs of this share of each Gaussian's radius (chosen here)
WRIST_MARGIN_MM: Final = 10.0  #: data beyond the wrist plane by more than this are the forearm
OUTLINE_RING_PX: Final = (1.5, 3.5)  #: the outline ring, grid pixels outside the silhouette
EDGE_MM: Final = 10.0  #: a step back of more than this is an edge (chosen here)
#: An edge stepping back by more than this is a step, whatever lies beyond it (a head's side
#: recedes 10-30 mm across the outline ring at 0.6 m; chosen on scenes_dev).
STEEP_MM: Final = 30.0
END_GAP_MM: Final = 25.0  #: finger-end samples this far (and 1.5 times) past the tip's skin (chosen here)
END_STRAIGHT_COS: Final = 0.5  #: fingers whose distal and proximal bones are nearer than 60 deg are checked
ON_LOW, ON_HIGH = 0.60, 0.85  #: ``on`` mapped onto 0 .. 1 (chosen on scenes_dev)
FINGERS_LOW, FINGERS_HIGH = 0.35, 0.65  #: ``fingers_on`` mapped onto 0 .. 1 (chosen on scenes_dev)
OUTLINE_LOW, OUTLINE_HIGH = 0.2, 0.6  #: ``outline`` mapped onto 0 .. 1 (chosen on scenes_dev)
EXPLAINED_LOW, EXPLAINED_HIGH = 0.70, 0.92  #: ``explained`` mapped onto 0 .. 1 (chosen on scenes_dev)
ENDS_LOW: Final = 0.3  #: share of ending fingers mapped onto 0 (chosen on scenes_dev)
#: ``steep`` mapped onto 0 .. 1 (chosen on scenes_dev and 16 dev heads: heads median 0.55-0.74,
#: 1% of their frames above 0.8; good hands at least 0.86, the labelled real frames 0.86).
STEEP_LOW, STEEP_HIGH = 0.8, 0.9
#: Default threshold of :class:`HandGate` (and of the node's ``hand_threshold``).
HAND_THRESHOLD: Final = 0.2
#: Default ``reset_frames`` of :class:`HandGate` (0.1 s at 30 Hz; chosen on scenes_dev).
RESET_FRAMES: Final = 3
#: A new track is reported from its first frame with at least this share of finger ends.
ENDS_CONFIRM: Final = 0.5
#: A tracked frame below this confidence resets the tracker at once (one evidence failed
#: outright: the model is on something else).
RESET_BELOW: Final = 0.05
_GRID_WIDTH = 160  #: the check's pixel grid is about this wide
#: ``points (n, 3) mm -> (n,) bool``: which data another hand explains (see :func:`check_hand`).
Theirs = Callable[[NDArray[np.float64]], NDArray[np.bool_]]


def _ramp(x: float, lo: float, hi: float) -> float:
    return float(min(max((x - lo) / (hi - lo), 0.0), 1.0))


def check_hand(
    depth_mm: NDArray,
    intr: Intrinsics,
    model: HandModel,
    result: TrackResult,
    theirs: Theirs | None = None,
) -> HandDecision:
    """Check that the tracked model of ``result`` sits on a hand in ``depth_mm``.

    Parameters
    ----------
    depth_mm : array, shape (H, W)
        The frame's depth, mm (0, NaN invalid), at the resolution of ``intr``.
    intr : Intrinsics
    model : HandModel
        The model ``result`` was tracked with (its ``g_chain`` orders ``result.gaussians_mm``).
    result : TrackResult
        The tracker's result; without a pose the decision is "no hand", confidence 0.
    theirs : callable, optional
        ``points (n, 3) mm -> (n,) bool``: the data that another hand explains (the multi-hand
        tracker's split, :mod:`.hands`).  Their pixels count neither way (as occluded ones):
        not on or off the model, not foreground to explain, not outline, no finger end, and a
        finger whose visible part they all are is left out of ``fingers_on``.

    Returns
    -------
    HandDecision
        ``present`` is left False; :class:`HandGate` sets it against its threshold.
    """
    if result.pose is None or result.gaussians_mm is None or result.skeleton_mm is None:
        return HandDecision(False, 0.0)
    s = max(1, int(round(intr.width / _GRID_WIDTH)))
    full = np.asarray(depth_mm)  # (read as float32 where read: the box and the finger ends' pixels)
    gh, gw = -(-full.shape[0] // s), -(-full.shape[1] // s)  # the grid's shape
    fx, fy, cx, cy = intr.fx / s, intr.fy / s, intr.cx / s, intr.cy / s
    C = np.asarray(result.gaussians_mm, dtype=np.float64)
    r = np.asarray(model.g_sigmas, dtype=np.float64)
    chain = np.asarray(model.g_chain)
    z = np.maximum(C[:, 2], 50.0)
    u = fx * C[:, 0] / z + cx
    v = fy * C[:, 1] / z + cy
    rp = fx * r / z
    z_sorted, half = sorted(z.tolist()), z.size // 2  # (the median as np.median takes it, cheaper)
    z_mid = z_sorted[half] if z.size % 2 else (z_sorted[half - 1] + z_sorted[half]) / 2
    pad = int(math.ceil(fx * MARGIN_MM / z_mid)) + 1
    # The grid box around the model (may extend past the image: those pixels are off the data).
    u0, u1 = int(math.floor((u - rp).min())) - pad, int(math.ceil((u + rp).max())) + pad + 1
    v0, v1 = int(math.floor((v - rp).min())) - pad, int(math.ceil((v + rp).max())) + pad + 1
    if u1 - u0 > 4 * gw or v1 - v0 > 4 * gh:  # (a degenerate pose: nothing sensible to check)
        return HandDecision(False, 0.0, evidence=HandEvidence(0.0, 0.0, 0.0, math.nan, 0.0, 0.0))
    uu = np.arange(u0, u1, dtype=np.float64)
    vv = np.arange(v0, v1, dtype=np.float64)
    bh, bw = vv.size, uu.size
    front, owner, core = _front(C, r, z, (u, v, rp), (fx, fy), (uu, vv))
    on_model = np.isfinite(front)
    # The data in the box (0 outside the image).
    data = np.zeros((bh, bw), dtype=np.float32)
    data_f = np.zeros((bh, bw), dtype=np.float32)  # (invalid pixels unknown: for ``on``)
    iu0, iu1, iv0, iv1 = max(u0, 0), min(u1, gw), max(v0, 0), min(v1, gh)
    if iu0 < iu1 and iv0 < iv1:  # (the grid of the box's part in the image only)
        depth, filled = _grid_depth(full[iv0 * s : iv1 * s, iu0 * s : iu1 * s], s)
        data[iv0 - v0 : iv1 - v0, iu0 - u0 : iu1 - u0] = depth
        data_f[iv0 - v0 : iv1 - v0, iu0 - u0 : iu1 - u0] = filled
    inside = np.zeros((bh, bw), dtype=bool)
    inside[max(iv0 - v0, 0) : max(iv1 - v0, 0), max(iu0 - u0, 0) : max(iu1 - u0, 0)] = True
    valid = data > 0
    valid_f = data_f > 0
    diff = np.where(valid_f, data_f - np.where(on_model, front, 0.0), np.inf)
    on = core & (np.abs(diff) <= DEPTH_TOL_MM)  # (diff: inf without data)
    occluded = core & (diff < -DEPTH_TOL_MM)
    other = None if theirs is None else _theirs_grid(theirs, data_f, valid_f, (uu, vv), (fx, fy, cx, cy))
    if other is not None:
        on &= ~other
        occluded |= core & other
    off = core & ~on & ~occluded
    n_on, n_off = int(np.count_nonzero(on)), int(np.count_nonzero(off))
    on_share = n_on / max(n_on + n_off, 1)
    in_view = float(np.count_nonzero(on_model & inside)) / max(int(np.count_nonzero(on_model)), 1)

    # Foreground data near the model on the hand side of the wrist plane, not behind it.
    k = 2 * pad + 1
    near_front = cv2.erode(front.astype(np.float32), np.ones((k, k), np.uint8))  # (front: inf off the model)
    axis = _hand_axis(result.pose)
    px = ((uu[None, :] - cx) / fx) * data  # (data: 0 where there are none)
    py = ((vv[:, None] - cy) / fy) * data
    along = (px - result.pose[0]) * axis[0] + (py - result.pose[1]) * axis[1] + (data - result.pose[2]) * axis[2]
    fg = valid & np.isfinite(near_front) & (data <= near_front + DEPTH_TOL_MM)
    fg &= (data >= near_front - 3.0 * MARGIN_MM) & (along > -WRIST_MARGIN_MM)
    if other is not None:
        fg &= ~other
    covered = cv2.dilate(on_model.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    n_fg = int(np.count_nonzero(fg))
    explained = float(np.count_nonzero(fg & covered)) / max(n_fg, 1) if n_fg else 0.0

    own_chain = np.append(chain, -2)[owner]  # (owner -1: none, chain -2)
    outline, finger_edges, steep = _outline(
        data, valid, inside, on_model, own_chain, (uu, vv), (fx, fy, cx, cy), result.pose, axis, other
    )
    # Per finger (chains 0-4; -1 the palm, -2 no owner): its core, on and off pixels counted.
    n, n_c_on, n_c_off = (np.bincount(own_chain[mask] + 2, minlength=7)[2:] for mask in (core, on, off))
    fingers = n_c_on / np.maximum(n, 1)  # per finger: on / all (occluded counts against: not shown; 0 without)
    visible_on = n_c_on / np.maximum(n_c_on + n_c_off, 1)  # per finger: on / (on + off)
    shown = visible_on >= FINGERS_LOW  # (a finger off the data has no end to see)
    ends = _finger_ends(full, s, result, model, (fx, fy, cx, cy), on_model, (u0, v0), shown, other)
    counted = np.ones(5, dtype=bool)  # the fingers in ``fingers_on``'s mean
    if other is not None:  # (another hand hides the whole finger: it counts neither way)
        counted = (n_c_on + n_c_off > 0) | (np.bincount(own_chain[core & other] + 2, minlength=7)[2:] == 0)
    fingers_on = float(visible_on[counted].mean()) if counted.any() else float(visible_on.mean())
    e_factor = 1.0 if math.isnan(ends) else _ramp(ends, ENDS_LOW, 1.0)
    s_factor = 1.0 if math.isnan(steep) else _ramp(steep, STEEP_LOW, STEEP_HIGH)
    confidence = (
        _ramp(on_share, ON_LOW, ON_HIGH)
        * _ramp(fingers_on, FINGERS_LOW, FINGERS_HIGH)
        * _ramp(explained, EXPLAINED_LOW, EXPLAINED_HIGH)
        * _ramp(outline, OUTLINE_LOW, OUTLINE_HIGH)
        * e_factor
        * s_factor
    )
    fingers *= confidence > 0  # (no finger of a frame that is no hand)
    evidence = HandEvidence(on_share, explained, fingers_on, ends, in_view, outline, finger_edges, steep)
    return HandDecision(False, confidence, fingers, evidence)


def _front(
    C: NDArray[np.float64],
    r: NDArray[np.float64],
    z: NDArray[np.float64],
    proj: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    f: tuple[float, float],
    grid: tuple[NDArray[np.float64], NDArray[np.float64]],
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.bool_]]:
    """The model's front surface on the grid box ``grid`` (the box's u (bw,) and v (bh,)
    pixel coordinates): its depth (bh, bw) mm (inf: off the model), the Gaussian that makes it
    (-1: none; the first on a tie) and the cores (discs of ``ON_CORE`` times the radius).

    ``C`` (m, 3) mm the Gaussians' centres, ``r`` (m,) their skin radii, ``z`` (m,) their
    depths, ``proj`` their projections u, v and projected radii (m,) each, grid px.  Each
    Gaussian is a sphere drawn on the pixels of its own box; all of them at once, as patches
    of one size, then the nearest per pixel."""
    u, v, rp = proj
    fx, fy = f
    uu, vv = grid
    bh, bw = vv.size, uu.size
    u0, v0 = int(uu[0]), int(vv[0])
    m = C.shape[0]
    # Each Gaussian's box (as ints: truncated toward zero, as ``int()``), clipped to the grid box.
    a0 = np.maximum((u - rp).astype(np.int64) - u0, 0)
    a1 = np.minimum((u + rp).astype(np.int64) + 2 - u0, bw)
    b0 = np.maximum((v - rp).astype(np.int64) - v0, 0)
    b1 = np.minimum((v + rp).astype(np.int64) + 2 - v0, bh)
    pw, ph = max(int((a1 - a0).max()), 1), max(int((b1 - b0).max()), 1)
    cols = a0[:, None] + np.arange(pw)  # (m, pw) box columns of each patch
    rows = b0[:, None] + np.arange(ph)  # (m, ph)
    in_box = (rows < b1[:, None])[:, :, None] & (cols < a1[:, None])[:, None, :]  # (m, ph, pw)
    du = (uu.take(np.minimum(cols, bw - 1)) - u[:, None]) * (z / fx)[:, None]
    dv = (vv.take(np.minimum(rows, bh - 1)) - v[:, None]) * (z / fy)[:, None]
    d2 = (r * r)[:, None, None] - (du * du)[:, None, :] - (dv * dv)[:, :, None]
    disc = np.flatnonzero(in_box & (d2 >= 0))  # (the drawn patch pixels, Gaussian after Gaussian)
    idx = (rows[:, :, None] * bw + cols[:, None, :]).take(disc)  # their flat box pixels
    gi = disc // (ph * pw)  # their Gaussians
    d2 = d2.take(disc)  # (>= 0: only the drawn pixels' square roots)
    zf = C[:, 2].take(gi) - np.sqrt(d2)
    front = np.full(bh * bw, np.inf)
    np.minimum.at(front, idx, zf)
    nearest = zf == front[idx]
    owner = np.full(bh * bw, m, dtype=np.int64)
    np.minimum.at(owner, idx[nearest], gi[nearest])
    owner[owner == m] = -1
    core = np.zeros(bh * bw, dtype=bool)
    core[idx[d2 >= ((1.0 - ON_CORE * ON_CORE) * r * r).take(gi)]] = True
    return front.reshape(bh, bw), owner.reshape(bh, bw), core.reshape(bh, bw)


def _grid_depth(depth_mm: NDArray, s: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The check's grid of ``depth_mm`` (the image or a block of it starting at a multiple of
    ``s``), every ``s``-th pixel (mm, 0 no data), shape (ceil(H/s), ceil(W/s)),
    and the same grid with each invalid pixel (0, NaN, Inf) replaced by the first valid pixel
    of its ``s`` x ``s`` block.

    The second is for the evidence where no data counts against the model (``on``,
    ``fingers_on``): there an invalid pixel is unknown, and a cell is "no data" only when none
    of its pixels has data (a stream with every third row invalid is checked like a clean
    one).  Where no data speaks for a hand (an outline, a finger end) the plain grid is used: a
    block's other pixel there is often the hand's own edge."""
    h, w = depth_mm.shape
    gh, gw = -(-h // s), -(-w // s)
    block = np.asarray(depth_mm, dtype=np.float32)
    if h % s or w % s:  # (the image's edge padded with no data)
        block = np.zeros((gh * s, gw * s), dtype=np.float32)
        block[:h, :w] = depth_mm
    cells = block.reshape(gh, s, gw, s)  # each cell's s x s block as axes 1 and 3
    valid = (cells > 0) & (cells < np.inf)  # (NaN: neither)
    grid = np.zeros((gh, gw), dtype=np.float32)
    for k in range(s * s - 1, -1, -1):  # (the block's pixels from its last: the first valid one stays)
        dy, dx = divmod(k, s)
        np.copyto(grid, cells[:, dy, :, dx], where=valid[:, dy, :, dx])
    return np.where(valid[:, 0, :, 0], cells[:, 0, :, 0], np.float32(0.0)), grid


def _outline(
    data: NDArray[np.float32],
    valid: NDArray[np.bool_],
    inside: NDArray[np.bool_],
    on_model: NDArray[np.bool_],
    own_chain: NDArray[np.int64],
    grid: tuple[NDArray[np.float64], NDArray[np.float64]],
    k: tuple[float, float, float, float],
    theta: NDArray[np.float64],
    axis: NDArray[np.float64],
    other: NDArray[np.bool_] | None = None,
) -> tuple[float, float, float]:
    """Share of the outline ring (``OUTLINE_RING_PX`` outside the silhouette) that is a depth
    edge: no data, or data more than ``EDGE_MM`` behind the data of the nearest model pixel;
    the same share over the ring pixels whose nearest model pixel is a finger's
    (``own_chain``: the chain of each box pixel's front Gaussian, 0-4 the fingers; NaN: none);
    and the share of those edges that are steps, not a surface curving away (see
    :class:`~hand_sog_tracker.core.types.HandEvidence`; NaN: no edge).  ``other``: the box
    pixels another hand explains (not counted)."""
    if not on_model.any():
        return 0.0, math.nan, math.nan
    dist, labels = cv2.distanceTransformWithLabels(
        (~on_model).astype(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    lut = np.zeros(int(labels.max()) + 1, dtype=np.int64)
    model_flat = np.flatnonzero(on_model)
    lut[labels.ravel()[model_flat]] = model_flat
    ring = (dist > OUTLINE_RING_PX[0]) & (dist <= OUTLINE_RING_PX[1]) & inside
    ring_idx = np.flatnonzero(ring)
    near = lut[labels.ravel()[ring_idx]]
    inner = data.ravel()[near]
    ok = valid.ravel()[near]
    ring_idx, near, inner = ring_idx[ok], near[ok], inner[ok]
    if ring_idx.size == 0:
        return 0.0, math.nan, math.nan
    fx, fy, cx, cy = k
    uu, vv = grid
    w = on_model.shape[1]
    rv, ru = np.divmod(ring_idx, w)
    pu, pv = uu[ru], vv[rv]
    p = np.empty((inner.size, 3))
    p[:, 0], p[:, 1], p[:, 2] = (pu - cx) / fx * inner, (pv - cy) / fy * inner, inner
    hand_side = (p - theta[:3]) @ axis > -WRIST_MARGIN_MM
    d = data.ravel()[ring_idx]
    has = valid.ravel()[ring_idx]
    edge = ~has | (d > inner + EDGE_MM)
    occluder = has & (d < inner - DEPTH_TOL_MM)
    count = hand_side & ~occluder
    if other is not None:
        count &= ~other.ravel()[ring_idx]
    n = int(np.count_nonzero(count))
    near_chain = own_chain.ravel()[near]
    finger = count & (near_chain >= 0) & (near_chain < 5)
    n_f = int(np.count_nonzero(finger))
    finger_edges = float(np.count_nonzero(edge & finger)) / n_f if n_f else math.nan
    n_edge = int(np.count_nonzero(edge & count))
    # A surface curving away: an edge less than STEEP_MM behind that keeps receding (or ends)
    # one ring width further out; a step onto a wall or a table close behind does not recede.
    nv, nu = np.divmod(near, w)
    du, dv = ru - nu, rv - nv
    reach = (OUTLINE_RING_PX[1] - OUTLINE_RING_PX[0]) / np.maximum(np.hypot(du, dv), 1e-6)
    ou = np.clip(np.rint(ru + du * reach).astype(np.int64), 0, w - 1)
    ov = np.clip(np.rint(rv + dv * reach).astype(np.int64), 0, on_model.shape[0] - 1)
    receding = has & (d <= inner + STEEP_MM) & (~valid[ov, ou] | (data[ov, ou] > d + EDGE_MM))
    steep = float(np.count_nonzero(edge & count & ~receding)) / n_edge if n_edge else math.nan
    return (n_edge / n if n else 0.0), finger_edges, steep


def _hand_axis(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    from hand_sog_tracker.core.kinematics import global_rotation

    return global_rotation(theta)[:, 1]


def _finger_ends(
    full: NDArray,
    s: int,
    result: TrackResult,
    model: HandModel,
    k: tuple[float, float, float, float],
    on_model: NDArray[np.bool_],
    origin: tuple[int, int],
    shown: NDArray[np.bool_],
    other: NDArray[np.bool_] | None = None,
) -> float:
    """Share of the extended fingers seen from the side whose data end past the tip (NaN:
    none checked).  ``full``: the depth image (mm), read on the grid of every ``s``-th pixel;
    ``on_model``: the model's silhouette on the grid box at ``origin`` (u0, v0); ``shown``
    (5,): the fingers on the data (only those are checked: a model finger hanging in the air
    beside a forearm has no data past its tip either); ``other``: the box pixels another hand
    explains (cannot tell)."""
    fx, fy, cx, cy = k
    assert result.pose is not None and result.fingertips_mm is not None
    sk = skeleton_points(model, result.pose)  # (the kinematic joints: the fingers' bones)
    tips = np.asarray(result.fingertips_mm)
    radii = model.tip_radii.tolist()
    # (Per finger in Python floats from its unit direction on: the same IEEE operations.)
    gh, gw = -(-full.shape[0] // s), -(-full.shape[1] // s)
    bh, bw = on_model.shape
    checked = ended = 0
    for c in range(5):
        if not shown[c]:
            continue  # off the data: its end says nothing
        tip = tips[c]
        d = tip - sk[4 * c + 3]
        base = sk[4 * c + 2] - sk[4 * c + 1]
        n, nb = math.sqrt(d @ d), math.sqrt(base @ base)  # (as np.linalg.norm takes them)
        if n < 1e-6 or nb < 1e-6 or (d @ base) / (n * nb) < END_STRAIGHT_COS:
            continue  # a curled finger ends against the palm
        ux, uy, _ = (d / n).tolist()
        lateral = math.hypot(ux, uy)
        if lateral < 0.6:  # end-on: the end is not seen against the image
            continue
        ux, uy = ux / lateral, uy / lateral
        tx, ty, tz = tip.tolist()
        fg = samples = 0
        for gap in (END_GAP_MM, 1.5 * END_GAP_MM):
            step = radii[c] + gap
            px, py = tx + step * ux, ty + step * uy  # (z: the tip's)
            iu, iv = int(round(fx * px / tz + cx)), int(round(fy * py / tz + cy))
            if not (0 <= iu < gw and 0 <= iv < gh):
                continue
            bu, bv = iu - origin[0], iv - origin[1]
            if 0 <= bu < bw and 0 <= bv < bh and on_model[bv, bu]:
                continue  # another part of the model lies there (a crossing thumb)
            if other is not None and 0 <= bu < bw and 0 <= bv < bh and other[bv, bu]:
                continue  # another hand lies there (touching fingertips): cannot tell
            dz = float(np.float32(full[iv * s, iu * s]))  # (the grid's pixel: 0 without data)
            dz = dz if math.isfinite(dz) and dz > 0 else 0.0
            surface = tz - radii[c]
            if 0 < dz < surface - DEPTH_TOL_MM:
                continue  # something in front of the finger: cannot tell
            samples += 1
            fg += 0 < dz <= surface + EDGE_MM
        if samples == 0:
            continue
        checked += 1
        ended += fg == 0
    return ended / checked if checked else math.nan


def _theirs_grid(
    theirs: Theirs,
    data: NDArray[np.float32],
    valid: NDArray[np.bool_],
    grid: tuple[NDArray[np.float64], NDArray[np.float64]],
    k: tuple[float, float, float, float],
) -> NDArray[np.bool_]:
    """The grid box pixels (``data`` (bh, bw) mm, ``valid``) whose data ``theirs`` gives to
    another hand (bh, bw) bool; ``grid``: the box's u (bw,) and v (bh,), ``k`` the grid's
    intrinsics."""
    uu, vv = grid
    fx, fy, cx, cy = k
    out = np.zeros(data.shape, dtype=bool)
    rows, cols = np.nonzero(valid)
    if rows.size:
        z = data[rows, cols].astype(np.float64)
        pts = np.stack([(uu[cols] - cx) / fx * z, (vv[rows] - cy) / fy * z, z], 1)
        out[rows, cols] = theirs(pts)
    return out


class _Resettable(Protocol):
    def reset(self) -> None: ...


class HandGate:
    """Decide per frame whether a hand is reported; reset the tracker when it is no hand.

    A tracked frame below the threshold is reported as "no hand" at once.  The tracker is
    reset (the next frame searches the whole image afresh instead of keeping a wrong lock) at
    once when the confidence is below ``RESET_BELOW``, and after ``reset_frames`` frames in a
    row below the threshold otherwise: resetting on every unsure frame made good but unsure
    tracks start over (on the back of the hand, scenes_dev, the frames within 20 mm fell from
    56% to 29%).

    Parameters
    ----------
    threshold : float
        Confidence at or above which the tracked hand is reported (in [0, 1]).
    reset_frames : int
        Low frames in a row that reset the tracker (>= 1).
    confirm_ends : bool
        A new track waits for a finger end (see the module docstring); False reports it from
        its first sure frame (a fist then is reported at once, a head fitted by a fist too).
    """

    def __init__(
        self, threshold: float = HAND_THRESHOLD, reset_frames: int = RESET_FRAMES, confirm_ends: bool = True
    ) -> None:
        if not (0.0 <= threshold <= 1.0):
            raise ValueError(f"threshold must be in [0, 1], got {threshold!r}")
        if reset_frames < 1:
            raise ValueError(f"reset_frames must be >= 1, got {reset_frames!r}")
        self.threshold = float(threshold)
        self.reset_frames = int(reset_frames)
        self._low = 0
        self.confirm_ends = bool(confirm_ends)
        self._confirmed = False  # the current track has shown a finger end

    def decide(
        self,
        tracker: _Resettable,
        depth_mm: NDArray,
        intr: Intrinsics,
        model: HandModel,
        result: TrackResult,
        checked: HandDecision | None = None,
        theirs: Theirs | None = None,
    ) -> HandDecision:
        """The decision of ``result`` (see :func:`check_hand`, ``theirs`` too; ``checked``: its
        check when already made); resets ``tracker`` as the class docstring says."""
        if checked is not None:
            dec = checked
        elif theirs is None:
            dec = check_hand(depth_mm, intr, model, result)
        else:
            dec = check_hand(depth_mm, intr, model, result, theirs)
        if result.pose is None:
            self._low = 0
            self._confirmed = False
            return dec
        ends = math.nan if dec.evidence is None else dec.evidence.ends
        conf = dec.confidence
        if not self.confirm_ends:
            self._confirmed = True
        if not self._confirmed:  # a new track: no finger seen to end counts as none ending
            conf *= _ramp(0.0 if math.isnan(ends) else ends, ENDS_LOW, 1.0)
        sure = conf >= self.threshold
        if sure and not self._confirmed and ends >= ENDS_CONFIRM:  # (NaN: no finger seen)
            self._confirmed = True
        present = sure and self._confirmed
        # (the resets go by the evidence alone: a fist that waits for a finger keeps its track)
        self._low = 0 if dec.confidence >= self.threshold else self._low + 1
        if self._low >= self.reset_frames or dec.confidence < RESET_BELOW:
            tracker.reset()
            self._low = 0
            self._confirmed = False
        return HandDecision(present, conf, dec.fingers * (conf > 0), dec.evidence)

    def forget(self) -> None:
        """Forget the current track (the tracker was reset): the next one is new."""
        self._low = 0
        self._confirmed = False

    def gate(
        self,
        tracker: _Resettable,
        depth_mm: NDArray,
        intrinsics: Intrinsics,
        model: HandModel,
        result: TrackResult,
        withhold: bool = True,
        checked: HandDecision | None = None,
        theirs: Theirs | None = None,
    ) -> TrackResult:
        """``result`` with its :meth:`decide` decision as ``hand``; with ``withhold``, a frame
        that is no hand comes back with status ``NO_HAND`` and no pose (False: the pose is
        kept, for the evidence of the raw track)."""
        dec = self.decide(tracker, depth_mm, intrinsics, model, result, checked, theirs)
        if result.pose is not None and not dec.present and withhold:
            return replace(
                result, status=TrackerStatus.NO_HAND, pose=None, fingertips_mm=None, skeleton_mm=None,
                gaussians_mm=None, gaussian_radii_mm=None, hand=dec,
            )
        return replace(result, hand=dec)
