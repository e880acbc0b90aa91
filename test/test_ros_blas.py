"""The node's BLAS runs on one thread (issue 50): ``hand_sog_tracker.ros.blas``."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.ros import blas


@pytest.fixture
def restore_threads():
    """Give every OpenBLAS its thread count back after the test."""
    before = blas.blas_threads()
    yield before
    for path, lib, set_name, _ in blas._openblas():
        getattr(lib, set_name)(before.get(path, 1))


def _uses_openblas() -> bool:
    config = np.show_config(mode="dicts") if hasattr(np, "show_config") else {}
    name = str(config.get("Build Dependencies", {}).get("blas", {}).get("name", ""))
    return "openblas" in name.lower()


def test_every_loaded_openblas_is_set_to_one_thread(restore_threads, monkeypatch: pytest.MonkeyPatch) -> None:
    for var in blas.THREADS_ENV:
        monkeypatch.delenv(var, raising=False)
    found = blas._openblas()
    if _uses_openblas():
        assert found, "NumPy's OpenBLAS was not found among the loaded libraries"
    for _, lib, set_name, _ in found:
        getattr(lib, set_name)(2)
    counts = blas.limit_blas_threads(1)
    assert set(counts) == {path for path, *_ in found}
    assert all(n == 1 for n in counts.values()), counts


def test_an_explicit_thread_count_in_the_environment_is_left_alone(
    restore_threads, monkeypatch: pytest.MonkeyPatch
) -> None:
    found = blas._openblas()
    if not found:
        pytest.skip("no OpenBLAS loaded")
    for _, lib, set_name, _ in found:
        getattr(lib, set_name)(2)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    assert all(n == 2 for n in blas.limit_blas_threads(1).values())


def test_one_thread_gives_the_same_values() -> None:
    """The data terms' candidate product (B m x 6 by 6 x n) on one thread and on several: the
    same values up to rounding (a split may change the kernel and the order of a sum: OpenBLAS
    0.3.31 on Haswell differs in the last bit of 20 of 422 096 elements)."""
    found = blas._openblas()
    if not found:
        pytest.skip("no OpenBLAS loaded")
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(184, 6)), rng.normal(size=(2, 6, 1147)) * 300.0
    before = blas.blas_threads()
    try:
        results = []
        for threads in (1, 2):
            for _, lib, set_name, _ in found:
                getattr(lib, set_name)(threads)
            results.append(np.matmul(a, b))
    finally:
        for path, lib, set_name, _ in found:
            getattr(lib, set_name)(before.get(path, 1))
    np.testing.assert_allclose(results[0], results[1], rtol=1e-12, atol=0.0)
