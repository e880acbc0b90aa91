"""Depth-sensor models applied to a clean rendered depth image (used by the mesh-hand renderer).

Sensor models (:data:`SENSORS`): ``clean``; ``tof``
(Gaussian depth noise growing with depth, flying pixels interpolated between
foreground and background at depth edges, dropout at grazing angles from the
true surface normal, sparse random dropout, whole millimetres like the uint16
output of ToF cameras); ``structured`` (a projector
50 mm to the right of the camera: shadow holes left of depth edges, holes
at grazing angles and on the left border of the silhouette, sub-pixel
disparity noise, a 3x3 median over the disparity, and disparity quantised in
1/8 px, so the depth step grows with ``z**2``).
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.errors import InputError

__all__ = ["SENSORS", "apply_sensor"]

#: Sensor models of :func:`apply_sensor`.
SENSORS: Final[tuple[str, ...]] = ("clean", "tof", "structured")

_EDGE_JUMP_MM = 20.0
_TOF_NOISE_MM = 1.2  #: ToF noise sigma at 400 mm, grows with (z / 400)^2
_TOF_FLYING_SHARE = 0.4
_TOF_GRAZING_COS = 0.3
_TOF_RANDOM_DROPOUT = 0.002
_SL_BASELINE_MM = 50.0
_SL_SUBPIXEL = 8.0  #: disparity steps per pixel
_SL_DISP_NOISE_PX = 0.06
_SL_GRAZING_COS = (0.2, 0.4)  #: holes certain below the first, none above the second


def _neighbours(z: NDArray[np.float32], fill: float) -> NDArray[np.float32]:
    p = np.pad(z, 1, mode="constant", constant_values=fill)
    return np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])


def _roi(mask: NDArray[np.bool_], pad: int) -> tuple[slice, slice] | None:
    rows = np.nonzero(mask.any(axis=1))[0]
    cols = np.nonzero(mask.any(axis=0))[0]
    if rows.size == 0:
        return None
    H, W = mask.shape
    return (
        slice(max(rows[0] - pad, 0), min(rows[-1] + pad + 1, H)),
        slice(max(cols[0] - pad, 0), min(cols[-1] + pad + 1, W)),
    )


def _tof(depth: NDArray[np.float32], cos: NDArray[np.float32], rng: np.random.Generator) -> None:
    roi = _roi(depth > 0, 2)
    if roi is None:
        return
    d = depth[roi]
    c = cos[roi]
    clean = d.copy()
    ok = clean > 0
    # Dropout at grazing angles (weak return).
    p_drop = 0.75 * np.clip((_TOF_GRAZING_COS - c) / _TOF_GRAZING_COS, 0.0, 1.0)
    cand = np.nonzero(ok & (p_drop > 0))
    drop = rng.random(cand[0].size) < p_drop[cand]
    d[cand[0][drop], cand[1][drop]] = 0.0
    # Flying pixels: mixed returns between foreground and background at depth edges.
    nb = _neighbours(clean, -1.0)
    valid_nb = nb > 0
    lo = np.minimum(np.where(valid_nb, nb, np.inf).min(axis=0), clean)
    hi = np.maximum(np.where(valid_nb, nb, -np.inf).max(axis=0), clean)
    jump = ok & (hi - lo > _EDGE_JUMP_MM)
    cand = np.nonzero(jump)
    pick = rng.random(cand[0].size) < _TOF_FLYING_SHARE
    iy, ix = cand[0][pick], cand[1][pick]
    frac = rng.uniform(0.1, 0.9, iy.size)
    d[iy, ix] = (lo[iy, ix] + frac * (hi[iy, ix] - lo[iy, ix])).astype(np.float32)
    cand = np.nonzero(ok & ~jump & np.any(nb == 0, axis=0))  # next to no return: weak, often lost
    drop = rng.random(cand[0].size) < 0.3
    d[cand[0][drop], cand[1][drop]] = 0.0
    # Depth noise and sparse dropout.
    sigma = np.float32(_TOF_NOISE_MM / 400.0**2) * d * d
    d += sigma * rng.standard_normal(d.shape, dtype=np.float32)
    np.maximum(d, 0.0, out=d)
    n_drop = rng.binomial(d.size, _TOF_RANDOM_DROPOUT)
    # (``flat``: ``d`` is a view of the depth image; reshaping a view that is not contiguous
    # copies it, and the dropout was lost on every image whose valid depth did not span its width.)
    d.flat[rng.integers(0, d.size, n_drop)] = 0.0
    np.round(d, out=d)  # ToF cameras report whole millimetres


def _structured(
    depth: NDArray[np.float32], cos: NDArray[np.float32], rng: np.random.Generator, intr: Intrinsics
) -> None:
    roi = _roi(depth > 0, 2)
    if roi is None:
        return
    d = depth[roi]
    c = cos[roi]
    ok = d > 0
    fb = intr.fx * _SL_BASELINE_MM
    disp = np.where(ok, fb / np.maximum(d, 1e-3), 0.0).astype(np.float64)  # px, 0 = none
    # Projector shadow: the projector sits to the right (+x); a pixel is hidden
    # from it if something to its right has a disparity larger by the pixel distance.
    Hh, Ww = disp.shape
    span = int(np.ceil(disp[ok].max() - disp[ok].min())) if ok.any() else 0
    shadow = np.zeros_like(ok)
    for k in range(1, min(span, Ww - 1) + 1):
        occl = np.zeros_like(disp)
        occl[:, :-k] = disp[:, k:] - k
        shadow |= occl > disp + 0.5
    # Left border of the silhouette: the matching window straddles the edge.
    left = np.zeros_like(ok)
    left[:, 1:] = ok[:, 1:] & (~ok[:, :-1] | (disp[:, :-1] < disp[:, 1:] - fb / 400.0**2 * _EDGE_JUMP_MM))
    left &= rng.random(left.shape) < 0.5
    # Grazing angles.
    p_hole = np.clip((_SL_GRAZING_COS[1] - c) / (_SL_GRAZING_COS[1] - _SL_GRAZING_COS[0]), 0.0, 1.0)
    graze = ok & (rng.random(ok.shape) < p_hole)
    # Disparity noise, 3x3 median over valid neighbours of similar disparity, quantisation.
    noisy = disp + _SL_DISP_NOISE_PX * rng.standard_normal(disp.shape)
    pad = np.pad(noisy, 1, mode="edge")
    padok = np.pad(ok, 1, mode="constant", constant_values=False)
    stack = np.stack([pad[i : i + Hh, j : j + Ww] for i in range(3) for j in range(3)])
    sok = np.stack([padok[i : i + Hh, j : j + Ww] for i in range(3) for j in range(3)])
    sok &= np.abs(stack - noisy[None]) < 1.0
    srt = np.sort(np.where(sok, stack, np.inf), axis=0)  # valid values first
    cnt = np.maximum(sok.sum(axis=0), 1)
    lo_i = ((cnt - 1) // 2)[None]
    hi_i = (cnt // 2)[None]
    med = 0.5 * (np.take_along_axis(srt, lo_i, axis=0)[0] + np.take_along_axis(srt, hi_i, axis=0)[0])
    med = np.where(ok & np.isfinite(med), med, 0.0)
    q = np.round(med * _SL_SUBPIXEL) / _SL_SUBPIXEL
    out = np.where(ok & (q > 0), fb / np.maximum(q, 1e-6), 0.0)
    out[shadow | left | graze] = 0.0
    n_drop = rng.binomial(out.size, 0.001)
    out.reshape(-1)[rng.integers(0, out.size, n_drop)] = 0.0
    d[...] = out.astype(np.float32)


def apply_sensor(
    depth: NDArray[np.float32],
    cos: NDArray[np.float32],
    sensor: str,
    intrinsics: Intrinsics,
    rng: np.random.Generator,
) -> None:
    """Apply a sensor model (:data:`SENSORS`) in place to a clean depth image (H, W) mm (0 = none).

    ``cos`` (H, W) is |cos| of the angle between the viewing ray and the surface normal.
    """
    if sensor == "clean":
        return
    if sensor == "tof":
        _tof(depth, cos, rng)
    elif sensor == "structured":
        _structured(depth, cos, rng, intrinsics)
    else:
        raise InputError(f"unknown sensor {sensor!r}; choose one of {', '.join(SENSORS)}")
