"""Calibration of the four scale factors (paper 000, sec. 5.4) on rendered hands of known size."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.core.calibration import _draw_skin, calibrate, shape_score
from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import HandShape, default_hand_model
from hand_sog_tracker.core.kinematics import gaussian_centres
from hand_sog_tracker.core.tracker import Tracker, hand_roi
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import CalibrationError
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence

INTR = default_intrinsics()


def user_hand(length: float, width: float) -> HandShape:
    """A user's hand: finger and palm thickness follow the overall size."""
    size = float(np.sqrt(length * width))
    return HandShape(length=length, width=width, depth=size, sigma=size)


def open_hand_frames(shape: HandShape, seed: int, n: int = 3) -> list[np.ndarray]:
    return [f.depth_mm for f in synthetic_sequence("abdadd", n, INTR, shape=shape, seed=seed)]


@pytest.mark.parametrize(("length", "width", "seed"), [(0.85, 0.9, 1), (1.15, 1.1, 2)])
def test_scaled_hands_are_fitted_within_five_percent(length: float, width: float, seed: int) -> None:
    truth = user_hand(length, width)
    res = calibrate(open_hand_frames(truth, seed), INTR, TrackerConfig(), default_hand_model(True))
    print(f"truth L={length} W={width}: fitted {res.shape}, score {res.energy_before:.3f} -> "
          f"{res.energy_after:.3f} in {res.seconds:.2f} s")
    assert res.shape.length == pytest.approx(length, rel=0.05)
    assert res.shape.width == pytest.approx(width, rel=0.05)
    assert res.energy_after > res.energy_before and res.seconds > 0
    assert res.model.shape == res.shape and res.pose.shape == (26,)


def test_tracking_error_is_lower_after_calibration() -> None:
    truth = user_hand(1.15, 1.1)
    fitted = calibrate(open_hand_frames(truth, 4), INTR, TrackerConfig(), default_hand_model(True)).model
    errors = {}
    for name, model in (("default", default_hand_model(True)), ("calibrated", fitted)):
        tracker = Tracker(TrackerConfig(), model)
        per_frame = []
        for f in synthetic_sequence("fingercount", 45, INTR, shape=truth, seed=5):
            res = tracker.process(f.depth_mm, INTR)
            assert res.fingertips_mm is not None
            per_frame.append(np.linalg.norm(res.fingertips_mm - f.fingertips_mm, axis=1).mean())
        errors[name] = float(np.mean(per_frame))
    print(f"mean fingertip error on a 1.15 x 1.1 hand: {errors}")
    assert errors["calibrated"] < errors["default"]


def test_score_is_highest_for_the_true_shape_at_the_true_pose() -> None:
    truth = user_hand(1.1, 0.92)
    frame = next(iter(synthetic_sequence("abdadd", 1, INTR, shape=truth, seed=6)))
    pre = preprocess(frame.depth_mm, INTR, TrackerConfig())
    base = default_hand_model(True)
    roi, _ = hand_roi(base.scaled(truth), frame.pose, INTR, 160.0)
    best = shape_score(base.scaled(truth), frame.pose, pre, roi)
    assert best > 0.85
    for other in (HandShape(), user_hand(1.1, 1.05), user_hand(1.0, 0.92), user_hand(1.2, 0.92)):
        assert shape_score(base.scaled(other), frame.pose, pre, roi) < best


def test_drawn_skin_is_as_wide_as_the_finger() -> None:
    """A straight finger seen face-on is drawn 2 r f / z pixels wide (OpenCV's half-pixel rim removed)."""
    model = default_hand_model(True)
    theta = np.zeros(26)
    theta[:3] = (0.0, 60.0, 400.0)
    theta[3] = np.pi
    depth = _draw_skin(model, theta, INTR, (0, 0, INTR.width, INTR.height))
    tip = model.tip_index[2]  # middle finger's distal Gaussian
    centre = gaussian_centres(model, theta)[tip]
    col, row = (int(round(c)) for c in INTR.project(centre[None])[0])
    covered = np.isfinite(depth[row])
    left = col - np.argmin(covered[col::-1]) + 1
    right = col + np.argmin(covered[col:]) - 1
    expected = 2 * model.g_sigmas[tip] * INTR.fx / centre[2]
    assert abs((right - left + 1) - expected) <= 1.5
    assert depth[row, col] == pytest.approx(centre[2] - model.g_sigmas[tip], abs=3.0)


def test_failures_are_calibration_errors() -> None:
    config, model = TrackerConfig(), default_hand_model(True)
    with pytest.raises(CalibrationError, match="no depth frames"):
        calibrate([], INTR, config, model)
    with pytest.raises(CalibrationError, match="no hand in view"):
        calibrate([np.zeros((INTR.height, INTR.width), np.float32)], INTR, config, model)
    with pytest.raises(CalibrationError, match="unusable depth frame"):
        calibrate([np.zeros((10, 10), np.float32)], INTR, config, model)
