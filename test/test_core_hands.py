"""The multi-hand tracker (core/hands.py) on the shipped two-hand dev bag and its mirror image."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.core.depth_sog import Preprocessed
from hand_sog_tracker.core.hand_model import chain_slice, default_hand_model, rest_pose
from hand_sog_tracker.core.hands import (
    COVERED_MM,
    FOREARM_RADIUS_MM,
    OWN_MARGIN_MM,
    SAME_HAND_MM,
    SHARED_VOLUME,
    MultiHandTracker,
    _palm,
    _Slot,
    _theirs,
    hidden_by,
    shared_volume,
    skin_distance,
)
from hand_sog_tracker.core.kinematics import gaussian_centres, global_rotation, posed_centres
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools.bagio import BagTopics, DepthBagReader
from hand_sog_tracker.tools.twohand_bags import read_hand_truth

APART = Path(__file__).resolve().parents[1] / "bags" / "twohands_dev" / "apart"
CLAP = APART.parent / "clap"


def _frames(n: int, mirror: bool = False):
    """The first ``n`` frames of the dev 'apart' bag: (depth mm, intrinsics, truth tips per label);
    ``mirror``: the image mirrored left-right (a right hand becomes a left one)."""
    truth = read_hand_truth(APART)
    with DepthBagReader(APART, BagTopics(), require_truth=False) as reader:
        for f in reader.frames():
            if f.index >= n:
                return
            depth, intr = f.depth_mm, f.intrinsics
            gt = {s: truth[s][f.stamp_ns].fingertips_mm.copy() for s in ("left", "right")}
            if mirror:
                depth = np.ascontiguousarray(depth[:, ::-1])
                intr = Intrinsics(intr.fx, intr.fy, intr.width - 1 - intr.cx, intr.cy, intr.width, intr.height)
                for g in gt.values():
                    g[:, 0] *= -1.0
                gt = {"left": gt["right"], "right": gt["left"]}
            yield depth, intr, gt


@pytest.mark.parametrize("mirror", [False, True])
def test_two_hands_are_tracked_each_with_its_handedness(mirror: bool) -> None:
    """Both hands get their own track, labelled by the data (the mirror image swaps the labels
    with the hands), each within 12 mm of its hand, and no label moves to the other hand."""
    mt = MultiHandTracker(TrackerConfig(), max_hands=2)
    on: dict[str, set[str]] = {"left": set(), "right": set()}
    reported = 0
    for depth, intr, gt in _frames(8, mirror):
        out = mt.process(depth, intr)
        for h in out.hands:
            err = {s: float(np.linalg.norm(h.result.fingertips_mm - g, axis=1).mean()) for s, g in gt.items()}
            hand = min(err, key=err.get)
            on[h.handedness].add(hand)
            assert hand == h.handedness, f"label {h.handedness} on the {hand} hand ({err})"
            assert err[hand] < 12.0
        reported = len(out.hands)
    assert reported == 2
    assert on == {"left": {"left"}, "right": {"right"}}
    assert len({tid for _, tid in mt.tracks}) == 2


def test_one_hand_with_fixed_handedness_answers_as_the_one_hand_tracker() -> None:
    """max_hands 1 with a fixed handedness is today's tracker, pose for pose."""
    mt = MultiHandTracker(TrackerConfig(), max_hands=1, handedness="right")
    one = Tracker(TrackerConfig())
    for depth, intr, _ in _frames(3):
        a, b = mt.process(depth, intr), one.process(depth, intr)
        assert b.status is TrackerStatus.TRACKING and len(a.hands) == 1
        np.testing.assert_array_equal(a.hands[0].result.pose, b.pose)


