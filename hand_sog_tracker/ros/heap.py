"""Free heap given back to the system after a frame that grew the process (issue 50).

glibc keeps freed memory in its heap: after one frame far dearer than usual (plausible but
wrong intrinsics, a resolution change, a new track on much data) the process stays 25-35 MB
above steady tracking although the tracker holds none of it (the chunks are free but
fragmented, so the top of the heap cannot be trimmed).  ``malloc_trim(0)`` gives the free
pages back.  Trimming after every frame would page-fault the per-frame working set back in
every frame (what ``depth_sog``'s raised malloc thresholds avoid, issue 14), so
:class:`HeapTrim` trims only after a frame that left the resident set ``TRIM_GROWTH_MB`` above
its level (right after the last trim, or its lowest since), at most once per
``TRIM_INTERVAL_S``.  A frame's working set (the free heap between two frames of steady
tracking, 9-10 MB) lies just over the growth, so steady tracking trims about once per interval
too, and each such trim costs the page faults of one working set (about 2 000, a millisecond).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import time
from typing import Callable

__all__ = ["HeapTrim", "TRIM_GROWTH_MB", "TRIM_INTERVAL_S"]

#: Growth of the resident set (MB) over its level that triggers a trim (what may stay over steady
#: tracking: issue 50 allows 10 MB; chosen here).
TRIM_GROWTH_MB = 8.0
#: Least time between two trims (s): bounds their cost (about 1 ms per 10 MB given back, and
#: the page faults of the working set after it) when the working set exceeds the growth.
TRIM_INTERVAL_S = 1.0
_STATM = "/proc/self/statm"


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, or None (another C library, or no C library found)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def resident_mb() -> float | None:
    """The process's resident set (MB, from ``/proc/self/statm``), or None where there is none."""
    try:
        with open(_STATM, "rb") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


class HeapTrim:
    """Calls ``malloc_trim(0)`` after a frame that grew the resident set by ``growth_mb`` (at
    most once per ``interval_s``).

    :meth:`after_frame` costs one read of ``/proc/self/statm`` (about 10 us) per frame; a trim
    costs about 1 ms per 10 MB it gives back.  Without glibc or ``/proc`` (:attr:`enabled`
    False) it does nothing.
    """

    def __init__(self, growth_mb: float = TRIM_GROWTH_MB, interval_s: float = TRIM_INTERVAL_S) -> None:
        self._trim = _malloc_trim()
        self._growth = float(growth_mb)
        self._interval = float(interval_s)
        self._level = resident_mb() if self._trim is not None else None
        self._last = -float("inf")  # time.monotonic() of the last trim
        #: Trims done so far.
        self.trims = 0

    @property
    def enabled(self) -> bool:
        """Whether trimming works here (glibc and ``/proc/self/statm``)."""
        return self._level is not None

    def trim(self) -> bool:
        """Trim now (after memory was freed outside a frame); whether it could."""
        if self._level is None or self._trim is None:
            return False
        self._trim(0)
        self.trims += 1
        self._last = time.monotonic()
        after = resident_mb()
        if after is not None:
            self._level = after
        return True

    def after_frame(self) -> bool:
        """Trim when the resident set grew ``growth_mb`` over its level; whether it trimmed."""
        if self._level is None or self._trim is None:
            return False
        rss = resident_mb()
        if rss is None:
            return False
        if rss < self._level:
            self._level = rss
            return False
        now = time.monotonic()
        if rss <= self._level + self._growth or now - self._last < self._interval:
            return False
        self._trim(0)
        self.trims += 1
        self._last = now
        after = resident_mb()
        self._level = rss if after is None else after
        return True
