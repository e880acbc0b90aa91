"""Shortcuts of the objective's and the restarts' hot paths: the same bits as the plain code."""

from __future__ import annotations

import numpy as np
import pytest
from test_core_energy import data_near
from test_core_silhouette import _first_frame

from hand_sog_tracker.core.hand_model import FINGER_ABD, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.objective import ORDER_MIN_GAP_RAD, TAU1_MM, Objective
from hand_sog_tracker.core.objective.arrays import _as_slice
from hand_sog_tracker.core.objective.data import _NEAR_SAFE
from hand_sog_tracker.core.salient import Detections, assign_detections
from hand_sog_tracker.core.search.score import sq_distances as _sq_distances
from hand_sog_tracker.core.silhouette import silhouette, silhouette_term
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig


def test_squared_distances_are_the_bits_of_the_plain_sum() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = rng.normal(0.0, 100.0, (int(rng.integers(1, 9)), 3)) + [0.0, 0.0, 400.0]
        b = rng.normal(0.0, 100.0, (int(rng.integers(1, 200)), 3)) + [0.0, 0.0, 400.0]
        d2 = _sq_distances(a, b)
        assert d2.tobytes() == ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1).tobytes()
        norm = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
        assert np.sqrt(d2).tobytes() == norm.tobytes()


def test_evenly_spaced_indices_become_a_slice() -> None:
    g = np.arange(46 * 3, dtype=np.float64).reshape(46, 3)
    for idx in ([21, 27, 33, 39, 45], [0, 1, 2], [5, 9]):
        sl = _as_slice(np.array(idx))
        assert isinstance(sl, slice)
        np.testing.assert_array_equal(g[sl], g[np.array(idx)])
    for idx in ([3, 1, 2], [0, 2, 3], [7], [4, 4]):
        arr = np.array(idx)
        assert _as_slice(arr) is arr


