"""The README's "Use the tracker without ROS" example runs and tracks the hand."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Use the tracker without ROS"


def readme_example() -> str:
    """The first ```python block of the README section (the section ends at the next heading)."""
    text = (REPO / "README.md").read_text()
    assert SECTION in text, f"README.md has no {SECTION!r} section"
    section = re.split(r"\n## ", text.split(SECTION, 1)[1], maxsplit=1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert blocks, "no python code block in the section"
    return blocks[0]


def test_readme_example_tracks_without_ros() -> None:
    code = readme_example()
    assert 5 <= len([line for line in code.splitlines() if line.strip()]) <= 15
    assert "from hand_sog_tracker import" in code
    check = "\nimport sys\nassert not [m for m in sys.modules if m.split('.')[0] in ('rclpy', 'sensor_msgs')]\n"
    out = subprocess.run([sys.executable, "-c", code + check], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines[0].startswith("tracking confidence"), out.stdout
    assert len([line for line in lines if line.strip().startswith("[")]) >= 5  # the (5, 3) fingertips
    errors = [float(v) for v in lines[-1].split("[", 1)[1].rstrip("]").split()]
    assert len(errors) == 5 and max(errors) < 15.0, lines[-1]


def test_front_door_exports_the_core_names() -> None:
    import hand_sog_tracker
    from hand_sog_tracker.core import hand_model, tracker, types

    homes = {"Tracker": tracker, "HandModel": hand_model, "HandShape": hand_model, "default_hand_model": hand_model}
    assert set(hand_sog_tracker.__all__) == {*homes, "TrackerConfig", "Intrinsics", "TrackResult", "TrackerStatus"}
    for name in hand_sog_tracker.__all__:
        assert getattr(hand_sog_tracker, name) is getattr(homes.get(name, types), name)
        assert name in dir(hand_sog_tracker)


def test_readme_is_a_front_door() -> None:
    """One or two screens: the title, the two set-up-free commands at the top, a picture that
    exists, and links that lead to files of this repository."""
    text = (REPO / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines"
    assert lines[0] == "# hand_sog_tracker"
    top = "\n".join(lines[:12])
    assert "```sh\nmake demo\nmake test\n```" in top
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if not target.startswith("http"):
            assert (REPO / target).exists(), target
    assert re.search(r"!\[[^\]]+\]\(doc/images/[^)]+\.png\)", text)
