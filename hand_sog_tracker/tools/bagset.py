"""Which bags to evaluate: bags and folders of bags, with their ``hand_sog_sample.json`` sidecar.

A path that is itself a bag (a directory with ``metadata.yaml``, one of its
storage files, or a ROS 1 ``.bag`` file) is one bag; any other directory stands
for every bag directly inside it, sorted by name.

``make_sample_bags`` writes a sidecar ``hand_sog_sample.json`` into each bag
directory (keys ``renderer``, ``split`` = ``dev`` | ``test`` | ``capsule``,
``motion``, ``seed``, ``handedness`` = ``right`` | ``left``, ``shape``,
``sensor``, ``width``, ``height``, ``encoding``, ``frames``).  A bag without one
has split ``-``.

The dev/test protocol: bags of the ``test`` split are for final numbers only;
the tools refuse per-frame looking aids (overlays, per-frame JSON records,
error-over-time plots) on them unless explicitly allowed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from hand_sog_tracker.errors import BagError
from hand_sog_tracker.tools.bagio import resolve_bag_path

__all__ = ["SIDECAR", "TEST_SPLIT", "PROTOCOL", "BagEntry", "read_sidecar", "discover_bags"]

#: File name of the sample-bag sidecar inside a bag directory.
SIDECAR = "hand_sog_sample.json"
#: The held-out split.
TEST_SPLIT = "test"
#: Why looking at test frames is refused (shown to the user).
PROTOCOL = (
    "bags of the 'test' split are held out: tune and inspect on 'dev' bags, and only read the totals "
    "of 'test' bags (per-frame overlays, per-frame records and error-over-time plots of them are "
    "refused); pass --allow-test-inspection for a final report that shows them"
)


@dataclass(frozen=True)
class BagEntry:
    """One bag to evaluate.

    Attributes
    ----------
    path : Path
        The bag (as :func:`bagio.resolve_bag_path` returns it).
    sample : dict
        Its sidecar (empty without one).
    """

    path: Path
    sample: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        """The bag's directory (or file) name."""
        return self.path.name

    @property
    def split(self) -> str:
        """``dev``, ``test``, ``capsule`` ... from the sidecar; ``-`` without one."""
        return str(self.sample.get("split", "-"))

    @property
    def handedness(self) -> str | None:
        """``right`` / ``left`` from the sidecar, or None."""
        h = self.sample.get("handedness")
        return h if h in ("right", "left") else None

    @property
    def is_test(self) -> bool:
        """True for a bag of the held-out test split."""
        return self.split == TEST_SPLIT


def read_sidecar(bag: Path) -> dict[str, Any]:
    """The ``hand_sog_sample.json`` of a bag directory ({} if there is none).

    Raises
    ------
    BagError
        The sidecar exists but is not a JSON object.
    """
    f = bag / SIDECAR if bag.is_dir() else bag.parent / SIDECAR if bag.suffix != ".bag" else None
    if f is None or not f.is_file():
        return {}
    try:
        data = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise BagError(f"cannot read the sample sidecar {f}: {err}") from err
    if not isinstance(data, dict):
        raise BagError(f"the sample sidecar {f} is not a JSON object")
    return data


def _is_bag(p: Path) -> bool:
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or (p.is_file() and p.suffix == ".bag")


def discover_bags(paths: Sequence[str | Path]) -> list[BagEntry]:
    """The bags named by ``paths`` (see the module docstring), in order, without duplicates.

    Raises
    ------
    BagError
        A path does not exist, or is a directory holding no bag.
    """
    found: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if not p.exists():
            raise BagError(f"bag not found: {p}")
        if p.is_dir() and not (p / "metadata.yaml").is_file():
            inside = sorted(c for c in p.iterdir() if _is_bag(c))
            if not inside:
                raise BagError(
                    f"{p} is neither a bag (no metadata.yaml) nor a folder of bags (no bag directly inside it)"
                )
            found.extend(inside)
        else:
            found.append(resolve_bag_path(p))
    seen: set[Path] = set()
    out: list[BagEntry] = []
    for bag in found:
        key = bag.resolve()
        if key not in seen:
            seen.add(key)
            out.append(BagEntry(bag, read_sidecar(bag)))
    return out
