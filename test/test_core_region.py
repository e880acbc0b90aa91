"""The hand's region: the pairs a search pays for (:func:`pairs`, :func:`within_reach`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hand_sog_tracker.core.depth_sog import preprocess, quadtree_sog
from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import posed_centres
from hand_sog_tracker.core.region import MAX_PAIRS, hand_roi, pairs
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.synth.render import RenderOptions, render_depth

INTR = Intrinsics(fx=287.0, fy=287.0, cx=159.5, cy=119.5, width=320, height=240)
MODEL = default_hand_model()


def _data(intr: Intrinsics, theta: np.ndarray):
    depth = render_depth(MODEL, theta, INTR, RenderOptions(noise_mm=1.0), rng=np.random.default_rng(0))
    cfg = TrackerConfig()
    pre = preprocess(depth, intr, cfg)
    roi, window = hand_roi(MODEL, theta, intr, cfg.roi_radius_mm)
    return quadtree_sog(pre, cfg.quadtree_threshold_mm, roi, (window[0], window[1] + 2000.0), 4)


def test_pairs_counts_both_candidate_tests_pair_by_pair() -> None:
    theta = rest_pose((5.0, 10.0, 420.0))
    data = _data(INTR, theta)
    P = posed_centres(MODEL, theta)
    expected = 0
    for p, s in zip(P, MODEL.g_sigmas):
        z = max(p[2], 1.0)
        u, v = INTR.fx * p[0] / z + INTR.cx, INTR.fy * p[1] / z + INTR.cy
        sp = s * math.sqrt(INTR.fx * INTR.fy) / z
        for (mu_u, mu_v), sq, dq in zip(data.mu, data.sigma, data.depth):
            image = (u - mu_u) ** 2 + (v - mu_v) ** 2 < 36.0 * (sp * sp + sq * sq)
            expected += bool(image and abs(z - s - dq) < 2.0 * s)
    assert 0 < pairs(MODEL, theta, data) == expected


def test_a_hands_data_stay_whole_and_a_model_over_every_leaf_is_thinned(monkeypatch) -> None:
    """Every data set a frame's search gets (tracked, new track): a hand's own data as they are;
    with a focal length 10x too large (every model Gaussian as wide as the image) thinned to
    about ``MAX_PAIRS`` pairs at the start pose, spread over the same box."""
    from hand_sog_tracker.core import region, tracker
    from hand_sog_tracker.core.search import start

    seen = []

    def spy(model, theta, data, max_pairs=MAX_PAIRS):
        thin = region.within_reach(model, theta, data, max_pairs)
        seen.append((pairs(model, theta, data), pairs(model, theta, thin), data, thin))
        return thin

    monkeypatch.setattr(tracker, "within_reach", spy)
    monkeypatch.setattr(start, "within_reach", spy)
    theta = rest_pose((5.0, 10.0, 420.0))
    depth = render_depth(MODEL, theta, INTR, RenderOptions(noise_mm=1.0), rng=np.random.default_rng(0))
    t = tracker.Tracker()
    for _ in range(2):
        t.process(depth, INTR)
    assert len(seen) >= 4 and all(b <= MAX_PAIRS and thin is data for b, _, data, thin in seen)
    seen.clear()
    wrong = dataclasses.replace(INTR, fx=10 * INTR.fx, fy=10 * INTR.fy)
    for _ in range(2):
        tracker.Tracker().process(depth, wrong)
    assert max(b for b, *_ in seen) > 2 * MAX_PAIRS
    for before, after, data, thin in seen:
        assert after <= min(before, 1.1 * MAX_PAIRS)
        if before > MAX_PAIRS:
            assert after >= 0.8 * MAX_PAIRS
            assert np.all(np.abs(thin.mu.min(0) - data.mu.min(0)) <= 16)
            assert np.all(np.abs(thin.mu.max(0) - data.mu.max(0)) <= 16)