def test_skin_distance_of_the_model_and_its_forearm() -> None:
    model = default_hand_model()
    theta = rest_pose((0.0, 0.0, 400.0))
    centres = gaussian_centres(model, theta)
    # (a centre lies at least its own radius inside the skin; a neighbour may cover it more)
    assert np.all(skin_distance(model, theta, centres) <= -model.g_sigmas + 1e-3)
    tip = centres[model.tip_index[2]] + (model.tip_radii[2] + 5.0) * global_rotation(theta)[:, 1]
    assert skin_distance(model, theta, tip[None])[0] == pytest.approx(5.0, abs=0.5)
    back = -global_rotation(theta)[:, 1]  # from the wrist toward the elbow
    arm = theta[:3] + 150.0 * back
    d = skin_distance(model, theta, np.array([arm, arm + np.array([0.0, 0.0, 200.0])]))
    assert d[0] == pytest.approx(-FOREARM_RADIUS_MM)
    assert d[1] > 100.0


def _sphere_depth(model, theta, intr: Intrinsics) -> np.ndarray:
    """A depth image (mm) of the model's Gaussians as spheres seen from the camera (nearest
    surface per pixel), without noise: the hand in front of a scene."""
    depth = np.zeros((intr.height, intr.width), np.float32)
    vv, uu = np.mgrid[0 : intr.height, 0 : intr.width]
    for c, s in zip(gaussian_centres(model, theta), model.g_sigmas):
        u, v = intr.fx * c[0] / c[2] + intr.cx, intr.fy * c[1] / c[2] + intr.cy
        r2 = ((uu - u) ** 2 + (vv - v) ** 2) * (c[2] / intr.fx) ** 2
        on = r2 < s * s
        z = c[2] - np.sqrt(np.maximum(s * s - r2, 0.0))
        depth[on] = np.where((depth[on] == 0) | (z[on] < depth[on]), z[on], depth[on])
    return depth


def test_hidden_by_another_hand() -> None:
    """A sphere behind another hand's skin (its pixel shows that hand far in front) is hidden;
    one beside the hand, one in front of it, or one behind a surface that is no hand is not."""
    intr = Intrinsics(300.0, 300.0, 160.0, 120.0, 320, 240)
    model = default_hand_model()
    front = rest_pose((0.0, 0.0, 350.0))
    depth = _sphere_depth(model, front, intr)
    palm = gaussian_centres(model, front)[0]
    pre = Preprocessed(depth_mm=depth, intrinsics=intr, decimation=1)
    points = np.array([
        palm * (500.0 / palm[2]),  # on the palm's line of sight, 150 mm behind it
        palm * (500.0 / palm[2]) + np.array([150.0, 0.0, 0.0]),  # beside the hand
        palm * (330.0 / palm[2]),  # in front of the palm
    ])
    radii = np.full(3, 10.0)
    np.testing.assert_array_equal(hidden_by(pre, [(model, front)], points, radii), [True, False, False])
    # (the same surface, but the hand said to be elsewhere: an occluder that is no hand)
    away = rest_pose((300.0, 0.0, 350.0))
    assert not hidden_by(pre, [(model, away)], points, radii).any()
    assert not hidden_by(pre, [], points, radii).any()


def test_held_joints_keep_their_start_in_the_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    """``Tracker.held`` holds the joints it names at the fit's start pose; without it (None)
    the same frame's fit moves them (the search's candidates left out: the fit answers)."""
    import hand_sog_tracker.core.tracker as tracker_module

    depth, intr, _ = next(_frames(1))
    one = Tracker(TrackerConfig())
    first = one.process(depth, intr)
    assert first.pose is not None
    thumb = np.zeros(26, dtype=bool)
    thumb[chain_slice(0)] = True
    start = first.pose.copy()
    start[chain_slice(0)] += 0.2  # (off the data: a free fit would move it back)
    from hand_sog_tracker.core.depth_sog import preprocess

    pre = preprocess(depth, intr, TrackerConfig())
    monkeypatch.setattr(tracker_module, "search", lambda frame, proposals: (frame.fit, None))
    fits, proposals = {}, {}
    for name, held in (("free", None), ("held", lambda theta: thumb)):
        t = Tracker(TrackerConfig(), one.model)
        t.start_at(start)
        t.held = held
        fits[name] = t.process_preprocessed(pre).pose
        proposals[name] = t.last_proposal
    assert fits["held"] is not None and fits["free"] is not None
    assert proposals["held"] is None  # (the answer is the fit's)
    np.testing.assert_array_equal(fits["held"][chain_slice(0)], start[chain_slice(0)])
    assert not np.array_equal(fits["held"][:6], start[:6])  # (the rest is fitted)
    assert np.abs(fits["free"][chain_slice(0)] - start[chain_slice(0)]).max() > 0.05


