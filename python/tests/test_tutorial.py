"""docs/python.md: every ```python block runs, in order, in one namespace, against the live
rigd --sim (found through $RIGD_SOCKET, as the page says). A failing block fails the test."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from conftest import REPO, Daemon

PAGE = REPO / "docs" / "python.md"


def blocks() -> list[tuple[int, str]]:
    text = PAGE.read_text(encoding="utf-8")
    found = []
    for m in re.finditer(r"^```python\n(.*?)^```", text, re.S | re.M):
        found.append((text.count("\n", 0, m.start()) + 1, m.group(1)))
    return found


def test_the_page_has_code() -> None:
    assert len(blocks()) >= 8


def test_the_tutorial_runs(daemon: Daemon, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("RIGD_SOCKET", str(daemon.socket))
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"__name__": "__tutorial__"}
    for line, code in blocks():
        try:
            exec(compile(code, f"{PAGE}:{line}", "exec"), namespace)
        except Exception as e:
            pytest.fail(f"docs/python.md, the block at line {line} failed: {type(e).__name__}: {e}")
