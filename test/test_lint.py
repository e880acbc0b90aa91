"""The code passes the lint configuration in ruff.toml (ruff is in the test extras)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: What is linted: the package, the tests, the launch file and the packaging script.
TARGETS = ("hand_sog_tracker", "test", "launch", "setup.py")


def test_ruff_finds_nothing() -> None:
    assert (REPO / "ruff.toml").is_file()
    out = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", *TARGETS],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )
    assert "No module named ruff" not in out.stderr, "ruff is missing: pip install '.[test]'"
    assert out.returncode == 0, f"ruff findings (fix them or see ruff.toml):\n{out.stdout}{out.stderr}"
