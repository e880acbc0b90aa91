"""The one search (issue 45): proposals with names and reasons, one batch, one score."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
from hand_sog_tracker.core.optimizer import OptimizeResult
from hand_sog_tracker.core.search import NEW_TRACK_PROPOSALS, TRACK_PROPOSALS, Candidate, Frame, Proposal, search
from hand_sog_tracker.core.search import fit as fit_module
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence


def test_every_proposal_has_a_name_and_a_reason() -> None:
    names = [p.name for p in (*TRACK_PROPOSALS, *NEW_TRACK_PROPOSALS)]
    assert len(set(names)) == 7 and all(p.reason for p in (*TRACK_PROPOSALS, *NEW_TRACK_PROPOSALS))
    assert {"lateral"} == {p.name for p in NEW_TRACK_PROPOSALS} - {p.name for p in TRACK_PROPOSALS}


class _Fit:
    """A stand-in for the batch fit: each candidate ends where it starts, its value given."""

    def __init__(self, values: dict[float, float]) -> None:
        self.values = values

    def __call__(self, fun, x0, **kwargs):
        return [OptimizeResult(x, self.values[float(x[0])], 0, True, 0, "", np.zeros(1)) for x in x0]


@pytest.mark.parametrize(
    "values, margins, expected",
    [
        ({1.0: 0.55, 2.0: 0.60}, (0.0, 0.0), 2.0),  # the highest score wins
        ({1.0: 0.55, 2.0: 0.60}, (0.0, 0.2), 1.0),  # ... that beats the fit by its margin
        ({1.0: 0.45, 2.0: 0.52}, (0.0, 0.05), None),  # none does: the fit is the answer
    ],
)
def test_the_highest_score_that_beats_the_fit_by_its_margin_wins(
    monkeypatch: pytest.MonkeyPatch, values: dict, margins: tuple, expected: float | None
) -> None:
    monkeypatch.setattr(fit_module, "maximise_batch", _Fit(values))
    monkeypatch.setattr(Frame, "score", lambda self, x, value=None: 0.5 if value is None else value)
    base = rest_pose()
    fit = OptimizeResult(base, 0.5, 7, True, 0, "", np.zeros(1))
    starts = []
    for k, margin in zip((1.0, 2.0), margins):
        x = base.copy()
        x[0] = k
        starts.append(Candidate(f"c{int(k)}", x, margin))
    proposal = Proposal("test", "two candidates", lambda f: iter(starts))
    # (The stand-in fit does not evaluate it; without targets it is its own plain objective.)
    plain = SimpleNamespace(batch=None, data=SimpleNamespace(n=100), targets=None)
    frame = Frame(default_hand_model(), fit, plain, None, None, (None, None))  # type: ignore[arg-type]
    res, name = search(frame, (proposal,))
    if expected is None:
        assert res is fit and name is None
    else:
        assert res.x[0] == expected and name == f"c{int(expected)}"


def test_no_candidate_no_fit() -> None:
    fit = OptimizeResult(rest_pose(), 0.5, 7, True, 0, "", np.zeros(1))
    frame = Frame(default_hand_model(), fit, None, None, None, (None, None))  # type: ignore[arg-type]
    assert search(frame, (Proposal("none", "never applies", lambda f: iter(())),)) == (fit, None)


def test_two_trackers_give_the_same_answers_and_proposals() -> None:
    """Nothing in the search depends on timing or on earlier trackers: the same frames give the
    same poses and the same winning proposals."""
    intr = default_intrinsics()
    frames = list(synthetic_sequence("fingercount", 20, intrinsics=intr, seed=2))
    runs = [_answers(frames, intr) for _ in range(2)]
    assert runs[0] == runs[1]


def _answers(frames, intr) -> list:
    """A new tracker's answers on ``frames``: (pose bytes or None, winning proposal) per frame."""
    tracker = Tracker(TrackerConfig())
    out = []
    for f in frames:
        res = tracker.process(f.depth_mm, intr)
        out.append((None if res.pose is None else res.pose.tobytes(), tracker.last_proposal))
    return out


