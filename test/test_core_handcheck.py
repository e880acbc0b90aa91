"""The hand check (issue 46): a hand passes, a head, a forearm stump and a table do not."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
from hand_sog_tracker.core.handcheck import HAND_THRESHOLD, STEEP_HIGH, STEEP_LOW, HandGate, check_hand
from hand_sog_tracker.core.kinematics import gaussian_centres, skeleton_points
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerStatus, TrackResult
from hand_sog_tracker.synth.raster import rasterise
from hand_sog_tracker.synth.render import RenderOptions, render_depth
from hand_sog_tracker.synth.scenes import _cylinder, _ellipsoid
from helpers import INTR

MODEL = default_hand_model()


def _result(theta: np.ndarray) -> TrackResult:
    c = gaussian_centres(MODEL, theta)
    return TrackResult(
        status=TrackerStatus.TRACKING, pose=theta.copy(), fingertips_mm=c[MODEL.tip_index],
        skeleton_mm=skeleton_points(MODEL, theta), confidence=1.0, energy=0.0, n_image_gaussians=1,
        gaussians_mm=c, gaussian_radii_mm=MODEL.g_sigmas.copy(),
    )


def _mesh_depth(*meshes: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    verts, tris, n = [], [], 0
    for v, t in meshes:
        verts.append(v)
        tris.append(t + n)
        n += v.shape[0]
    z, _ = rasterise(np.concatenate(verts), np.concatenate(tris), INTR)
    return np.where(np.isfinite(z), z, 0.0).astype(np.float32)


THETA = rest_pose((0.0, 60.0, 420.0))


def test_a_hand_under_its_model_passes_with_every_finger_shown() -> None:
    rng = np.random.default_rng(3)
    depth = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=1.0, background_mm=None), rng)
    dec = check_hand(depth, INTR, MODEL, _result(THETA))
    assert dec.confidence >= 0.9
    assert dec.evidence is not None and dec.evidence.on > 0.85 and dec.evidence.explained > 0.9
    assert np.all(dec.fingers > 0.6)


@pytest.mark.parametrize("factor", [1.0, 2.0])
def test_invalid_pixels_are_unknown_not_evidence_against(factor: float) -> None:
    """Every third row Inf (a 32FC1 stream's invalid rows), at 320x240 and 640x480: the hand
    is checked as on the clean frame, not as a model partly off its data."""
    intr = INTR.scaled(factor)
    depth = render_depth(MODEL, THETA, intr, RenderOptions(noise_mm=1.0, background_mm=None), np.random.default_rng(3))
    clean = check_hand(depth, intr, MODEL, _result(THETA))
    depth[::3] = np.inf
    rows = check_hand(depth, intr, MODEL, _result(THETA))
    assert clean.confidence >= 0.9 and rows.confidence >= clean.confidence - 0.05, rows.evidence


def test_a_hand_resting_on_a_wall_passes() -> None:
    """The wall 25 mm behind the hand's centre (the back of the hand on it) is background; the
    hand's outline steps onto it and the wall does not recede beyond: steep edges."""
    rng = np.random.default_rng(5)
    depth = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=1.0, background_mm=445.0), rng)
    dec = check_hand(depth, INTR, MODEL, _result(THETA))
    assert dec.confidence >= 0.9, dec.evidence
    assert dec.evidence is not None and dec.evidence.steep >= STEEP_HIGH


def test_the_outline_of_a_model_on_a_head_curves_away() -> None:
    """The model in front of a head-sized ellipsoid: its outline is the head's surface receding,
    not a step (``steep`` low); the same model on its hand has steep edges."""
    palm = THETA[:3] + np.array([0.0, -50.0, 0.0])
    res = _result(THETA)
    head = check_hand(_mesh_depth(_ellipsoid(palm + [0.0, 0.0, 60.0], (75.0, 95.0, 85.0))), INTR, MODEL, res)
    depth = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=1.0, background_mm=None), np.random.default_rng(5))
    hand = check_hand(depth, INTR, MODEL, res)
    assert head.evidence is not None and hand.evidence is not None
    assert head.evidence.steep < STEEP_LOW <= STEEP_HIGH <= hand.evidence.steep, (head.evidence, hand.evidence)


def test_a_head_a_forearm_stump_and_a_wall_are_no_hand() -> None:
    res = _result(THETA)
    palm = THETA[:3] + np.array([0.0, -50.0, 0.0])
    head = _mesh_depth(_ellipsoid(palm + [0.0, 0.0, 60.0], (75.0, 95.0, 85.0)))
    # A forearm ending under the knuckles: the fingers hang in the air.
    stump = _mesh_depth(_cylinder(THETA[:3] + [0.0, 30.0, 28.0], 30.0, 250.0, np.eye(3)))
    wall = np.full((INTR.height, INTR.width), 432.0, dtype=np.float32)
    for depth in (head, stump, wall):
        dec = check_hand(depth, INTR, MODEL, res)
        assert dec.confidence < HAND_THRESHOLD, dec.evidence


