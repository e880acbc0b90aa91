"""Pictures of an evaluation: the error plot (matplotlib, optional) and overlays of the worst frames.

* :func:`write_plot`: mean fingertip error over time per bag (left) and the
  %-of-frames-below curve per bag (right).  Needs matplotlib, the optional
  ``plot`` extra (``pip install 'hand_sog_tracker[plot]'``); drawn with the Agg
  canvas, never a GUI backend;
* :func:`write_overlays` / :func:`overlay_image`: for the worst frames kept by
  :func:`~hand_sog_tracker.tools.evaluation.evaluate_core` (``keep_worst``), the
  depth colour map with the tracked model
  (:func:`~hand_sog_tracker.core.overlay.draw_overlay`: Gaussians, skeleton,
  fingertips as filled dots), the TRUE fingertips as white rings with the
  finger's colour inside and a line to the tracked tip, and the error of each
  finger written in its colour.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from hand_sog_tracker.errors import HandSogError, InputError
from hand_sog_tracker.tools.metrics import FINGERS, THRESHOLDS_MM, pct_frames_below
from hand_sog_tracker.tools.records import Evaluation, WorstFrame, pool

__all__ = ["PLOT_EXTRA_HINT", "write_plot", "overlay_image", "overlay_name", "write_overlays"]

#: How to get matplotlib for ``--plot``.
PLOT_EXTRA_HINT = "pip install 'hand_sog_tracker[plot]'"
#: Colour of the %-below curve of a single bag (RGB, 0-1).
SINGLE_CURVE_RGB = (0.0, 0.55, 0.0)


def _figure(width_in: float, height_in: float) -> Any:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:
        raise HandSogError(f"the plot needs matplotlib, which is not installed: {PLOT_EXTRA_HINT}") from err
    fig = Figure(figsize=(width_in, height_in), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def write_plot(
    evaluations: Evaluation | Sequence[Evaluation],
    path: str | Path,
    time_series: Sequence[bool] | None = None,
) -> None:
    """PNG (1120x420 px): error over time (left) and the %-of-frames-below curves (right).

    Parameters
    ----------
    evaluations : Evaluation or sequence of Evaluation
    path : str or Path
        Output PNG.
    time_series : sequence of bool, optional
        Per bag: draw its error over time (default: all).  The test split's
        bags are left out by the caller (see :mod:`hand_sog_tracker.tools.bagset`).

    Raises
    ------
    HandSogError
        matplotlib is not installed (the message says how to install it).
    InputError
        The PNG cannot be written to ``path``.
    """
    evs = [evaluations] if isinstance(evaluations, Evaluation) else list(evaluations)
    show = list(time_series) if time_series is not None else [True] * len(evs)
    fig = _figure(11.2, 4.2)
    left, right = fig.subplots(1, 2)
    single = len(evs) == 1
    y_top = 50.0
    shown = 0
    for ev, keep in zip(evs, show):
        err = ev.frame_errors_mm()
        finite = err[np.isfinite(err)]
        if finite.size:
            y_top = max(y_top, float(np.ceil(finite.max() / 10.0) * 10.0))
        if not keep:
            continue
        shown += 1
        scored = [r for r in ev.records if r.truth_mm is not None]
        t0 = ev.records[0].stamp_ns if ev.records else 0
        t = np.array([(r.stamp_ns - t0) / 1e9 for r in scored])
        (line,) = left.plot(t, err, marker="." if len(t) <= 120 else None, lw=1, label=ev.name)
        lost = ~np.isfinite(err)
        if lost.any():  # no estimate: a red tick on the time axis
            left.plot(t[lost], np.zeros(int(lost.sum())), "|", color="tab:red", ms=10)
    for thr in THRESHOLDS_MM:
        left.axhline(thr, color="0.85", lw=0.8, zorder=0)
    left.set_ylim(0.0, y_top)
    left.set_xlabel("time (s)")
    left.set_ylabel("mean fingertip error (mm)")
    left.set_title(f"fingertip error over time ({evs[0].mode if evs else ''})", fontsize=10)
    if not shown:
        left.text(0.5, 0.5, "test split: per-frame errors not shown", ha="center", transform=left.transAxes)

    x_max = min(y_top, 200.0)
    grid = np.linspace(0.0, x_max, 201)
    for ev in evs:
        err = ev.frame_errors_mm()
        pct = pct_frames_below(err, grid) if err.size else np.zeros_like(grid)
        colour = SINGLE_CURVE_RGB if single else None
        right.plot(grid, pct, lw=2 if single else 1, color=colour, label=ev.name)
        if single:
            for key, v in ev.errors.pct_below_mm.items():
                if math.isfinite(v):
                    right.plot([float(key)], [v], "o", color="tab:red", ms=4)
                    right.annotate(f"{v:.0f}%", (float(key), v), xytext=(4, -10),
                                   textcoords="offset points", fontsize=7, color="tab:red")
    if not single and evs:
        p = pool(evs, "total")
        err = np.array([float(np.mean(r.errors_mm)) for ev in evs for r in ev.records if r.errors_mm is not None])
        right.plot(grid, pct_frames_below(err, grid), "k--", lw=1.5, label=f"all ({p.frames} frames)")
        right.legend(fontsize=6, ncol=2 if len(evs) > 8 else 1, loc="lower right")
        if shown:
            left.legend(fontsize=6, loc="upper right")
    right.set_xlim(0.0, x_max)
    right.set_ylim(0.0, 100.0)
    right.set_xlabel("error threshold (mm)")
    right.set_ylabel("% of frames below")
    right.set_title("frames with mean error below threshold", fontsize=10)
    fig.subplots_adjust(left=0.07, right=0.98, wspace=0.25, bottom=0.13)
    out = Path(path)
    try:
        fig.savefig(str(out), format="png")
    except (OSError, ValueError) as err:
        raise InputError(f"cannot write plot {out}: {err}") from err


def overlay_name(bag_name: str, w: WorstFrame) -> str:
    """``<bag>_<frame>_<err>mm.png`` (``<bag>_<frame>_lost.png`` without an estimate)."""
    err = w.error_mm
    tail = f"{err:.1f}mm" if math.isfinite(err) else "lost"
    return f"{bag_name}_{w.record.index:04d}_{tail}.png"


def _px(uv: NDArray[np.float64]) -> tuple[int, int] | None:
    u, v = float(uv[0]), float(uv[1])
    return (int(round(u)), int(round(v))) if math.isfinite(u) and math.isfinite(v) else None


def overlay_image(w: WorstFrame, label: str = "", near_mm: float = 150.0, far_mm: float = 600.0) -> NDArray[np.uint8]:
    """The overlay picture of one frame, BGR, the size of its depth image.

    Tracked model and fingertips (filled dots) as :func:`core.overlay.draw_overlay`
    draws them; true fingertips as white rings with the finger's colour inside, a
    thin line from each to its tracked tip; per-finger errors (mm) bottom left.
    """
    import cv2

    from hand_sog_tracker.core.overlay import TIP_COLOURS_BGR, draw_overlay

    model = w.model if w.pose is not None else None
    img = draw_overlay(w.depth_mm, w.intrinsics, model, w.pose, near_mm, far_mm, label)
    scale = max(1, int(round(img.shape[1] / 320)))
    est, truth = w.record.estimate_mm, w.record.truth_mm
    est_uv = None if est is None else w.intrinsics.project(np.asarray(est, dtype=np.float64))
    if est_uv is not None and model is None:  # no model drawn: show the tracked tips themselves
        for uv, colour in zip(est_uv, TIP_COLOURS_BGR):
            if (p := _px(uv)) is not None:
                cv2.circle(img, p, 2 * scale + 1, colour, -1, cv2.LINE_AA)
    if truth is not None:
        truth_uv = w.intrinsics.project(np.asarray(truth, dtype=np.float64))
        r = 3 * scale + 2
        for i, (uv, colour) in enumerate(zip(truth_uv, TIP_COLOURS_BGR)):
            if (p := _px(uv)) is None:
                continue
            if est_uv is not None and (q := _px(est_uv[i])) is not None:
                cv2.line(img, p, q, colour, 1, cv2.LINE_AA)
            cv2.circle(img, p, r, (255, 255, 255), scale, cv2.LINE_AA)
            cv2.circle(img, p, max(r - scale - 1, 1), colour, scale, cv2.LINE_AA)
    errors = w.record.errors_mm
    if errors is not None:
        fs = 0.3 * scale
        step = int(10 * scale)
        y0 = img.shape[0] - 4 - step * (len(FINGERS) - 1)
        for i, (name, e, colour) in enumerate(zip(FINGERS, errors, TIP_COLOURS_BGR)):
            text = f"{name} {e:.1f} mm" if math.isfinite(e) else f"{name} -"
            cv2.putText(img, text, (3, y0 + i * step), cv2.FONT_HERSHEY_SIMPLEX, fs, colour, 1, cv2.LINE_AA)
    return img


def write_overlays(
    ev: Evaluation, out_dir: str | Path, near_mm: float = 150.0, far_mm: float = 600.0, name: str | None = None
) -> list[Path]:
    """Write :func:`overlay_image` of each of ``ev.worst`` into ``out_dir`` (created); the files.

    ``name`` replaces the bag's name in the file names (default ``ev.name``).

    Raises
    ------
    InputError
        ``out_dir`` cannot be created or a PNG cannot be written.
    """
    import cv2

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"cannot create the overlay folder {out}: {err}") from err
    files = []
    for w in ev.worst:
        err = w.error_mm
        what = f"mean {err:.1f} mm" if math.isfinite(err) else "no estimate"
        img = overlay_image(w, f"{name or ev.name} #{w.record.index} {what}", near_mm, far_mm)
        f = out / overlay_name(name or ev.name, w)
        if not cv2.imwrite(str(f), img):
            raise InputError(f"cannot write overlay {f}")
        files.append(f)
    return files