def test_near_bound_implies_the_exact_distance_within_tau1() -> None:
    # A pair with r2 scale^2 + beh^2 <= _NEAR_SAFE has the exact distance of the dangling
    # term, lat = max(sqrt(r2) - half, 0), within TAU1 (the rounding cannot cross it), also
    # right at the bound.
    rng = np.random.default_rng(3)
    k = 200_000
    scale2 = rng.uniform(0.05, 20.0, k) ** 2
    beh = -rng.uniform(0.0, TAU1_MM, k)
    beh[: k // 4] = 0.0
    room = np.maximum(_NEAR_SAFE - beh * beh, 0.0)
    r2 = room / scale2 * (1.0 - rng.uniform(0.0, 1e-15, k))  # at the bound, within rounding
    half = rng.uniform(0.0, 6.0, k)
    half[: k // 3] = 1e-300
    bound = r2 * scale2
    bound += beh * beh
    ok = bound <= _NEAR_SAFE
    assert ok.mean() > 0.3
    lat = np.sqrt(r2) - half
    np.maximum(lat, 0.0, out=lat)
    exact = lat * lat
    exact *= scale2
    exact += beh * beh
    assert (exact[ok] <= TAU1_MM * TAU1_MM).all()


def _objective() -> tuple[Objective, np.ndarray]:
    model = default_hand_model()
    theta = rest_pose((0.0, 60.0, 400.0))
    data = data_near(model, theta, np.random.default_rng(0))
    return Objective(model, data, TrackerConfig()), theta


def test_limits_and_order_shortcuts_equal_the_full_terms() -> None:
    # Within the limits (also at a limit, with either sign of zero) and with the fingers in
    # order the terms are 0 without a gradient; near the boundaries the value and gradient
    # match the plain formulas.
    obj, theta = _objective()
    model = obj.model
    lo = np.concatenate([np.full(6, -np.inf), model.limits_low])
    hi = np.concatenate([np.full(6, np.inf), model.limits_high])
    rng = np.random.default_rng(1)
    for _ in range(300):
        th = theta.copy()
        th[6:] = rng.uniform(lo[6:] - 0.05, hi[6:] + 0.05)
        at = rng.integers(6, th.size, 3)
        th[at] = np.where(rng.random(3) < 0.5, lo[at], hi[at])
        th[th == 0.0] *= rng.choice([-1.0, 1.0])  # (-0.0 at a limit of 0)
        val, grad = obj._limits(th)
        low, high = np.minimum(th - lo, 0.0), np.maximum(th - hi, 0.0)
        expect = float((low[6:] ** 2).sum() + (high[6:] ** 2).sum())
        assert val == pytest.approx(expect, rel=1e-12, abs=0.0)
        g = np.zeros(th.size) if grad is None else grad
        np.testing.assert_array_equal(g, 2.0 * (low + high))
        abd = th[FINGER_ABD] + obj._const.fan
        short = np.minimum(np.diff(abd) - ORDER_MIN_GAP_RAD, 0.0)
        val, grad = obj._order(th)
        assert val == float((short * short).sum())
        assert (grad is None) == (not short.any())


def test_assignment_ties_go_as_in_a_sequential_update() -> None:
    # Duplicate detections (exact ties): the choice read back along the optimal path is the
    # first minimum, as in the DP that kept every choice (commit 808a933: [1, 2, 0, -1, -1]).
    tips = np.array([[0.0, 0, 400], [20, 0, 400], [40, 0, 400], [60, 0, 400], [80, 0, 400]])
    pts = np.array([[20.0, 0, 400], [0, 0, 400], [20, 0, 400], [0, 0, 400], [200, 0, 400]])
    det = Detections(points=pts, uv=np.zeros((5, 2)), confidence=np.ones(5), end_on=np.zeros(5, bool))
    np.testing.assert_array_equal(assign_detections(tips, det, 30.0), [1, 2, 0, -1, -1])


def test_silhouette_term_with_the_shared_projection_is_the_same() -> None:
    # The objective hands the silhouette term the depths and projections it computed for the
    # data terms: the same value and gradient, bit for bit, on and off the hand.
    frame, pre, model, roi, window = _first_frame("fistopen", 4)
    rng = np.random.default_rng(2)
    P0 = gaussian_centres(model, frame.pose)
    intr = pre.intrinsics
    for cell in (1, 2):
        sil = silhouette(pre, window, roi, cell=cell)
        for shift in (0.0, 3.0, 12.0, 40.0):
            P = P0 + rng.normal(0.0, shift, P0.shape) * [1.0, 1.0, 0.2]
            z = np.maximum(P[:, 2], 1.0)
            q = np.array([[intr.fx], [intr.fy]]) * P[:, :2].T
            q /= z
            g_own, g_shared = np.zeros_like(P), np.zeros_like(P)
            v_own = silhouette_term(sil, P, g_own, 1.0)
            v_shared = silhouette_term(sil, P, g_shared, 1.0, (z, q))
            assert v_own == v_shared
            assert g_own.tobytes() == g_shared.tobytes()
        assert v_own > 0.0


def test_deferred_gradient_is_the_gradient_bit_for_bit_and_only_until_the_next_evaluation() -> None:
    # Objective.value_then_gradient (the optimiser's possibly-last iterate): the same value and,
    # on demand, the same gradient bits as one evaluation with gradient, every term active
    # (data, dangling, collisions, salient targets, silhouette off the hand, limits, order).
    frame, pre, model, roi, window = _first_frame("fistopen", 4)
    tracker = Tracker(TrackerConfig())
    data, det, sil = tracker._data_near(pre, frame.pose)
    assert det.n > 0 and sil is not None
    obj = Objective(
        model, data, tracker.config, previous=(frame.pose, frame.pose),
        targets=tracker._targets(frame.pose, det), silhouette=sil,
    )
    rng = np.random.default_rng(5)
    seen = set()
    for _ in range(12):
        theta = frame.pose + rng.normal(0.0, 1.0, frame.pose.size) * np.r_[[6.0] * 3, [0.08] * 3, [0.25] * 20]
        v_full, g_full = obj(theta)
        v_lazy, finish = obj.value_then_gradient(theta)
        terms = obj.evaluate(theta, gradient=False)[0]
        seen.update(name for name in ("dan", "sil", "lim", "ord", "sal") if getattr(terms, name) > 0)
        with pytest.raises(RuntimeError):
            finish()  # (evaluate() ran since: the buffers it read are gone)
        v_lazy, finish = obj.value_then_gradient(theta)
        assert v_lazy == v_full
        assert finish().tobytes() == g_full.tobytes()
    assert seen == {"dan", "sil", "lim", "ord", "sal"}, seen
