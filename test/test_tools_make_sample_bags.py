"""make_sample_bags: deterministic content, bag convention, CLI (tiny images, few frames)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.synth.motions import MOTIONS
from hand_sog_tracker.synth.render import RenderOptions
from hand_sog_tracker.synth.sequence import default_intrinsics, synthetic_sequence
from hand_sog_tracker.tools import bagio
from hand_sog_tracker.tools.bagio import DepthBagReader
from hand_sog_tracker.tools.make_sample_bags import (
    BASE_STAMP_NS,
    bag_digest,
    main,
    motion_seed,
    write_sample_bag,
)


def test_same_bag_on_rerun_and_different_with_another_seed(tmp_path: Path) -> None:
    a = write_sample_bag(tmp_path / "a", "pinch", 3, width=96, height=72)
    b = write_sample_bag(tmp_path / "b", "pinch", 3, width=96, height=72)
    c = write_sample_bag(tmp_path / "c", "pinch", 3, width=96, height=72, seed=motion_seed("pinch") + 1)
    assert a.frames == 3 and a.size_bytes > 0
    assert bag_digest(a.path) == bag_digest(b.path)
    assert bag_digest(a.path) != bag_digest(c.path)
    # the container does not matter, the messages do
    d = write_sample_bag(tmp_path / "d", "pinch", 3, width=96, height=72, storage="sqlite3")
    assert bag_digest(d.path) == bag_digest(a.path)


def test_bag_follows_the_convention(tmp_path: Path) -> None:
    intr = default_intrinsics(96, 72)
    bag = write_sample_bag(tmp_path / "fw", "fingerwave", 4, width=96, height=72)
    seq = list(
        synthetic_sequence(
            "fingerwave", 4, intrinsics=intr, seed=motion_seed("fingerwave"), options=RenderOptions(background_mm=None)
        )
    )
    with bagio.open_bag(bag.path) as reader:
        table = bagio.topic_table(reader)
        assert table == {
            bagio.INFO_TOPIC: (bagio.INFO_TYPE, 4),
            bagio.DEPTH_TOPIC: (bagio.IMAGE_TYPE, 4),
            bagio.GT_TOPIC: (bagio.GT_TYPE, 4),
        }
        frame_ids = set()
        for conn, log_ns, raw in bagio.iter_messages(reader, bag.path, list(reader.connections)):
            msg = reader.deserialize(raw, conn.msgtype)
            frame_ids.add(msg.header.frame_id)
            assert bagio.stamp_to_ns(msg.header.stamp) == log_ns
            if conn.topic == bagio.DEPTH_TOPIC:
                assert (msg.encoding, msg.width, msg.height, msg.step) == ("16UC1", 96, 72, 192)
    assert frame_ids == {"camera_depth_optical_frame"}
    with DepthBagReader(bag.path) as r:
        frames = list(r.frames())
    assert [f.stamp_ns - BASE_STAMP_NS for f in frames] == [0, 33_333_333, 66_666_667, 100_000_000]
    for f, s in zip(frames, seq):
        assert f.intrinsics is not None
        assert (f.intrinsics.fx, f.intrinsics.cx) == pytest.approx((intr.fx, intr.cx))
        assert f.truth_mm is not None and f.depth_mm is not None
        np.testing.assert_allclose(f.truth_mm, s.fingertips_mm, atol=1e-9)
        np.testing.assert_array_equal(f.depth_mm, np.where(s.depth_mm > 0, np.rint(s.depth_mm), 0))
        assert np.count_nonzero(f.depth_mm) > 100  # the hand is in view


def test_32fc1_bag(tmp_path: Path) -> None:
    bag = write_sample_bag(tmp_path / "hi", "abdadd", 1, width=128, height=96, encoding="32FC1")
    intr = default_intrinsics(128, 96)
    (s,) = synthetic_sequence(
        "abdadd", 1, intrinsics=intr, seed=motion_seed("abdadd"), options=RenderOptions(background_mm=None)
    )
    with DepthBagReader(bag.path) as r:
        (f,) = list(r.frames())
    assert f.depth_mm is not None
    np.testing.assert_allclose(f.depth_mm, s.depth_mm, rtol=1e-6, atol=1e-3)


def test_cli_writes_replaces_and_rejects(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bags"
    args = ["--out", str(out), "--frames", "2", "--motions", "flexex", "random"]
    assert main(args) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["flexex", "flexex_640x480_32fc1", "random"]
    assert "wrote 3 bags" in capsys.readouterr().out
    first = bag_digest(out / "flexex")
    assert main(args + ["--no-hires"]) == 0  # replaces the existing bags with identical ones
    assert bag_digest(out / "flexex") == first
    assert not any(p.name.endswith(".partial") for p in out.iterdir())
    assert main(args + ["--no-hires", "--no-force"]) == 2
    assert "exists already" in capsys.readouterr().err
    (tmp_path / "x" / "pinch").mkdir(parents=True)
    (tmp_path / "x" / "pinch" / "notes.txt").write_text("keep me")
    assert main(["--out", str(tmp_path / "x"), "--frames", "1", "--motions", "pinch", "--no-hires"]) == 2
    assert "not a rosbag2 directory" in capsys.readouterr().err
    assert (tmp_path / "x" / "pinch" / "notes.txt").exists()
    assert main(["--out", str(out), "--motions", "juggling"]) == 2
    assert "unknown motion" in capsys.readouterr().err


def test_every_motion_has_a_distinct_seed() -> None:
    seeds = {motion_seed(m) for m in MOTIONS}
    assert len(seeds) == len(MOTIONS)
    assert all(0 <= s < 2**31 for s in seeds)


# --- mesh renderer, sidecars, protocol sets ------------------------------------------------------

from hand_sog_tracker.errors import InputError  # noqa: E402


def test_sidecar_for_both_renderers_and_mesh_bag(tmp_path: Path) -> None:
    import json

    from hand_sog_tracker.synth.mesh import MeshRenderOptions, MeshShape, mesh_sequence
    from hand_sog_tracker.tools.make_sample_bags import SIDECAR

    cap = write_sample_bag(tmp_path / "cap", "pinch", 2, width=96, height=72)
    side = json.loads((cap.path / SIDECAR).read_text())
    assert side["renderer"] == "capsule" and side["split"] == "capsule" and side["handedness"] == "right"
    assert (side["motion"], side["seed"], side["frames"], side["width"], side["height"], side["encoding"]) == (
        "pinch", motion_seed("pinch"), 2, 96, 72, "16UC1",
    )
    shape = MeshShape(0.9, 1.05, 0.95)
    mesh = write_sample_bag(
        tmp_path / "mesh", "fistopen", 3, width=96, height=72, renderer="mesh", sensor="structured",
        shape=shape, right=False, seed=11, split="test",
    )
    side = json.loads((mesh.path / SIDECAR).read_text())
    assert side["renderer"] == "mesh" and side["split"] == "test" and side["sensor"] == "structured"
    assert side["handedness"] == "left" and side["seed"] == 11
    assert side["shape"] == {"length": 0.9, "palm_width": 1.05, "thickness": 0.95}
    seq = list(mesh_sequence("fistopen", 3, default_intrinsics(96, 72), shape, right=False, seed=11,
                             options=MeshRenderOptions(sensor="structured")))
    with DepthBagReader(mesh.path) as r:
        frames = list(r.frames())
    assert len(frames) == 3
    for f, s in zip(frames, seq):
        np.testing.assert_allclose(f.truth_mm, s.fingertips_mm, atol=1e-9)
        np.testing.assert_array_equal(f.depth_mm, np.where(s.depth_mm > 0, np.rint(s.depth_mm), 0))
    # sensor/shape are mesh options; the new motions work with the capsule renderer too.
    assert write_sample_bag(tmp_path / "x", "fistopen", 1, width=96, height=72).frames == 1
    with pytest.raises(InputError):
        write_sample_bag(tmp_path / "y", "pinch", 1, width=96, height=72, sensor="tof")


def test_protocol_sets_differ_and_follow_the_plan() -> None:
    from hand_sog_tracker.tools.make_sample_bags import PROTOCOL_MOTIONS, protocol_set

    dev, test = protocol_set("mesh_dev"), protocol_set("mesh_test")
    for specs, split in ((dev, "dev"), (test, "test")):
        assert [s.motion for s in specs] == list(PROTOCOL_MOTIONS) and len(PROTOCOL_MOTIONS) == 9
        assert {s.split for s in specs} == {split}
        hires = [s for s in specs if s.width == 640]
        assert len(hires) == 2 and all(s.encoding == "32FC1" and s.name.endswith("_640x480_32fc1") for s in hires)
        assert all(s.encoding == "16UC1" and s.frames == 60 for s in specs if s.width == 320)
        left = [s for s in specs if not s.right]
        assert len(left) == 1 and left[0].name.endswith("_left")
        assert {s.sensor for s in specs} == {"tof", "structured"} == {s.sensor for s in hires}
        assert len({s.shape for s in specs}) == 3
        assert all(0.85 <= f <= 1.15 for s in specs for f in s.shape.as_tuple())
    assert not {s.seed for s in dev} & {s.seed for s in test}
    assert not {s.shape for s in dev} & {s.shape for s in test}
    assert [(s.motion, s.sensor) for s in dev] != [(s.motion, s.sensor) for s in test]
    assert protocol_set("mesh_dev") == dev  # deterministic
    with pytest.raises(InputError):
        protocol_set("mesh_train")


def test_cli_mesh_renderer_and_sets(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    out = tmp_path / "m"
    assert main(["--out", str(out), "--frames", "2", "--renderer", "mesh", "--sensor", "tof",
                 "--motions", "rotate", "--no-hires"]) == 0
    assert json.loads((out / "rotate" / "hand_sog_sample.json").read_text())["sensor"] == "tof"
    assert main(["--set", "mesh_test", "--out", str(tmp_path / "t"), "--frames", "2"]) == 0
    assert "wrote 9 bags" in capsys.readouterr().out
    names = sorted(p.name for p in (tmp_path / "t").iterdir())
    assert "rotate_640x480_32fc1" in names and "tigergrasp_left" in names and len(names) == 9
    side = json.loads((tmp_path / "t" / "tigergrasp_left" / "hand_sog_sample.json").read_text())
    assert side["split"] == "test" and side["handedness"] == "left" and side["frames"] == 2
    for bad in (
        ["--sensor", "tof"],  # the capsule renderer has no sensor option
        ["--set", "mesh_dev", "--motions", "pinch"],  # a set fixes its motions
    ):
        with pytest.raises(SystemExit) as exc:
            main(bad + ["--out", str(tmp_path / "z")])
        assert exc.value.code == 2
    assert main(["--out", str(tmp_path / "z"), "--renderer", "mesh", "--motions", "juggling"]) == 2
    assert "unknown motion" in capsys.readouterr().err


def test_a_protocol_set_at_another_rate_keeps_its_hands_and_split(tmp_path: Path, monkeypatch) -> None:
    """``--set mesh_test --fps 100``: the held-out set's hands, seeds and split, 2 s of motion
    per bag at 100 Hz (200 frames), into bags/mesh_test_100hz (the 30 fps set stays)."""
    import hand_sog_tracker.tools.make_sample_bags as msb

    calls = []

    def fake(path, motion, frames, width, height, encoding, **kw):
        calls.append((Path(path), motion, frames, width, kw))
        return msb.SampleBag(Path(path), motion, frames, width, height, encoding, 1, 0.0)

    monkeypatch.setattr(msb, "write_sample_bag", fake)
    monkeypatch.chdir(tmp_path)
    assert msb.main(["--set", "mesh_test", "--fps", "100"]) == 0
    specs = msb.protocol_set("mesh_test", 200, 66)
    assert [c[0] for c in calls] == [Path("bags/mesh_test_100hz") / s.name for s in specs]
    assert [c[2] for c in calls] == [s.frames for s in specs]
    assert {c[4]["fps"] for c in calls} == {100.0}
    assert [(c[4]["seed"], c[4]["shape"], c[4]["split"]) for c in calls] == [(s.seed, s.shape, "test") for s in specs]
    calls.clear()
    assert msb.main(["--set", "mesh_dev"]) == 0
    assert calls[0][0].parent == Path("bags/mesh_dev") and calls[0][2] == 60 and calls[0][4]["fps"] == 30.0


def test_fps_samples_the_motion_and_stamps_at_that_rate(tmp_path: Path) -> None:
    import json

    fast = write_sample_bag(tmp_path / "fast", "pinch", 4, width=96, height=72, fps=100.0)
    slow = write_sample_bag(tmp_path / "slow", "pinch", 4, width=96, height=72)
    with DepthBagReader(fast.path) as r:
        frames = list(r.frames())
    assert [f.stamp_ns - BASE_STAMP_NS for f in frames] == [0, 10_000_000, 20_000_000, 30_000_000]
    # Same seed, finer sampling of the same motion: the first frame agrees, the later ones move less.
    with DepthBagReader(slow.path) as r:
        slow_frames = list(r.frames())
    np.testing.assert_allclose(frames[0].truth_mm, slow_frames[0].truth_mm, atol=1e-9)
    moved_fast = np.abs(frames[3].truth_mm - frames[0].truth_mm).max()
    moved_slow = np.abs(slow_frames[3].truth_mm - slow_frames[0].truth_mm).max()
    assert 0.0 < moved_fast < moved_slow
    assert json.loads((fast.path / "hand_sog_sample.json").read_text())["fps"] == 100.0
    assert "fps" not in json.loads((slow.path / "hand_sog_sample.json").read_text())  # 30 fps: as before
    with pytest.raises(Exception, match="fps"):
        write_sample_bag(tmp_path / "bad", "pinch", 2, width=96, height=72, fps=0.0)
