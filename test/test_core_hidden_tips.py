"""A curled fingertip hidden against the palm costs no missing detection (issue 11)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from hand_sog_tracker.core.articulations import CLOSED, FINGER_CURLED
from hand_sog_tracker.core.depth_sog import preprocess
from hand_sog_tracker.core.hand_model import chain_slice, default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips, global_rotation
from hand_sog_tracker.core.objective import Objective
from hand_sog_tracker.core.optimizer import OptimizeResult, maximise
from hand_sog_tracker.core.rotations import euler_from_matrix, rot_x
from hand_sog_tracker.core.salient import Detections, assign_detections
from hand_sog_tracker.core.search import Frame, candidates, score
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.synth.render import RenderOptions, render_depth
from hand_sog_tracker.synth.sequence import default_intrinsics


def _brute_force(tips: np.ndarray, det: Detections, lam: float, tip_lam: np.ndarray) -> float:
    cost = np.linalg.norm(tips[:, None] - det.points[None], axis=-1)
    best = np.inf
    for choice in itertools.product(range(-1, det.n), repeat=tips.shape[0]):
        used = [s for s in choice if s >= 0]
        if len(used) != len(set(used)):
            continue
        c = sum(cost[t, s] if s >= 0 else tip_lam[t] for t, s in enumerate(choice))
        best = min(best, c + lam * sum(det.confidence[s] for s in range(det.n) if s not in used))
    return best


@pytest.mark.parametrize("seed", range(4))
def test_assignment_with_per_fingertip_costs_is_optimal(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tips = rng.normal(0.0, 40.0, (5, 3))
    S = int(rng.integers(1, 5))
    det = Detections(
        tips[rng.integers(0, 5, S)] + rng.normal(0.0, 25.0, (S, 3)),
        np.zeros((S, 2)), rng.uniform(0.2, 1.0, S), np.zeros(S, bool),
    )
    tip_lam = rng.choice([0.0, 10.0, 30.0], 5)
    a = assign_detections(tips, det, 30.0, tip_lam)
    got = sum(np.linalg.norm(tips[t] - det.points[s]) if s >= 0 else tip_lam[t] for t, s in enumerate(a))
    got += 30.0 * sum(det.confidence[s] for s in range(S) if s not in a)
    assert got == pytest.approx(_brute_force(tips, det, 30.0, tip_lam))


def _curled_middle_ring(theta: np.ndarray) -> np.ndarray:
    x = theta.copy()
    for c in (2, 3):
        x[chain_slice(c)] = FINGER_CURLED
    return x


def test_curled_fingers_facing_the_camera_cost_no_missing_detection() -> None:
    lam = score.ASSIGN_LAMBDA_MM
    open_hand = rest_pose()  # palm toward the camera
    np.testing.assert_array_equal(score.tip_lambdas(open_hand), [lam] * 5)
    curled = _curled_middle_ring(open_hand)
    expected = [lam, lam, score.HIDDEN_TIP_LAMBDA * lam, score.HIDDEN_TIP_LAMBDA * lam, lam]
    np.testing.assert_allclose(score.tip_lambdas(curled), expected)
    # The back of the hand toward the camera: a curled tip lies under the hand, hidden too
    # (issue 46); an open one is not.
    back = curled.copy()
    back[3:6] = 0.0  # identity rotation: the palm faces away from the camera
    np.testing.assert_allclose(score.tip_lambdas(back), expected)
    back_open = open_hand.copy()
    back_open[3:6] = 0.0
    np.testing.assert_array_equal(score.tip_lambdas(back_open), [lam] * 5)
    # Edge-on (the palm normal across the view): no discount.
    edge = curled.copy()
    edge[3:6] = (0.0, np.pi / 2, 0.0)
    assert abs(global_rotation(edge)[2, 2]) < score.HIDDEN_PALM_COS
    np.testing.assert_array_equal(score.tip_lambdas(edge), [lam] * 5)


def test_two_model_tips_on_one_seen_tip_score_worse_than_a_curled_finger() -> None:
    """Finger counting: index extended, middle curled.  A model whose middle lies extended
    beside the index (one seen tip for two model tips) must cost more in the assignment than
    the model with the middle curled where it is, as neither middle tip has a detection."""
    tracker = Tracker()
    right = _curled_middle_ring(rest_pose())
    wrong = right.copy()
    wrong[chain_slice(2)] = right[chain_slice(1)]  # middle extended like the index
    wrong[chain_slice(2).start + 1] = -0.2  # and turned toward it
    tips = fingertips(tracker.model, right)
    seen = tips[[0, 1]] + 2.0  # thumb and index detected
    det = Detections(seen, np.zeros((2, 2)), np.ones(2), np.zeros(2, bool))
    cost = [score.assignment_cost(tracker.model, x, det, hidden_tips=True) for x in (wrong, right)]
    assert cost[0] > cost[1] + 0.2


def _shift_sides(tracker: Tracker, fit: np.ndarray, det: Detections) -> list[int]:
    """The sides of the shift proposal's candidates for a frame fitted at ``fit`` (26,)."""
    res = OptimizeResult(fit, 0.0, 0, True, 0, "", np.zeros(1))
    frame = candidates.Frame(tracker.model, res, None, None, det, tracker._limits())  # type: ignore[arg-type]
    out = []
    for c in candidates.SHIFT.generate(frame):
        side = [s for s in (1, -1) if np.array_equal(c.x0, candidates.shifted(fit, s))]
        out += side
    return out


