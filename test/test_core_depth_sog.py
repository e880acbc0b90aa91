"""Depth preprocessing and the quadtree Sum of Gaussians."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.core.depth_sog import (
    MAX_QUAD_PX,
    MIN_QUAD_PX,
    check_depth,
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


def test_wide_images_are_decimated() -> None:
    intr = Intrinsics(fx=574.5, fy=574.5, cx=320.0, cy=240.0, width=640, height=480)
    depth = np.full((480, 640), 400.0, np.float32)
    pre = preprocess(depth, intr, TrackerConfig())
    assert pre.depth_mm.shape == (240, 320) and pre.decimation == 2
    assert pre.intrinsics.fx == pytest.approx(287.25)
    assert pre.intrinsics.cx == pytest.approx(160.0)


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
