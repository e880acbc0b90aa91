"""Core-mode evaluation of one bag: the core tracker on every depth image, scored.

:func:`evaluate_core` runs the core :class:`~hand_sog_tracker.core.tracker.Tracker`
directly on every depth image of a bag (contract 5, see
:mod:`hand_sog_tracker.tools.bagio`), as fast as it can, deterministically;
``ms per frame`` is the wall time of :meth:`Tracker.process`.  With
``calibrate=True`` the hand model is first fitted on the first (up to three)
usable frames (:func:`~hand_sog_tracker.core.calibration.calibrate`), then the
whole bag is tracked from its start with the fitted model.  Otherwise, with
``auto_calibrate=True`` (the default, as the node's parameter), the hand model is fitted
automatically when :class:`~hand_sog_tracker.core.autocalibration.AutoCalibration` says so,
on the frames the node would keep, in place (the node fits in a child process while it
tracks on; the fit's time is not in ``ms per frame``).  With ``keep_worst=N`` the
depth images of the N worst frames are kept (a bounded
heap) for :func:`hand_sog_tracker.tools.report.write_overlays`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.core.autocalibration import AutoCalibration, FrameHistory, usable_automatically
from hand_sog_tracker.core.hand_model import HandModel
from hand_sog_tracker.core.types import Intrinsics, TrackerConfig, TrackerStatus
from hand_sog_tracker.errors import BagError, CalibrationError, InputError
from hand_sog_tracker.tools.bagio import BagFrame, BagTopics, DepthBagReader
from hand_sog_tracker.tools.records import (
    CALIBRATION_FRAMES,
    FIT_FRAMES,
    STATUS_ERROR,
    Evaluation,
    FrameRecord,
    Progress,
    TrackerLike,
    WorstFrame,
    WorstFrames,
    build_evaluation,
)

__all__ = ["auto_fit", "auto_step", "evaluate_core"]


def _status_name(status: TrackerStatus) -> str:
    return status.value


def _calibrate_model(
    frames: Sequence[BagFrame], config: TrackerConfig, model: HandModel
) -> tuple[HandModel, dict[str, Any]]:
    """Fit the hand model on the first three usable frames, checked on the next three.

    A fit the guard refuses (it does not explain the held-out frames better than ``model``)
    leaves ``model`` in use; the numbers are in the returned info either way.
    """
    from hand_sog_tracker.core.calibration import CalibrationRejected, calibrate

    usable = [f for f in frames if f.depth_mm is not None and f.intrinsics is not None]
    if not usable:
        raise CalibrationError("no usable depth frame at the start of the bag to calibrate on")
    intr = usable[0].intrinsics
    assert intr is not None
    same = [f.depth_mm for f in usable if f.intrinsics == intr and f.depth_mm is not None]
    fit, holdout = same[:FIT_FRAMES], same[FIT_FRAMES:CALIBRATION_FRAMES]
    info: dict[str, Any] = {"frames": len(fit), "holdout_frames": len(holdout)}
    try:
        res = calibrate(fit, intr, config, model, holdout=holdout)
    except CalibrationRejected as err:
        v = err.validation
        info.update(accepted=False, reason=str(err), holdout_score_current=v.score_current,
                    holdout_score_fitted=v.score_fitted)
        return model, info
    info.update(
        accepted=True,
        shape=res.shape.as_dict(),
        fit_score_before=res.score_before,
        fit_score_after=res.score_after,
        seconds=res.seconds,
    )
    if res.validation is not None:
        info.update(holdout_score_current=res.validation.score_current,
                    holdout_score_fitted=res.validation.score_fitted)
    return res.model, info


def auto_fit(tracker: TrackerLike, frames: Any, config: TrackerConfig) -> tuple[dict[str, Any], HandModel | None]:
    """Run one automatic fit in place (``frames``: a due
    :class:`~hand_sog_tracker.core.autocalibration.FitFrames`).  Returns what happened (for the
    evaluation's ``auto_calibration``: ``accepted`` by the guard, ``used``, ``already_fits``) and
    the model to switch to (None: the guard refused the fit or it is not
    :func:`usable_automatically`)."""
    from hand_sog_tracker.core.calibration import CalibrationRejected, calibrate

    args, kwargs = frames.calibrate_args(config, tracker.model, automatic=True)  # type: ignore[attr-defined]
    t0 = time.perf_counter()
    info: dict[str, Any] = {"frames": len(frames.fit), "holdout_frames": len(frames.holdout)}
    model = None
    try:
        res = calibrate(*args, **kwargs)
    except CalibrationRejected as err:
        info.update(accepted=False, already_fits=err.validation.already_fits, reason=str(err))
    except CalibrationError as err:
        info.update(accepted=False, already_fits=False, reason=str(err))
    else:
        used = usable_automatically(res.shape)
        model = res.model if used else None
        info.update(accepted=True, used=used, shape=res.shape.as_dict())
        if res.validation is not None:
            info["by_corroboration"] = res.validation.accepted_by_corroboration
    info["seconds"] = time.perf_counter() - t0
    return info, model


def auto_step(
    tracker: TrackerLike,
    history: FrameHistory,
    auto: AutoCalibration,
    depth_mm: NDArray,
    intrinsics: Intrinsics,
    pose: NDArray[np.float64] | None,
    stamp_ns: int,
    config: TrackerConfig,
) -> dict[str, Any] | None:
    """Remember a frame's tracked ``pose`` (26,) (None: no hand) in ``history`` and run the
    automatic fit in place when ``auto`` says it is due: what :func:`auto_fit` says, or None.
    An accepted fit's model is switched to on the frame
    :meth:`~hand_sog_tracker.core.autocalibration.AutoCalibration.take` names, as in the node."""
    model = auto.take(stamp_ns)
    if model is not None:
        tracker.set_model(model)  # type: ignore[attr-defined]
    history.remember(depth_mm, intrinsics, pose, stamp_ns)
    due = auto.due(history, stamp_ns)
    if due is None:
        return None
    auto.started(stamp_ns)
    info, fitted = auto_fit(tracker, due, config)
    auto.finished(bool(info["accepted"] or info["already_fits"]), fitted)
    return info


def evaluate_core(
    bag: str | Path,
    topics: BagTopics = BagTopics(),
    calibrate: bool = False,
    config: TrackerConfig | None = None,
    tracker: TrackerLike | None = None,
    max_frames: int | None = None,
    progress: bool | None = None,
    keep_worst: int = 0,
    split: str = "-",
    auto_calibrate: bool = True,
) -> Evaluation:
    """Track every depth image of ``bag`` with the core tracker and score it.

    Parameters
    ----------
    bag : str or Path
        Bag path (see :func:`bagio.resolve_bag_path`).
    topics : BagTopics
    calibrate : bool
        Fit the hand model on the first usable frames first (core tracker only).
    config : TrackerConfig, optional
        Tracker configuration (default: ``TrackerConfig()``).
    tracker : TrackerLike, optional
        Use this object instead of a new core Tracker (tests, other trackers).
    max_frames : int, optional
        Stop after this many depth images.
    progress : bool, optional
        Draw a progress bar on stderr; default: only if stderr is a terminal.
    keep_worst : int
        Keep the depth images of this many worst scored frames
        (:attr:`Evaluation.worst`, for overlays); 0 keeps none.
    split : str
        Stored in :attr:`Evaluation.split`.
    auto_calibrate : bool
        Fit the model automatically as the node does (not with ``calibrate``; only for a
        tracker with ``set_model`` and ``model``).

    Returns
    -------
    Evaluation

    Raises
    ------
    BagError
        Bag unreadable, topic missing, no CameraInfo, no ground truth, no
        depth image usable.
    CalibrationError
        ``calibrate`` and the fit failed.
    """
    cfg = config or TrackerConfig()
    calib_info: dict[str, Any] | None = None
    if tracker is None:
        from hand_sog_tracker.core.tracker import Tracker

        tracker = Tracker(cfg)
    elif calibrate and not hasattr(tracker, "set_model"):
        raise InputError("calibrate=True needs a tracker with set_model()")
    records: list[FrameRecord] = []
    history = FrameHistory()
    auto = AutoCalibration(
        enabled=auto_calibrate and not calibrate and hasattr(tracker, "set_model") and hasattr(tracker, "model")
    )
    auto_fits: list[dict[str, Any]] = []
    worst = WorstFrames(keep_worst)
    first_error: str | None = None
    image_size: tuple[int, int] | None = None
    t_start = time.perf_counter()
    with DepthBagReader(bag, topics, require_truth=True) as reader:
        total = reader.n_depth if max_frames is None else min(reader.n_depth, max_frames)
        bar = Progress(total, enabled=progress if progress is not None else None)
        frames: Iterable[BagFrame] = reader.frames()
        if calibrate:
            head: list[BagFrame] = []
            it = iter(frames)
            for f in it:
                head.append(f)
                if sum(h.depth_mm is not None for h in head) >= CALIBRATION_FRAMES:
                    break
            model, calib_info = _calibrate_model(head, cfg, tracker.model)  # type: ignore[attr-defined]
            tracker.set_model(model)  # type: ignore[attr-defined]
            if hasattr(tracker, "reset"):
                tracker.reset()  # type: ignore[attr-defined]
            frames = _chain(head, it)
        try:
            for f in frames:
                if max_frames is not None and len(records) >= max_frames:
                    break
                record, pose, problem = _track_one(tracker, f)
                records.append(record)
                if auto.enabled and f.depth_mm is not None and f.intrinsics is not None:
                    info = auto_step(tracker, history, auto, f.depth_mm, f.intrinsics, pose, f.stamp_ns, cfg)
                    if info is not None:
                        auto_fits.append({"frame": f.index, **info})
                if f.depth_mm is not None and f.intrinsics is not None:
                    make = functools.partial(
                        WorstFrame, record, f.depth_mm, f.intrinsics, pose, getattr(tracker, "model", None)
                    )
                    worst.offer(make, record)
                if problem is not None and first_error is None:
                    first_error = f"frame {f.index} (stamp {f.stamp_ns} ns): {problem}"
                if image_size is None and f.depth_mm is not None:
                    image_size = (f.depth_mm.shape[1], f.depth_mm.shape[0])
                bar.update(1, f"{record.ms:6.1f} ms {record.status}")
        finally:
            bar.close()
    wall = time.perf_counter() - t_start
    if not records:
        raise BagError(f"bag {bag}: no depth image on {topics.depth!r} could be read")
    if all(r.status == STATUS_ERROR for r in records):
        raise BagError(f"bag {bag}: no depth image could be used; first problem: {first_error}")
    extra: dict[str, Any] = {"handedness": "right" if cfg.right_hand else "left"}
    if auto.enabled:
        extra["auto_calibration"] = auto_fits
    if first_error is not None:
        extra["first_frame_error"] = first_error
    ev = build_evaluation(str(bag), "core", records, wall, image_size, calib_info, extra)
    return dataclasses.replace(ev, split=split, worst=worst.worst_first())


def _chain(head: list[BagFrame], rest: Iterable[BagFrame]) -> Iterable[BagFrame]:
    yield from head
    yield from rest


def _track_one(tracker: TrackerLike, f: BagFrame) -> tuple[FrameRecord, NDArray[np.float64] | None, str | None]:
    """Track one frame: its record, the tracked pose (or None) and, for an unusable frame, why."""
    if f.depth_mm is None or f.intrinsics is None:
        return FrameRecord(f.index, f.stamp_ns, STATUS_ERROR, None, f.truth_mm, math.nan), None, f.error
    t0 = time.perf_counter()
    try:
        res = tracker.process(f.depth_mm, f.intrinsics)
    except InputError as err:  # DepthImageError, IntrinsicsError: frame unusable, track left intact
        return FrameRecord(f.index, f.stamp_ns, STATUS_ERROR, None, f.truth_mm, math.nan), None, str(err)
    ms = (time.perf_counter() - t0) * 1e3
    est = None
    pose = None
    if res.status is TrackerStatus.TRACKING and res.fingertips_mm is not None:
        est = np.asarray(res.fingertips_mm, dtype=np.float64)
        pose = None if res.pose is None else np.asarray(res.pose, dtype=np.float64)
    return FrameRecord(f.index, f.stamp_ns, _status_name(res.status), est, f.truth_mm, ms), pose, None
