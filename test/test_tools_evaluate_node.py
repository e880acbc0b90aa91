"""evaluate_bag --through-node: the ROS node driven over loopback DDS by a tiny bag."""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.core.types import Intrinsics
from hand_sog_tracker.tools.bagio import DepthSample, write_depth_bag
from hand_sog_tracker.tools.evaluate_bag import evaluate_through_node, loopback_dds, main
from hand_sog_tracker.tools.make_sample_bags import write_sample_bag
from helpers import BASE_DOMAIN_ID, test_domain

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "hand_sog_tracker" / "data" / "fastdds_loopback.xml"
DOMAIN = test_domain(2)
BASE = str(BASE_DOMAIN_ID)

pytest.importorskip("hand_sog_tracker.ros.node", reason="the tracker node (hand_sog_tracker.ros.node) is not there")


@pytest.fixture(autouse=True)
def _loopback_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", str(PROFILE))
    monkeypatch.setenv("ROS_DOMAIN_ID", BASE)


def test_loopback_dds_forces_and_restores_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/somewhere/else.xml")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "SUBNET")
    with loopback_dds(DOMAIN) as profile:
        assert profile.read_text() == PROFILE.read_text()
        assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(profile)
        assert os.environ["ROS_DOMAIN_ID"] == str(DOMAIN)
        assert os.environ["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
        assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in os.environ
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/somewhere/else.xml"
    assert os.environ["ROS_DOMAIN_ID"] == BASE
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"


def test_through_node_without_a_hand_accounts_for_every_frame(tmp_path: Path) -> None:
    """No warm-up skip here: the node answers nothing, its counters must still add up."""
    intr = Intrinsics(fx=120.0, fy=120.0, cx=79.5, cy=59.5, width=160, height=120)
    tips = np.tile([0.0, 0.0, 400.0], (5, 1))
    t0 = 1_700_000_000_000_000_000
    write_depth_bag(
        tmp_path / "wall",
        [DepthSample(t0 + i * 33_333_333, np.full((120, 160), 900.0), intr, tips) for i in range(5)],
    )
    ev = evaluate_through_node(tmp_path / "wall", domain_id=DOMAIN, progress=False)
    x = ev.extra
    assert x["frames_published"] == 5 and ev.frames == 5
    st = x["node_stats"]
    assert st["received"] >= 1
    assert st["processed"] + st["rejected"] + st["dropped"] == st["received"]
    # a wall is no hand: the node publishes no markers, nothing is scored as tracked
    assert ev.status_counts == {"no_output": 5}
    assert ev.errors.frames_scored == 5 and ev.errors.frames_with_estimate == 0
    assert ev.errors.pct_below_mm["30"] == 0.0
    assert x["frames_dropped"] == 5 - st["processed"] - st["rejected"]
    assert x["warmup"]["answered"] is True and x["warmup"]["tracking"] is False
    assert os.environ["ROS_DOMAIN_ID"] == BASE  # restored


def test_through_node_cli_on_a_synthetic_hand(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_sample_bag(tmp_path / "b", "flexex", 8, width=160, height=120)
    out = tmp_path / "r.json"
    code = main([str(bag.path), "--through-node", "--domain-id", str(DOMAIN), "--json", str(out), "--rate", "0.5"])
    assert code == 0
    text = capsys.readouterr().out
    assert "end-to-end latency: median" in text and "published 8 frames" in text
    js = json.loads(out.read_text())["bags"][0]
    assert js["mode"] == "through_node" and js["frames"] == 8 and js["domain_id"] == DOMAIN
    keys = ("frames_published", "frames_with_output", "frames_dropped", "latency_ms", "node_stats")
    for key in (*keys, "node_calibration_log"):
        assert key in js
    assert js["warmup"]["answered"] is True
    assert js["frames_with_output"] >= 1, js["node_stats"]
    assert js["status_counts"].get("tracking", 0) >= 1
    assert js["latency_ms"]["median"] > 0.0
    assert math.isfinite(js["mean_fingertip_error_mm"])
    # the node tracks the synthetic hand about as well as the core does (ground truth matched by stamp)
    assert js["mean_fingertip_error_mm"] < 40.0
    assert js["frames_dropped"] + js["frames_with_output"] <= 8


def test_the_node_s_automatic_calibration_is_reported_from_its_log() -> None:
    from hand_sog_tracker.tools.node_eval import _calibration_log

    log = (
        "[INFO] [1704067200.100] [hand_sog_tracker]: tracking started\n"
        "[INFO] [1704067200.600] [hand_sog_tracker]: automatic calibration (attempt 1): fitting ...\n"
        "[INFO] [1704067201.000] [hand_sog_tracker]: automatic calibration refused, the model is unchanged: x\n"
    )
    assert _calibration_log(log) == [
        "automatic calibration (attempt 1): fitting ...",
        "automatic calibration refused, the model is unchanged: x",
    ]
    assert _calibration_log("") == []
    # ... and printed with the bag's table.
    import numpy as np

    from hand_sog_tracker.tools.records import FrameRecord, build_evaluation
    from hand_sog_tracker.tools.report import format_table

    tips = np.zeros((5, 3)) + [0.0, 0.0, 400.0]
    rec = FrameRecord(0, 1, "tracking", tips, tips, 7.0)
    extra = {"node_calibration_log": ["automatic calibration in use"]}
    ev = build_evaluation("b", "through_node", [rec], 1.0, (320, 240), None, extra)
    assert "node: automatic calibration in use" in format_table(ev)


def test_a_node_that_dies_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    intr = Intrinsics(fx=120.0, fy=120.0, cx=79.5, cy=59.5, width=160, height=120)
    write_depth_bag(tmp_path / "b", [DepthSample(10**18, np.full((120, 160), 900.0), intr, np.ones((5, 3)))])
    fake = tmp_path / "fake_python"
    fake.write_text("#!/bin/sh\necho 'cannot start: simulated failure'\nexit 3\n")
    fake.chmod(0o755)
    monkeypatch.setattr("sys.executable", str(fake))
    t0 = time.monotonic()
    assert main([str(tmp_path / "b"), "--through-node", "--domain-id", str(DOMAIN), "--node-timeout", "20"]) == 2
    err = capsys.readouterr().err
    assert "error: the tracker node exited with code 3 before connecting" in err
    assert "simulated failure" in err and "Traceback" not in err
    assert time.monotonic() - t0 < 15.0  # noticed at once, not after the timeout


def test_through_node_scores_a_two_hand_bag_per_hand(tmp_path: Path) -> None:
    """Today's node tracks one hand: the right hand of the ``apart`` scene, the left one missing."""
    from hand_sog_tracker.tools.twohand_bags import twohand_set, write_twohand_bag
    from hand_sog_tracker.tools.twohand_eval import evaluate_two_hands_node

    spec = next(s for s in twohand_set("twohands_dev", frames=6) if s.name == "apart")
    bag, _, _ = write_twohand_bag(tmp_path / "apart", spec)
    s = evaluate_two_hands_node(bag, DOMAIN, split="dev")
    assert s.mode == "through_node" and s.frames == 6
    assert s.per_hand["left"].frames_scored == 6 and s.per_hand["left"].frames_with_estimate == 0
    right = s.per_hand["right"]
    assert right.frames_with_estimate >= 1 and right.mean_mm < 20.0
    assert s.followed["right"]["left"] == 0 and s.swaps == 0 and s.handedness_accuracy_pct == 100.0
