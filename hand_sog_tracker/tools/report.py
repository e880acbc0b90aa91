"""Output of the evaluation tools: text tables, JSON, plot (matplotlib) and overlay pictures.

* :func:`format_table`: one bag in detail (errors per finger, % below, timing);
* :func:`format_table1`: one row per bag in the form of the paper's Table 1,
  with a split column, a total row per split and an overall total
  (frame-weighted, see :func:`~hand_sog_tracker.tools.records.pool`); bags of
  the test split get their own block;
* :func:`write_json`: everything (per-bag summaries, totals, per-frame records).

Pictures (plot, overlays) are in :mod:`hand_sog_tracker.tools.figures`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Sequence

from hand_sog_tracker.errors import InputError
from hand_sog_tracker.tools.metrics import FINGERS, THRESHOLDS_MM
from hand_sog_tracker.tools.records import Evaluation, Pooled, pool

__all__ = ["format_table", "format_table1", "totals", "write_json"]


def _fmt(v: float, spec: str = ".1f") -> str:
    return "n/a" if not math.isfinite(v) else format(v, spec)


def _fit_text(info: dict) -> str:
    """One calibration outcome (``Evaluation.calibration`` or an automatic fit) as text."""
    seconds = f" ({info['seconds']:.1f} s)" if "seconds" in info else ""
    if "shape" not in info:
        return f"refused, model unchanged{seconds}: {info.get('reason', '')}"
    unused = "; not used (a smaller hand keeps the default model)" if info.get("used") is False else ""
    return ", ".join(f"{k} {v:.3f}" for k, v in info["shape"].items()) + seconds + unused


def format_table(ev: Evaluation) -> str:
    """The paper's table plus timing, as text."""
    e = ev.errors
    size = f", {ev.image_size[0]}x{ev.image_size[1]}" if ev.image_size else ""
    hand = f", {ev.extra['handedness']} hand" if "handedness" in ev.extra else ""
    lines = [
        f"bag: {ev.bag}  ({ev.mode} mode{size}{hand})",
        f"frames: {ev.frames} {'published' if ev.mode == 'through_node' else 'tracked'}, "
        f"{e.frames_scored} with ground truth "
        f"({ev.frames_without_truth} without, not scored), {e.frames_with_estimate} scored with an estimate",
        "status: " + ", ".join(f"{k} {v}" for k, v in ev.status_counts.items()),
    ]
    if ev.calibration:
        lines.append(f"calibration: {_fit_text(ev.calibration)}")
    for fit in ev.extra.get("auto_calibration", []):
        lines.append(f"automatic calibration at frame {fit['frame']}: {_fit_text(fit)}")
    for message in ev.extra.get("node_calibration_log", []):
        lines.append(f"node: {message}")
    cols = ["mean"] + list(FINGERS)
    vals = [e.mean_mm] + [e.per_finger_mm[f] for f in FINGERS]
    lines += [
        "",
        "mean fingertip error (mm)",
        "  " + "".join(f"{c:>9}" for c in cols),
        "  " + "".join(f"{_fmt(v):>9}" for v in vals),
        "",
        "% of frames with mean fingertip error below",
        "  " + "".join(f"{t + ' mm':>9}" for t in e.pct_below_mm),
        "  " + "".join(f"{_fmt(v) + '%':>9}" for v in e.pct_below_mm.values()),
        "",
    ]
    what = "end-to-end latency" if ev.mode == "through_node" else "ms per frame"
    lines.append(
        f"{what}: median {_fmt(ev.timing.median_ms)} ms, p95 {_fmt(ev.timing.p95_ms)} ms, "
        f"{_fmt(ev.fps)} fps"
    )
    if ev.mode == "through_node":
        x = ev.extra
        lines.append(
            f"published {x.get('frames_published')} frames, node answered {x.get('frames_with_output')}, "
            f"dropped {x.get('frames_dropped')}"
        )
    if ev.split != "-":
        lines.insert(1, f"split: {ev.split}")
    return "\n".join(lines)


def totals(evaluations: Sequence[Evaluation]) -> list[Pooled]:
    """A total per split (in order of appearance, test last) and, for several bags, an overall total."""
    splits = list(dict.fromkeys(ev.split for ev in evaluations))
    splits = [s for s in splits if s != "test"] + [s for s in splits if s == "test"]
    out = [pool([ev for ev in evaluations if ev.split == s], f"total {s}") for s in splits]
    if len(evaluations) > 1:
        out.append(pool(evaluations, "total"))
    return out


