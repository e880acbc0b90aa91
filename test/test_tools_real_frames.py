"""The labelled-frame tool (``tools/real_frames.py``) on frames rendered here, labelled with their truth."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hand_sog_tracker.core.hand_model import default_hand_model, rest_pose
from hand_sog_tracker.core.kinematics import fingertips
from hand_sog_tracker.errors import InputError
from hand_sog_tracker.synth.render import RenderOptions, render_depth
from hand_sog_tracker.tools.real_frames import VARIANTS, Variant, labelled_frame, main, run_real_frames
from helpers import INTR


def _write_frames(root: Path, poses: dict[int, np.ndarray]) -> dict:
    """Render each pose of the default right hand into ``root/<frame>/depth.png`` (uint16 mm)
    and return labels in the format of ``test/data/realsense_fingertips.json`` (true tips)."""
    model = default_hand_model()
    frames = {}
    for frame, theta in poses.items():
        depth = render_depth(model, theta, INTR, RenderOptions(noise_mm=0.0), rng=np.random.default_rng(frame))
        (root / str(frame)).mkdir(parents=True)
        cv2.imwrite(str(root / str(frame) / "depth.png"), np.round(depth).astype(np.uint16))
        tips = fingertips(model, theta)
        uv = INTR.project(tips)
        tip_list = [{"u": float(u), "v": float(v), "depth_mm": float(z)} for (u, v), z in zip(uv, tips[:, 2])]
        frames[str(frame)] = {"tips": tip_list}
    k = {"fx": INTR.fx, "fy": INTR.fy, "cx": INTR.cx, "cy": INTR.cy, "width": INTR.width, "height": INTR.height}
    return {"intrinsics": k, "frames": frames}


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("frames")
    open_hand = rest_pose((-10.0, 40.0, 420.0))
    turned = open_hand.copy()
    turned[5] = 0.3  # turned in the image plane
    return root, _write_frames(root, {1: open_hand, 2: turned})


def test_labels_move_with_the_image_and_mirror_with_it(frames: tuple[Path, dict]) -> None:
    root, labels = frames
    depth, intr, truth = labelled_frame(root, labels, 1)
    for variant in (Variant(du=1), Variant(dv=-1), Variant(dz_mm=3.0)):
        d2, i2, t2 = labelled_frame(root, labels, 1, variant=variant)
        uv, uv2 = intr.project(truth), i2.project(t2)
        np.testing.assert_allclose(uv2 - uv, [[variant.du, variant.dv]] * 5, atol=1e-9)
        np.testing.assert_allclose(t2[:, 2] - truth[:, 2], variant.dz_mm, atol=1e-9)
        np.testing.assert_array_equal(d2 > 0, np.roll(depth > 0, (variant.dv, variant.du), axis=(0, 1)))
    dm, im, tm = labelled_frame(root, labels, 1, mirror=True)
    np.testing.assert_array_equal(dm, depth[:, ::-1])
    # The mirrored camera sees the mirrored hand: x flips sign about the principal point.
    np.testing.assert_allclose(tm * [-1.0, 1.0, 1.0], truth, atol=1e-9)
    assert im.cx == INTR.width - 1 - INTR.cx


def test_rendered_frames_score_within_a_few_mm_as_right_and_left_hands(frames: tuple[Path, dict]) -> None:
    root, labels = frames
    runs = run_real_frames(root, labels, [1, 2], mirrored=True, variants=VARIANTS[:2])
    assert len(runs) == 8 and {r["mirror"] for r in runs} == {False, True}
    for r in runs:
        assert r["errors_mm"] is not None, r
        assert max(r["errors_mm"]) < 10.0, r


def test_missing_frames_and_other_image_sizes_are_refused(frames: tuple[Path, dict], tmp_path: Path) -> None:
    root, labels = frames
    with pytest.raises(InputError, match="no labels"):
        labelled_frame(root, labels, 9)
    small = dict(labels, intrinsics=dict(labels["intrinsics"], width=160, height=120))
    with pytest.raises(InputError, match="320x240"):
        labelled_frame(root, small, 1)
    (tmp_path / "1").mkdir()
    with pytest.raises(InputError, match="cannot read"):
        labelled_frame(tmp_path, labels, 1)


def test_command_prints_the_summary_and_writes_every_run(
    frames: tuple[Path, dict], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root, labels = frames
    label_file = tmp_path / "labels.json"
    label_file.write_text(json.dumps(labels))
    out = tmp_path / "runs.json"
    args = [str(root), "--labels", str(label_file), "--frames", "1", "--no-mirror", "--unperturbed", "--json", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "frame 1: mean" in text and "all 1 runs" in text and "5 of 5 fingertips within 15 mm" in text
    assert len(json.loads(out.read_text())["runs"]) == 1
    assert main([str(root), "--labels", str(label_file), "--frames", "2", "--no-mirror", "--wide"]) == 0
    wide = capsys.readouterr().out
    assert "all 16 runs" in wide and "runs over 20 mm 0" in wide  # a rendered open hand, shifted
    assert main([str(root), "--labels", str(tmp_path / "absent.json")]) == 2
    assert "real_frames:" in capsys.readouterr().err