def test_invalid_arguments_are_refused() -> None:
    with pytest.raises(InputError):
        MultiHandTracker(max_hands=3)
    with pytest.raises(InputError):
        MultiHandTracker(handedness="both")


def test_two_trials_are_decided_together_once_the_pairs_preference_leads_by_pair_lead() -> None:
    """Two hands in their trials at once are decided together, with different labels, once the
    pair's summed preference exceeds ``PAIR_LEAD`` (below ``TRIAL_LEAD``); not before."""
    from hand_sog_tracker.core.hands import PAIR_LEAD, TRIAL_LEAD, _Slot
    from hand_sog_tracker.core.types import TrackResult

    def result() -> TrackResult:
        return TrackResult(TrackerStatus.TRACKING, rest_pose(), np.zeros((5, 3)), np.zeros((21, 3)), 0.6, 0.0, 10, {})

    def trials(lead_a: float, lead_b: float) -> MultiHandTracker:
        mt = MultiHandTracker(TrackerConfig(), max_hands=2)
        for k, lead in enumerate((lead_a, lead_b)):
            # (both tracks led so far by their left model: the track's tracker is the left one)
            main, alt = Tracker(TrackerConfig(right_hand=False)), Tracker(TrackerConfig(right_hand=True))
            mt._slots.append(_Slot(main, "left", k, result(), alt, result(), lead, 3))
        return mt

    assert PAIR_LEAD < TRIAL_LEAD
    # Track 1 prefers left more than track 0 does: the pair says track 0 right, track 1 left.
    mt = trials(0.01, 0.01 + 0.5 * (PAIR_LEAD + TRIAL_LEAD))
    mt._decide()
    assert [(s.track_id, s.side, s.alt is None) for s in mt._slots] == [(0, "right", True), (1, "left", True)]
    assert mt._slots[0].tracker.model.right and not mt._slots[1].tracker.model.right
    # A preference within PAIR_LEAD leaves both on trial.
    mt = trials(0.01, 0.01 + 0.5 * PAIR_LEAD)
    mt._decide()
    assert all(s.alt is not None for s in mt._slots)


@pytest.mark.parametrize("kind", ["nohand_head", "nohand_objects"])
def test_no_hand_is_reported_on_a_scene_without_a_hand(kind: str) -> None:
    """The hand decision gates every hand of the multi-hand tracker as it gates the one-hand
    tracker: a head and torso, or cups and a bottle, are not reported as hands."""
    from hand_sog_tracker.synth.scenes import scene_frames
    from hand_sog_tracker.synth.sequence import default_intrinsics

    intr = default_intrinsics()
    mt = MultiHandTracker(TrackerConfig(), max_hands=2)
    reported = [len(mt.process(f.depth_mm, intr).hands) for f in scene_frames(kind, 8, intr, seed=2)]
    assert reported == [0] * 8


def test_a_withheld_hand_keeps_its_decision(monkeypatch: pytest.MonkeyPatch) -> None:
    """A labelled track that its hand gate withholds is not among the hands, and its gate's
    decision is in ``withheld`` under its label (the node publishes its confidence)."""
    from dataclasses import replace

    from hand_sog_tracker.core.handcheck import HandGate
    from hand_sog_tracker.core.types import HandDecision

    mt = MultiHandTracker(TrackerConfig(), max_hands=2)
    frames = list(_frames(9))
    for depth, intr, _ in frames[:8]:
        out = mt.process(depth, intr)
    assert {h.handedness for h in out.hands} == {"left", "right"}
    doubt = HandDecision(False, 0.07, np.full(5, 0.2), None)
    gate = HandGate.gate

    def withhold_right(self, tracker, depth_mm, intrinsics, model, result, **kw):  # type: ignore[no-untyped-def]
        answer = gate(self, tracker, depth_mm, intrinsics, model, result, **kw)
        if tracker.side != "right":
            return answer
        return replace(answer, status=TrackerStatus.NO_HAND, pose=None, fingertips_mm=None, hand=doubt)

    monkeypatch.setattr(HandGate, "gate", withhold_right)
    out = mt.process(*frames[8][:2])
    assert [h.handedness for h in out.hands] == ["left"]
    assert out.withheld == {"right": doubt}


