"""Small array helpers of the objective's terms (exact: the same bits as the plain NumPy calls)."""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

_TWO_PI = 2.0 * np.pi
_UNSET = object()
_INV_SQRT2 = 1.0 / np.sqrt(2.0)
#: ``x.sum(axis)`` without the method's Python layer (it calls exactly this): the objective
#: runs a few dozen NumPy calls on small arrays per evaluation, where that layer counts.
_sum = np.add.reduce
#: A term's deferred gradient: adds its ``dE/dP`` (with sign and weight) into ``g3`` (m, 3).
Backward = Callable[[NDArray[np.float64]], None]


def _accumulate(index: NDArray[np.int64], weights: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """Sum ``weights`` per ``index`` into a float array of length ``size`` (empty-safe)."""
    return np.bincount(index, weights=weights, minlength=size).astype(np.float64, copy=False)


_FLAT_COLS: dict[tuple[int, int], NDArray[np.int64]] = {}


def _flat_cols(m: int, n: int) -> NDArray[np.int64]:
    """Column of every flat index of an (m, n) array, shape (m n,) (cached: divmod is slow)."""
    hit = _FLAT_COLS.get((m, n))
    if hit is None:
        if len(_FLAT_COLS) >= 4:  # n changes from frame to frame: keep only the latest few
            _FLAT_COLS.clear()
        hit = np.empty((m, n), dtype=np.int64)
        hit[:] = np.arange(n)  # (= np.tile(np.arange(n), m), several times cheaper)
        hit = _FLAT_COLS[(m, n)] = hit.reshape(-1)
    return hit


def _as_slice(index: NDArray[np.int64]) -> slice | NDArray[np.int64]:
    """``index`` (k,) as the equivalent slice when its entries are evenly spaced and increasing
    (a slice indexes a view: cheaper than a gather and a scatter), else ``index`` itself."""
    idx = np.asarray(index)
    if idx.ndim != 1 or idx.size < 2 or idx[0] < 0:
        return index
    step = int(idx[1] - idx[0])
    if step <= 0 or not (np.diff(idx) == step).all():
        return index
    return slice(int(idx[0]), int(idx[-1]) + 1, step)



def _per_pose(value: NDArray[np.float64]) -> float | NDArray[np.float64]:
    """A term's value as a float for one pose (a 0-d result), else the (B,) values."""
    return float(value) if value.ndim == 0 else value


def _squares(x: NDArray[np.float64]) -> float | NDArray[np.float64]:
    """Sum of squares of ``x`` (k,) >= 0 as a float, or of each row of ``x`` (B, k) (the same
    bits as the row alone: its own product; the rows of zeros are 0)."""
    if x.ndim == 1:
        return float(x @ x)
    out = np.zeros(x.shape[0])
    for b in np.flatnonzero(np.logical_or.reduce(x > 0.0, axis=1)).tolist():
        out[b] = x[b] @ x[b]
    return out


def _segment_sums(values: NDArray[np.float64], bounds: NDArray[np.int64]) -> NDArray[np.float64]:
    """Sums of ``values[bounds[b]:bounds[b + 1]]`` (B,), each as the sum of that segment
    alone (np.add.reduceat adds in another order: other bits)."""
    out = np.zeros(bounds.size - 1)
    for b in np.flatnonzero(bounds[1:] > bounds[:-1]).tolist():
        out[b] = _sum(values[bounds[b] : bounds[b + 1]])
    return out
