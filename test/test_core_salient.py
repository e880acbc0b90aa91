"""Fingertip detection and the optimal assignment of detections to fingertips (seed 001)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import default_hand_model
from hand_sog_tracker.core.salient import Detections, assign_detections, detect_fingertips
from hand_sog_tracker.core.tracker import hand_roi
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig
from hand_sog_tracker.synth.mesh import MeshRenderOptions, MeshShape, mesh_sequence
from hand_sog_tracker.synth.sequence import default_intrinsics


def _detect(depth: np.ndarray, pose: np.ndarray):
    intr = default_intrinsics()
    pre = preprocess(depth, intr, TrackerConfig())
    roi, window = hand_roi(default_hand_model(), pose, pre.intrinsics, 160.0)
    return detect_fingertips(pre, roi, window)


@pytest.mark.parametrize("sensor", ["clean", "tof", "structured"])
def test_open_mesh_hand_has_a_detection_at_every_fingertip(sensor: str) -> None:
    frame = next(mesh_sequence("abdadd", 1, shape=MeshShape(1.05, 0.95, 1.0), seed=3,
                               options=MeshRenderOptions(sensor=sensor)))
    det = _detect(frame.depth_mm, frame.pose)
    d = np.linalg.norm(frame.fingertips_mm[:, None, :] - det.points[None, :, :], axis=-1)
    # Every fingertip found within 15 mm (a detection is a region centroid, a few mm off).
    assert d.min(axis=1).max() < 15.0, d.min(axis=1).round(1)
    # Few false positives on an open hand (the forearm cut and the wrist are not tips).
    assert det.n <= 7
    assert np.all((det.confidence > 0) & (det.confidence <= 1))


def test_a_fist_has_no_detection_far_from_the_hand_and_empty_input_has_none() -> None:
    frames = list(mesh_sequence("fistopen", 40, seed=5))
    fist = max(frames, key=lambda f: f.pose[10])  # index flexed most
    det = _detect(fist.depth_mm, fist.pose)
    centre = fist.fingertips_mm.mean(axis=0)
    assert det.n == 0 or np.linalg.norm(det.points - centre, axis=1).max() < 150.0
    empty = np.zeros_like(fist.depth_mm)
    assert _detect(empty, fist.pose).n == 0


def _brute_force(tips: np.ndarray, det: Detections, lam: float) -> float:
    """Smallest cost of eq. 11 by enumerating every partial injection."""
    T, S = tips.shape[0], det.n
    cost = np.linalg.norm(tips[:, None] - det.points[None], axis=-1)
    best = np.inf
    for choice in itertools.product(range(-1, S), repeat=T):
        used = [s for s in choice if s >= 0]
        if len(used) != len(set(used)):
            continue
        c = sum(cost[t, s] if s >= 0 else lam for t, s in enumerate(choice))
        c += lam * sum(det.confidence[s] for s in range(S) if s not in used)
        best = min(best, c)
    return best


def _cost(tips: np.ndarray, det: Detections, assigned: np.ndarray, lam: float) -> float:
    used = [s for s in assigned if s >= 0]
    c = sum(np.linalg.norm(tips[t] - det.points[s]) if s >= 0 else lam for t, s in enumerate(assigned))
    return c + lam * sum(det.confidence[s] for s in range(det.n) if s not in used)


@pytest.mark.parametrize("seed", range(6))
def test_assignment_is_optimal(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tips = rng.normal(0.0, 40.0, (5, 3))
    S = int(rng.integers(0, 6))
    det = Detections(
        points=tips[rng.integers(0, 5, S)] + rng.normal(0.0, 25.0, (S, 3)),
        uv=np.zeros((S, 2)),
        confidence=rng.uniform(0.2, 1.0, S),
        end_on=np.zeros(S, bool),
    )
    lam = 30.0
    assigned = assign_detections(tips, det, lam)
    assert assigned.shape == (5,)
    used = assigned[assigned >= 0]
    assert len(set(used.tolist())) == used.size  # each detection at most once
    assert _cost(tips, det, assigned, lam) == pytest.approx(_brute_force(tips, det, lam))


def test_assignment_gives_each_finger_its_own_detection() -> None:
    tips = np.array([[0.0, 0, 0], [20, 0, 0], [40, 0, 0], [60, 0, 0], [80, 0, 0]])
    det = Detections(tips[[4, 1, 2]] + 3.0, np.zeros((3, 2)), np.ones(3), np.zeros(3, bool))
    np.testing.assert_array_equal(assign_detections(tips, det, 30.0), [-1, 1, 2, -1, 0])
    # A detection far from every fingertip is a false positive.
    far = Detections(np.array([[500.0, 0, 0]]), np.zeros((1, 2)), np.ones(1), np.zeros(1, bool))
    np.testing.assert_array_equal(assign_detections(tips, far, 30.0), [-1] * 5)



def _detect_reference(pre, roi, window_mm, max_detections: int = 8) -> Detections:
    """The detector as first written (one ring sample at a time, statistics by OpenCV)."""
    import cv2

    from hand_sog_tracker.core.salient import (
        END_ON_MM,
        MIN_REGION_SHARE,
        RING_RADIUS_MM,
        RING_SAMPLES,
        SAME_SURFACE_MM,
        TIP_DEPTH_OFFSET_MM,
    )

    def _ring_offsets(radius_px: float) -> np.ndarray:
        a = 2.0 * np.pi * np.arange(RING_SAMPLES) / RING_SAMPLES
        return np.round(np.stack([np.cos(a), np.sin(a)], 1) * radius_px).astype(np.int64)

    roi = tuple(roi)
    depth = pre.depth_mm
    h, w = depth.shape
    u0, v0, u1, v1 = max(roi[0], 0), max(roi[1], 0), min(roi[2], w), min(roi[3], h)
    if u1 - u0 < 8 or v1 - v0 < 8:
        return Detections.empty()
    near, far = window_mm
    d = depth[v0:v1, u0:u1]
    d = np.where((d > near) & (d < far), d, np.float32(0.0))
    valid = d > 0
    if valid.sum() < 20:
        return Detections.empty()
    intr = pre.intrinsics
    f = float(np.sqrt(intr.fx * intr.fy))
    cu = int(np.floor(intr.cx + 0.5) - u0) % 2
    cv = int(np.floor(intr.cy + 0.5) - v0) % 2
    z_ref = float(np.median(d[cv::2, cu::2][valid[cv::2, cu::2]]))  # over the candidates
    r_px = max(RING_RADIUS_MM * f / z_ref, 3.0)
    offsets = _ring_offsets(r_px)
    pad = int(np.abs(offsets).max()) + 1
    # The ROI padded by the ring: outside the image is "unknown" (-1), invalid is 0.
    hh, ww = v1 - v0, u1 - u0
    big = np.full((hh + 2 * pad, ww + 2 * pad), -1.0, np.float32)
    bu0, bv0 = max(u0 - pad, 0), max(v0 - pad, 0)
    bu1, bv1 = min(u1 + pad, w), min(v1 + pad, h)
    src = depth[bv0:bv1, bu0:bu1]
    big[bv0 - v0 + pad : bv1 - v0 + pad, bu0 - u0 + pad : bu1 - u0 + pad] = np.where(
        (src > near) & (src < far), src, np.float32(0.0)
    )
    # Candidates: valid pixels on a 2-pixel grid (a tip region is several pixels wide)
    # through the pixel nearest the principal point.
    vv, uu = np.nonzero(valid[cv::2, cu::2])
    vv, uu = vv * 2 + cv, uu * 2 + cu
    stride = big.shape[1]
    flat = big.ravel()
    centre = (vv + pad) * stride + (uu + pad)
    dc = flat[centre]
    same = np.empty((RING_SAMPLES, centre.size), bool)
    blocked = np.zeros(centre.size, bool)
    behind = np.zeros(centre.size, np.int32)
    for k, (du, dv) in enumerate(offsets):
        s = flat[centre + dv * stride + du]
        diff = s - dc
        same[k] = (s > 0) & (np.abs(diff) < SAME_SURFACE_MM)
        blocked |= (s < 0) | ((s > 0) & (diff < -SAME_SURFACE_MM))
        behind += (s == 0) | (diff > END_ON_MM)
    n_same = same.sum(0)
    transitions = (same != np.roll(same, 1, axis=0)).sum(0)
    side_tip = (n_same >= 1) & (n_same <= RING_SAMPLES // 4) & (transitions == 2)
    end_on = (n_same == 0) & (behind >= RING_SAMPLES - 2)
    keep = ~blocked & (side_tip | end_on)
    if not keep.any():
        return Detections.empty()
    grid = np.zeros(valid[cv::2, cu::2].shape, np.uint8)
    grid[vv[keep] // 2, uu[keep] // 2] = 1
    n_lab, labels, stats, cents = cv2.connectedComponentsWithStats(grid, connectivity=8)
    expected = np.pi * (0.5 * r_px) ** 2 / 4.0  # in grid cells
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    big = np.flatnonzero(area >= MIN_REGION_SHARE * expected)
    if big.size == 0:
        return Detections.empty()
    # Per region: mean depth and share of end-on cells, from the candidate cells' labels.
    lab = labels[vv[keep] // 2, uu[keep] // 2] - 1
    n_reg = n_lab - 1
    z_sum = np.bincount(lab, weights=dc[keep], minlength=n_reg)
    end_sum = np.bincount(lab, weights=end_on[keep].astype(np.float64), minlength=n_reg)
    cnt = np.maximum(np.bincount(lab, minlength=n_reg), 1)
    uv_all = 2.0 * cents[1:] + np.array([u0 + cu, v0 + cv], dtype=np.float64)
    z_all = z_sum / cnt + TIP_DEPTH_OFFSET_MM
    uvs = uv_all[big]
    pts = intr.backproject(uvs, z_all[big])
    conf = np.minimum(1.0, area[big] / expected)
    ends = end_sum[big] / cnt[big] > 0.5
    order = sorted(range(conf.size), key=lambda i: (-conf[i], uvs[i, 1], abs(uvs[i, 0] - intr.cx), pts[i, 2]))
    order = np.array(order[:max_detections], dtype=np.int64)
    return Detections(points=pts[order], uv=uvs[order], confidence=conf[order], end_on=ends[order])


@pytest.mark.parametrize("motion", ["abdadd", "fistopen", "pinch"])
def test_detector_equals_its_reference_implementation(motion: str) -> None:
    # The vectorised ring test, the label statistics from bincounts and the windowing by
    # OpenCV thresholds give exactly the detections of the straightforward implementation.
    intr = default_intrinsics()
    model = default_hand_model()
    found = 0
    for frame in mesh_sequence(motion, 12, seed=7, options=MeshRenderOptions(sensor="tof")):
        pre = preprocess(frame.depth_mm, intr, TrackerConfig())
        for radius, shift in ((160.0, 0.0), (120.0, 25.0)):
            pose = frame.pose.copy()
            pose[0] += shift
            roi, window = hand_roi(model, pose, pre.intrinsics, radius)
            got, ref = detect_fingertips(pre, roi, window), _detect_reference(pre, roi, window)
            found += got.n
            for a, b in ((got.points, ref.points), (got.uv, ref.uv), (got.confidence, ref.confidence),
                         (got.end_on, ref.end_on)):
                np.testing.assert_array_equal(a, b)
    assert found >= 12  # the comparison saw detections


@pytest.mark.parametrize("seed", range(3))
def test_assignment_is_optimal_with_many_detections(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    tips = rng.normal(0.0, 40.0, (5, 3))
    S = 6 + seed
    points = tips[rng.integers(0, 5, S)] + rng.normal(0.0, 25.0, (S, 3))
    points[1] = points[0]  # two identical detections: ties
    det = Detections(points, np.zeros((S, 2)), rng.choice([0.5, 1.0], S), np.zeros(S, bool))
    assigned = assign_detections(tips, det, 30.0)
    used = assigned[assigned >= 0]
    assert len(set(used.tolist())) == used.size
    assert _cost(tips, det, assigned, 30.0) == pytest.approx(_brute_force(tips, det, 30.0))


@pytest.mark.parametrize("shift", [0, 1])
def test_mirrored_frame_gives_the_mirrored_detections(shift: int) -> None:
    # A frame mirrored left-right (u -> W - 1 - u, cx -> W - 1 - cx) is the same hand seen as
    # a left hand: the detector must sample the mirrored pixels and find the mirrored tips,
    # for ROIs of either parity.
    base = default_intrinsics()
    intr = Intrinsics(base.fx, base.fy, 160.0, 120.0, 320, 240)  # principal point on a pixel
    mirrored = Intrinsics(base.fx, base.fy, 319.0 - intr.cx, intr.cy, 320, 240)
    model = default_hand_model()
    found = 0
    for frame in mesh_sequence("abdadd", 3, seed=4, intrinsics=intr):
        pre = preprocess(frame.depth_mm, intr, TrackerConfig())
        prem = preprocess(np.ascontiguousarray(frame.depth_mm[:, ::-1]), mirrored, TrackerConfig())
        roi, window = hand_roi(model, frame.pose, pre.intrinsics, 160.0)
        roi = (roi[0] - shift, roi[1], roi[2], roi[3])
        a = detect_fingertips(pre, roi, window)
        b = detect_fingertips(prem, (320 - roi[2], roi[1], 320 - roi[0], roi[3]), window)
        found += a.n
        assert a.n == b.n
        np.testing.assert_allclose(b.uv, np.column_stack([319.0 - a.uv[:, 0], a.uv[:, 1]]), atol=1e-9)
        np.testing.assert_allclose(b.points, a.points * [-1.0, 1.0, 1.0], atol=1e-9)
        np.testing.assert_array_equal(b.confidence, a.confidence)
        np.testing.assert_array_equal(b.end_on, a.end_on)
    assert found >= 10


def test_median_by_partition_equals_numpys() -> None:
    from hand_sog_tracker.core.salient import _median

    rng = np.random.default_rng(5)
    for n in [1, 2, 3, 4, 7, 10, 999, 1000]:
        for _ in range(10):
            a = np.round(rng.uniform(200.0, 700.0, n)).astype(np.float32)  # with ties
            assert _median(a) == float(np.median(a))