def _slot(side: str, pose: np.ndarray, track_id: int) -> _Slot:
    """A live track of the ``side`` model last tracked at ``pose`` (26,)."""
    tracker = Tracker(TrackerConfig(right_hand=side == "right"), default_hand_model(right=side == "right"))
    tracker.start_at(pose)
    return _Slot(tracker, side, track_id)


def test_two_hands_in_contact_are_not_one_hand() -> None:
    """A right and a left hand turned edge-on, back to back, their skins touching (no sphere of
    one inside the other): the palm centres are nearer than SAME_HAND_MM, but the two models do
    not share a volume, so both tracks are kept.  Two fits of one hand (moved 5 mm, or the
    mirrored model turned half a turn about the long axis) are one hand."""
    right, left = default_hand_model(), default_hand_model(right=False)
    xr = rest_pose((0.0, 0.0, 450.0))
    xr[4] = np.pi / 2
    xl = rest_pose((0.0, 0.0, 450.0))
    xl[4] = -np.pi / 2
    cr = posed_centres(right, xr)
    for dx in np.arange(0.0, 80.0, 1.0):  # (the left hand moved away until the skins just touch)
        x = xl.copy()
        x[0] -= dx
        gap = np.linalg.norm(cr[:, None] - posed_centres(left, x)[None], axis=2)
        if (gap - right.g_sigmas[:, None] - left.g_sigmas[None, :]).min() >= 0.0:
            break
    assert np.linalg.norm(_palm(right, xr) - _palm(left, x)) < SAME_HAND_MM
    assert shared_volume((right, xr), (left, x)) <= SHARED_VOLUME
    mt = MultiHandTracker(max_hands=2)
    assert not mt._same_hand(_slot("right", xr, 0), _slot("left", x, 1))
    moved = xr.copy()
    moved[0] += 5.0
    mirrored = xr.copy()
    mirrored[4] += np.pi
    assert mt._same_hand(_slot("right", xr, 0), _slot("right", moved, 1))
    assert mt._same_hand(_slot("right", xr, 0), _slot("left", mirrored, 1))


def test_a_hand_keeps_its_track_while_the_other_claps_against_it() -> None:
    """Dev ``clap``: the right hand is tracked within 15 mm on frames 3-8, as the palms come
    together; its track goes on through frame 9 (before, the hands' palm centres came within
    SAME_HAND_MM on frame 8 and the younger track was dropped as the same hand)."""
    truth = read_hand_truth(CLAP)
    mt = MultiHandTracker(TrackerConfig(), max_hands=2)
    ids: list[int] = []
    with DepthBagReader(CLAP, BagTopics(), require_truth=False) as reader:
        for f in reader.frames():
            if f.index > 9:
                break
            out = mt.process(f.depth_mm, f.intrinsics)
            hand = out.hand("right")
            if f.index < 3:
                continue
            assert hand is not None, f"frame {f.index}: no right hand"
            ids.append(hand.track_id)
            true = truth["right"][f.stamp_ns].fingertips_mm
            err = float(np.linalg.norm(hand.result.fingertips_mm - true, axis=1).mean())
            if f.index <= 8:
                assert err < 15.0, (f.index, err)
    assert len(set(ids)) == 1, ids


