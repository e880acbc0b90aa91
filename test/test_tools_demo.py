"""``demo`` (``make demo``): the node on loopback DDS, fed a bag; rates, latency, Table-1 row, video."""

from __future__ import annotations

import io
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools import demo
from hand_sog_tracker.tools.make_sample_bags import write_sample_bag
from helpers import test_domain

DOMAIN_ID = test_domain(3)  # this test's own ROS domain (loopback DDS)
FRAMES = 10


def _read_video(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    cap.release()
    return frames


def _cyan_pixels(img: np.ndarray) -> int:
    """Pixels of the skeleton's colour (BGR 255, 255, 0; mp4 blurs it a little)."""
    b, g, r = (img[:, :, i].astype(int) for i in range(3))
    return int(np.sum((b > 170) & (g > 170) & (r < 110)))


def test_demo_runs_the_node_and_prints_rates_latency_table_and_writes_a_video(tmp_path: Path) -> None:
    bag = write_sample_bag(tmp_path / "wave", "fingerwave", FRAMES, width=320, height=240).path
    out = io.StringIO()
    res = demo.run_demo(bag, domain_id=DOMAIN_ID, video=tmp_path / "demo.mp4", stream=out)
    text = out.getvalue()
    assert text == res.text + "\n"

    # Topic rates: the three per-frame outputs at about the 30 Hz replay, /diagnostics at 1 Hz.
    for topic in ("hand/joint_states", "hand/fingertips", "hand/keypoints"):
        m = re.search(rf"^  /demo/{topic}\s+([\d.]+) Hz  \((\d+) messages?\)$", text, re.M)
        assert m, (topic, text)
        hz, n = float(m.group(1)), int(m.group(2))
        assert FRAMES // 2 <= n <= FRAMES, (topic, n)
        assert 12.0 < hz < 60.0, (topic, hz)
        assert res.counts[f"/demo/{topic}"] == n
    m = re.search(r"^  /diagnostics\s+([\d.]+) Hz", text, re.M)
    assert m and 0.5 < float(m.group(1)) < 2.0, text

    # Latency and frames answered, as measured.
    m = re.search(r"^end-to-end latency .*: median ([\d.]+) ms, p95 ([\d.]+) ms$", text, re.M)
    assert m, text
    median, p95 = float(m.group(1)), float(m.group(2))
    assert 0.0 < median <= p95 < 1000.0
    assert median == pytest.approx(res.evaluation.timing.median_ms, abs=0.06)
    m = re.search(r"^frames answered: (\d+) of (\d+) published \((\d+) with a hand", text, re.M)
    assert m, text
    answered, published, tracked = map(int, m.groups())
    assert published == FRAMES and answered >= FRAMES // 2 and tracked >= FRAMES // 2

    # The Table-1 row: this bag, its split, frames, mean error, % below 15/20/25/30 mm, ms.
    row = next(line for line in text.splitlines() if line.startswith("wave "))
    cells = row.split()
    assert cells[:3] == ["wave", "capsule", str(FRAMES)]
    mean_mm = float(cells[3])
    assert mean_mm == pytest.approx(res.evaluation.errors.mean_mm, abs=0.06)
    assert mean_mm < 15.0  # the node tracks this easy capsule hand
    assert all(c.endswith("%") for c in cells[4:8])
    assert float(cells[8]) == pytest.approx(median, abs=0.06)

    # The video: every frame, enlarged to 640 wide, with the node's skeleton drawn over the depth.
    assert res.video == tmp_path / "demo.mp4" and f": {res.video}" in text
    frames = _read_video(res.video)
    assert len(frames) == FRAMES == res.video_frames
    assert frames[0].shape == (480, 640, 3)
    drawn = [_cyan_pixels(f) for f in frames]
    assert sum(d > 100 for d in drawn) >= answered - 1, drawn


def test_demo_refuses_a_bag_of_the_test_split(tmp_path: Path) -> None:
    bag = write_sample_bag(tmp_path / "held_out", "fingerwave", 1, width=160, height=120, split="test").path
    with pytest.raises(InputError, match="held out"):
        demo.run_demo(bag, domain_id=DOMAIN_ID, video=tmp_path / "x.mp4", stream=io.StringIO())
    assert not (tmp_path / "x.mp4").exists()
    assert demo.main([str(bag), "--domain-id", str(DOMAIN_ID), "--video", str(tmp_path / "x.mp4")]) == 2


def _frames(n: int = 4) -> list[np.ndarray]:
    return [np.full((40, 60, 3), 40 * i, np.uint8) for i in range(n)]


def test_write_video_falls_back_to_gif_then_png(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from PIL import Image

    class Broken:  # an OpenCV without the mp4v codec: the writer never opens
        def __init__(self, *args: object) -> None:
            pass

        def isOpened(self) -> bool:
            return False

        def release(self) -> None:
            pass

    monkeypatch.setattr(demo.cv2, "VideoWriter", Broken)
    gif = demo.write_video(_frames(), tmp_path / "v.mp4", fps=10)
    assert gif == tmp_path / "v.gif"
    with Image.open(gif) as im:
        assert im.n_frames == 4 and im.size == (60, 40)

    monkeypatch.setitem(__import__("sys").modules, "PIL", None)  # no Pillow either
    png = demo.write_video(_frames(), tmp_path / "w.mp4", fps=10)
    assert png == tmp_path / "w.png"
    strip = cv2.imread(str(png))
    assert strip.shape == (40, 4 * 60, 3)
    assert [int(strip[0, 60 * i + 1, 0]) for i in range(4)] == [0, 40, 80, 120]


def _magenta_pixels(img: np.ndarray) -> int:
    """Pixels of the left hand's skeleton colour (BGR 255, 0, 255)."""
    b, g, r = (img[:, :, i].astype(int) for i in range(3))
    return int(np.sum((b > 170) & (g < 110) & (r > 170)))


def test_demo_of_a_two_hand_bag_draws_both_hands(tmp_path: Path) -> None:
    """A two-hand DEMO_BAG: the node runs with max_hands 2, each hand is scored by its label and
    drawn (left magenta, right cyan) once its label is decided."""
    bag = Path(__file__).resolve().parents[1] / "bags" / "twohands_dev" / "apart"
    out = io.StringIO()
    res = demo.run_demo(bag, domain_id=DOMAIN_ID, video=tmp_path / "two.mp4", stream=out, max_frames=10, rate=0.25)
    text = out.getvalue()
    assert res.evaluation.extra["node_params"]["max_hands"] == 2
    cells = [line.split() for line in text.splitlines()]
    rows = {c[2]: c for c in cells if c[:1] == ["apart"] and c[2] in ("left", "right")}
    assert set(rows) == {"left", "right"}, text
    for side in ("left", "right"):
        assert float(rows[side][3]) < 12.0, text  # each label on its own hand
    last = _read_video(res.video)[-1]
    assert _magenta_pixels(last) > 100 and _cyan_pixels(last) > 100