def test_a_finger_off_the_data_is_not_seen_to_end() -> None:
    """The four fingers run on into a surface (no end); the thumb's data removed (the model's
    thumb in the air beside a forearm, issue 46): it is not checked, ``ends`` is 0, not 1/5;
    with the thumb on its data it ends (1/5)."""
    res = _result(THETA)
    shown = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=1.0, background_mm=None), np.random.default_rng(3))
    air = shown.copy()
    c, vv, uu = res.gaussians_mm, *np.mgrid[: INTR.height, : INTR.width]
    for i in np.flatnonzero(np.asarray(MODEL.g_chain) == 0):  # (the thumb's spheres, 8 mm wider)
        u, v = INTR.fx * c[i, 0] / c[i, 2] + INTR.cx, INTR.fy * c[i, 1] / c[i, 2] + INTR.cy
        air[(uu - u) ** 2 + (vv - v) ** 2 <= (INTR.fx * (MODEL.g_sigmas[i] + 8.0) / c[i, 2]) ** 2] = 0.0
    ends = []
    for depth in (shown, air):
        beyond = depth[10:75, 115:205]  # past the four fingertips (v 40-64 px, u 134-184 px)
        beyond[beyond == 0] = 420.0
        dec = check_hand(depth, INTR, MODEL, res)
        assert dec.evidence is not None
        ends.append(dec.evidence.ends)
    assert ends == [pytest.approx(0.2), 0.0], ends


def test_hidden_fingers_get_a_low_confidence() -> None:
    """A box in front of the index and middle fingers: those two are reported as not shown."""
    rng = np.random.default_rng(4)
    depth = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=0.0, background_mm=None), rng)
    tips = _result(THETA).fingertips_mm
    mid = 0.5 * (tips[1] + tips[2])
    u = int(INTR.fx * mid[0] / mid[2] + INTR.cx)
    v = int(INTR.fy * mid[1] / mid[2] + INTR.cy)
    depth[max(v - 12, 0) : v + 40, u - 14 : u + 12] = 300.0  # nearer than the hand: occluding
    dec = check_hand(depth, INTR, MODEL, _result(THETA))
    assert dec.fingers[[1, 2]].max() < dec.fingers[[0, 3, 4]].min()


def test_nothing_tracked_is_no_hand_with_zero_confidence() -> None:
    empty = TrackResult(TrackerStatus.NO_HAND, None, None, None, 0.0, 0.0, 0)
    dec = check_hand(np.zeros((INTR.height, INTR.width), np.float32), INTR, MODEL, empty)
    assert not dec.present and dec.confidence == 0.0 and dec.evidence is None


class _Counting:
    resets = 0

    def reset(self) -> None:
        self.resets += 1


