"""The silhouette distance map and its window."""

from __future__ import annotations

import numpy as np

from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import default_hand_model
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.silhouette import silhouette, silhouette_term
from hand_sog_tracker.core.tracker import hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence


def _first_frame(motion: str, seed: int):
    """A rendered frame, its preprocessed depth, the default model and the hand's ROI and window."""
    intr = default_intrinsics()
    frame = next(synthetic_sequence(motion, 1, intrinsics=intr, seed=seed))
    pre = preprocess(frame.depth_mm, intr, TrackerConfig(far_mm=600.0))  # (the wall at 900 mm: out)
    model = default_hand_model()
    roi, window = hand_roi(model, frame.pose, pre.intrinsics, 160.0)
    return frame, pre, model, roi, window


def test_window_map_gives_the_full_image_values_near_the_hand() -> None:
    frame, pre, model, roi, window = _first_frame("abdadd", 2)
    full = silhouette(pre, window)
    part = silhouette(pre, window, roi)
    assert part.distance.size < full.distance.size and part.distance.dtype == np.float32
    assert part.cell == full.cell and full.origin == (0, 0)
    u0, v0 = part.origin[0] // part.cell, part.origin[1] // part.cell  # in cells
    assert (u0 * part.cell, v0 * part.cell) == part.origin  # the same cells
    h, w = part.distance.shape
    np.testing.assert_array_equal(part.distance[:, :] == 0, full.distance[v0 : v0 + h, u0 : u0 + w] == 0)
    # The true pose lies on the hand (small cost), a pose moved 30 mm sideways does not.
    P = gaussian_centres(model, frame.pose)
    moved = P + np.array([30.0, 0.0, 0.0])
    for sil in (full, part):
        assert silhouette_term(sil, P, None, 1.0) < 0.05 * silhouette_term(sil, moved, None, 1.0)
    assert silhouette_term(part, moved, None, 1.0) == silhouette_term(full, moved, None, 1.0)


def test_half_resolution_map_is_close_to_the_exact_one_and_its_gradient_is_exact() -> None:
    frame, pre, model, roi, window = _first_frame("fingerwave", 3)
    exact, half = silhouette(pre, window, roi, cell=1), silhouette(pre, window, roi)
    assert half.cell == 2 and half.distance.size * 3 < exact.distance.size
    # Distances at the cell centres within a pixel of the exact map's (interpolated) values.
    uu, vv = np.meshgrid(np.arange(half.distance.shape[1]), np.arange(half.distance.shape[0]))
    u = half.origin[0] + 2 * uu + 0.5 - exact.origin[0]
    v = half.origin[1] + 2 * vv + 0.5 - exact.origin[1]
    inside = (u >= 0) & (v >= 0) & (u < exact.distance.shape[1] - 1) & (v < exact.distance.shape[0] - 1)
    ui, vi = u[inside].astype(int), v[inside].astype(int)
    e = exact.distance
    ref = 0.25 * (e[vi, ui] + e[vi, ui + 1] + e[vi + 1, ui] + e[vi + 1, ui + 1])
    err = half.distance[inside] - ref
    assert np.abs(err).max() < 1.6 and abs(err.mean()) < 0.5
    # The term moves little (over 10 random displacements per size: one alone varies, up to
    # 15-23% at 10 mm, where the term itself is small); its gradient is the derivative of
    # the interpolated map.
    rng = np.random.default_rng(0)
    P = gaussian_centres(model, frame.pose)
    for shift in (10.0, 25.0):
        rel = []
        for _ in range(10):
            Q = P + rng.normal(0.0, shift, P.shape) * [1.0, 1.0, 0.0]
            a, b = silhouette_term(exact, Q, None, 1.0), silhouette_term(half, Q, None, 1.0)
            rel.append(abs(a - b) / a)
        assert np.median(rel) < 0.1 and max(rel) < 0.3, np.round(rel, 3)
    g = np.zeros_like(Q)
    silhouette_term(half, Q, g, 1.0)
    num = np.zeros_like(Q)
    for i in range(0, Q.shape[0], 3):
        for j in range(3):
            e = np.zeros_like(Q)
            e[i, j] = 1e-4
            num[i, j] = -(silhouette_term(half, Q + e, None, 1.0) - silhouette_term(half, Q - e, None, 1.0)) / 2e-4
    np.testing.assert_allclose(g[::3], num[::3], atol=1e-7 * np.abs(g).max() + 1e-12, rtol=1e-4)


