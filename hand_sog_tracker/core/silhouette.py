"""The silhouette term: every part of the hand projects onto the hand's pixels.

Depth overlap (``E_sim``) rewards model Gaussians on data but does not punish Gaussians over
empty background, and the dangling term (``E_dan``) only acts beyond 15 mm from the data.  A
finger lying next to its real finger, over the background (typically after the fingers have
shifted over by one), costs nothing in either.  Whatever the self-occlusion, every point of
the hand projects inside the hand's silhouette, so a model Gaussian whose centre projects
outside it is wrong by the distance to the silhouette.

``E_sil = 1 / m sum_p (max(D(u_p, v_p) - SILHOUETTE_MARGIN_PX, 0) z_p / f / SILHOUETTE_SCALE_MM)^2``

with ``D`` the distance (px) of a pixel to the nearest pixel of the hand's depth (computed on
cells of :data:`SILHOUETTE_CELL_PX` pixels, bilinear between cell centres), ``(u_p, v_p)`` and
``z_p`` a model Gaussian's projected centre and depth (mm), ``f = sqrt(fx fy)``: the squared
distance in mm at the Gaussian's depth, in units of ``SILHOUETTE_SCALE_MM``, averaged over the
``m`` Gaussians.

Units: millimetres, pixels of the processing image.
"""

from __future__ import annotations

import math
from dataclasses import FrozenInstanceError
from typing import Callable, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.depth_sog import Preprocessed, _in_window, hand_window, lattice_anchor
from hand_sog_tracker.core.types import Intrinsics

__all__ = [
    "SILHOUETTE_CELL_PX",
    "SILHOUETTE_MARGIN_PX",
    "SILHOUETTE_SCALE_MM",
    "Silhouette",
    "silhouette",
    "silhouette_term",
    "run_or_defer",
]

# The term is not in the papers: both constants are chosen here.
#: Distances up to this (px) cost nothing: pixel quantisation and a ragged depth edge.
SILHOUETTE_MARGIN_PX: Final[float] = 1.0
#: The term measures distances in units of this (mm).
SILHOUETTE_SCALE_MM: Final[float] = 10.0


class Silhouette:
    """Distance (px) of the hand's surroundings to the hand's pixels, on a grid of cells.

    A read-only value (attributes cannot be set), made from its distance map or from its
    hand cells (:func:`silhouette` gives the cells: the map is made when first asked for).

    Attributes
    ----------
    distance : array, shape (h, w), float32
        Distance (pixels of the processing image) from each cell's centre to the nearest
        cell on the hand; 0 on the hand.  Made on first access when only ``hand`` was given
        (:func:`silhouette_term` asks for it only once a model Gaussian's cell lies off the
        hand: while every Gaussian projects onto the hand the term is 0 and reads only
        ``hand``).
    hand : array, shape (h, w), uint8
        1 on the cells on the hand (distance 0), 0 elsewhere.
    origin : (u0, v0)
        Image pixel at the top-left corner of the first cell.
    intrinsics : Intrinsics
        Of the processing image the distances belong to.
    cell : int
        Cell side (pixels of the processing image): cell ``(i, j)`` covers pixels
        ``v0 + cell i ... v0 + cell (i + 1) - 1`` (rows), likewise for columns; its centre is
        at pixel ``u0 + cell j + (cell - 1) / 2``.
    """

    __slots__ = ("_distance", "_hand", "origin", "intrinsics", "cell")

    def __init__(
        self,
        distance: NDArray[np.float32] | None,
        origin: tuple[int, int],
        intrinsics: Intrinsics,
        cell: int = 1,
        hand: NDArray[np.uint8] | None = None,
    ) -> None:
        if distance is None and hand is None:
            raise ValueError("a Silhouette needs its distance map or its hand cells")
        for name, value in (("_distance", distance), ("_hand", hand), ("origin", origin),
                            ("intrinsics", intrinsics), ("cell", cell)):
            object.__setattr__(self, name, value)

    def __setattr__(self, name: str, value: object) -> None:
        raise FrozenInstanceError(f"cannot assign to field {name!r}")

    def __reduce__(self) -> tuple:
        return (Silhouette, (self._distance, self.origin, self.intrinsics, self.cell, self._hand))

    @property
    def distance(self) -> NDArray[np.float32]:
        """The distance map, shape (h, w), float32, px (see the class docstring; cached)."""
        dist = self._distance
        if dist is None:
            dist = _distance_map(self._hand, self.cell)
            dist.setflags(write=False)
            object.__setattr__(self, "_distance", dist)
        return dist

    @property
    def hand(self) -> NDArray[np.uint8]:
        """The cells on the hand, shape (h, w), uint8, 1 on the hand (see the class docstring)."""
        hand = self._hand
        if hand is None:
            hand = (self._distance == 0).view(np.uint8)
            object.__setattr__(self, "_hand", hand)
        return hand

    def has_distance(self) -> bool:
        """Whether the distance map is made (given, or asked for before)."""
        return self._distance is not None