def test_only_a_lost_hand_calls_for_a_search_on_the_next_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """A track the hand gate drops calls for a search on the next frame when it was a hand on
    its last frame; one that never was (a new track that is not a hand) leaves the search's
    cadence as it was (every ``SEARCH_EVERY`` frames)."""
    from hand_sog_tracker.core.handcheck import HandGate
    from hand_sog_tracker.core.hands import SEARCH_EVERY
    from hand_sog_tracker.core.types import HandDecision, TrackResult

    depth, intr, _ = next(_frames(1))
    res = TrackResult(TrackerStatus.TRACKING, rest_pose(), np.zeros((5, 3)), np.zeros((21, 3)), 0.6, 0.0, 10, {})
    no = HandDecision(False, 0.01, np.zeros(5), None)

    def dropped(present: bool) -> MultiHandTracker:
        mt = MultiHandTracker(TrackerConfig(), max_hands=2)
        mt._frame, mt._searched = 7, 6
        kept, lost = _slot("right", rest_pose(), 0), _slot("left", rest_pose(), 1)
        kept.present, lost.present = True, present
        kept.result = lost.result = res
        mt._slots = [kept, lost]

        def gate(self, slot, *a, **kw):  # type: ignore[no-untyped-def]
            if slot is lost:
                slot.reset()
            return replace(res, hand=no)

        monkeypatch.setattr(HandGate, "gate", gate)
        mt._gate(depth, intr)
        assert mt.tracks == (("right", 0),)
        return mt

    mt = dropped(present=True)
    assert mt._frame + 1 - mt._searched >= SEARCH_EVERY  # (the next frame searches)
    mt = dropped(present=False)
    assert mt._searched == 6  # (the next search 5 frames after the last)


