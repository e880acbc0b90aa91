"""The hand model's skin drawn as depth capsules, and the depth-aware silhouette overlap score.

Used by :mod:`hand_sog_tracker.core.calibration` to score candidate hand shapes
(:func:`shape_score`): the tracking objective's similarity term is normalised by
the data alone, so it cannot compare model sizes; this overlap can.  The skin is
drawn with OpenCV (about 1 ms a candidate and frame at 320 x 240).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import Preprocessed
from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.kinematics import chain_bases, global_rotation, posed_centres
from hand_sog_tracker.core.types import Intrinsics

__all__ = ["SCORE_TOLERANCE_MM", "ScoreData", "draw_skin", "overlap_score", "score_data", "shape_score"]

#: Model and data depths within this (mm) count as the same surface in :func:`shape_score`.
SCORE_TOLERANCE_MM = 12.0


def _skin(model: HandModel, theta: NDArray[np.float64]):
    """Capsules of the model's skin: centres (k, 3) mm, radii (k,) mm, index pairs (a, b).

    Consecutive Gaussians along each chain are joined, starting at the chain's
    first joint (spheres alone leave gaps along a finger); neighbouring palm
    Gaussians are joined too, so the palm is a filled plate.
    """
    ia, ib, extra_radius_of = _skin_topology(model)[:3]
    radii = np.concatenate([model.g_sigmas, model.g_sigmas[extra_radius_of]])
    return np.concatenate([posed_centres(model, theta), chain_bases(model, theta)]), radii, ia, ib


#: What :func:`_skin_topology` returns: the capsules' index pairs ``ia``, ``ib`` (k,), per chain
#: base the Gaussian whose radius it takes (5,), the draw lists of :func:`draw_skin`: per
#: capsule whether its quad is drawn (two different ends) and the points whose discs it draws
#: (none for a palm quad: the palm's own discs are drawn by its one-Gaussian capsules), and per
#: capsule its chain (k,; -1: the palm).
_Topology = tuple[
    NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], list[bool], list[tuple[int, ...]], NDArray[np.int64]
]
_TOPOLOGY_CACHE: dict[tuple[int, bool], _Topology] = {}


def _skin_topology(model: HandModel) -> _Topology:
    """Index pairs of the skin capsules, per chain base the Gaussian whose radius it takes, and
    the draw lists (see :data:`_Topology`).

    Depends only on the default layout (scaling keeps the order along each chain
    and the palm grid's neighbourhoods), so it is cached per Gaussian count.
    """
    key = (model.n_gaussians, bool(model.right))
    if key in _TOPOLOGY_CACHE:
        return _TOPOLOGY_CACHE[key]
    m = model.n_gaussians
    a_idx, b_idx, chain_of = [], [], []
    palm = np.flatnonzero(model.g_chain < 0)
    off = model.g_offsets[palm] / np.array([model.shape.width, model.shape.length, 1.0])
    near = np.linalg.norm(off[:, None, :] - off[None, :, :], axis=-1)
    spacing = np.sort(near + np.eye(palm.size) * 1e9, axis=1)[:, 0].max() * 1.5
    for i in range(palm.size):
        for j in range(i, palm.size):
            if near[i, j] <= spacing:
                a_idx.append(palm[i]), b_idx.append(palm[j]), chain_of.append(-1)
    first = np.zeros(5, np.int64)
    for c in range(5):
        ks = np.flatnonzero(model.g_chain == c)
        order = ks[np.lexsort((model.g_offsets[ks, 1], model.g_segment[ks]))]
        first[c] = order[0]
        chain = [m + c, *order]
        for k0, k1 in zip(chain[:-1], chain[1:]):
            a_idx.append(k0), b_idx.append(k1), chain_of.append(c)
    ia, ib = np.array(a_idx), np.array(b_idx)
    quad_only = _palm_pairs(model, ia, ib)
    ia_l, ib_l = ia.tolist(), ib.tolist()
    has_quad = [a != b for a, b in zip(ia_l, ib_l)]
    discs = [() if q else ((a,) if a == b else (a, b)) for a, b, q in zip(ia_l, ib_l, quad_only)]
    out = (ia, ib, first, has_quad, discs, np.array(chain_of))
    _TOPOLOGY_CACHE[key] = out
    return out


def _palm_pairs(model: HandModel, ia: NDArray[np.int64], ib: NDArray[np.int64]) -> list[bool]:
    """Per capsule: joins two different palm Gaussians (drawn as a quad without end discs)."""
    m = model.n_gaussians
    pa = (ia < m) & (model.g_chain[np.minimum(ia, m - 1)] < 0)
    pb = (ib < m) & (model.g_chain[np.minimum(ib, m - 1)] < 0)
    return (pa & pb & (ia != ib)).tolist()


#: :func:`_drawn` by (Gaussian count, side, chains).
_DRAWN_CACHE: dict[tuple[int, bool, tuple[int, ...] | None], list[int]] = {}


def _drawn(model: HandModel, chains: tuple[int, ...] | None) -> list[int]:
    """The capsules of :func:`_skin` in ``chains`` (all: None), cached (a fit draws one chain
    of a hundred candidates: the lookup costs less than ``np.isin``)."""
    key = (model.n_gaussians, bool(model.right), None if chains is None else tuple(chains))
    hit = _DRAWN_CACHE.get(key)
    if hit is None:
        chain_of = _skin_topology(model)[5]
        hit = list(range(len(chain_of))) if chains is None else np.flatnonzero(np.isin(chain_of, chains)).tolist()
        _DRAWN_CACHE[key] = hit
    return hit


_SUBPIXEL_BITS = 3
_SUB = float(1 << _SUBPIXEL_BITS)


def draw_skin(
    model: HandModel,
    theta: NDArray[np.float64],
    intr: Intrinsics,
    roi: tuple[int, int, int, int],
    chains: tuple[int, ...] | None = None,
) -> NDArray[np.float32]:
    """Front depth (mm) of the model's skin over ``roi``; ``inf`` where the skin is absent.

    Each capsule of :func:`_skin` is drawn with OpenCV (the quad between its end discs, and
    each end disc once at the nearest depth of the capsules it ends, subpixel precision) at one
    depth, its front surface at its middle, far shapes first so that near ones cover them: each
    pixel gets the smallest depth of the capsules covering it.  With ``chains`` (chain numbers,
    -1: the palm) only those chains' capsules are drawn; since each pixel keeps the smallest
    depth, ``np.minimum`` of the drawings of two sets of chains is the drawing of both.
    """
    u0, v0, u1, v1 = roi
    out = np.full((v1 - v0, u1 - u0), np.inf, dtype=np.float32)
    P, radii, ia, ib = _skin(model, theta)
    has_quad, discs = _skin_topology(model)[3:5]
    drawn = _drawn(model, chains)
    if chains is not None:
        ia, ib = ia[drawn], ib[drawn]
    z = np.maximum(P[:, 2], 1.0)
    uv = intr.project(P) - np.array([u0, v0])
    # OpenCV fills every pixel a shape's outline touches: half a pixel wider all round.
    r_px = np.maximum(radii * intr.fx / z - 0.5, 0.0)
    front = 0.5 * (z[ia] + z[ib]) - 0.5 * (radii[ia] + radii[ib])
    ab = uv[ib] - uv[ia]
    normal = np.stack([-ab[:, 1], ab[:, 0]], 1) / np.maximum(np.linalg.norm(ab, axis=1), 1e-9)[:, None]
    ra, rb = r_px[ia][:, None], r_px[ib][:, None]
    quads = np.stack(
        [uv[ia] + ra * normal, uv[ib] + rb * normal, uv[ib] - rb * normal, uv[ia] - ra * normal], 1
    )
    quads_i = list(np.round(quads * _SUB).astype(np.int32))
    centres_i = np.round(uv * _SUB).astype(np.int64).tolist()
    radii_i = np.round(r_px * _SUB).astype(np.int64).tolist()
    has_disc = (radii > 0).tolist()
    front_l = front.tolist()
    # (depth, point, capsule): a quad (point -1) per capsule, a disc (capsule -1) per point at
    # the nearest depth of the capsules ending there (drawing it once per capsule, far first,
    # leaves the same pixels).
    disc_depth: dict[int, float] = {}
    shapes = []
    for j, k in enumerate(drawn):
        value = front_l[j]
        if has_quad[k]:
            shapes.append((value, -1, j))
        for e in discs[k]:
            if has_disc[e] and value < disc_depth.get(e, np.inf):
                disc_depth[e] = value
    shapes.extend((value, e, -1) for e, value in disc_depth.items())
    shapes.sort(key=lambda t: -t[0])
    fill, circle, line8 = cv2.fillConvexPoly, cv2.circle, cv2.LINE_8
    for value, e, k in shapes:
        if e < 0:
            fill(out, quads_i[k], value, line8, _SUBPIXEL_BITS)
        else:
            circle(out, centres_i[e], radii_i[e], value, -1, line8, _SUBPIXEL_BITS)
    return out


@dataclass(frozen=True, eq=False)
class ScoreData:
    """One frame's data inside the scoring box (see :func:`shape_score`)."""

    roi: tuple[int, int, int, int]
    depth: NDArray[np.float32]  # (h, w) mm, 0 = none
    points: NDArray[np.float64]  # (h, w, 3) back-projected pixels, mm
    cache: dict = field(default_factory=dict)  # points projected on the last hand axis


def score_data(
    pre: Preprocessed, roi: tuple[int, int, int, int], window_mm: tuple[float, float] | None = None
) -> ScoreData:
    """The depth inside ``roi`` (u0, v0, u1, v1, px, end-exclusive) that :func:`overlap_score`
    compares the model with; with ``window_mm`` (near, far) only the depth strictly inside it
    (the hand's depth window: a wall or body behind the hand is not hand)."""
    intr = pre.intrinsics
    u0, v0, u1, v1 = (max(0, roi[0]), max(0, roi[1]), min(intr.width, roi[2]), min(intr.height, roi[3]))
    u1, v1 = max(u1, u0), max(v1, v0)
    depth = pre.depth_mm[v0:v1, u0:u1].astype(np.float32)
    if window_mm is not None:
        depth[(depth <= window_mm[0]) | (depth >= window_mm[1])] = 0.0
    vv, uu = np.mgrid[v0:v1, u0:u1]
    pts = intr.backproject(np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64), depth.ravel().astype(np.float64))
    return ScoreData((u0, v0, u1, v1), depth, pts.reshape(depth.shape + (3,)))