def test_the_gate_resets_at_once_on_no_hand_and_after_reset_frames_when_unsure(monkeypatch) -> None:
    import hand_sog_tracker.core.handcheck as hc

    conf = [0.0]
    ev = hc.HandEvidence(1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    monkeypatch.setattr(hc, "check_hand", lambda *a: hc.HandDecision(False, conf[0], np.ones(5), ev))
    t = _Counting()
    gate = HandGate(threshold=0.5, reset_frames=3)
    wall = np.zeros((INTR.height, INTR.width), np.float32)
    assert not gate.decide(t, wall, INTR, MODEL, _result(THETA)).present and t.resets == 1  # no hand: at once
    conf[0] = 0.3  # unsure: reported as no hand, reset on the third frame in a row
    decisions = [gate.decide(t, wall, INTR, MODEL, _result(THETA)) for _ in range(3)]
    assert not any(d.present for d in decisions) and t.resets == 2
    conf[0] = 0.6
    assert gate.decide(t, wall, INTR, MODEL, _result(THETA)).present and t.resets == 2
    with pytest.raises(ValueError):
        HandGate(threshold=1.5)


def test_a_new_track_is_reported_from_its_first_frame_with_a_finger_end(monkeypatch) -> None:
    """A model curled into a fist fits a head: a new track waits for a finger seen to end."""
    import hand_sog_tracker.core.handcheck as hc

    ends = [math.nan]
    monkeypatch.setattr(
        hc, "check_hand",
        lambda *a: hc.HandDecision(False, 0.9, np.ones(5), hc.HandEvidence(1.0, 1.0, 1.0, ends[0], 1.0, 1.0)),
    )
    gate, t = HandGate(), _Counting()
    wall = np.zeros((INTR.height, INTR.width), np.float32)
    assert not gate.decide(t, wall, INTR, MODEL, _result(THETA)).present  # no finger seen yet
    ends[0] = 1.0
    assert gate.decide(t, wall, INTR, MODEL, _result(THETA)).present
    ends[0] = math.nan  # the hand closes: still the same track
    assert gate.decide(t, wall, INTR, MODEL, _result(THETA)).present
    gate.decide(t, wall, INTR, MODEL, TrackResult(TrackerStatus.LOST, None, None, None, 0.0, 0.0, 0))
    assert not gate.decide(t, wall, INTR, MODEL, _result(THETA)).present  # a new track: again
    assert HandGate(confirm_ends=False).decide(t, wall, INTR, MODEL, _result(THETA)).present


def test_the_tracker_answers_with_its_hand_decision_and_withholds_a_frame_that_is_no_hand(monkeypatch) -> None:
    """The decision is the core tracker's own (node = core): a hand is reported with its pose;
    a frame the check calls no hand has none and starts afresh (``withhold=False`` keeps both)."""
    import hand_sog_tracker.core.handcheck as hc

    depth = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=1.0, background_mm=None), np.random.default_rng(3))
    t = Tracker()
    res = t.process(depth, INTR)
    assert res.hand is not None and res.hand.present and res.pose is not None
    assert res.hand.confidence >= HAND_THRESHOLD and "check" in res.timings_ms
    ev = hc.HandEvidence(0.0, 0.0, 0.0, math.nan, 1.0, 0.0)
    monkeypatch.setattr(hc, "check_hand", lambda *a: hc.HandDecision(False, 0.0, np.zeros(5), ev))
    res = t.process(depth, INTR)
    assert res.pose is None and res.status is TrackerStatus.NO_HAND and res.hand is not None
    assert not res.hand.present and t.last_fit is not None and t.last_fit.pose is not None
    assert t.last_pose is None  # (reset: the next frame searches the whole image)
    kept = Tracker(withhold=False)
    res = kept.process(depth, INTR)
    assert res.pose is not None and res.hand is not None and not res.hand.present
    assert kept.last_pose is not None


def test_a_doubted_track_is_replaced_by_a_fresh_start_on_the_hand_in_the_same_frame(monkeypatch) -> None:
    """Issue 46, finding it again: the hand moved away and a head is where it was; the track
    on the head is doubted by the check, and the fresh start from the hand found in the same
    frame replaces it on that frame (without it, that frame reports no hand)."""
    import hand_sog_tracker.core.tracker as tr

    a, b = rest_pose((-110.0, 40.0, 520.0)), rest_pose((110.0, 40.0, 470.0))
    opts = RenderOptions(noise_mm=1.0, background_mm=None)
    first = render_depth(MODEL, a, INTR, opts, np.random.default_rng(1))
    hand = render_depth(MODEL, b, INTR, opts, np.random.default_rng(2))
    head = _mesh_depth(_ellipsoid(a[:3] + [0.0, -50.0, 60.0], (75.0, 95.0, 85.0)))
    both = np.where((hand > 0) & ((head <= 0) | (hand < head)), hand, head).astype(np.float32)

    def second_frame() -> tuple[Tracker, TrackResult]:
        t = Tracker()
        assert t.process(first, INTR).pose is not None
        return t, t.process(both, INTR)

    t, res = second_frame()
    assert res.pose is not None and t.last_proposal == "fresh_start", res.hand
    assert np.linalg.norm(res.pose[:3] - b[:3]) < 30.0
    assert t.last_fit is not None and t.last_fit.pose is not None  # (the fresh start's)
    monkeypatch.setattr(tr, "FRESH_BELOW", -1.0)  # (no fresh start)
    t, res = second_frame()
    assert res.pose is None and t.last_fit is not None and t.last_fit.pose is not None
    assert np.linalg.norm(t.last_fit.pose[:3] - a[:3]) < 60.0  # (the track stayed on the head)


