"""Progress bars only on a terminal (issue 27 defect 6: with stderr redirected, `xyzcyl client` wrote
`upload: 0.00B [00:00, ?B/s]` lines into logs): runtime.progress.progress_bar is the one place a tqdm bar is made,
and it is off when its stream is not a terminal."""

from __future__ import annotations

import argparse
import io
import re
from pathlib import Path

from xyzcyl.common.progress import is_terminal, progress_bar

REPO = Path(__file__).resolve().parents[2]


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _run(stream, **kw) -> str:
    bar = progress_bar(total=1000, unit="B", unit_scale=True, desc="upload", file=stream, mininterval=0, **kw)
    bar.update(500)
    bar.update(500)
    bar.close()
    return stream.getvalue()


def test_no_bar_when_the_stream_is_not_a_terminal():
    assert _run(io.StringIO()) == ""


def test_a_bar_on_a_terminal_unless_disabled():
    assert "upload" in _run(Terminal())
    assert _run(Terminal(), enabled=False) == ""


def test_is_terminal():
    closed = io.StringIO()
    closed.close()
    assert not is_terminal(None) and not is_terminal(closed) and not is_terminal(object())
    assert is_terminal(Terminal())


def test_the_client_command_draws_no_bar_into_a_log(monkeypatch):
    from xyzcyl.clients.commands import client as cmd

    log = io.StringIO()
    monkeypatch.setattr("sys.stderr", log)
    update, close = cmd._bar(argparse.Namespace(quiet=False), None, "B", "upload")
    assert update is None
    close()
    assert log.getvalue() == ""
    term = Terminal()
    monkeypatch.setattr("sys.stderr", term)
    update, close = cmd._bar(argparse.Namespace(quiet=False), 100, "B", "upload")
    update(100, 100)
    close()
    assert "upload" in term.getvalue()


def test_every_bar_goes_through_the_helper():
    """No product module creates a tqdm bar itself (docs/runs holds old run scripts, not product code)."""
    found = []
    for folder in ("runtime", "model_export", "server", "clients", "benchmarks", "scripts", "examples"):
        for path in (REPO / folder).rglob("*.py"):
            if path == REPO / "runtime" / "progress.py":
                continue
            for n, line in enumerate(path.read_text().splitlines(), 1):
                if re.search(r"\b(from tqdm|import tqdm|tqdm\()", line):
                    found.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert found == [], found