def test_mirrored_frame_gives_the_mirrored_map() -> None:
    intr = default_intrinsics(320, 240)
    intr = Intrinsics(intr.fx, intr.fy, 160.0, 120.0, 320, 240)  # a principal point on a pixel
    mirrored = Intrinsics(intr.fx, intr.fy, 319.0 - intr.cx, intr.cy, 320, 240)
    frame = next(synthetic_sequence("abdadd", 1, intrinsics=intr, seed=2))
    pre = preprocess(frame.depth_mm, intr, TrackerConfig())
    prem = preprocess(np.ascontiguousarray(frame.depth_mm[:, ::-1]), mirrored, TrackerConfig())
    roi, window = hand_roi(default_hand_model(), frame.pose, pre.intrinsics, 160.0)
    for shift in (0, 1):  # a ROI of odd and of even width
        box = (roi[0], roi[1], roi[2] + shift, roi[3])
        a = silhouette(pre, window, box)
        b = silhouette(prem, window, (320 - box[2], box[1], 320 - box[0], box[3]))
        assert b.origin == (320 - a.origin[0] - a.cell * a.distance.shape[1], a.origin[1])
        np.testing.assert_array_equal(b.distance, a.distance[:, ::-1])


def test_map_is_reproducible() -> None:
    # The same frame gives the same map to the last bit (OpenCV's exact transform alone does not).
    intr = default_intrinsics()
    frame = next(synthetic_sequence("pinch", 1, intrinsics=intr, seed=1))
    model = default_hand_model()
    maps = []
    for _ in range(4):
        pre = preprocess(frame.depth_mm.copy(), intr, TrackerConfig())
        roi, window = hand_roi(model, frame.pose, pre.intrinsics, 160.0)
        maps.append(silhouette(pre, window, roi).distance)
        maps.append(silhouette(pre, window).distance)
    for a, b in zip(maps[:-2], maps[2:]):  # each map against the same map of the next pass
        assert a.tobytes() == b.tobytes()
    d2 = (maps[0] / 2.0) ** 2  # squared distances in cells: integers
    np.testing.assert_allclose(d2, np.rint(d2), atol=1e-3)



def test_term_with_the_map_made_on_demand_equals_the_term_on_the_made_map() -> None:
    # The term reads the hand's cells first and makes the distance map only once a model
    # Gaussian's cell lies off the hand: value and gradient as with the map made up front.
    frame, pre, model, roi, window = _first_frame("fistopen", 4)
    rng = np.random.default_rng(1)
    P = gaussian_centres(model, frame.pose)
    for cell in (1, 2):
        lazy, eager = silhouette(pre, window, roi, cell=cell), silhouette(pre, window, roi, cell=cell)
        assert eager.distance.size > 0  # (the map made now)
        for shift in (0.0, 3.0, 12.0, 40.0):
            Q = P + rng.normal(0.0, shift, P.shape) * [1.0, 1.0, 0.0]
            g_lazy, g_eager = np.zeros_like(Q), np.zeros_like(Q)
            v_lazy = silhouette_term(lazy, Q, g_lazy, 1.0)
            v_eager = silhouette_term(eager, Q, g_eager, 1.0)
            assert v_lazy == v_eager
            np.testing.assert_array_equal(g_lazy, g_eager)
        assert v_lazy > 0.0  # (40 mm off: Gaussians off the hand, the map was made)
