"""One BLAS thread for the node's tracking (issue 50: no frame far over its budget).

The tracker is one thread of small array operations; its one large BLAS call per objective
evaluation is the data terms' candidate test, a product of the B m model Gaussians' six values
with the data's (B m x 6 by 6 x n, :mod:`hand_sog_tracker.core.objective.data`).  OpenBLAS
splits a product of that size over its threads (all cores by default), and each split waits for
the slowest thread: on a machine whose other core is busy (the node's own DDS threads, a
camera driver, other processes) the product took 20-40x as long as on one thread (at 570 data
Gaussians and 4 candidates, 29 ms against 0.8 ms on one thread, load 10-14 on 2 cores), and so
the frames of dear inputs (``min_quad_px`` 2 at 640x480, a plausible but wrong K) took 3-4x the
CPU time of one thread.  With one thread every product is what its arithmetic costs, whatever
the load.  The results are the same up to rounding (a split may change the kernel and the order
of a sum: the last bit of a few elements).

:func:`limit_blas_threads` sets the thread count of every OpenBLAS the process has loaded
(NumPy's wheel, ``scipy_openblas``, or the system's ``libopenblas``), at run time: NumPy is
imported long before the node starts.  An explicit ``OPENBLAS_NUM_THREADS`` or
``OMP_NUM_THREADS`` in the environment is left alone (the user chose).  Another BLAS (a
reference BLAS is single-threaded) or no ``/proc`` leaves it as it is.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["THREADS_ENV", "blas_threads", "limit_blas_threads"]

#: Environment variables that choose the BLAS thread count explicitly (then left alone).
THREADS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")
_MAPS = "/proc/self/maps"
#: (set, get) symbol names of OpenBLAS builds: the system's, and the ``scipy_openblas`` of
#: NumPy's wheels (64-bit integers, suffixed, or not).
_SYMBOLS = (
    ("openblas_set_num_threads", "openblas_get_num_threads"),
    ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
)


def _openblas() -> list[tuple[str, ctypes.CDLL, str, str]]:
    """The OpenBLAS libraries loaded in this process: (path, library, set, get symbol)."""
    try:
        with open(_MAPS) as f:
            paths = sorted({line.split()[-1] for line in f if "blas" in line.lower() and "/" in line})
    except OSError:
        return []
    found = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)  # (already loaded: the same handle)
        except OSError:
            continue
        for set_name, get_name in _SYMBOLS:
            if hasattr(lib, set_name) and hasattr(lib, get_name):
                found.append((path, lib, set_name, get_name))
                break
    return found


def blas_threads() -> dict[str, int]:
    """The thread count of every OpenBLAS loaded in this process, by library path."""
    return {path: int(getattr(lib, get)()) for path, lib, _, get in _openblas()}


def limit_blas_threads(threads: int = 1) -> dict[str, int]:
    """Set every loaded OpenBLAS to ``threads`` threads unless the environment chooses the
    count (:data:`THREADS_ENV`); returns the libraries' counts afterwards (path -> threads,
    empty without OpenBLAS)."""
    if not any(os.environ.get(var) for var in THREADS_ENV):
        for _, lib, set_name, _ in _openblas():
            setter = getattr(lib, set_name)
            setter.argtypes = [ctypes.c_int]
            setter.restype = None
            setter(int(threads))
    return blas_threads()
