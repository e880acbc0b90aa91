"""The tracker on real RealSense depth frames (``../shared/realdata``; skipped where it is absent).

The frames have no joint labels, only a hand/forearm mask: an open hand must be tracked with
every fingertip on the hand's own pixels, at the hand's depth, and spread across the hand.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core.overlay import draw_overlay
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import Intrinsics, TrackerStatus

REALSENSE = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "realsense-user1"
#: From the data's source (see ../shared/realdata/README.md).
INTR = Intrinsics(287.26, 287.26, 160.0, 120.0, 320, 240)

pytestmark = pytest.mark.skipif(not REALSENSE.is_dir(), reason="../shared/realdata is not here")


@pytest.mark.parametrize("frame", [1, 6])
def test_open_hand_fingertips_lie_on_the_hand(frame: int, tmp_path: Path) -> None:
    depth = cv2.imread(str(REALSENSE / str(frame) / "depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
    mask = cv2.imread(str(REALSENSE / str(frame) / "mask.png"), cv2.IMREAD_UNCHANGED) > 0
    tracker = Tracker()
    results = [tracker.process(depth, INTR) for _ in range(10)]  # a static sequence
    res = results[-1]
    assert all(r.status is TrackerStatus.TRACKING for r in results)
    assert res.fingertips_mm is not None and res.pose is not None
    cv2.imwrite(str(tmp_path / f"realsense_{frame}.png"), draw_overlay(depth, INTR, tracker.model, res.pose))
    # A fingertip centre sits about a finger radius inside the skin: allow 4 px around the mask.
    near_hand = cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    uv = np.round(INTR.project(res.fingertips_mm)).astype(int)
    assert np.all((uv >= 0) & (uv < [INTR.width, INTR.height])), uv
    assert near_hand[uv[:, 1], uv[:, 0]].all(), uv
    patch = [depth[max(v - 3, 0) : v + 4, max(u - 3, 0) : u + 4] for u, v in uv]
    surface = np.array([np.median(p[p > 0]) if (p > 0).any() else np.nan for p in patch])
    assert np.all(np.abs(res.fingertips_mm[:, 2] - surface) < 30.0), (res.fingertips_mm[:, 2], surface)
    # Open hand: the five tips are distinct, at least 12 mm apart from each other.
    d = np.linalg.norm(res.fingertips_mm[:, None] - res.fingertips_mm[None], axis=-1)
    assert d[np.triu_indices(5, 1)].min() > 12.0, d.round(0)
