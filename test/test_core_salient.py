"""Fingertip detection and the optimal assignment of detections to fingertips (seed 001)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import default_hand_model
from hand_sog_tracker.core.salient import Detections, assign_detections, detect_fingertips
from hand_sog_tracker.core.tracker import hand_roi
from hand_sog_tracker.core.types import TrackerConfig
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
