"""The tracker on real depth frames (``../shared/realdata``; skipped where it is absent).

RealSense frames: the hand/forearm masks of the data, and our own fingertip labels
(``data/realsense_fingertips.json``).  One Kinect frame of the NYU hand pose data set, with
its own joint labels: a hand at arm's length (0.74 m) in front of the body.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core.overlay import draw_overlay
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import Intrinsics, TrackerStatus
from hand_sog_tracker.tools.real_frames import Variant, labelled_frame, static_tip_errors

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
REALSENSE = REALDATA / "realsense-user1"
NYU = REALDATA / "nyu-test-frame1"
#: From the data's source (see ../shared/realdata/README.md); equal to helpers.INTR today but
#: bound to the recorded camera, so kept here.
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


LABELS = Path(__file__).resolve().parent / "data" / "realsense_fingertips.json"


def _static_tip_errors(
    frame: int, mirror: bool, shift: tuple[int, int] = (0, 0), withhold: bool = True
) -> np.ndarray:
    """Fingertip errors (5,) mm against the labels after tracking the frame 10 times (a static
    sequence; ``tools/real_frames.py``); the hand must be tracked.  ``mirror`` flips the image
    left-right (the same hand seen as a left hand); ``shift``: (du, dv) px, the image and labels
    moved by whole pixels (np.roll); ``withhold`` False scores the fit of a hand not reported."""
    labels = json.loads(LABELS.read_text())
    depth, intr, truth = labelled_frame(REALSENSE, labels, frame, mirror, Variant(du=shift[0], dv=shift[1]))
    err = static_tip_errors(depth, intr, truth, right_hand=not mirror, withhold=withhold)
    assert err is not None
    return err


# Frames 2, 4 and 7 (a finger curled toward the camera, crossed fingers, a fist seen from the
# back) are not tracked with every fingertip within 15 mm yet: see the README's known limitations.
@pytest.mark.parametrize("mirror", [False, True])
@pytest.mark.parametrize("frame", [1, 3, 5, 6, 8])
def test_labelled_fingertips_are_within_15_mm(frame: int, mirror: bool) -> None:
    err = _static_tip_errors(frame, mirror)
    assert err.max() < 15.0, err.round(1)


@pytest.mark.parametrize("mirror", [False, True])
def test_finger_curled_toward_the_camera_is_found(mirror: bool) -> None:
    """Frame 2: the middle finger points at the camera in front of the palm.  The unexplained
    end-on detection pulls the model's middle finger onto it (before the finger-only pull the
    model's middle finger lay on the ring finger's data, 60 mm off).  Its tip is 12.2 mm off
    (12-17 mm on copies shifted by a pixel or 3 mm in depth; before a less confident detection
    far from every model fingertip counted as unexplained too, four of those seven copies
    scored 14-19 mm mean error)."""
    err = _static_tip_errors(2, mirror)
    assert err.max() < 15.0, err.round(1)


@pytest.mark.parametrize("shift", [(1, 0), (-1, 0), (0, 1), (0, -1)])
def test_a_thin_fingers_faint_tip_far_from_the_model_is_found(shift: tuple[int, int]) -> None:
    """Frame 3 (ring finger curled) moved by a pixel: the extended little finger's tip is a small
    detection region (confidence 0.49), and the model's little finger lay curled on the ring
    finger's data 52 mm from it, the model's ring finger extended beside the middle finger (45
    and 37 mm mean error for (1, 0) and (0, -1) while only detections of confidence 0.5 or more
    counted as unexplained; restarts.FAR_UNEXPLAINED_MM).  (1, 0) was a known regression of the
    one batched search (its little finger left curled, 21 mm) until the edge-on start poses
    (issue 47) gave its new track another start."""
    err = _static_tip_errors(3, False, shift)
    assert err.max() < 15.0, err.round(1)


@pytest.mark.parametrize(("frame", "bound_mm"), [(4, 12.0), (7, 25.0)])
def test_crossed_fingers_and_a_fist_from_the_back_keep_their_side(frame: int, bound_mm: float) -> None:
    """Frames 4 and 7 are not within 15 mm per fingertip (README, known limitations), but the
    hand is found the right way round: mean 7.7 and 19.4 mm.  (Scoring initialisation's
    candidates with the hidden-tip cost of the tracked frames turned them palm-first: 32 and
    80 mm.)  The fist of frame 7 is not reported (below): its fit is scored."""
    err = _static_tip_errors(frame, False, withhold=False)
    assert err.mean() < bound_mm, err.round(1)


@pytest.mark.xfail(strict=True, reason="a new track waits for a finger seen to end; frame 7's fist shows none")
def test_a_fist_seen_from_the_back_is_reported() -> None:
    """Known limitation of the hand check (doc/design/hand_check.md): a new track is reported
    from its first frame with a finger seen to end, and a single image of a fist never shows
    one.  Strict: the mark fails the suite once the fist is reported, so it cannot hide a fix."""
    labels = json.loads(LABELS.read_text())
    depth, intr, truth = labelled_frame(REALSENSE, labels, 7, False, Variant())
    assert static_tip_errors(depth, intr, truth) is not None


@pytest.mark.skipif(not NYU.is_dir(), reason="../shared/realdata/nyu-test-frame1 is not here")
def test_kinect_hand_at_arm_length_is_tracked_with_the_default_depth_window() -> None:
    """NYU test frame 1 (Kinect, 640x480, an open right hand at 0.74 m, the body behind it):
    with the default parameters the hand is found and every fingertip is within 15 mm of the
    data set's labels (with the former 600 mm window nothing was found)."""
    bgr = cv2.imread(str(NYU / "depth_1_0000001.png"), cv2.IMREAD_UNCHANGED)
    depth = bgr[:, :, 1].astype(np.float32) * 256.0 + bgr[:, :, 0]  # depth_mm = G * 256 + B
    intr = Intrinsics(588.04, 587.08, 320.0, 240.0, 640, 480)
    u, v, d = (np.loadtxt(NYU / f"joint_1_{k}_row1.csv", delimiter=",") for k in "uvd")
    tips = [24, 18, 12, 6, 0]  # the data set's fingertip joints, thumb .. little
    truth = intr.backproject(np.c_[u[tips], v[tips]], d[tips])
    tracker = Tracker()
    results = [tracker.process(depth, intr) for _ in range(10)]  # a static sequence
    assert all(r.status is TrackerStatus.TRACKING for r in results), [r.status for r in results]
    err = np.linalg.norm(results[-1].fingertips_mm - truth, axis=1)
    assert err.max() < 15.0, err.round(1)