def overlap_score(
    model: HandModel,
    theta: NDArray[np.float64],
    data: ScoreData,
    intr: Intrinsics,
    tolerance_mm: float,
    skin: NDArray[np.float32] | None = None,
) -> float:
    """:func:`shape_score` on prepared data (:func:`score_data`); ``skin``: the model's
    :func:`draw_skin` over ``data.roi`` when already drawn (mm, shape of ``data.depth``)."""
    if data.depth.size == 0:
        return 0.0
    model_depth = draw_skin(model, theta, intr, data.roi) if skin is None else skin
    covered = np.isfinite(model_depth)
    axis = global_rotation(theta)[:, 1]
    key = axis.tobytes()
    cache = data.cache
    if cache.get("axis") != key:  # the rotation rarely changes between candidates
        cache["axis"], cache["along"] = key, data.points @ axis
    if "valid" not in cache:
        cache["valid"] = data.depth > 0
    hand = cache["along"] > float(theta[:3] @ axis)
    hand &= cache["valid"]
    both = np.abs(model_depth - data.depth) < tolerance_mm
    both &= covered
    both &= hand
    covered |= hand
    return float(np.count_nonzero(both) / max(np.count_nonzero(covered), 1))


def shape_score(
    model: HandModel,
    theta: NDArray[np.float64],
    pre: Preprocessed,
    roi: tuple[int, int, int, int],
    tolerance_mm: float = SCORE_TOLERANCE_MM,
    window_mm: tuple[float, float] | None = None,
) -> float:
    """Depth-aware overlap of the model's silhouette with the hand's, in [0, 1].

    The model's skin is drawn as capsules joining consecutive Gaussians of each
    chain and neighbouring palm Gaussians (radii = their sigmas, mm), projected
    into the image at the resolution of ``pre``.  Data pixels count if they lie
    inside ``roi`` (u0, v0, u1, v1, px, end-exclusive), inside ``window_mm`` (near, far; the
    hand's depth window, e.g. from :func:`~hand_sog_tracker.core.tracker.hand_roi`) when
    given, and on the finger side of the wrist (the forearm is not part of the model).  Score = pixels
    covered by both with depths within ``tolerance_mm`` (mm), divided by pixels
    covered by either.
    """
    return overlap_score(model, theta, score_data(pre, roi, window_mm), pre.intrinsics, tolerance_mm)