@pytest.mark.parametrize("side", [1, -1])
def test_the_shift_goes_to_the_side_the_detections_point_to(side: int) -> None:
    """The fingers of the fit sit one place over from the seen ones (finger counting: index,
    middle and ring extended where index and middle are).  The shift proposal takes the side
    whose shifted pose meets the detections; without detections none says where the fingers
    are, and nothing is proposed."""
    tracker = Tracker()
    fit = rest_pose()
    for c in (3, 4):
        fit[chain_slice(c)] = FINGER_CURLED
    fit[chain_slice(2 if side == 1 else 1)] = FINGER_CURLED  # 1 1 0 0 or 1 0 1 0 (index .. little)
    truth = candidates.shifted(fit, side)
    seen = [0] + [c for c in range(1, 5) if truth[chain_slice(c)][2] < 0.5]  # thumb, extended fingers
    n = len(seen)
    det = Detections(fingertips(tracker.model, truth)[seen], np.zeros((n, 2)), np.ones(n), np.zeros(n, bool))
    assert side in _shift_sides(tracker, fit, det)  # (both when a detection is unexplained)
    assert _shift_sides(tracker, fit, Detections.empty()) == []


@pytest.mark.parametrize("tilt", [0.3, 0.45])
def test_a_fist_seen_from_the_back_scores_above_its_fingers_pointing_away(tilt: float) -> None:
    """Issue 46: from the back (the camera above and behind the hand, tilted by ``tilt`` rad) a
    fist's fingers and fingers bent at the knuckles only, pointing away, hide behind the same
    knuckles: the depth gives both about the same value.  The fist's tips lie under the hand,
    where the detector cannot see them, so they cost no missing detection; the straight fingers'
    tips do, and the fist scores higher (by more than a curl's margin)."""
    truth = rest_pose()
    truth[3:6] = euler_from_matrix(rot_x(tilt))  # the back of the hand toward the camera
    truth[6:] = CLOSED
    away = truth.copy()
    for c in range(1, 5):
        away[chain_slice(c)] = (1.4, 0.0, 0.0, 0.0)  # bent at the MCP, straight beyond
    tracker = Tracker(TrackerConfig())
    intr = default_intrinsics()
    pre = preprocess(render_depth(default_hand_model(), truth, intr, RenderOptions()), intr, tracker.config)
    data, det, sil = tracker._data_near(pre, truth)
    obj = Objective(tracker.model, data, tracker.config, targets=tracker._targets(truth, det), silhouette=sil)
    bounds = tracker._limits()
    fist, wrong = (maximise(obj, x, iterations=7, bounds=bounds) for x in (truth, away))
    frame = Frame(tracker.model, wrong, obj, data, det, bounds)
    off = np.linalg.norm(fingertips(tracker.model, wrong.x) - fingertips(tracker.model, truth), axis=1)
    assert global_rotation(truth)[2, 2] > score.HIDDEN_PALM_COS and det.n > 0 and off[2:4].min() > 40.0
    assert frame.score(fist.x) > frame.score(wrong.x) + candidates.CURL_MARGIN
