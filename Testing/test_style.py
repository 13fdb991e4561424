"""The repository's own style gate: ``ruff check`` and ``ruff format --check``.

CI runs only the README's test command, so the linters run here, as part of it. ruff is
pinned in the ``test`` extra: formatting output may change between ruff releases, and a
gate that moves with whatever version a machine has would fail on code nobody touched.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _ruff(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_ruff_check_is_clean() -> None:
    r = _ruff("check", "--no-cache", ".")
    assert r.returncode == 0, r.stdout + r.stderr


def test_ruff_format_is_clean() -> None:
    r = _ruff("format", "--check", "--no-cache", ".")
    assert r.returncode == 0, "files need `ruff format`:\n" + r.stdout + r.stderr