def test_a_detection_whose_pulls_lost_is_not_pulled_onto_again_where_it_stays() -> None:
    from hand_sog_tracker.core.kinematics import fingertips
    from hand_sog_tracker.core.salient import Detections
    from hand_sog_tracker.core.search.candidates import SAME_DETECTION_MM, pull_target

    model = default_hand_model()
    theta = rest_pose((0.0, 20.0, 400.0))
    lonely = fingertips(model, theta)[2] + np.array([0.0, -60.0, -30.0])
    det = Detections(lonely[None], np.zeros((1, 2)), np.array([0.95]), np.array([False]))
    fit = OptimizeResult(theta, 0.5, 7, True, 0, "", np.zeros(1))

    def target(lost: np.ndarray) -> int | None:
        frame = Frame(model, fit, None, None, det, (None, None), lost_pulls=lost)  # type: ignore[arg-type]
        return pull_target(frame)

    assert target(np.zeros((0, 3))) == 0
    assert target(lonely[None] + 0.5 * SAME_DETECTION_MM) is None  # (within it: the same detection)
    assert target(lonely[None] + [2 * SAME_DETECTION_MM, 0.0, 0.0]) == 0  # moved on: another one


def test_a_frames_pulls_fitted_as_one_batch_are_the_pulls_fitted_one_by_one() -> None:
    """The detection pulls of a frame (one objective, each pull with its own targets, some with
    only a finger free) are fitted as one batch: each start pose is the one its own pull gives."""
    from dataclasses import replace

    from test_core_energy import data_near, silhouette_of

    from hand_sog_tracker.core.hand_model import chain_slice
    from hand_sog_tracker.core.objective import Objective, TipTargets
    from hand_sog_tracker.core.optimizer import maximise

    rng = np.random.default_rng(5)
    model = default_hand_model()
    theta = rest_pose((0.0, 10.0, 400.0))
    obj = Objective(model, data_near(model, theta, rng), TrackerConfig(), silhouette=silhouette_of(model, theta))
    strong = replace(obj.config, w_sal=20.0)
    limits = Tracker(TrackerConfig())._limits()
    candidates = [Candidate("plain", theta + rng.normal(0.0, 0.01, theta.size))]
    for k in range(5):
        points = rng.normal(0.0, 15.0, (5, 3)) + [0.0, 10.0, 400.0]
        weights = (rng.random(5) < 0.5) * rng.random(5)
        active = None
        if k % 2:
            active = np.zeros(theta.size, dtype=bool)
            active[chain_slice(1 + k % 4)] = True
        x0 = theta + rng.normal(0.0, 0.02, theta.size)
        candidates.append(Candidate("detection", x0, 0.0, TipTargets(points, weights), active))
    starts = fit_module._pulled(candidates, obj, limits)
    assert starts[0].tobytes() == candidates[0].x0.tobytes()
    for c, x in zip(candidates[1:], starts[1:]):
        pull = obj.variant(strong, c.pull)
        alone = maximise(pull, c.x0, iterations=fit_module.SEARCH_ITERATIONS, active=c.active, bounds=limits).x
        assert x.tobytes() == alone.tobytes() and np.abs(x - c.x0).max() > 1e-3


def test_the_fits_plain_value_is_its_value_with_the_salient_term_added_back() -> None:
    from test_core_energy import data_near

    from hand_sog_tracker.core.objective import Objective, TipTargets
    from hand_sog_tracker.core.search import plain

    rng = np.random.default_rng(8)
    model = default_hand_model()
    theta = rest_pose((0.0, 10.0, 400.0))
    targets = TipTargets(rng.normal(0.0, 20.0, (5, 3)) + [0.0, 10.0, 400.0], np.array([1.0, 0.0, 0.7, 0.4, 1.0]))
    obj = Objective(model, data_near(model, theta, rng), TrackerConfig(), targets=targets)
    x = theta + rng.normal(0.0, 0.01, theta.size)
    fit = OptimizeResult(x, obj(x, gradient=False)[0], 7, True, 0, "", np.zeros(1))
    frame = Frame(model, fit, obj, obj.data, None, (None, None))  # type: ignore[arg-type]
    assert obj.salient(x) > 0.0
    assert fit_module._plain_value(frame) == pytest.approx(plain(obj)(x, gradient=False)[0], rel=1e-13, abs=1e-13)


