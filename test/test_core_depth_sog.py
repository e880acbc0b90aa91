"""Depth preprocessing and the quadtree Sum of Gaussians."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from hand_sog_tracker.core.depth_sog import (
    EDGE_BEHIND_MM,
    MAX_QUAD_PX,
    MIN_QUAD_PX,
    check_depth,
    leaf_px,
    preprocess,
    quadtree_sog,
    self_overlap_2d,
)
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.errors import DepthImageError, IntrinsicsError
from helpers import INTR


def test_flat_square_becomes_few_large_quads() -> None:
    depth = np.zeros((240, 320), np.float32)
    depth[64:128, 96:160] = 400.0  # aligned with the 16 px grid
    pre = preprocess(depth, INTR, TrackerConfig(median_kernel=0))
    sog = quadtree_sog(pre, 20.0)
    assert sog.n == (64 // MAX_QUAD_PX) * (64 // MAX_QUAD_PX)
    np.testing.assert_allclose(sog.sigma, MAX_QUAD_PX / np.sqrt(2.0))
    np.testing.assert_allclose(sog.depth, 400.0)
    # Means at quad centres; the mixture's centroid is the square's centre.
    np.testing.assert_allclose(sog.mu.mean(axis=0), [127.5, 95.5])
    np.testing.assert_allclose(sog.points[:, 2], 400.0)


def test_quads_split_at_depth_steps_and_cover_each_pixel_once() -> None:
    rng = np.random.default_rng(4)
    depth = np.zeros((240, 320), np.float32)
    depth[40:200, 60:260] = 400.0
    depth[40:200, 150:260] = 450.0  # a 50 mm step
    depth[100:110, 100:110] = 0.0  # a hole
    depth += rng.normal(0, 1.0, depth.shape).astype(np.float32) * (depth > 0)
    pre = preprocess(depth, INTR, TrackerConfig(median_kernel=0))
    sog = quadtree_sog(pre, 20.0)
    side = sog.sigma * np.sqrt(2.0)
    assert side.min() >= MIN_QUAD_PX and side.max() <= MAX_QUAD_PX
    # Area covered by leaves equals the valid area up to the partial smallest quads.
    valid = int((pre.depth_mm > 0).sum())
    assert abs((side**2).sum() - valid) < 0.05 * valid
    # No leaf straddles the step: every leaf depth is near 400 or near 450.
    assert np.all(np.minimum(np.abs(sog.depth - 400), np.abs(sog.depth - 450)) < 5.0)


def test_range_filter_and_roi() -> None:
    depth = np.full((240, 320), 400.0, np.float32)
    depth[:, :100] = 100.0  # too near
    depth[:, 200:] = 900.0  # too far
    cfg = TrackerConfig(near_mm=150.0, far_mm=600.0, median_kernel=0)
    pre = preprocess(depth, INTR, cfg)
    assert np.all(pre.depth_mm[:, :100] == 0) and np.all(pre.depth_mm[:, 200:] == 0)
    sog = quadtree_sog(pre, 20.0, roi=(120, 50, 170, 90))
    assert sog.n > 0
    assert np.all((sog.mu[:, 0] > 118) & (sog.mu[:, 0] < 172))
    assert quadtree_sog(pre, 20.0, roi=(120, 50, 170, 90), depth_window_mm=(500, 600)).n == 0


def test_median_filter_removes_flying_pixels() -> None:
    rng = np.random.default_rng(2)
    depth = np.zeros((240, 320), np.float32)
    depth[60:180, 100:220] = 400.0
    fly = rng.random(depth.shape) < 0.02
    depth[fly] = rng.uniform(200, 580, fly.sum())
    with_median = preprocess(depth, INTR, TrackerConfig(median_kernel=3))
    stray = (with_median.depth_mm > 0) & (np.abs(with_median.depth_mm - 400) > 20)
    assert stray.sum() < 0.05 * fly.sum()


def test_what_lies_behind_the_hand_does_not_change_its_pixels() -> None:
    """A hand's edge pixels keep their depths whether a wall or nothing lies behind it.

    The median filter took values from a wall behind the hand into the hand's edge pixels:
    their medians moved farther back (toward the wall's values) than with nothing behind,
    and the fit turned about the palm normal (depth_sog.EDGE_BEHIND_MM).  Here a dome whose
    edge falls away from the camera, 400 to 470 mm, in front of a wall at 900 mm or of no
    data; also with a 5 x 5 median.
    """
    v, u = np.mgrid[0:240, 0:320]
    r2 = ((u - 160.0) ** 2 + (v - 120.0) ** 2) / 60.0**2
    dome = np.where(r2 < 1.0, 400.0 + 70.0 * r2, 0.0).astype(np.float32)
    hand = dome > 0
    for kernel in (3, 5):
        cfg = TrackerConfig(median_kernel=kernel)
        alone = preprocess(dome, INTR, cfg).depth_mm
        walled = preprocess(np.where(hand, dome, np.float32(900.0)), INTR, cfg).depth_mm
        assert np.array_equal(alone[hand], walled[hand]), np.abs(alone - walled)[hand].max()
        assert (alone[hand] > 0).mean() > 0.97  # (the dome itself survives the filter)
        np.testing.assert_array_equal(walled[~hand & (walled > 0)], 900.0)  # the wall stays a wall


def test_what_lies_behind_an_edge_keeps_its_pixels_and_stays_connected() -> None:
    """A forearm (700 mm) across a body (900 mm): the body's pixels along the forearm's edges
    stay (its blob stays one piece for the hand finder; 0 there, along a 1 px seam, turned the
    NYU Kinect frame's initialisation palm-for-back far more often), with their own depths.
    A finger 70 mm in front of the palm is no such edge: the plain median, as before."""
    depth = np.full((240, 320), 900.0, np.float32)
    depth[100:140, :] = 700.0  # the forearm, full width
    out = preprocess(depth, INTR, TrackerConfig()).depth_mm
    np.testing.assert_array_equal(out[98:100, 1:-1], 900.0)  # the body's rows next to the forearm
    np.testing.assert_array_equal(out[140:142, 1:-1], 900.0)
    np.testing.assert_array_equal(out[100:140, 1:-1], 700.0)
    v, u = np.mgrid[0:240, 0:320]
    palm = np.where((u > 80) & (u < 240), 450.0 + 0.3 * (u - 160) ** 2 / 10, 0.0).astype(np.float32)
    finger = np.where((u > 140) & (u < 158) & (v < 150), palm - 70.0 + (u - 149) ** 2 / 4, palm)
    finger = finger.astype(np.float32)
    import cv2

    med = cv2.medianBlur(finger, 3)
    plain = np.where((finger > 0) & (med > 0) & (np.abs(med - finger) < 20.0), med, np.float32(0.0))
    np.testing.assert_array_equal(preprocess(finger, INTR, TrackerConfig()).depth_mm, plain)


def test_wide_images_are_decimated() -> None:
    intr = Intrinsics(fx=574.5, fy=574.5, cx=320.0, cy=240.0, width=640, height=480)
    depth = np.full((480, 640), 400.0, np.float32)
    pre = preprocess(depth, intr, TrackerConfig())
    assert pre.depth_mm.shape == (240, 320) and pre.decimation == 2
    assert pre.intrinsics.fx == pytest.approx(287.25)
    assert pre.intrinsics.cx == pytest.approx(160.0)


@pytest.mark.parametrize(
    "width, height, fx, min_focal_px, decimation",
    [
        (640, 480, 385.0, 240.0, 1),  # a wide-angle camera (D435-like): 192 px decimated, kept whole
        (640, 480, 385.0, 0.0, 2),  # ... unless the floor is off
        (640, 480, 574.5, 240.0, 2),  # a 58 deg camera: 287 px decimated, as before
        (1280, 720, 640.0, 240.0, 2),  # 4 would leave 160 px, 2 leaves 320
        (848, 480, 425.0, 240.0, 1),  # 3 would leave 142 px, 2 leaves 212
    ],
)
def test_decimation_keeps_a_wide_angle_cameras_focal_length(
    width: int, height: int, fx: float, min_focal_px: float, decimation: int
) -> None:
    """A D435-like 640x480 camera decimated to 320x240 keeps 192 px of focal length: the hand at
    400 mm had 84 data Gaussians instead of about 250, and 18 mesh dev renders tracked at 6.85
    mm against 6.00 at full resolution (issue 11's held-out sensors include 640x480)."""
    intr = Intrinsics(fx=fx, fy=fx, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)
    depth = np.full((height, width), 400.0, np.float32)
    pre = preprocess(depth, intr, TrackerConfig(min_focal_px=min_focal_px))
    assert pre.decimation == decimation
    assert pre.depth_mm.shape[1] == -(-width // decimation)
    assert pre.intrinsics.fx == pytest.approx(fx / decimation)


def test_invalid_values_and_shapes() -> None:
    depth = np.full((240, 320), 400.0, np.float32)
    depth[0, 0] = np.nan
    depth[0, 1] = np.inf
    depth[0, 2] = -5
    clean = check_depth(depth, INTR)
    assert clean[0, 0] == 0 and clean[0, 1] == 0 and clean[0, 2] == 0
    with pytest.raises(IntrinsicsError):
        check_depth(np.zeros((100, 100), np.float32), INTR)
    with pytest.raises(DepthImageError):
        check_depth(np.zeros((240, 320, 3), np.float32), INTR)
    with pytest.raises(DepthImageError):
        check_depth(np.zeros((0, 0), np.float32), INTR)
    empty = quadtree_sog(preprocess(np.zeros((240, 320), np.float32), INTR, TrackerConfig()), 20.0)
    assert empty.n == 0 and empty.norm == 0.0


def test_normaliser_approximates_exact_self_overlap() -> None:
    depth = np.zeros((240, 320), np.float32)
    yy, xx = np.mgrid[:240, :320]
    depth[(xx - 160) ** 2 + (yy - 120) ** 2 < 60**2] = 400.0
    depth[(xx - 160) ** 2 + (yy - 120) ** 2 < 20**2] = 360.0
    sog = quadtree_sog(preprocess(depth, INTR, TrackerConfig()), 20.0)
    exact = self_overlap_2d(sog.mu, sog.sigma)
    assert 0.75 * sog.norm < exact < 1.05 * sog.norm


def test_depth_window_is_bit_identical_to_the_numpy_expression() -> None:
    from hand_sog_tracker.core.depth_sog import _in_window

    rng = np.random.default_rng(0)
    bounds = [
        (300.0, 700.0),  # Python floats: NumPy compares in float32
        (np.float64(300.1), np.float64(699.9)),  # NumPy floats: compared in float64
        (np.float32(250.5), 800.25),
        (299.99999999, 700.00000001),
        (-5.0, 1e9),
    ]
    for lo, hi in bounds:
        img = rng.uniform(0.0, 1000.0, (37, 53)).astype(np.float32)
        img[rng.random(img.shape) < 0.2] = 0.0
        for k, b in enumerate((lo, hi)):  # values at and one float32 step around each bound
            r = np.float32(b)
            img[k, :3] = [np.nextafter(r, np.float32(-np.inf)), r, np.nextafter(r, np.float32(np.inf))]
        for a in (img, img[3:30, 5:40]):  # whole and a strided view
            ref = np.where((a > lo) & (a < hi), a, np.float32(0.0))
            out = _in_window(a, lo, hi)
            assert out.dtype == np.float32 and out.shape == a.shape
            assert out.tobytes() == ref.tobytes()


def _quadtree_reference(img: np.ndarray, threshold: float, min_quad: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leaves (mu, sigma, depth) of a padded image by the plain 2x2-block recursion."""
    valid = img > 0
    vmin, vmax, vsum, cnt = np.where(valid, img, np.inf), np.where(valid, img, -np.inf), img, valid.astype(np.int16)
    levels, size = [], 1
    while size < MAX_QUAD_PX:
        q = [(a[0::2, 0::2], a[1::2, 0::2], a[0::2, 1::2], a[1::2, 1::2]) for a in (vmin, vmax, vsum, cnt)]
        vmin = np.minimum(np.minimum(q[0][0], q[0][1]), np.minimum(q[0][2], q[0][3]))
        vmax = np.maximum(np.maximum(q[1][0], q[1][1]), np.maximum(q[1][2], q[1][3]))
        vsum = (q[2][0] + q[2][1]) + (q[2][2] + q[2][3])
        cnt = (q[3][0] + q[3][1]) + (q[3][2] + q[3][3])
        size *= 2
        if size >= min_quad:
            levels.append((size, vmin, vmax, vsum, cnt))
    mus, sigmas, depths, taken = [], [], [], None
    for size, vmin, vmax, vsum, cnt in reversed(levels):
        full = cnt * 2 >= size * size if size == min_quad else cnt == size * size
        leaf = full & ((vmax - vmin) < threshold)
        if taken is not None:
            covered = np.repeat(np.repeat(taken, 2, axis=0), 2, axis=1)
            leaf &= ~covered
            leaf_or = covered | leaf
        else:
            leaf_or = leaf
        taken = leaf_or
        bv, bu = np.nonzero(leaf)
        mus.append(np.stack([(bu + 0.5) * size - 0.5, (bv + 0.5) * size - 0.5], axis=1))
        sigmas.append(np.full(bv.size, size / np.sqrt(2.0)))
        depths.append(vsum[bv, bu].astype(np.float64) / cnt[bv, bu])
    return np.concatenate(mus), np.concatenate(sigmas), np.concatenate(depths)


@pytest.mark.parametrize("min_quad", [2, 4, 8])
def test_quadtree_equals_the_plain_recursion(min_quad: int) -> None:
    # Same leaves, in the same order, with bit-identical depths, as the straightforward
    # implementation (the module reduces rows first and keeps invalid pixels as 0 for the max).
    rng = np.random.default_rng(min_quad)
    h, w = 64, 96
    yy, xx = np.mgrid[0:h, 0:w]
    img = (500.0 + 0.8 * xx + 0.3 * yy + 40.0 * (xx > 50)).astype(np.float32)
    img += rng.normal(0.0, 0.7, img.shape).astype(np.float32)
    img[rng.random(img.shape) < 0.05] = 0.0
    img[10:20, 30:44] = 0.0
    intr = Intrinsics(fx=200.0, fy=200.0, cx=w / 2, cy=h / 2, width=w, height=h)
    pre = preprocess(img, intr, TrackerConfig(median_kernel=0))
    sog = quadtree_sog(pre, 10.0, min_quad_px=min_quad)
    mu, sigma, depth = _quadtree_reference(pre.depth_mm, 10.0, min_quad)
    np.testing.assert_array_equal(sog.mu, mu)
    np.testing.assert_array_equal(sog.sigma, sigma)
    np.testing.assert_array_equal(sog.depth, depth)


def _sorted_leaves(sog, mirror_width: int | None = None) -> np.ndarray:
    mu = sog.mu.copy()
    if mirror_width is not None:
        mu[:, 0] = mirror_width - 1 - mu[:, 0]
    a = np.column_stack([mu, sog.sigma, sog.depth])
    return a[np.lexsort(a.T[::-1])]


@pytest.mark.parametrize("shift", [0, 1, 5])
def test_mirrored_frame_gives_the_mirrored_quads(shift: int) -> None:
    # u -> W - 1 - u with cx -> W - 1 - cx: the block lattice is centred on the image, so the
    # mirror image is cut into the mirrored blocks whatever the ROI (the same leaves, mirrored).
    rng = np.random.default_rng(shift)
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    img = (450.0 + 0.6 * xx + 0.2 * yy + 35.0 * (xx > 70 + 3 * shift)).astype(np.float32)
    img += rng.normal(0.0, 1.0, img.shape).astype(np.float32)
    img[rng.random(img.shape) < 0.03] = 0.0
    img[:, : 17 + shift] = 0.0
    intr = Intrinsics(fx=150.0, fy=150.0, cx=80.0, cy=60.0, width=w, height=h)
    mirrored = Intrinsics(fx=150.0, fy=150.0, cx=w - 1 - 80.0, cy=60.0, width=w, height=h)
    cfg = TrackerConfig(median_kernel=0)
    pre, prem = preprocess(img, intr, cfg), preprocess(np.ascontiguousarray(img[:, ::-1]), mirrored, cfg)
    roi = (9 + shift, 7, 150, 113)
    a = quadtree_sog(pre, 10.0, roi, (400.0, 700.0))
    b = quadtree_sog(prem, 10.0, (w - roi[2], roi[1], w - roi[0], roi[3]), (400.0, 700.0))
    assert a.n == b.n > 20
    np.testing.assert_array_equal(_sorted_leaves(a), _sorted_leaves(b, w))


def test_decimation_keeps_the_mirrored_pixels() -> None:
    # A 640-wide image mirrored (cx 320 -> 319) keeps the mirror images of the kept pixels:
    # the decimation lattice runs through the pixel nearest the principal point.
    rng = np.random.default_rng(0)
    depth = rng.uniform(200.0, 590.0, (480, 640)).astype(np.float32)
    intr = Intrinsics(fx=574.5, fy=574.5, cx=320.0, cy=240.0, width=640, height=480)
    mirrored = Intrinsics(fx=574.5, fy=574.5, cx=319.0, cy=240.0, width=640, height=480)
    cfg = TrackerConfig(median_kernel=0)
    a = preprocess(depth, intr, cfg)
    b = preprocess(np.ascontiguousarray(depth[:, ::-1]), mirrored, cfg)
    np.testing.assert_array_equal(b.depth_mm, a.depth_mm[:, ::-1])
    assert b.intrinsics.cx == pytest.approx(a.intrinsics.width - 1 - a.intrinsics.cx)
    np.testing.assert_array_equal(a.depth_mm, np.where((depth > 150) & (depth < 600), depth, 0)[::2, ::2])


def test_fast_preprocessing_equals_the_plain_expressions() -> None:
    # The window as validity test and the median agreement by OpenCV give exactly the pixels
    # of check_depth, the NumPy window and the NumPy agreement test, for all input types.
    rng = np.random.default_rng(1)
    x = rng.uniform(-100.0, 800.0, (60, 80)).astype(np.float32)
    for value in (np.nan, np.inf, -np.inf, 0.0):
        x[rng.random(x.shape) < 0.05] = value
    intr = Intrinsics(fx=100.0, fy=100.0, cx=40.0, cy=30.0, width=80, height=60)
    for arr in (x, x.astype(np.float64), np.nan_to_num(x, posinf=0, neginf=0).astype(np.uint16)):
        for cfg in (TrackerConfig(), TrackerConfig(median_kernel=5), TrackerConfig(quadtree_threshold_mm=400.0)):
            d = check_depth(arr, intr)
            d = np.where((d > cfg.near_mm) & (d < cfg.far_mm), d, np.float32(0.0))
            # The median blind to what lies behind a depth edge: over the window with 0 for
            # the pixels more than EDGE_BEHIND_MM behind its nearest valid pixel (the window
            # clipped at the image border); those pixels themselves get the plain median.
            k, r = cfg.median_kernel, cfg.median_kernel // 2
            padded = np.pad(np.where(d > 0, d, np.inf), r, constant_values=np.inf)
            nearest = sliding_window_view(padded, (k, k)).min(axis=(2, 3))
            behind = d > nearest + np.float32(EDGE_BEHIND_MM)
            import cv2

            blind = cv2.medianBlur(np.where(behind, np.float32(0.0), d), k)
            med = np.where(behind, cv2.medianBlur(d, k), blind)
            keep = (d > 0) & (med > 0) & (np.abs(med - d) < cfg.quadtree_threshold_mm)
            ref = np.where(keep, med, np.float32(0.0))
            assert preprocess(arr, intr, cfg).depth_mm.tobytes() == ref.tobytes()


def test_leaf_px_halves_the_leaf_for_far_hands() -> None:
    # f = 287.26 px (the helpers' 320x240 camera): 2 f = 575 mm, 4 f = 1149 mm.
    assert [leaf_px(4, z, INTR) for z in (250.0, 400.0, 570.0, 580.0, 900.0, 1200.0)] == [4, 4, 4, 2, 2, 2]
    assert [leaf_px(8, z, INTR) for z in (400.0, 580.0, 1200.0)] == [8, 4, 2]
    assert leaf_px(2, 900.0, INTR) == 2
    # The same camera at twice the resolution: the same depths (leaves in px of that image).
    double = Intrinsics(2 * INTR.fx, 2 * INTR.fy, 2 * INTR.cx, 2 * INTR.cy, 640, 480)
    assert [leaf_px(4, z, double) for z in (580.0, 1100.0, 1200.0)] == [4, 4, 2]


def test_the_data_gaussians_are_capped_whatever_the_texture() -> None:
    """A surface textured finer than the smallest leaves (a 2-pixel checkerboard of 1.5 mm
    steps, 2 px leaves) would give one Gaussian per 2x2 block: coarsened and thinned to at
    most ``max_gaussians``, spread over the whole ROI."""
    from hand_sog_tracker.core.depth_sog import MAX_DATA_GAUSSIANS

    intr = Intrinsics(fx=287.0, fy=287.0, cx=159.5, cy=119.5, width=320, height=240)
    v, u = np.mgrid[0:240, 0:320]
    depth = (500.0 + 1.5 * (((u // 2) + (v // 2)) % 2)).astype(np.float32)
    pre = preprocess(depth, intr, TrackerConfig())
    full = quadtree_sog(pre, 1.0, min_quad_px=2, max_gaussians=10**6)
    assert full.n == 320 * 240 // 4
    capped = quadtree_sog(pre, 1.0, min_quad_px=2)
    assert 0 < capped.n <= MAX_DATA_GAUSSIANS
    assert capped.mu[:, 0].min() < 20 and capped.mu[:, 0].max() > 300  # spread, not the first rows
    assert capped.mu[:, 1].min() < 20 and capped.mu[:, 1].max() > 220
    smooth = quadtree_sog(pre, 10.0, min_quad_px=2)  # (within the threshold: big leaves, not capped)
    assert smooth.n == 320 * 240 // 256