def test_front_draws_the_spheres_one_by_one() -> None:
    """The model's front surface, drawn for all Gaussians at once, is what drawing them one
    after the other gives (the nearest per pixel, the first on a tie; the cores)."""
    from hand_sog_tracker.core.handcheck import ON_CORE, _front

    rng = np.random.default_rng(3)
    m, fx, fy = 40, 140.0, 150.0
    C = np.column_stack([rng.uniform(-60, 60, m), rng.uniform(-60, 60, m), rng.uniform(300, 420, m)])
    C[5] = C[4]  # (a tie: the first Gaussian keeps the pixels)
    r = rng.uniform(4.0, 16.0, m)
    z = C[:, 2]
    u, v, rp = fx * C[:, 0] / z + 20.0, fy * C[:, 1] / z + 15.0, fx * r / z
    uu, vv = np.arange(-15, 50, dtype=np.float64), np.arange(-20, 45, dtype=np.float64)
    front, owner, core = _front(C, r, z, (u, v, rp), (fx, fy), (uu, vv))
    bh, bw = vv.size, uu.size
    want = np.full((bh, bw), np.inf)
    want_owner = np.full((bh, bw), -1)
    want_core = np.zeros((bh, bw), dtype=bool)
    for i in range(m):  # (each sphere on its own box of +-rp px, clipped to the grid box)
        a0, a1 = max(int(u[i] - rp[i]) + 15, 0), min(int(u[i] + rp[i]) + 2 + 15, bw)
        b0, b1 = max(int(v[i] - rp[i]) + 20, 0), min(int(v[i] + rp[i]) + 2 + 20, bh)
        for b in range(b0, b1):
            for a in range(a0, a1):
                du, dv = (uu[a] - u[i]) * (z[i] / fx), (vv[b] - v[i]) * (z[i] / fy)
                d2 = r[i] * r[i] - du * du - dv * dv
                if d2 < 0:
                    continue
                zf = C[i, 2] - math.sqrt(d2)
                if zf < want[b, a]:
                    want[b, a], want_owner[b, a] = zf, i
                want_core[b, a] |= d2 >= (1.0 - ON_CORE * ON_CORE) * r[i] * r[i]
    assert np.array_equal(front, want)
    assert np.array_equal(owner, want_owner)
    assert np.array_equal(core, want_core)
    assert (owner == 4).any() and not (owner == 5).any()


@pytest.mark.parametrize("s", [1, 2, 3, 4])
def test_grid_depth_takes_each_blocks_first_valid_pixel(s: int) -> None:
    """The check's grid: every s-th pixel (0 without data), and the same with an invalid pixel
    (0, NaN, +-Inf) replaced by the first valid one of its s x s block, row by row."""
    from hand_sog_tracker.core.handcheck import _grid_depth

    rng = np.random.default_rng(s)
    depth = rng.uniform(-50.0, 900.0, (17, 23))
    depth[rng.random(depth.shape) < 0.3] = np.nan
    depth[rng.random(depth.shape) < 0.1] = np.inf
    depth[rng.random(depth.shape) < 0.2] = 0.0
    plain, grid = _grid_depth(depth, s)
    ok = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    want = ok[::s, ::s]
    assert plain.dtype == grid.dtype == np.float32
    assert np.array_equal(plain, want)
    for gv in range(want.shape[0]):
        for gu in range(want.shape[1]):
            block = ok[gv * s : (gv + 1) * s, gu * s : (gu + 1) * s].ravel()
            first = block[block > 0][:1]
            assert grid[gv, gu] == (first[0] if first.size else 0.0)


def _hand_and_cylinder(
    seed: int, centre: np.ndarray, radius_mm: float, length_mm: float
) -> tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """The hand at ``THETA`` rendered (1 mm noise), the same with a cylinder along y at
    ``centre`` (3,) mm drawn over it where nearer, and ``theirs``: points within 12 mm of it."""
    rng = np.random.default_rng(seed)
    hand = render_depth(MODEL, THETA, INTR, RenderOptions(noise_mm=1.0, background_mm=None), rng)
    other = _mesh_depth(_cylinder(centre, radius_mm, length_mm, np.eye(3)))
    depth = np.where((other > 0) & ((hand == 0) | (other < hand)), other, hand).astype(np.float32)

    def theirs(points: np.ndarray) -> np.ndarray:
        return np.linalg.norm((points - centre)[:, [0, 2]], axis=1) < radius_mm + 12.0

    return hand, depth, theirs


def test_data_another_hand_explains_count_neither_way() -> None:
    """A forearm-sized cylinder lying across the hand's side at its depth (another hand's, as
    the multi-hand tracker's split says): it leaves data to explain and hides the outline, so
    the check doubts the hand; given as ``theirs`` it counts neither way and the hand passes."""
    hand, depth, theirs = _hand_and_cylinder(3, THETA[:3] + np.array([75.0, 0.0, 10.0]), 25.0, 300.0)
    res = _result(THETA)
    doubted = check_hand(depth, INTR, MODEL, res)
    given = check_hand(depth, INTR, MODEL, res, theirs)
    clean = check_hand(hand, INTR, MODEL, res)
    assert doubted.confidence < 0.8 * clean.confidence, doubted.evidence
    assert given.confidence >= clean.confidence - 0.05, (given.evidence, clean.evidence)


