"""``benchmark --renderer twohands --hands``: the two-hand tracker's time per frame against one hand's.

One job: the speed ratio of issue 47 ("two hands at most 1.8x one hand's median time per
frame"), kept apart from the per-stage benchmark of the one-hand tracker.

The scene (``synth.twohands``, structured light, the benchmark's seed) is rendered twice, not
timed: with both hands, tracked by :class:`~hand_sog_tracker.core.hands.MultiHandTracker`
(``max_hands`` 2), and with the right hand alone (the same pose, shape and sensor), tracked by
the one-hand :class:`~hand_sog_tracker.core.tracker.Tracker`.  The two are timed frame by
frame, alternating which goes first, so that the load of a shared machine weighs on both alike.
Medians over every frame and over the frames after the first ``skip`` (a new track's search,
and for two hands their handedness trial) are printed with their ratio.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from hand_sog_tracker.core.hands import MultiHandTracker
from hand_sog_tracker.core.tracker import Tracker
from hand_sog_tracker.core.types import TrackerConfig

__all__ = ["run_hands_ratio", "format_hands_ratio"]


def run_hands_ratio(
    scene: str, frames: int, width: int, height: int, seed: int, config: TrackerConfig | None = None, skip: int = 10
) -> dict[str, Any]:
    """Time both trackers on ``scene`` (see the module docstring).

    Returns
    -------
    dict
        ``one_ms`` / ``two_ms``: per-frame milliseconds (lists); ``median`` and ``median_after``
        (frames from ``skip`` on), each ``{"one", "two", "ratio"}``; ``hands``: hands reported on
        the last frame; ``scene``, ``frames``, ``resolution``.
    """
    from hand_sog_tracker.synth.sequence import default_intrinsics
    from hand_sog_tracker.synth.twohands import TwoHandScene, two_hand_sequence

    intr = default_intrinsics(width, height)
    sc = TwoHandScene(scene)
    both = [f.depth_mm for f in two_hand_sequence(sc, frames, intr, seed=seed, sensor="structured")]
    alone = [f.depth_mm for f in two_hand_sequence(sc, frames, intr, seed=seed, sensor="structured", shown=("right",))]
    cfg = config or TrackerConfig()
    one, two = Tracker(cfg), MultiHandTracker(cfg, max_hands=2)
    one_ms, two_ms = [], []
    hands = 0
    for k, (d1, d2) in enumerate(zip(alone, both)):
        for which in ((0, 1) if k % 2 == 0 else (1, 0)):
            t0 = time.perf_counter()
            if which == 0:
                one.process(d1, intr)
                one_ms.append((time.perf_counter() - t0) * 1e3)
            else:
                hands = len(two.process(d2, intr).hands)
                two_ms.append((time.perf_counter() - t0) * 1e3)

    def med(a: list[float], b: list[float]) -> dict[str, float]:
        m1, m2 = float(np.median(a)), float(np.median(b))
        return {"one": m1, "two": m2, "ratio": m2 / m1}

    return {
        "scene": scene, "frames": frames, "resolution": f"{width}x{height}", "one_ms": one_ms, "two_ms": two_ms,
        "median": med(one_ms, two_ms), "median_after": med(one_ms[skip:], two_ms[skip:]), "skip": skip,
        "hands": hands,
    }


def format_hands_ratio(r: dict[str, Any]) -> str:
    """The medians and ratios of :func:`run_hands_ratio` as a few lines."""
    a, b = r["median"], r["median_after"]
    return "\n".join([
        f"two hands vs one ({r['scene']}, {r['resolution']}, {r['frames']} frames, interleaved; "
        f"{r['hands']} hands on the last frame)",
        f"  all frames:          one hand {a['one']:6.1f} ms  two hands {a['two']:6.1f} ms  ratio {a['ratio']:.2f}",
        f"  from frame {r['skip']:<3}:      one hand {b['one']:6.1f} ms  two hands {b['two']:6.1f} ms  "
        f"ratio {b['ratio']:.2f}",
    ])
