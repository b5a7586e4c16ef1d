"""A one-line progress ticker on stderr, for long commands, only on a terminal.

``crosspath up``, ``lab run`` and the benches block for seconds to minutes; on
a terminal they show one status line, rewritten in place (``\\r``), that says
what is going on and for how long. When stderr is not a terminal (tests, logs,
pipes) the ticker writes nothing at all, so captured output stays exactly as
it was. A background thread redraws the line every ``interval_s`` from a
``status()`` callable; :meth:`Ticker.say` prints a whole line (on stdout)
without tearing the status line.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import TextIO

__all__ = ["Ticker", "elapsed"]


def elapsed(seconds: float) -> str:
    """``75.2`` -> ``1:15``; wall time for a status line."""
    whole = int(seconds)
    return f"{whole // 60}:{whole % 60:02d}"


class Ticker:
    """Redraws ``label: status()  [m:ss]`` on ``stream`` while in a ``with`` block.

    ``status`` is called from the ticker's thread: it must only read. Does
    nothing when ``stream`` is not a terminal (``enabled`` is then False).
    """

    def __init__(
        self,
        label: str,
        status: Callable[[], str] = lambda: "",
        *,
        stream: TextIO | None = None,
        interval_s: float = 0.5,
    ) -> None:
        self.label = label
        self.status = status
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s = interval_s
        self.enabled = _isatty(self.stream)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = time.monotonic()
        self._drawn = False

    @property
    def elapsed_s(self) -> float:
        """Wall seconds since the ticker started."""
        return time.monotonic() - self._started

    def __enter__(self) -> Ticker:
        self._started = time.monotonic()
        if self.enabled:
            self._thread = threading.Thread(target=self._loop, name="ticker", daemon=True)
            self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._clear()

    def say(self, message: str) -> None:
        """Print ``message`` on stdout as its own line, then let the status line come back."""
        with self._lock:
            self._clear_locked()
            sys.stdout.write(message + "\n")
            sys.stdout.flush()

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._draw()

    def _draw(self) -> None:
        try:
            text = self.status()
        except Exception as exc:  # a status callable's bug must not kill the command
            text = f"({type(exc).__name__})"
        head = f"{self.label}: {text}" if text else self.label
        clock = f"  [{elapsed(self.elapsed_s)}]"
        room = shutil.get_terminal_size().columns - 1 - len(clock)  # a wrapped line cannot be
        if len(head) > room:  # redrawn in place
            head = head[: max(room - 1, 0)] + "…"
        line = head + clock
        with self._lock:
            self.stream.write("\r" + line + "\x1b[K")
            self.stream.flush()
            self._drawn = True

    def _clear(self) -> None:
        with self._lock:
            self._clear_locked()

    def _clear_locked(self) -> None:
        if self._drawn:
            self.stream.write("\r\x1b[K")
            self.stream.flush()
            self._drawn = False


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False