def test_a_finger_another_hand_hides_wholly_is_left_out_of_fingers_on() -> None:
    """A bar well in front of the index finger, covering all of it (another hand's, as the
    multi-hand tracker's split says): without ``theirs`` the hidden finger counts as none of it
    on data (the one-hand rule); with it, the finger is left out of ``fingers_on``, which stays
    that of the four fingers shown."""
    index = gaussian_centres(MODEL, THETA)[MODEL.g_chain == 1]
    centre = index.mean(axis=0) - np.array([0.0, 0.0, 60.0])
    hand, depth, theirs = _hand_and_cylinder(4, centre, 14.0, np.ptp(index[:, 1]) + 40.0)
    res = _result(THETA)
    alone = check_hand(depth, INTR, MODEL, res)
    given = check_hand(depth, INTR, MODEL, res, theirs)
    clean = check_hand(hand, INTR, MODEL, res)
    assert alone.evidence is not None and given.evidence is not None and clean.evidence is not None
    assert alone.fingers[1] < 0.1  # (the index finger is hidden)
    assert alone.evidence.fingers_on < clean.evidence.fingers_on - 0.1, alone.evidence
    assert given.evidence.fingers_on >= clean.evidence.fingers_on - 0.05, (given.evidence, clean.evidence)


def test_a_fresh_start_on_the_same_hand_goes_on_as_the_track(monkeypatch) -> None:
    """Issue 46, hands that come back: a confirmed track doubted by its check competes with a
    fresh start; one that wins on the same hand keeps the track's confirmation, so the frame is
    reported although no finger is seen to end on it (a new track would be withheld), and the
    track's velocity (a new track starts at rest)."""
    import hand_sog_tracker.core.handcheck as hc
    import hand_sog_tracker.core.tracker as tr
    from hand_sog_tracker.core.search.candidates import Frame

    opts = RenderOptions(noise_mm=1.0, background_mm=None)
    moved = THETA + np.r_[8.0, -5.0, 0.0, np.zeros(23)]  # (the hand moving: mm)
    depth, again = (render_depth(MODEL, x, INTR, opts, np.random.default_rng(s)) for x, s in ((THETA, 4), (moved, 5)))
    fresh: list[np.ndarray] = []
    init, score, track_frame = tr.Tracker._initialise, Frame.score, tr.Tracker._track

    def initialise(self: Tracker, pre: object) -> TrackResult:
        res = init(self, pre)
        fresh.append(res.pose)
        return res

    tracked: list[np.ndarray] = []

    def track(self: Tracker, pre: object) -> TrackResult:
        res = track_frame(self, pre)
        tracked.append(res.pose)
        return res

    def won(x: np.ndarray) -> float:
        return float(bool(fresh) and np.array_equal(x, fresh[-1]))

    def second_frame() -> tuple[Tracker, TrackResult]:
        t = Tracker()
        assert t.process(depth, INTR).hand.present  # (a finger seen to end: confirmed)
        fresh.clear()
        tracked.append(t.last_pose)
        monkeypatch.setattr(tr.Tracker, "_track", track)
        confidences = iter([0.1, 0.9])  # (the track's check, then the fresh start's; no finger seen)
        ev = hc.HandEvidence(1.0, 1.0, 1.0, math.nan, 1.0, 1.0)
        monkeypatch.setattr(hc, "check_hand", lambda *a: hc.HandDecision(False, next(confidences), np.ones(5), ev))
        monkeypatch.setattr(tr.Tracker, "_initialise", initialise)
        # (the fresh start scores higher on the track's frame: it wins on the same hand)
        monkeypatch.setattr(Frame, "score", lambda f, x, v=None: score(f, x, v) + won(x))
        return t, t.process(again, INTR)

    t, res = second_frame()
    assert t.last_proposal == "fresh_start" and res.pose is not None and res.hand.present
    assert res.hand.evidence is not None and math.isnan(res.hand.evidence.ends)  # (a new track would wait)
    # ... and it goes on with the track's velocity (a new track's is at rest: the hand moving in lags)
    assert t.last_pose is not None and np.array_equal(t.last_pose, res.pose)
    step = tracked[1] - tracked[0]  # (the track's own answer on the second frame less its first)
    assert np.abs(step).max() > 0 and np.allclose(t._prev[0] - t._prev[1], step)
