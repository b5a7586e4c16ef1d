"""Service lifecycle: graceful stop on the first signal, forced exit on the second."""

from __future__ import annotations

import asyncio
import gc
import json
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from services.edge.lifecycle import EXIT_CONFIG, EXIT_FAILED, EXIT_OK, ServiceExit, serve
from services.edge.logs import JsonFormatter, NodeFilter

REPO = Path(__file__).resolve().parents[2]


def start_helper(mode: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "tests.edge.service_helper", mode],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def read_until(proc: subprocess.Popen[str], marker: str) -> list[str]:
    assert proc.stdout is not None
    lines: list[str] = []
    while True:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"no {marker!r} before EOF; got {lines}")
        lines.append(line.strip())
        if line.strip() == marker:
            return lines


def finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, out, err


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_first_signal_stops_gracefully(signum: signal.Signals) -> None:
    proc = start_helper("cooperative")
    assert read_until(proc, "running") == ["startup", "running"]
    proc.send_signal(signum)
    code, out, err = finish(proc)
    assert code == EXIT_OK, err
    assert out.split() == ["stopping", "shutdown"]
    assert f"{signum.name} received: stopping" in err
    assert "[helper-node]" in err and "crosspath.helper" in err  # logging format


def test_a_daemon_process_freezes_what_its_startup_left() -> None:
    """``run_service`` freezes the objects alive after startup, so no full collection walks
    the imported modules during the run (a 12-17 ms pause a control tick would feel)."""
    proc = start_helper("frozen")
    lines = read_until(proc, "running")
    proc.send_signal(signal.SIGTERM)
    code, _, err = finish(proc)
    assert code == EXIT_OK, err
    frozen = [int(line.split()[1]) for line in lines if line.startswith("frozen ")]
    assert len(frozen) == 1 and frozen[0] > 10_000  # the stdlib, asyncio and our modules


async def test_serve_freezes_only_when_asked() -> None:
    before = gc.get_freeze_count()
    stop = asyncio.Event()
    stop.set()
    try:
        assert await serve(Recorder(), install_signals=False, stop=stop) == EXIT_OK
        assert gc.get_freeze_count() == before
        assert await serve(Recorder(), install_signals=False, stop=stop, freeze_gc=True) == 0
        assert gc.get_freeze_count() > before
    finally:
        gc.unfreeze()  # the test process's objects back to the collector


def test_second_signal_forces_exit() -> None:
    proc = start_helper("stubborn")
    read_until(proc, "running")
    proc.send_signal(signal.SIGINT)
    read_until(proc, "stop ignored")
    proc.send_signal(signal.SIGINT)
    code, out, err = finish(proc)
    assert code == EXIT_FAILED
    assert out.split() == ["shutdown"]  # best-effort shutdown still ran
    assert "forcing exit" in err


class Recorder:
    """An in-process service recording its steps."""

    def __init__(self, fail_in: str = "", shutdown_s: float = 0.0) -> None:
        self.steps: list[str] = []
        self.fail_in = fail_in
        self.shutdown_s = shutdown_s

    async def startup(self) -> None:
        self.steps.append("startup")
        if self.fail_in == "startup":
            raise RuntimeError("no network")
        if self.fail_in == "endpoint":
            raise ServiceExit("cannot listen on tcp/127.0.0.1:1: in use", EXIT_CONFIG)

    async def run(self, stop: asyncio.Event) -> None:
        self.steps.append("run")
        if self.fail_in == "run":
            raise RuntimeError("bug")
        await stop.wait()

    async def shutdown(self) -> None:
        self.steps.append("shutdown")
        await asyncio.sleep(self.shutdown_s)


async def test_serve_with_an_external_stop_event() -> None:
    service = Recorder()
    stop = asyncio.Event()
    task = asyncio.ensure_future(serve(service, install_signals=False, stop=stop))
    await asyncio.sleep(0.01)
    assert service.steps == ["startup", "run"]
    stop.set()
    assert await task == EXIT_OK
    assert service.steps == ["startup", "run", "shutdown"]


@pytest.mark.parametrize("where", ["startup", "run"])
async def test_a_failing_step_still_shuts_down(where: str) -> None:
    service = Recorder(fail_in=where)
    assert await serve(service, install_signals=False) == EXIT_FAILED
    assert service.steps[-1] == "shutdown"
    assert ("run" in service.steps) is (where == "run")


async def test_a_service_exit_is_one_line_and_its_status(
    caplog: pytest.LogCaptureFixture,
) -> None:
    service = Recorder(fail_in="endpoint")
    with caplog.at_level(logging.INFO, logger="crosspath"):
        assert await serve(service, install_signals=False) == EXIT_CONFIG
    assert service.steps == ["startup", "shutdown"]
    errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert [r.getMessage() for r in errors] == ["cannot listen on tcp/127.0.0.1:1: in use"]
    assert errors[0].exc_info is None  # no traceback


async def test_an_unexpected_exception_is_logged_with_its_traceback(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.ERROR, logger="crosspath"):
        assert await serve(Recorder(fail_in="run"), install_signals=False) == EXIT_FAILED
    (record,) = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert record.exc_info is not None and isinstance(record.exc_info[1], RuntimeError)


async def test_a_slow_shutdown_times_out() -> None:
    service = Recorder(shutdown_s=10.0)
    stop = asyncio.Event()
    stop.set()
    code = await serve(service, install_signals=False, stop=stop, shutdown_timeout=0.05)
    assert code == EXIT_FAILED


def test_json_log_lines_carry_the_node() -> None:
    record = logging.LogRecord(
        "crosspath.rsu", logging.INFO, __file__, 1, "mode %s", ("C_SLOW",), None
    )
    NodeFilter("rsu-1").filter(record)
    entry = json.loads(JsonFormatter().format(record))
    assert entry["node"] == "rsu-1" and entry["logger"] == "crosspath.rsu"
    assert entry["level"] == "INFO" and entry["message"] == "mode C_SLOW"
