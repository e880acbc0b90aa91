"""The bad-input battery's table (issue 50's closing note) from its records.

``test/test_ros_node_bounded.py`` appends one JSON line per kind to the file named by
``HAND_SOG_BATTERY_RECORD`` (and one summary line per run); run it once per image size::

    HAND_SOG_BATTERY_RECORD=/tmp/b320.jsonl pytest test/test_ros_node_bounded.py
    HAND_SOG_BATTERY_SIZE=640x480 HAND_SOG_BATTERY_RECORD=/tmp/b640.jsonl pytest test/test_ros_node_bounded.py
    python -m hand_sog_tracker.tools.battery_table /tmp/b320.jsonl /tmp/b640.jsonl

prints a Markdown table, one row per kind with the observed outcome, the worst frame (wall ms,
and the executor thread's CPU ms in brackets) and the peak resident memory of each size, then
the totals per size.  ``--json OUT`` writes the rows and totals.  The last run of each size in
the files counts.  Nothing here judges the numbers (the tests do).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any, Sequence

__all__ = ["load", "main", "table"]


def load(paths: Sequence[Path]) -> tuple[dict[str, dict[str, dict]], dict[str, dict]]:
    """The records of ``paths``: ``(rows, summaries)``, rows by size then kind, summaries by
    size (the last line of each kind and size counts)."""
    rows: dict[str, dict[str, dict]] = {}
    summaries: dict[str, dict] = {}
    for path in paths:
        recs = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
        # (Records without a size: the size of their file's summary line, else 320x240.)
        size = next((r["summary"] for r in recs if "summary" in r), "320x240")
        for rec in recs:
            if "summary" in rec:
                summaries[rec["summary"]] = rec
            else:
                rows.setdefault(rec.get("size", size), {})[rec["kind"]] = rec
    return rows, summaries


def _ok(rec: dict) -> str:
    if rec["problems"]:
        return "xfail: " + "; ".join(rec["problems"]) if rec.get("xfail") else "**" + "; ".join(rec["problems"]) + "**"
    return "ok"


def _frame(rec: dict) -> str:
    cpu = rec.get("worst_cpu_ms")
    return f"{rec['worst_ms']:.0f}" + ("" if cpu is None else f" ({cpu:.0f})")


def table(rows: dict[str, dict[str, dict]], summaries: dict[str, dict]) -> tuple[str, dict[str, Any]]:
    """The Markdown table and the totals per size."""
    sizes = sorted(rows, key=lambda s: int(s.split("x")[0]))
    kinds: list[tuple[str, str, str]] = []
    for size in sizes:
        for rec in rows[size].values():
            key = (rec["group"], rec["kind"], rec["expected"])
            if key not in kinds:
                kinds.append(key)
    head = ["group", "kind", "expected"]
    for size in sizes:
        head += [f"observed {size}", f"result {size}", f"worst frame ms (CPU) {size}", f"peak RSS MB {size}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for group, name, expected in kinds:
        cells = [group, name, expected]
        for size in sizes:
            rec = rows[size].get(name)
            if rec is None:
                cells += ["not run"] * 4
            else:
                cells += [rec["observed"], _ok(rec), _frame(rec), f"{rec['rss_mb']:.0f}"]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    totals: dict[str, Any] = {}
    for size in sizes:
        recs = list(rows[size].values())
        failed = [r["kind"] for r in recs if r["problems"] and not r.get("xfail")]
        xfailed = [r["kind"] for r in recs if r["problems"] and r.get("xfail")]
        worst = max(recs, key=lambda r: r["worst_ms"])
        worst_cpu = max(recs, key=lambda r: r.get("worst_cpu_ms", 0.0))
        s = summaries.get(size, {})
        totals[size] = dict(
            kinds=len(recs), as_expected=len(recs) - len(failed) - len(xfailed), failed=failed, xfailed=xfailed,
            worst_frame_ms=worst["worst_ms"], worst_frame_kind=worst["kind"],
            worst_cpu_ms=worst_cpu.get("worst_cpu_ms"), worst_cpu_kind=worst_cpu["kind"],
            worst_clean_ms=max(r["recover_ms"] for r in recs),
            peak_rss_mb=s.get("peak_rss", max(r["rss_mb"] for r in recs)), steady_rss_mb=s.get("steady_rss"),
            after_rss_mb=s.get("after_rss"), steady_worst_ms=s.get("steady_ms"), blas_threads=s.get("blas_threads"),
        )
    lines.append("")
    for size, t in totals.items():
        over = ""
        if t["steady_rss_mb"] is not None:
            after = t["after_rss_mb"] - t["steady_rss_mb"]
            over = f" (steady tracking {t['steady_rss_mb']:.0f} MB; after the battery {after:+.0f} MB)"
        lines.append(
            f"- {size}: {t['as_expected']} of {t['kinds']} kinds as expected"
            + (f", {len(t['xfailed'])} expected failure ({', '.join(t['xfailed'])})" if t["xfailed"] else "")
            + (f", **failed: {', '.join(t['failed'])}**" if t["failed"] else "")
            + f"; worst frame {t['worst_frame_ms']:.0f} ms ({t['worst_frame_kind']})"
            + ("" if t["worst_cpu_ms"] is None else f", most CPU {t['worst_cpu_ms']:.0f} ms ({t['worst_cpu_kind']})")
            + f"; worst clean frame after a kind {t['worst_clean_ms']:.0f} ms; peak RSS {t['peak_rss_mb']:.0f} MB{over}"
        )
    return "\n".join(lines), totals


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="battery_table", description=__doc__.split("\n\n")[0])
    ap.add_argument("records", nargs="+", type=Path, help="JSON-lines files of HAND_SOG_BATTERY_RECORD")
    ap.add_argument("--json", type=Path, help="also write the rows and totals as JSON")
    args = ap.parse_args(argv)
    rows, summaries = load(args.records)
    text, totals = table(rows, summaries)
    print(text)
    if args.json:
        args.json.write_text(json.dumps(dict(rows=rows, totals=totals), indent=1))


if __name__ == "__main__":
    main()