_HEAD = ("bag", "split", "frames", "mean error (mm)", *(f"< {t} mm" for t in THRESHOLDS_MM))


def _row(name: str, split: str, frames: int, e: Any, timing: Any) -> list[str]:
    return [name, split, str(frames), _fmt(e.mean_mm),
            *(_fmt(v, ".1f") + "%" if math.isfinite(v) else "n/a" for v in e.pct_below_mm.values()),
            _fmt(timing.median_ms), _fmt(timing.p95_ms)]


def format_table1(evaluations: Sequence[Evaluation], markdown: bool = False) -> str:
    """One row per bag (the paper's Table 1 plus timing and split), totals per split and overall.

    Rows are grouped by split (in order of first appearance), each group
    followed by its total; the test split comes in its own block after the others.  Totals
    pool the frames of their bags (frame-weighted); with a single split only
    the overall total is shown.  ``markdown`` writes a
    Markdown table instead of aligned text.
    """
    if not evaluations:
        return ""
    node = evaluations[0].mode == "through_node"
    head = [*_HEAD, "latency ms median" if node else "ms/frame median", "p95"]
    pooled = {p.label: p for p in totals(evaluations)}
    names = [ev.name for ev in evaluations]
    label = {id(ev): f"{Path(ev.bag).parent.name}/{ev.name}" if names.count(ev.name) > 1 else ev.name
             for ev in evaluations}  # same name in two folders: say which
    blocks: list[tuple[str, list[list[str]]]] = []
    for title, evs in (
        ("", [ev for ev in evaluations if ev.split != "test"]),
        ("test split (held out)", [ev for ev in evaluations if ev.split == "test"]),
    ):
        if not evs:
            continue
        rows: list[list[str]] = []
        for s in dict.fromkeys(ev.split for ev in evs):  # grouped by split, each followed by its total
            rows += [_row(label[id(ev)], ev.split, ev.frames, ev.errors, ev.timing) for ev in evs if ev.split == s]
            if len(set(ev.split for ev in evaluations)) > 1:  # else it is the overall total
                p = pooled[f"total {s}"]
                rows.append(_row(p.label, s, p.frames, p.errors, p.timing))
        blocks.append((title, rows))
    if "total" in pooled:
        p = pooled["total"]
        blocks.append(("", [_row("total (all bags)", "all", p.frames, p.errors, p.timing)]))
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
        for title, rows in blocks:
            if title:
                lines.append("| " + " | ".join([f"**{title}**"] + [""] * (len(head) - 1)) + " |")
            lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    width = [max(len(head[i]), *(len(r[i]) for _, rows in blocks for r in rows)) for i in range(len(head))]

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, width))).rstrip()

    out = [line(head)]
    for title, rows in blocks:
        rule = sum(width) + 2 * len(width)
        out.append(f"-- {title} " + "-" * max(rule - len(title) - 4, 4) if title else "-" * (rule - 2))
        out += [line(r) for r in rows]
    return "\n".join(out)


def write_json(
    evaluations: Sequence[Evaluation], path: str | Path, per_frame: Sequence[bool] | None = None,
    withheld_note: str = "",
) -> None:
    """Write ``{"bags": [...], "totals": [...]}`` to ``path``.

    Parameters
    ----------
    evaluations : sequence of Evaluation
    path : str or Path
    per_frame : sequence of bool, optional
        Per bag: include its per-frame records (default: all).  A bag without
        them gets ``"per_frame_withheld": withheld_note``.

    Raises
    ------
    InputError
        If the file cannot be written.
    """
    flags = list(per_frame) if per_frame is not None else [True] * len(evaluations)
    bags = []
    for ev, keep in zip(evaluations, flags):
        js = ev.to_json(per_frame=keep)
        if not keep:
            js["per_frame_withheld"] = withheld_note or "withheld"
        bags.append(js)
    doc = {
        "mode": evaluations[0].mode if evaluations else None,
        "bags": bags,
        "totals": [p.to_json() for p in totals(evaluations)],
    }
    try:
        with open(path, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2, allow_nan=False)
            fh.write("\n")
    except OSError as err:
        raise InputError(f"cannot write JSON to {path}: {err}") from err