def _distance_map(hand: NDArray[np.uint8], cell: int) -> NDArray[np.float32]:
    """Distance (px) of every cell's centre to the nearest cell on ``hand`` (nonzero),
    float32, a multiple of ``cell`` times the square root of an integer."""
    background = np.subtract(1, hand, dtype=np.uint8)
    dist = cv2.distanceTransform(background, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # OpenCV's exact transform varies in the last bits from call to call (and between an
    # image and its mirror image); the squared distances between cell centres are integers:
    # rounding them makes the map exact, reproducible and mirror-symmetric.
    np.multiply(dist, dist, out=dist)
    np.rint(dist, out=dist)
    np.sqrt(dist, out=dist)
    if cell > 1:
        dist *= np.float32(cell)
    return dist


#: The distance map covers the box of the hand's pixels in the region of interest plus this
#: margin (px; chosen here: 25-30 mm at the hand's usual depth, no effect on the term inside
#: it; a model Gaussian farther out is clamped to the map's edge, where the dangling term
#: pulls it back).
ROI_MARGIN_PX: Final[int] = 16
#: Cell side (px) of the distance map.  The term only costs where a model Gaussian lies more
#: than :data:`SILHOUETTE_MARGIN_PX` outside the hand, in units of 10 mm (7 px at 400 mm):
#: half resolution changes it by at most ~1 px there and costs a quarter of the full map
#: (0.2 against 0.75 ms at 320 x 240).  A cell is on the hand when any of its pixels is.
SILHOUETTE_CELL_PX: Final[int] = 2


def silhouette(
    pre: Preprocessed,
    window_mm: tuple[float, float],
    roi: tuple[int, int, int, int] | None = None,
    cell: int = SILHOUETTE_CELL_PX,
) -> Silhouette:
    """The silhouette of the depth inside ``window_mm`` (near, far) and its distance map.

    With ``roi`` (u0, v0, u1, v1, end-exclusive) only the box of the hand's pixels inside it
    plus :data:`ROI_MARGIN_PX` is mapped (a model Gaussian projecting beyond it is clamped to
    its edge).  The cells (``cell`` px square) lie on a lattice centred on the image
    (:func:`hand_sog_tracker.core.depth_sog.lattice_anchor`), so that a mirrored image gets
    the mirrored map; cells reaching beyond the image count as background there.
    """
    d = pre.depth_mm
    h, w = d.shape
    near, far = window_mm
    hw = hand_window(pre, roi, window_mm) if roi is not None else None
    if hw is not None and hw.valid_box is not None:
        # The hand's pixels in the ROI and the margin around them (within the ROI's margin).
        u0, v0, u1, v1 = hw.valid_box
    else:
        u0, v0, u1, v1 = (0, 0, w, h) if roi is None else roi
    u0, v0 = max(u0 - ROI_MARGIN_PX, 0), max(v0 - ROI_MARGIN_PX, 0)
    u1, v1 = min(u1 + ROI_MARGIN_PX, w), min(v1 + ROI_MARGIN_PX, h)
    if u1 - u0 < 2 or v1 - v0 < 2:
        u0, v0, u1, v1 = 0, 0, w, h
        hw = None
    if cell > 1:
        au, av = lattice_anchor(w, cell), lattice_anchor(h, cell)
        u0, v0 = au + ((u0 - au) // cell) * cell, av + ((v0 - av) // cell) * cell
        u1, v1 = au - ((au - u1) // cell) * cell, av - ((av - v1) // cell) * cell
    # Hand pixels, 1; a part of the (cell-aligned) box outside the image stays 0.
    hand = np.zeros((v1 - v0, u1 - u0), np.uint8)
    cu0, cv0, cu1, cv1 = max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)
    if hw is not None and hw.contains(cu0, cv0, cu1, cv1):
        part = hw.view(cu0, cv0, cu1, cv1)  # the windowed depth shared with the other stages
    else:
        part = _in_window(d[cv0:cv1, cu0:cu1], near, far, nan_free=True)
    np.greater(part, 0, out=hand[cv0 - v0 : cv1 - v0, cu0 - u0 : cu1 - u0].view(bool))
    if cell == 2:
        # A cell is on the hand when any of its pixels is (maximum over the cell).
        rows = np.maximum(hand[0::2], hand[1::2])
        hand = np.maximum(rows[:, 0::2], rows[:, 1::2])
    elif cell > 2:
        hc, wc = hand.shape[0] // cell, hand.shape[1] // cell
        hand = hand.reshape(hc, cell, wc, cell).max(axis=(1, 3))
    hand.setflags(write=False)
    # (The distance map is computed when first asked for: the term reads a few cells.)
    return Silhouette(None, (u0, v0), pre.intrinsics, cell, hand=hand)


#: ``[(sil, constants)]`` of the last map (one tuple: replaced atomically).
_TERM_CACHE: list = [(None, None)]


def _term_constants(sil: Silhouette) -> tuple:
    """Constants of :func:`silhouette_term` for one map (cached for the last map: a frame's
    objective evaluates the same map many times): ``(fx, fy)``, the offsets of ``(u, v)``,
    the clamp limits, the flat offsets of a cell's four corners, the row length ``w`` (a
    cell's flat index is its column plus ``w`` times its row) and the map as float64, flat:
    until a cell off the hand is
    read, 0 on the hand and -1 off it (:func:`silhouette_term` then fills in the distance
    map; at once when no cell is on the hand), and ``[filled]``: whether it holds the distances."""
    hit = _TERM_CACHE[0]
    if hit[0] is sil:
        return hit[1]
    intr = sil.intrinsics
    h, w = sil.hand.shape
    if not sil.has_distance() and sil.hand.any():
        flat_map = sil.hand.reshape(-1).astype(np.float64)
        flat_map -= 1.0  # (hand: 1 - 1 = 0; off the hand -1, not computed)
        filled = [False]
    else:
        flat_map = sil.distance.astype(np.float64).reshape(-1)
        filled = [True]
    half = 0.5 * (sil.cell - 1)
    const = (
        np.array((intr.fx, intr.fy)),
        np.array((intr.cx - sil.origin[0] - half, intr.cy - sil.origin[1] - half)),
        np.array((w - 1.000001, h - 1.000001)),
        np.array((0, 1, w, w + 1)),
        float(w),
        flat_map,
        filled,
    )
    _TERM_CACHE[0] = (sil, const)
    return const


def run_or_defer(
    backward: Callable[[NDArray[np.float64]], None],
    g3: NDArray[np.float64] | None,
    later: list[Callable[[NDArray[np.float64]], None]] | None,
) -> None:
    """Add a term's gradient into ``g3`` now, or, with ``later``, append the function that does
    (a deferred gradient, see :meth:`hand_sog_tracker.core.objective.Objective.value_then_gradient`)."""
    if later is None:
        assert g3 is not None
        backward(g3)
    else:
        later.append(backward)


def silhouette_term(
    sil: Silhouette,
    P: NDArray[np.float64],
    g3: NDArray[np.float64] | None,
    weight: float,
    projected: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    later: list[Callable[[NDArray[np.float64]], None]] | None = None,
) -> float | NDArray[np.float64]:
    """``E_sil`` at the model Gaussian centres ``P`` (m, 3) mm; adds ``-weight dE/dP`` into ``g3``.

    For a batch of poses, ``P`` and ``g3`` are (B, m, 3) and ``E_sil`` is (B,) (0.0 where it
    is 0 at every pose): the B m Gaussians go through every step as the m of one pose.
    ``projected``: ``(z, q)`` when already computed with the silhouette's intrinsics, ``z =
    max(P_z, 1)`` (B m,) mm and ``q = (fx x / z, fy y / z)`` (2, B m) px (the same operations
    as here: the same bits).  ``later``: instead of adding into ``g3`` now, append the function
    that does (a deferred gradient, :meth:`hand_sog_tracker.core.objective.Objective.value_then_gradient`).
    """
    poses = P.shape[0] if P.ndim == 3 else 0
    m = P.shape[-2]  # (per pose)
    if poses:
        P = P.reshape(-1, 3)
    intr = sil.intrinsics
    k_fxy, k_off, top, corners, row_len, flat_map, filled = _term_constants(sil)
    # Map coordinates (cells, from the first cell's centre), u and v as the columns of one
    # (m, 2) array: every step below does both at once (the per-call cost of NumPy dominates).
    cell = sil.cell
    if projected is None:
        z = np.maximum(P[:, 2], 1.0)
        uv = k_fxy * P[:, :2]
        uv /= z[:, None]
        uv += k_off
    else:
        z, q = projected
        uv = q.T + k_off
    zc = z[:, None]
    if cell != 1:  # (a division by 1 changes no bit)
        uv /= cell  # (fx x / z + offset) / cell
    # Bilinear interpolation between cell centres (clamped to the map).
    uvc = np.minimum(np.maximum(uv, 0.0), top)  # = np.clip, several times cheaper
    ab, uv0 = np.modf(uvc)  # (m, 2): a, b and the cell (uvc >= 0: = uvc - floor, floor)
    one_ab = 1 - ab  # (m, 2): 1 - a, 1 - b
    # The four corners of every cell square in one gather: d[:, i, j] = d_ij (row i, column j).
    flat = uv0[:, 1] * row_len
    flat += uv0[:, 0]  # (integers: exact; cheaper than a matrix product at this size)
    corner = flat.astype(np.int64)[:, None] + corners
    d = flat_map.take(corner)
    if not np.count_nonzero(d):
        # Every corner on the hand (distance 0; typical while tracking): D = 0 at every
        # Gaussian, nothing beyond the margin, E_sil = 0 exactly and no gradient.
        return 0.0
    if not filled[0] and np.minimum.reduce(d, axis=None) < 0.0:  # a cell off the hand: the distances needed
        np.copyto(flat_map, sil.distance.reshape(-1), casting="safe")
        filled[0] = True
        d = flat_map.take(corner)
    d = d.reshape(-1, 2, 2)
    # Both rows interpolated along u, then along v.
    along_u = one_ab[:, :1] * d[:, :, 0] + ab[:, :1] * d[:, :, 1]  # (m, 2)
    D = one_ab[:, 1] * along_u[:, 0] + ab[:, 1] * along_u[:, 1]
    if not poses and np.maximum.reduce(D) <= SILHOUETTE_MARGIN_PX:
        return 0.0  # (nothing beyond the margin: E_sil = 0 exactly, no gradient, as below)
    over = np.maximum(D - SILHOUETTE_MARGIN_PX, 0.0)
    f = math.sqrt(intr.fx * intr.fy)
    k = 1.0 / (f * SILHOUETTE_SCALE_MM)
    s = over * z * k  # (m,)
    if poses:
        val: float | NDArray[np.float64] = np.add.reduce((s * s).reshape(poses, m), axis=1) / m
        positive = bool(np.logical_or.reduce(val > 0))
    else:
        val = float(np.add.reduce(s * s) / m)  # (= (s * s).sum(), without the method's Python layer)
        positive = val > 0
    if (g3 is None and later is None) or weight <= 0 or not positive:
        return val

    def backward(g3: NDArray[np.float64]) -> None:
        g3 = g3.reshape(-1, 3)  # (a view: a batch's (B, m, 3) as its rows)
        # dD/du = (1 - b)(d01 - d00) + b (d11 - d10), dD/dv = (1 - a)(d10 - d00) + a (d11 - d01),
        # zero where the coordinate is clamped.  With steps[:, 0] = (d01 - d00, d11 - d10)
        # and steps[:, 1] = (d10 - d00, d11 - d01): dD = (1 - (b, a)) steps[.., 0] + (b, a) steps[.., 1].
        steps = np.empty((P.shape[0], 2, 2))
        np.subtract(d[:, :, 1], d[:, :, 0], out=steps[:, 0])
        np.subtract(d[:, 1, :], d[:, 0, :], out=steps[:, 1])
        dD = one_ab[:, ::-1] * steps[:, :, 0]
        dD += ab[:, ::-1] * steps[:, :, 1]
        dD *= (uv > 0.0) & (uv < top)
        # dE/dD is 2 / m s z k (zero off the margin, where s = 0); per mm of P through (u, v):
        c = (2.0 / m * k) * s  # (m,)
        cz = c * z
        if cell != 1:  # (a division by 1 changes no bit)
            cz /= cell
        g_uv = cz[:, None] * dD * k_fxy / zc  # d E / d(x, y) at fixed z, (m, 2): c z / cell ...
        # z: through u = fx x / z + .. (-u' x / z) and the explicit z of the mm conversion.
        g_z = c * over - (g_uv[:, 0] * P[:, 0] + g_uv[:, 1] * P[:, 1]) / z
        g3[:, :2] -= weight * g_uv
        g3[:, 2] -= weight * g_z

    run_or_defer(backward, g3, later)
    return val
