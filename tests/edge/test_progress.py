"""The terminal status line: silent when stderr is not a terminal, redrawn in place when it is."""

from __future__ import annotations

import io
import os
import time

import pytest

from services.edge.progress import Ticker, elapsed


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_elapsed() -> None:
    assert elapsed(0.4) == "0:00" and elapsed(75.2) == "1:15" and elapsed(3600) == "60:00"


def test_not_a_terminal_writes_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    stream = io.StringIO()
    with Ticker("crosspath up", lambda: "busy", stream=stream, interval_s=0.01) as ticker:
        time.sleep(0.05)
        ticker.say("a whole line")
    assert not ticker.enabled
    assert stream.getvalue() == ""
    assert capsys.readouterr().out == "a whole line\n"  # say still prints


def test_a_terminal_gets_a_status_line_and_it_is_cleared(
    capsys: pytest.CaptureFixture[str],
) -> None:
    stream = FakeTerminal()
    calls = []

    def status() -> str:
        calls.append(1)
        return f"case {len(calls)}/9"

    with Ticker("crosspath bench sim", status, stream=stream, interval_s=0.01) as ticker:
        deadline = time.monotonic() + 5.0
        while not calls and time.monotonic() < deadline:
            time.sleep(0.01)
        ticker.say("between")
    text = stream.getvalue()
    assert ticker.enabled and calls
    assert "\rcrosspath bench sim: case 1/9  [0:00]\x1b[K" in text
    assert text.endswith("\r\x1b[K")  # the status line is gone afterwards
    assert "\n" not in text  # never more than one line on the terminal
    assert capsys.readouterr().out == "between\n"


def test_a_failing_status_does_not_stop_the_command() -> None:
    stream = FakeTerminal()

    def broken() -> str:
        raise KeyError("x")

    with Ticker("crosspath up", broken, stream=stream, interval_s=0.01):
        deadline = time.monotonic() + 5.0
        while "KeyError" not in stream.getvalue() and time.monotonic() < deadline:
            time.sleep(0.01)
    assert "crosspath up: (KeyError)" in stream.getvalue()


def test_a_long_status_is_cut_to_the_terminal_width(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("shutil.get_terminal_size", lambda: os.terminal_size((30, 24)))
    stream = FakeTerminal()
    with Ticker("crosspath lab run", lambda: "x" * 100, stream=stream, interval_s=0.01):
        deadline = time.monotonic() + 5.0
        while "x" not in stream.getvalue() and time.monotonic() < deadline:
            time.sleep(0.01)
    drawn = [d.removesuffix("\x1b[K") for d in stream.getvalue().split("\r") if "x" in d]
    assert drawn and all(len(d) == 29 for d in drawn)  # one column short: no wrap
    assert drawn[0].endswith("…  [0:00]")
