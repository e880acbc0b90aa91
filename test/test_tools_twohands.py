"""Two-hand bags (per-hand ground-truth topics, deterministic) and their score (matched by handedness, swaps)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.synth.mesh import MeshShape
from hand_sog_tracker.synth.sequence import default_intrinsics
from hand_sog_tracker.synth.twohands import TwoHandScene, two_hand_sequence
from hand_sog_tracker.tools import evaluate_bag
from hand_sog_tracker.tools.bagio import GT_TOPIC, iter_messages, open_bag, topic_table
from hand_sog_tracker.tools.make_sample_bags import BASE_STAMP_NS, bag_digest
from hand_sog_tracker.tools.twohand_bags import (
    TwoHandBagSpec,
    hand_topic,
    read_hand_truth,
    twohand_set,
    write_twohand_bag,
)
from hand_sog_tracker.tools.twohand_eval import (
    HandPrediction,
    TwoHandRecord,
    evaluate_two_hands_core,
    position_match,
    score_two_hands,
)

BAGS = Path(__file__).resolve().parent.parent / "bags"
SPEC = TwoHandBagSpec("cross", TwoHandScene("cross", (MeshShape(0.9, 1.0, 1.0), MeshShape())), 11, "tof", 3, "dev",
                      width=160, height=120)


def test_bag_has_per_hand_topics_and_is_deterministic(tmp_path: Path) -> None:
    a, size, _ = write_twohand_bag(tmp_path / "a", SPEC)
    b, _, _ = write_twohand_bag(tmp_path / "b", SPEC)
    c, _, _ = write_twohand_bag(tmp_path / "c", TwoHandBagSpec(**{**SPEC.__dict__, "seed": 12}))
    assert size > 0 and bag_digest(a) == bag_digest(b) != bag_digest(c)
    with open_bag(a) as reader:
        topics = topic_table(reader)
    for side in ("left", "right"):
        for kind in ("fingertips", "keypoints", "visibility"):
            assert topics[hand_topic(side, kind)][1] == 3
    assert GT_TOPIC not in topics  # the one-hand topic means "the hand": not written with two
    truth = read_hand_truth(a)
    frames = list(two_hand_sequence(SPEC.scene, 3, default_intrinsics(160, 120), seed=11, sensor="tof"))
    for f in frames:
        stamp = BASE_STAMP_NS + int(round(f.index * 1e9 / 30.0))
        for h in f.hands:
            rec = truth[h.handedness][stamp]
            np.testing.assert_allclose(rec.fingertips_mm, h.fingertips_mm, atol=1e-9)
            np.testing.assert_allclose(rec.keypoints_mm, h.keypoints_mm, atol=1e-9)
            assert rec.visible_fraction == pytest.approx(h.visible_fraction)
            np.testing.assert_array_equal(rec.tips_visible, h.tips_visible)
    side = json.loads((a / "hand_sog_sample.json").read_text())
    assert side["hands"] == 2 and side["split"] == "dev" and side["scene"] == "cross"


def _messages_digest(bag: Path, before_ns: int, skip_prefix: str) -> str:
    h = hashlib.sha256()
    with open_bag(bag) as reader:
        for conn, log_ns, raw in iter_messages(reader, Path(bag), list(reader.connections)):
            if log_ns < before_ns and not conn.topic.startswith(skip_prefix):
                h.update(conn.topic.encode() + int(log_ns).to_bytes(8, "little") + bytes(raw))
    return h.hexdigest()


@pytest.mark.parametrize("name", ["twohands_dev", "twohands_test"])
def test_bundled_sets_are_what_the_generator_writes(tmp_path: Path, name: str) -> None:
    """The first frames of one bundled bag per set, regenerated, give the same messages.

    The sensor topics (depth, CameraInfo) must be equal byte for byte. The ground truth is
    float64 kinematics, whose last bits differ between NumPy releases (2.4 rounds a few
    keypoints one ulp apart from the release that wrote the bags), so it is compared to 1e-6 mm.
    """
    specs = twohand_set(name)
    assert {p.name for p in (BAGS / name).iterdir() if p.is_dir()} == {s.name for s in specs}
    spec = next(s for s in specs if s.name == "occlude")
    short = TwoHandBagSpec(**{**spec.__dict__, "frames": 3})
    path, _, _ = write_twohand_bag(tmp_path / "occlude", short)
    bundled = BAGS / name / "occlude"
    end = BASE_STAMP_NS + int(round(3 * 1e9 / 30.0))
    gt = hand_topic("left", "fingertips").split("/left/")[0]
    assert _messages_digest(path, end, gt) == _messages_digest(bundled, end, gt)
    ours, theirs = read_hand_truth(path), read_hand_truth(bundled)
    for side in ("left", "right"):
        assert ours[side] and set(ours[side]) <= set(theirs[side])
        for stamp, rec in ours[side].items():
            ref = theirs[side][stamp]
            np.testing.assert_allclose(rec.fingertips_mm, ref.fingertips_mm, rtol=0, atol=1e-6)
            np.testing.assert_allclose(rec.keypoints_mm, ref.keypoints_mm, rtol=0, atol=1e-6)
            assert rec.visible_fraction == ref.visible_fraction
            np.testing.assert_array_equal(rec.tips_visible, ref.tips_visible)


def test_sets_differ_in_seeds_shapes_sensors_and_front_hand() -> None:
    dev, test = twohand_set("twohands_dev"), twohand_set("twohands_test")
    assert {s.seed for s in dev}.isdisjoint({s.seed for s in test})
    assert {s.scene.shapes for s in dev}.isdisjoint({s.scene.shapes for s in test})
    assert all(a.sensor != b.sensor for a, b in zip(dev, test))
    assert {s.scene.front for s in dev} == {"right"} and {s.scene.front for s in test} == {"left"}


def _truth(k: int) -> dict[str, np.ndarray]:
    base = np.arange(15, dtype=np.float64).reshape(5, 3)
    return {"left": base + [-100.0, 0.0, 400.0 + k], "right": base + [100.0, 0.0, 400.0 + k]}


def test_each_hand_is_scored_by_its_label() -> None:
    recs = []
    for k in range(6):
        t = _truth(k)
        preds = (HandPrediction("right", t["right"] + [2.0, 0.0, 0.0], 0.9),
                 HandPrediction("left", t["left"] + [0.0, 3.0, 0.0], 0.8))
        recs.append(TwoHandRecord(k, k, t, {"left": 1.0, "right": 0.7}, preds, 10.0))
    s = score_two_hands(recs)
    assert s.per_hand["right"].mean_mm == pytest.approx(2.0) and s.per_hand["left"].mean_mm == pytest.approx(3.0)
    assert s.handedness_accuracy_pct == 100.0 and s.swaps == 0
    assert s.followed["right"] == {"left": 0, "right": 6, "none": 0}
    assert s.mean_visible_fraction["right"] == pytest.approx(0.7)


def test_a_label_that_jumps_to_the_other_hand_is_a_swap_and_the_missing_hand_fails() -> None:
    recs = []
    for k in range(10):
        t = _truth(k)
        on = "left" if k < 4 else "right"  # a one-hand tracker labelled "right" takes the left hand first
        recs.append(TwoHandRecord(k, k, t, {}, (HandPrediction("right", t[on] + 1.0),)))
    s = score_two_hands(recs)
    assert s.swaps == 1 and s.swap_frames == (4,)
    assert s.handedness_accuracy_pct == pytest.approx(60.0)
    assert s.followed["right"] == {"left": 4, "right": 6, "none": 0}
    left = s.per_hand["left"]
    assert left.frames_with_estimate == 0 and left.pct_below_mm["30"] == 0.0
    right = s.per_hand["right"]
    assert right.pct_below_mm["20"] == pytest.approx(60.0)  # the four frames on the left hand fail
    # a label swapped consistently is no identity swap, but every frame has the wrong handedness
    swapped = [TwoHandRecord(k, k, _truth(k), {}, (HandPrediction("left", _truth(k)["right"]),)) for k in range(5)]
    s2 = score_two_hands(swapped)
    assert s2.swaps == 0 and s2.handedness_accuracy_pct == 0.0


def test_position_match_is_one_to_one_and_gated() -> None:
    t = _truth(0)
    both = [HandPrediction("right", t["left"] + 5.0), HandPrediction("left", t["left"] + 8.0)]
    assert position_match(both, t) == ["left", None]
    assert position_match([HandPrediction("left", t["left"] + 200.0)], t) == [None]
    assert position_match([HandPrediction("left", t["right"])], {"left": t["left"], "right": None}) == [None]


def test_core_evaluation_with_a_plugged_in_predictor_and_the_cli(tmp_path: Path, capsys) -> None:
    bag, _, _ = write_twohand_bag(tmp_path / "cross", SPEC)
    truth = read_hand_truth(bag)
    stamps = iter(sorted(truth["left"]))

    def oracle(depth_mm, intrinsics):  # the truth itself, in frame order
        st = next(stamps)
        return [HandPrediction(s, truth[s][st].fingertips_mm, 1.0) for s in ("left", "right")]

    s = evaluate_two_hands_core(bag, oracle, split="dev")
    assert s.frames == 3 and s.swaps == 0 and s.handedness_accuracy_pct == 100.0
    assert s.per_hand["left"].mean_mm == pytest.approx(0.0, abs=1e-9)
    out = tmp_path / "r.json"
    assert evaluate_bag.main([str(bag), "--max-frames", "2", "--json", str(out)]) == 0
    assert "swaps" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["two_hands"][0]["frames"] == 2 and set(doc["two_hands"][0]["per_hand"]) == {"left", "right"}
    (bag / "hand_sog_sample.json").unlink()  # without its sidecar: known by its per-hand topics
    assert evaluate_bag.main([str(bag), "--max-frames", "1", "--quiet"]) == 0
