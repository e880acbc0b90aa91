"""The silhouette distance map and its window."""

from __future__ import annotations

import numpy as np

from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import default_hand_model
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.silhouette import silhouette, silhouette_term
from hand_sog_tracker.core.tracker import hand_roi
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence


def test_window_map_gives_the_full_image_values_near_the_hand() -> None:
    intr = default_intrinsics()
    frame = next(synthetic_sequence("abdadd", 1, intrinsics=intr, seed=2))
    pre = preprocess(frame.depth_mm, intr, TrackerConfig())
    model = default_hand_model()
    roi, window = hand_roi(model, frame.pose, pre.intrinsics, 160.0)
    full = silhouette(pre, window)
    part = silhouette(pre, window, roi)
    assert part.distance.size < full.distance.size and part.distance.dtype == np.float32
    u0, v0 = part.origin
    h, w = part.distance.shape
    np.testing.assert_array_equal(part.distance[:, :] == 0, full.distance[v0 : v0 + h, u0 : u0 + w] == 0)
    # The true pose lies on the hand (small cost), a pose moved 30 mm sideways does not.
    P = gaussian_centres(model, frame.pose)
    moved = P + np.array([30.0, 0.0, 0.0])
    for sil in (full, part):
        assert silhouette_term(sil, P, None, 1.0) < 0.05 * silhouette_term(sil, moved, None, 1.0)
    assert silhouette_term(part, moved, None, 1.0) == silhouette_term(full, moved, None, 1.0)
