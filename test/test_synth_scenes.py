"""Scene renderer and scene bags (issue 46): visibility, ground truth, determinism, round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.mesh import MeshShape, pose_mesh
from hand_sog_tracker.synth.scenes import ABSENT, FULL, PARTIAL, SCENE_TYPES, scene_frames, scene_group
from hand_sog_tracker.synth.sequence import default_intrinsics
from hand_sog_tracker.tools.bagio import DepthBagReader
from hand_sog_tracker.tools.make_scene_bags import read_scene_truth, scene_set, write_scene_bag

INTR = default_intrinsics()


def test_a_hand_leaving_is_full_then_partial_then_absent_then_back() -> None:
    frames = list(scene_frames("leave_bottom", 45, INTR, seed=5))
    vis = [f.visibility for f in frames]
    assert vis[0] == FULL and vis[-1] == FULL and ABSENT in vis and PARTIAL in vis
    k = vis.index(ABSENT)
    assert PARTIAL in vis[:k] and FULL in vis[k:]
    for f in frames:
        assert f.joints_mm is not None and f.joints_mm.shape == (21, 3)
        np.testing.assert_array_equal(f.fingertips_mm, f.joints_mm[4::4])
    # While the hand is out, nothing of it is left in the image (no forearm from below either).
    assert not np.any(frames[k].depth_mm > 0)


def test_no_hand_scenes_have_depth_but_no_hand() -> None:
    for kind in ("nohand_head", "nohand_objects", "nohand_arm"):
        f = next(iter(scene_frames(kind, 1, INTR, seed=2)))
        assert f.visibility == ABSENT and np.count_nonzero(f.depth_mm) > 500
        assert (f.joints_mm is None) == (kind != "nohand_arm")  # the arm's hand is beyond the border


def test_the_ground_truth_is_the_posed_mesh_and_renders_are_deterministic() -> None:
    a = next(iter(scene_frames("hold_ball", 1, INTR, MeshShape(0.9, 1.05, 0.95), seed=11, sensor="tof")))
    b = next(iter(scene_frames("hold_ball", 1, INTR, MeshShape(0.9, 1.05, 0.95), seed=11, sensor="tof")))
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    assert a.joints_mm is not None
    # The wrist row is the pose's translation; the tips are the mesh's ground-truth fingertips.
    c = next(iter(scene_frames("hold_ball", 1, INTR, MeshShape(0.9, 1.05, 0.95), seed=12, sensor="tof")))
    assert not np.array_equal(a.depth_mm, c.depth_mm)
    assert np.all(np.linalg.norm(a.joints_mm[1:] - a.joints_mm[0], axis=1) < 220.0)


def test_every_scene_type_renders_and_groups() -> None:
    for kind in SCENE_TYPES:
        f = next(iter(scene_frames(kind, 1, INTR, seed=1, sensor="clean")))
        assert f.depth_mm.shape == (240, 320) and np.count_nonzero(f.depth_mm) > 0
        assert scene_group(kind) in ("leave", "no_hand", "hold", "back", "table")
    with pytest.raises(InputError):
        next(iter(scene_frames("juggling", 1, INTR)))


def test_scene_sets_differ_between_splits() -> None:
    dev, test = scene_set("scenes_dev"), scene_set("scenes_test")
    assert [s.kind for s in dev] == [s.kind for s in test] == list(SCENE_TYPES)
    assert not {s.seed for s in dev} & {s.seed for s in test}
    assert {s.shape for s in dev}.isdisjoint({s.shape for s in test})
    assert [s.sensor for s in dev] != [s.sensor for s in test]


def test_a_scene_bag_round_trips(tmp_path: Path) -> None:
    spec = scene_set("scenes_dev", frames=3)[SCENE_TYPES.index("nohand_head")]
    write_scene_bag(tmp_path / "b", spec)
    truth = read_scene_truth(tmp_path / "b")
    with DepthBagReader(tmp_path / "b", require_truth=False) as r:
        frames = list(r.frames())
    assert len(frames) == 3 and all(truth[f.stamp_ns] == (ABSENT, None) for f in frames)
    assert all(f.truth_mm is None for f in frames)


def test_pose_mesh_wrist_is_the_pose_translation() -> None:
    """(The scenes' wrist row relies on the mesh's hand frame having its origin at the wrist.)"""
    theta = np.zeros(26)
    theta[:3] = (10.0, 20.0, 400.0)
    theta[3] = np.pi
    pm = pose_mesh(theta)
    d = np.linalg.norm(pm.joints[:, 0] - theta[:3], axis=1)
    assert d.min() > 20.0 and d.max() < 120.0


def test_scene_metrics_auc_refind_and_no_hand_share() -> None:
    from hand_sog_tracker.tools.scene_eval import refind_frames, roc_auc, summarise

    assert roc_auc([0.9, 0.8, 0.1], [True, True, False]) == 1.0
    assert roc_auc([0.5, 0.5], [True, False]) == 0.5
    assert np.isnan(roc_auc([0.5], [True]))

    def rec(vis: str, reported: bool, tip: float, conf: float) -> dict:
        return {"visibility": vis, "reported": reported, "posed": reported or conf > 0, "tip_mm": tip,
                "tip_max_mm": tip, "palm_mm": tip, "confidence": conf}

    recs = [rec(FULL, True, 5.0, 0.9), rec(ABSENT, False, np.nan, 0.0), rec(ABSENT, True, np.nan, 0.4),
            rec(FULL, True, 50.0, 0.1), rec(FULL, False, 30.0, 0.0), rec(FULL, True, 8.0, 0.8)]
    s = summarise(recs)
    assert s["no_hand_reported"] == 0.5 and s["full_ok"] == 0.5
    assert s["auc"] == 1.0 and s["auc_frames"] == (2, 2)  # good: 0.9, 0.8; bad: 0.4 (no hand), 0.1
    assert refind_frames(recs) == [2]  # back in full view at frame 3, all tips < 20 mm at frame 5
    assert s["longest_wrong"] == 2  # (a hand on the no-hand frame 2, then 50 mm off on frame 3)


def test_scene_eval_sets_tracker_parameters(tmp_path: Path) -> None:
    """``scene_eval --set max_hands=2`` scores the multi-hand tracker (core mode); a bad name fails."""
    import json

    from hand_sog_tracker.tools.scene_eval import main

    spec = scene_set("scenes_dev", frames=3)[SCENE_TYPES.index("nohand_objects")]
    write_scene_bag(tmp_path / "b", spec)
    assert main([str(tmp_path / "b"), "--set", "max_hands=2", "--json", str(tmp_path / "o.json")]) == 0
    recs = json.loads((tmp_path / "o.json").read_text())["b"]["records"]
    assert len(recs) == 3 and all("hands" in r for r in recs)
    assert main([str(tmp_path / "b"), "--set", "no_such_parameter=1"]) == 2


def test_scene_eval_scores_test_scenes_but_shows_no_frames_of_them(tmp_path: Path) -> None:
    """A test-split scene gets its summary, not its per-frame records or overlays, unless
    ``--allow-test-inspection`` (the dev/test protocol of ``evaluate_bag``)."""
    import json

    from hand_sog_tracker.tools.scene_eval import main

    spec = scene_set("scenes_test", frames=2)[SCENE_TYPES.index("nohand_head")]
    write_scene_bag(tmp_path / "b", spec)
    out = tmp_path / "o.json"
    assert main([str(tmp_path / "b"), "--json", str(out)]) == 0
    scored = json.loads(out.read_text())["b"]
    assert scored["split"] == "test" and scored["records"] == [] and "no_hand_reported" in scored["summary"]
    assert main([str(tmp_path / "b"), "--overlays", str(tmp_path / "ov")]) == 2
    assert not (tmp_path / "ov").exists()
    assert main([str(tmp_path / "b"), "--json", str(out), "--allow-test-inspection"]) == 0
    assert len(json.loads(out.read_text())["b"]["records"]) == 2


def test_a_scene_set_can_be_rendered_with_one_sensor_and_one_shape_and_is_otherwise_unchanged() -> None:
    own = scene_set("scenes_dev", repeats=2)
    assert {s.sensor for s in own if s.kind == "back"} == {"structured"}  # (why --sensor exists)
    wide = MeshShape(1.0, 1.12, 1.0)
    tof = scene_set("scenes_dev", repeats=2, sensor="tof", shape=wide)
    assert {s.sensor for s in tof} == {"tof"} and {s.shape for s in tof} == {wide}
    assert [(s.name, s.seed, s.frames) for s in tof] == [(s.name, s.seed, s.frames) for s in own]
