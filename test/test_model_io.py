"""The user hand-model file: round trip, atomic writes, clear errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from hand_sog_tracker.core import model_io
from hand_sog_tracker.core.hand_model import HandShape
from hand_sog_tracker.core.model_io import (
    default_model_path,
    load_hand_shape,
    read_model_file,
    save_hand_shape,
)
from hand_sog_tracker.errors import InputError, ModelFileError


def test_round_trip_creates_directories_and_keeps_extras(tmp_path: Path) -> None:
    rng = np.random.default_rng(11)
    shape = HandShape(*rng.uniform(0.8, 1.25, 4))
    path = tmp_path / "a" / "b" / "hand_model.yaml"
    written = save_hand_shape(path, shape, right=False, extra={"energy_before": 0.5, "frames": 3, "note": 'x: "y" # z', "ok": True})
    assert written == path and path.is_file()
    loaded, right = load_hand_shape(path)
    assert right is False
    np.testing.assert_array_equal(loaded.as_array(), shape.as_array())  # repr() round-trips floats
    values = read_model_file(path)
    assert values["energy_before"] == 0.5 and values["frames"] == 3 and values["ok"] is True
    assert values["note"] == 'x: "y" # z'
    assert sorted(p.name for p in path.parent.iterdir()) == ["hand_model.yaml"]  # no temp files


def test_overwrite_replaces_the_file(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    save_hand_shape(path, HandShape(length=1.1), right=True)
    save_hand_shape(path, HandShape(length=0.9), right=True)
    assert load_hand_shape(path)[0].length == 0.9


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "m.yaml"
    save_hand_shape(path, HandShape(width=1.2), right=True)
    before = path.read_text()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(model_io.os, "replace", broken_replace)
    with pytest.raises(ModelFileError, match="cannot write .*disk full"):
        save_hand_shape(path, HandShape(width=0.9), right=True)
    assert path.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.yaml"]


def test_comments_and_blank_lines_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(
        "# my hand\n\nformat: hand_sog_tracker/hand_model\nversion: 1\n"
        "handedness: 'right'  \nlength: 1.05 # measured\nwidth: 1\ndepth: 0.95\nsigma: 1.0\n"
    )
    shape, right = load_hand_shape(path)
    assert right and shape == HandShape(1.05, 1.0, 0.95, 1.0)


GOOD = "format: hand_sog_tracker/hand_model\nversion: 1\nhandedness: right\nlength: 1.0\nwidth: 1.0\ndepth: 1.0\nsigma: 1.0\n"


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "not a hand model file"),
        ("just some words\n", "expected 'key: value'"),
        (GOOD.replace("format: hand_sog_tracker/hand_model", "format: other"), "not a hand model file"),
        (GOOD.replace("version: 1", "version: 2"), "unsupported version 2"),
        (GOOD.replace("sigma: 1.0\n", ""), "missing keys sigma"),
        (GOOD.replace("handedness: right", "handedness: both"), "handedness must be"),
        (GOOD.replace("length: 1.0", "length: 5.0"), r"length must be in \[0.3, 3.0\]"),
        (GOOD.replace("width: 1.0", "width: nan"), "width must be in"),
        (GOOD.replace("depth: 1.0", "depth: true"), "depth must be a number"),
        (GOOD.replace("depth: 1.0", "depth: big"), "depth must be a number"),
        (GOOD + "length: 1.1\n", "duplicate key 'length'"),
        (GOOD.replace("sigma: 1.0", "sigma:"), "has no value"),
        (GOOD + 'note: "unterminated\n', "bad value for 'note'"),
    ],
)
def test_malformed_files_raise_model_file_error(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=match):
        load_hand_shape(path)


def test_missing_and_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ModelFileError, match="does not exist"):
        load_hand_shape(tmp_path / "nope.yaml")
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ModelFileError, match="cannot read"):
        load_hand_shape(tmp_path / "bin.yaml")


def test_bad_extras_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="reserved"):
        save_hand_shape(tmp_path / "m.yaml", HandShape(), True, extra={"length": 2.0})
    with pytest.raises(InputError, match="reserved"):
        save_hand_shape(tmp_path / "m.yaml", HandShape(), True, extra={"bad key": 1})
    with pytest.raises(InputError, match="finite"):
        save_hand_shape(tmp_path / "m.yaml", HandShape(), True, extra={"e": float("inf")})
    assert not (tmp_path / "m.yaml").exists()


def test_default_path_follows_ros_home(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ROS_HOME", str(tmp_path))
    assert default_model_path() == tmp_path / "hand_sog_tracker" / "hand_model.yaml"
    monkeypatch.delenv("ROS_HOME")
    assert default_model_path() == Path(os.path.expanduser("~/.ros/hand_sog_tracker/hand_model.yaml"))


def test_calibration_metadata_round_trips_and_old_names_still_load(tmp_path: Path) -> None:
    from hand_sog_tracker.core.calibration import CalibrationResult, Validation
    from hand_sog_tracker.core.hand_model import default_hand_model
    from hand_sog_tracker.core.model_io import calibration_metadata, read_calibration_info

    shape = HandShape(1.1, 0.95, 1.02, 1.02)
    poses = np.arange(2 * 26, dtype=float).reshape(2, 26) / 7.0
    res = CalibrationResult(
        shape, default_hand_model().scaled(shape), poses[0], 0.71, 0.86, 0.42,
        poses=poses, used_frames=(0, 2), validation=Validation(3, 0.80, 0.84, 0.01),
    )
    extra = calibration_metadata(res, fit_stamps_ns=[1_700_000_000_100_000_000, 5], holdout_stamps_ns=[7])
    path = save_hand_shape(tmp_path / "m.yaml", shape, right=True, extra=extra)
    assert load_hand_shape(path) == (shape, True)
    info = read_calibration_info(path)
    assert info["fit_frames"] == 2 and info["holdout_frames"] == 3
    assert info["fit_stamps"] == "1700000000.100000000 0.000000005" and info["holdout_stamps"] == "0.000000007"
    assert info["fit_score_before"] == 0.71 and info["fit_score_after"] == 0.86
    assert info["holdout_score_current"] == 0.80 and info["holdout_score_fitted"] == 0.84
    assert info["guard_margin"] == 0.01 and info["fit_seconds"] == 0.42
    np.testing.assert_allclose([float(x) for x in str(info["fit_pose_1"]).split()], poses[1], rtol=1e-3)
    assert "calibrated_at" in info and "length" not in info
    # A file written before the rename: energy_* and frames are read under the new names.
    old = save_hand_shape(tmp_path / "old.yaml", shape, right=True, extra={"energy_before": 0.5, "energy_after": 0.7, "frames": 3})
    assert load_hand_shape(old) == (shape, True)
    assert read_calibration_info(old) == {"fit_score_before": 0.5, "fit_score_after": 0.7, "fit_frames": 3}