def test_a_search_that_starts_no_track_waits_twice_as_long_up_to_search_every_max(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With one hand tracked, the search for a second runs every ``SEARCH_EVERY`` frames; each
    search that starts no track doubles the wait up to ``SEARCH_EVERY_MAX``, and a new track
    that is a hand brings it back to ``SEARCH_EVERY``."""
    from hand_sog_tracker.core.handcheck import HandGate
    from hand_sog_tracker.core.hands import SEARCH_EVERY, SEARCH_EVERY_MAX
    from hand_sog_tracker.core.types import HandDecision, TrackResult

    depth, intr, _ = next(_frames(1))
    mt = MultiHandTracker(TrackerConfig(), max_hands=2)
    mt._slots = [_slot("right", rest_pose(), 0)]
    searched: list[int] = []
    monkeypatch.setattr(mt, "_track", lambda pre: None)  # (the tracked hand stays, without a result)
    monkeypatch.setattr(mt, "_search", lambda pre, image: searched.append(mt._frame))
    for _ in range(60):
        mt.process(depth, intr)
    assert (SEARCH_EVERY, SEARCH_EVERY_MAX) == (5, 20)
    assert searched == [0, 10, 30, 50]  # (each started none: waits of 10, 20, 20)
    new = _slot("left", rest_pose(), 1)
    res = TrackResult(TrackerStatus.TRACKING, rest_pose(), np.zeros((5, 3)), np.zeros((21, 3)), 0.6, 0.0, 10, {})
    new.result = res
    mt._slots.append(new)
    present = HandDecision(True, 0.9, np.ones(5), None)
    monkeypatch.setattr(HandGate, "gate", lambda self, slot, *a, **kw: replace(res, hand=present))
    mt._gate(depth, intr)
    assert new.reported and mt._every == SEARCH_EVERY


def test_skin_distance_within_measures_only_what_can_be_that_near() -> None:
    # ``within``: the same distance for every point nearer than ``within`` (hand and forearm),
    # inf only for points farther, around a turned hand (a box test must hold at any rotation).
    rng = np.random.default_rng(47)
    model = default_hand_model()
    theta = rest_pose((20.0, -10.0, 450.0))
    theta[3:6] = (0.4, -0.7, 0.9)
    centre = posed_centres(model, theta).mean(axis=0)
    points = centre + rng.normal(0.0, 80.0, (4000, 3))
    full = skin_distance(model, theta, points)
    for within in (OWN_MARGIN_MM, COVERED_MM, 60.0):
        d = skin_distance(model, theta, points, within)
        near = full < within
        assert 100 < near.sum() < 3900  # (both kinds of point are tested)
        np.testing.assert_allclose(d[near], full[near], rtol=0, atol=1e-9)
        assert np.all(np.isinf(d) | (np.abs(d - full) < 1e-9))
        assert np.isinf(d[~near]).mean() > 0.2  # (the box leaves many far points unmeasured)
    assert skin_distance(model, theta, np.zeros((0, 3)), OWN_MARGIN_MM).shape == (0,)


def test_the_split_gives_another_hand_the_points_near_its_skin_and_nearer_to_it() -> None:
    # The split's definition, on every point: within OWN_MARGIN_MM of the other hand's skin and
    # nearer to it than to this hand's (the box of ``within`` only skips points it cannot give).
    rng = np.random.default_rng(470)
    model = default_hand_model()
    mine, other = rest_pose((-60.0, 0.0, 450.0)), rest_pose((60.0, 10.0, 460.0))
    other[3:6] = (0.2, 0.3, -0.4)
    points = np.array([0.0, 0.0, 450.0]) + rng.normal(0.0, 90.0, (3000, 3))
    d_mine, d_other = skin_distance(model, mine, points), skin_distance(model, other, points)
    want = (d_other < OWN_MARGIN_MM) & (d_other < d_mine)
    assert 50 < want.sum() < 2950
    np.testing.assert_array_equal(_theirs(model, mine, [(model, other)])(points), want)


def test_a_new_track_whose_finalists_leave_the_data_unexplained_is_dropped_before_their_fits(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A new track whose every finalist leaves the data around it unexplained (``explained``
    below ``EXPLAINED_LOW``: the gate would drop it on its first frame) finds no hand before the
    finalists' full fits; it takes its track id, as a track the gate drops.  The same finalists
    on the hands start both tracks."""
    from hand_sog_tracker.core import hands
    from hand_sog_tracker.core.search.start import Finalists

    depth, intr, _ = next(_frames(1))
    real = hands.start_search
    fitted: list[int] = []
    finalist_fits = Tracker._finalist_fits

    def counted(self, *a):  # type: ignore[no-untyped-def]
        fitted.append(1)
        return finalist_fits(self, *a)

    monkeypatch.setattr(Tracker, "_finalist_fits", counted)
    for toward_mm in (0.0, 200.0):  # (200 mm toward the camera: the model floats before the data)

        def start(pre, model, config, bounds, toward=toward_mm):  # type: ignore[no-untyped-def]
            found = real(pre, model, config, bounds)
            moved = [x - np.eye(x.size)[2] * toward for x in found.poses]
            return Finalists(moved, found.end_mm)

        monkeypatch.setattr(hands, "start_search", start)
        fitted.clear()
        mt = MultiHandTracker(TrackerConfig(), max_hands=2)
        mt.process(depth, intr)
        if toward_mm == 0.0:
            assert len(mt.tracks) == 2 and fitted
        else:
            assert mt.tracks == () and not fitted and mt._next_id == 2 and mt._doomed


def test_each_label_tracks_with_its_own_model_once_its_trial_ends() -> None:
    """set_model per label: both tracks start in trials on one shape (the right model's), and
    each takes its label's model once its label is decided (from the next frame on); model()
    answers the label's model, a bad label is refused."""
    from hand_sog_tracker.core.hand_model import HandShape

    shapes = {"left": HandShape(0.92, 1.05, 0.97, 0.96), "right": HandShape(1.06, 0.97, 1.0, 1.02)}
    mt = MultiHandTracker(TrackerConfig(), max_hands=2)
    for side, shape in shapes.items():
        mt.set_model(side, default_hand_model(True).scaled(shape))  # (mirrored to the label)
        assert mt.model(side).shape == shape and mt.model(side).right == (side == "right")
    with pytest.raises(InputError):
        mt.set_model("both", default_hand_model())
    last = None
    for depth, intr, _ in _frames(10):
        last = mt.process(depth, intr)
    assert last is not None and {h.handedness for h in last.hands} == {"left", "right"}
    for h in last.hands:
        assert h.model.shape == shapes[h.handedness] and h.model.right == (h.handedness == "right")
        assert mt.model(h.handedness) is h.model