def test_a_fingertip_against_another_hand_calls_for_no_curl() -> None:
    """The curl proposal curls the open fingers when one has no detection of its own, unless
    that tip lies against another hand (``Frame.covered``: the detector sees no end there)."""
    from hand_sog_tracker.core.kinematics import fingertips
    from hand_sog_tracker.core.salient import Detections
    from hand_sog_tracker.core.search.candidates import CURL

    model = default_hand_model()
    theta = rest_pose((0.0, 20.0, 400.0))
    tips = fingertips(model, theta)[:4]  # (no detection at the little fingertip)
    det = Detections(tips, np.zeros((4, 2)), np.full(4, 0.95), np.zeros(4, bool))
    fit = OptimizeResult(theta, 0.5, 7, True, 0, "", np.zeros(1))

    def curls(covered) -> int:
        frame = Frame(model, fit, None, None, det, (None, None), covered=covered)  # type: ignore[arg-type]
        return len(list(CURL.generate(frame)))

    assert curls(None) == 4  # (each open finger curled)
    assert curls(lambda t: np.arange(5) == 4) == 0
    assert curls(lambda t: np.arange(5) == 2) == 4  # (another tip's cover does not explain it)


def test_a_fingertip_another_hand_hides_does_not_dangle() -> None:
    """The dangling proposal restarts the finger whose tip lies farthest from the data, unless
    another hand covers that tip (``Frame.covered``: hidden behind it or against it)."""
    from hand_sog_tracker.core.depth_sog import ImageSoG
    from hand_sog_tracker.core.kinematics import fingertips
    from hand_sog_tracker.core.search.candidates import DANGLING

    model = default_hand_model()
    theta = rest_pose((0.0, 20.0, 400.0))
    tips = fingertips(model, theta)
    pts = np.delete(tips, 1, axis=0)  # (data at every tip but the index finger's)
    intr = default_intrinsics(320, 240)
    uv = intr.project(pts)
    data = ImageSoG(uv, np.full(4, 2.0), pts[:, 2].copy(), pts, intr, 1.0)
    fit = OptimizeResult(theta, 0.5, 7, True, 0, "", np.zeros(1))

    def dangling(covered) -> int:
        frame = Frame(model, fit, None, data, None, (None, None), covered=covered)  # type: ignore[arg-type]
        return len(list(DANGLING.generate(frame)))

    assert dangling(None) == 3  # (the index finger extended, curled, like the others)
    assert dangling(lambda t: np.arange(5) == 1) == 0
    assert dangling(lambda t: np.arange(5) == 3) == 3


def test_the_race_stops_candidates_and_changes_no_answer(monkeypatch: pytest.MonkeyPatch) -> None:
    """A candidate stopped below its floor (the fit's score plus its margin) could not have won:
    the search with the race gives the poses and proposals of the search without it."""
    intr = default_intrinsics()
    frames = list(synthetic_sequence("fistopen", 24, intrinsics=intr, seed=3))
    fit_batch = fit_module.fit_batch
    stopped = []

    def counted(fun, starts, n_data, **kwargs):
        out = fit_batch(fun, starts, n_data, **kwargs)
        stopped.extend(r.status == 2 for r in out)
        return out

    def unraced(fun, starts, n_data, **kwargs):
        kwargs.pop("floor", None)
        return fit_batch(fun, starts, n_data, **kwargs)

    runs = []
    for patch in (counted, unraced):
        monkeypatch.setattr(fit_module, "fit_batch", patch)
        runs.append(_answers(frames, intr))
    assert any(stopped)
    assert runs[0] == runs[1]


def test_the_shift_costs_from_one_batch_of_fingertips_are_those_pose_by_pose() -> None:
    from hand_sog_tracker.core.kinematics import centres_batch, fingertips
    from hand_sog_tracker.core.salient import Detections
    from hand_sog_tracker.core.search.candidates import shifted
    from hand_sog_tracker.core.search.score import assignment_cost

    rng = np.random.default_rng(5)
    model = default_hand_model()
    for _ in range(20):
        x = rest_pose() + rng.normal(0.0, 0.3, 26)
        x[:3] = (0.0, 0.0, 400.0) + rng.normal(0.0, 20.0, 3)
        poses = np.array([shifted(x, s) for s in (0, 1, -1)])
        tips = centres_batch(model, poses, pullback=False)[0].take(model.tip_index, axis=1)
        points = (0.0, 0.0, 400.0) + rng.normal(0.0, 60.0, (5, 3))
        det = Detections(points, points[:, :2], rng.uniform(0.2, 1.0, 5), rng.uniform(size=5) < 0.3)
        for p, t in zip(poses, tips):
            # (Equal bit for bit: the shift proposal decides on differences of these costs.)
            assert np.array_equal(t, fingertips(model, p))
            assert assignment_cost(model, p, det, True, t) == assignment_cost(model, p, det, True)
