"""Finger thickness and knuckle span measured in rendered depth at a known pose (core/measure.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import HandShape, default_hand_model, rest_pose
from hand_sog_tracker.core.measure import (
    FINGER_FRACTIONS,
    WidthMeasurement,
    _median,
    measure_widths,
    reference_widths,
    shape_from_widths,
)
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.errors import CalibrationError
from hand_sog_tracker.synth.render import RenderOptions, render_depth
from hand_sog_tracker.synth.sequence import default_intrinsics

INTR = default_intrinsics()


def open_poses() -> list[np.ndarray]:
    """Three open hands, fingers slightly spread, at different places, distances and tilts."""
    poses = []
    places = ((0.0, 380.0, 0.15, 0.0), (-25.0, 430.0, -0.1, 0.3), (20.0, 340.0, 0.25, -0.25))
    for k, (x, z, tilt, roll) in enumerate(places):
        th = rest_pose((x, 20.0, z))
        th[3] += tilt
        th[5] = roll
        th[6 + 4 + 1 :: 4] = np.array([-0.08, 0.0, 0.06, 0.12]) * (1 + k % 2)  # finger abduction
        poses.append(th)
    return poses


def measured(shape: HandShape, right: bool = True, seed: int = 0) -> tuple[float, float, WidthMeasurement]:
    """Factors measured on ToF-like capsule renders of ``shape`` at the true poses."""
    model = default_hand_model(right).scaled(shape)
    rng = np.random.default_rng(seed)
    depths = [render_depth(model, th, INTR, RenderOptions(), rng) for th in open_poses()]
    pres = [preprocess(d, INTR, TrackerConfig()) for d in depths]
    # The poses place the axes with the hand's own length (as the fit does after its first round).
    at = default_hand_model(right).scaled(HandShape(length=shape.length))
    meas = measure_widths([p.depth_mm for p in pres], [p.intrinsics for p in pres], at, open_poses())
    sigma, width = shape_from_widths(meas)
    return sigma, width, meas


@pytest.mark.parametrize(
    ("length", "width", "thickness"), [(1.0, 1.0, 1.0), (0.9, 1.12, 0.88), (1.1, 0.88, 1.12)]
)
def test_measured_factors_are_within_five_percent_of_the_rendered_hand(
    length: float, width: float, thickness: float
) -> None:
    """Width and thickness vary independently (a wide hand with thin fingers and the reverse)."""
    sigma, fitted_width, meas = measured(HandShape(length, width, thickness, thickness))
    print(f"truth W={width} T={thickness}: measured sigma {sigma:.3f} width {fitted_width:.3f}, "
          f"fingers {meas.finger_mm.round(1)} mm, knuckles {meas.knuckle_mm:.1f} mm, palm {meas.palm_mm:.1f} mm")
    assert sigma == pytest.approx(thickness, rel=0.05)
    assert fitted_width == pytest.approx(width, rel=0.05)
    assert np.all(meas.finger_profiles >= 9) and meas.knuckle_frames == 3 and meas.palm_profiles >= 9
    # The palm outline (not used for the factor when the knuckles are seen) agrees too.
    fingers, knuckle, rim = reference_widths()
    assert meas.palm_mm == pytest.approx(knuckle * width + rim * thickness, rel=0.05)


def test_one_frame_gives_the_width_without_knowing_the_spread() -> None:
    """Each frame alone, at its pose with the abduction zeroed (calibrate sets the joints open),
    gives the width factor within 4.5%: the knuckle span is an average over the many profiles
    of :data:`FINGER_FRACTIONS` (with 3 a segment a frame could miss the index or little finger's
    axis and fall back to the palm outline, 6% off)."""
    errors = []
    for shape in (HandShape(1.0, 1.0, 1.0, 1.0), HandShape(0.9, 1.12, 0.88, 0.88), HandShape(1.1, 0.88, 1.12, 1.12)):
        model = default_hand_model(True).scaled(shape)
        at = default_hand_model(True).scaled(HandShape(length=shape.length))
        rng = np.random.default_rng(1)
        for th in open_poses():
            zeroed = th.copy()
            zeroed[6 + 4 + 1 :: 4] = 0.0
            pre = preprocess(render_depth(model, th, INTR, RenderOptions(), rng), INTR, TrackerConfig())
            meas = measure_widths([pre.depth_mm], pre.intrinsics, at, [zeroed])
            assert meas.knuckle_frames == 1 and meas.finger_profiles.sum() >= 2 * len(FINGER_FRACTIONS)
            errors.append(shape_from_widths(meas)[1] / shape.width - 1)
    print("width factor errors %", np.round(100 * np.array(errors), 1))
    assert np.max(np.abs(errors)) < 0.045


def test_left_hand_measures_like_the_right_hand() -> None:
    shape = HandShape(1.0, 1.08, 0.92, 0.92)
    right, left = measured(shape, True)[:2], measured(shape, False)[:2]
    print(f"right {right}, left {left}")
    assert left == pytest.approx(right, rel=0.03)
    assert left[1] == pytest.approx(1.08, rel=0.05)


def test_nothing_measured_without_a_hand_in_view() -> None:
    empty = np.zeros((INTR.height, INTR.width), np.float32)
    meas = measure_widths([empty], INTR, default_hand_model(True), [open_poses()[0]])
    assert np.all(meas.finger_profiles == 0) and np.all(np.isnan(meas.finger_mm))
    assert meas.knuckle_frames == 0 and meas.palm_profiles == 0
    assert all(np.isnan(v) for v in shape_from_widths(meas))
    with pytest.raises(CalibrationError):
        measure_widths([empty, empty], INTR, default_hand_model(True), [open_poses()[0]])


def test_reference_widths_follow_the_default_model() -> None:
    fingers, knuckle, rim = reference_widths()
    model = default_hand_model(True)
    assert knuckle == pytest.approx(model.bases[1, 0] - model.bases[4, 0])  # 57 mm
    assert rim == pytest.approx(2 * 12.5)
    assert fingers.shape == (4,) and np.all((fingers > 12) & (fingers < 22))
    # A scaled model's reference is the default's (the factors are relative to the default model).
    assert np.allclose(reference_widths(model.scaled(HandShape(1.1, 0.9, 1.2, 1.2)))[0], fingers)


def test_the_robust_mean_of_two_clusters_without_a_value_near_their_median_is_nan_without_a_warning() -> None:
    """Run lengths of a finger measured half on its own data and half merged with a surface
    behind it (a wall 120 mm behind the wrist): no value lies within [0.75, 1.33] times the
    median, and there is nothing to average (NumPy would warn about the empty mean)."""
    import warnings

    from hand_sog_tracker.core.measure import _robust_mean

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(_robust_mean([2.67, 2.72, 2.73, 15.0, 13.3, 14.7]))
        assert _robust_mean([10.0, 10.5, 30.0]) == pytest.approx(10.25)
        assert np.isnan(_robust_mean([]))


def test_the_profile_median_is_numpys_median() -> None:
    """The fit's per-profile median (a sorted Python list: cheaper than NumPy's call on a few
    dozen samples) gives NumPy's value bit for bit: odd and even counts, ties, whole and
    fractional depths, the order of the samples."""
    rng = np.random.default_rng(49)
    for n in range(1, 40):
        for _ in range(20):
            z = rng.uniform(250.0, 700.0, n)
            if rng.random() < 0.5:
                z = np.round(z)  # (ties: depth in whole millimetres)
            assert _median(z.tolist()) == float(np.median(z))
            assert _median(z[::-1].tolist()) == float(np.median(z))
