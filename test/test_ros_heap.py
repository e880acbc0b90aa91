"""HeapTrim: free heap given back after a frame that grew the process, never in steady state."""

from __future__ import annotations

import ctypes.util

import numpy as np
import pytest

from hand_sog_tracker.ros import heap
from hand_sog_tracker.ros.heap import HeapTrim, resident_mb


def test_it_trims_after_growth_and_not_in_steady_state() -> None:
    trim = HeapTrim(growth_mb=16.0, interval_s=0.0)
    if not trim.enabled:
        pytest.skip("no glibc malloc_trim or /proc here")
    work = [np.ones(20_000) for _ in range(50)]  # a steady working set, allocated and freed
    del work
    trim.after_frame()
    assert not any(trim.after_frame() for _ in range(5))
    # A dear frame: 80 MB in 160 kB blocks (kept in the heap, under depth_sog's raised mmap
    # threshold), every second one still held, so that the heap's top cannot shrink by itself.
    import hand_sog_tracker.core.depth_sog  # noqa: F401 - raises the thresholds, as in the node

    blocks = [np.ones(20_000) for _ in range(500)]
    held = blocks[1::2]
    del blocks
    before = resident_mb()
    assert trim.after_frame() and trim.trims == 1
    assert resident_mb() < before - 25.0
    # The next frames fault their working set back in: no trim for that (nor within the interval).
    for _ in range(5):
        work = [np.ones(20_000) for _ in range(50)]
        del work
        assert not trim.after_frame()
    del held
    slow = HeapTrim(growth_mb=0.0, interval_s=3600.0)
    blocks = [np.ones(20_000) for _ in range(100)]
    assert slow.after_frame() and not slow.after_frame() and slow.trims == 1
    del blocks


def test_without_glibc_it_does_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    trim = HeapTrim()
    assert not trim.enabled and not trim.after_frame() and trim.trims == 0


def test_without_proc_it_does_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(heap, "_STATM", "/nonexistent/statm")
    trim = HeapTrim()
    assert resident_mb() is None and not trim.enabled and not trim.after_frame()


def test_trim_gives_back_what_was_freed_outside_a_frame() -> None:
    trim = HeapTrim(growth_mb=1e9, interval_s=3600.0)  # (never after a frame)
    if not trim.enabled:
        pytest.skip("no glibc malloc_trim or /proc here")
    import hand_sog_tracker.core.depth_sog  # noqa: F401 - raises the thresholds, as in the node

    blocks = [np.ones(20_000) for _ in range(500)]  # 80 MB in the heap, every second one held
    held = blocks[1::2]
    del blocks
    before = resident_mb()
    assert not trim.after_frame()
    assert trim.trim() and trim.trims == 1
    assert resident_mb() < before - 25.0
    del held
