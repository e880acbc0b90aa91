"""NodeHarness: tracker_node in a child process on loopback DDS, with parameters, inputs and outputs."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.errors import HandSogError, InputError
from hand_sog_tracker.tools.node_harness import NodeHarness, ros_param_args
from helpers import test_domain

DOMAIN = test_domain(4)
T0 = 1_700_000_000_000_000_000
DT = 33_333_333

pytest.importorskip("hand_sog_tracker.ros.node", reason="the tracker node (hand_sog_tracker.ros.node) is not there")


def test_ros_param_args_keep_the_types() -> None:
    args = ros_param_args({"iterations": 7, "far_mm": 700.0, "debug_image": True, "handedness": "left"})
    assert args == ["-p", "iterations:=7", "-p", "far_mm:=700.0", "-p", "debug_image:=true", "-p", "handedness:='left'"]


def test_harness_runs_the_node_with_parameters_and_collects_its_outputs(tmp_path: Path) -> None:
    from rcl_interfaces.srv import GetParameters

    from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence

    intr = default_intrinsics(160, 120)
    frames = list(synthetic_sequence("flexex", 2, intrinsics=intr, seed=3))
    env_before = os.environ.get("ROS_DOMAIN_ID")
    with NodeHarness(DOMAIN, params={"iterations": 7}, workdir=tmp_path / "w", namespace="/harness_test") as h:
        # the node really runs with the parameter (asked through its parameter service)
        client = h.node.create_client(GetParameters, "/harness_test/hand_sog_tracker/get_parameters")
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(GetParameters.Request(names=["iterations", "user_model_path"]))
        t0 = time.monotonic()
        while not future.done() and time.monotonic() - t0 < 10.0:
            time.sleep(0.02)
        values = future.result().values
        assert values[0].integer_value == 7
        assert values[1].string_value == str(tmp_path / "w" / "no_user_model.yaml")
        stamps = []
        for i, f in enumerate(frames):
            stamp = T0 + i * DT
            stamps.append(stamp)
            for _ in range(8):  # inputs are best effort: re-send until the node answers
                h.publish_depth(f.depth_mm, intr, stamp)
                if h.wait_for(lambda out, s=stamp: s in out.markers, timeout_s=2.0):
                    break
        out = h.outputs
        for stamp, f in zip(stamps, frames):
            tips = out.markers[stamp].fingertips_mm
            assert tips is not None and tips.shape == (5, 3)
            assert float(np.mean(np.linalg.norm(tips - f.fingertips_mm, axis=1))) < 30.0
        assert h.wait_for(lambda o: all(s in o.joint_states for s in stamps), timeout_s=5.0)
        assert h.outputs.joint_states[stamps[-1]][1].shape == (20,)
        assert h.wait_for(lambda o: any(c["processed"] >= 2 for _, c in o.diagnostics), timeout_s=5.0)
        assert os.environ["ROS_DOMAIN_ID"] == str(DOMAIN)
        proc = h.process
    assert proc is not None and not proc.alive()
    assert (tmp_path / "w" / "tracker_node.log").is_file()
    assert os.environ.get("ROS_DOMAIN_ID") == env_before  # restored
    assert h.stop() is not None  # idempotent


def test_harness_reports_a_node_that_rejects_its_parameters(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="params file not found"):
        NodeHarness(DOMAIN, params_file=tmp_path / "missing.yaml").start()
    t0 = time.monotonic()
    with pytest.raises(HandSogError, match=r"the tracker node exited with code \d+ before connecting") as exc:
        with NodeHarness(DOMAIN, params={"near_mm": 1500.0}, namespace="/harness_bad"):
            pass
    assert "near_mm" in str(exc.value)  # the end of the node's log tells why
    assert time.monotonic() - t0 < 25.0


def test_diagnostic_counters_can_be_limited_to_one_node() -> None:
    from types import SimpleNamespace as NS

    from hand_sog_tracker.tools.node_harness import diagnostic_counters

    def status(name: str, received: int) -> NS:
        keys = {"frames_received": received, "frames_processed": 1, "frames_dropped": 0, "frames_rejected": 0}
        return NS(name=name, values=[NS(key=k, value=str(v)) for k, v in keys.items()])

    msg = NS(
        status=[status("hand_sog_tracker: /a/hand_sog_tracker", 3), status("hand_sog_tracker: /b/hand_sog_tracker", 7)]
    )
    assert diagnostic_counters(msg)["received"] == 3
    assert diagnostic_counters(msg, "/b/hand_sog_tracker")["received"] == 7
    assert diagnostic_counters(msg, "/c/hand_sog_tracker") is None
    assert diagnostic_counters(NS(status=[NS(name="other", values=[])])) is None
