"""No process of a ``crosspath up`` run outlives its launcher (issue 16).

Checked by process listing: every daemon's command line carries the run id, so
``/proc`` shows any leftover (``launcher.processes_carrying``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.supervise.launcher import processes_carrying, sweep

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"


def test_processes_carrying_finds_a_marked_process_and_sweep_ends_it() -> None:
    marker = f"crosspath-test-{os.getpid()}-{time.monotonic_ns()}"
    proc = subprocess.Popen(
        [sys.executable, "-c", "import signal, time; "
         "signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ready', flush=True); "
         "time.sleep(60)", marker],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
        assert processes_carrying(marker) == [proc.pid]
        assert sweep(marker, grace_s=0.3) == [proc.pid]  # ignores SIGTERM: killed
        assert proc.wait(timeout=5.0) == -signal.SIGKILL
        assert processes_carrying(marker) == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    with pytest.raises(ValueError, match="empty marker"):
        processes_carrying("")


class Up:
    """``crosspath up`` in the background (rsu mode, speed 2), waited until mid-run."""

    def __init__(self, tmp_path: Path) -> None:
        self.run_dir = tmp_path / "run"
        self.result_path = tmp_path / "result.json"  # the launcher's result, not the monitor's
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli.main", "up", str(PAPER), "--mode", "rsu",
             "--speed", "2", "--run-dir", str(self.run_dir), "--timeout", "120",
             "--json", str(tmp_path / "result.json")],
            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        monitor_log = self.run_dir / "monitor.log"
        deadline = time.monotonic() + 60.0
        while not (monitor_log.exists() and "starting run" in monitor_log.read_text()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.proc.kill()
                raise AssertionError(f"the run did not start: {self.proc.communicate()}")
            time.sleep(0.1)
        time.sleep(2.0)
        self.children = json.loads((self.run_dir / "children.json").read_text())
        monitor_argv = self.children["monitor"]["argv"]
        self.run_id = str(monitor_argv[monitor_argv.index("--run-id") + 1])
        assert sorted(self.children) == ["A", "B", "monitor", "rsu1"]
        for node, child in self.children.items():
            assert self.run_id in " ".join(child["argv"]), node  # every child carries it
        assert len(processes_carrying(self.run_id)) == 4

    def pid(self, node: str) -> int:
        return int(self.children[node]["pid"])

    def finish(self, timeout_s: float = 60.0) -> tuple[int, str]:
        try:
            _out, err = self.proc.communicate(timeout=timeout_s)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode, err

    def assert_no_orphan(self, within_s: float = 0.0) -> None:
        deadline = time.monotonic() + within_s
        while processes_carrying(self.run_id) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = processes_carrying(self.run_id)
        for pid in left:  # never leave them behind, even when the test fails
            os.kill(pid, signal.SIGKILL)
        assert left == [], f"orphans of run {self.run_id}: {left}"


@pytest.mark.daemons
def test_no_orphan_after_an_rsu_kill_and_a_restart_by_hand(tmp_path: Path) -> None:
    up = Up(tmp_path)
    os.kill(up.pid("rsu1"), signal.SIGKILL)
    # restarted by hand from children.json, in its own session: not the launcher's child
    argv = up.children["rsu1"]["argv"]
    with (up.run_dir / "rsu1-restarted.log").open("wb") as log:
        restarted = subprocess.Popen(
            argv, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
    try:
        code, err = up.finish()
        assert code == 1, err  # without --expect-crash the run fails ...
        assert "rsu1 exited during the run with code -9" in err
        assert "swept 1 leftover process(es)" in err  # ... and the restarted RSU goes too
        restarted.wait(timeout=10.0)
        up.assert_no_orphan()
        result = json.loads(up.result_path.read_text())
        lost = [c for c in result["crashes"] if c["node"] == "rsu1" and c["event"] == "lost"]
        assert len(lost) == 1 and lost[0]["t_s"] is not None and lost[0]["t_s"] > 0
    finally:
        if restarted.poll() is None:
            restarted.kill()
            restarted.wait()


@pytest.mark.daemons
def test_no_orphan_after_a_car_kill(tmp_path: Path) -> None:
    up = Up(tmp_path)
    os.kill(up.pid("B"), signal.SIGKILL)
    code, err = up.finish()
    assert code == 1 and "B exited during the run with code -9" in err
    up.assert_no_orphan()
    result = json.loads(up.result_path.read_text())
    assert [c["node"] for c in result["crashes"]] == ["B"]


@pytest.mark.daemons
def test_no_orphan_after_a_monitor_kill(tmp_path: Path) -> None:
    up = Up(tmp_path)
    os.kill(up.pid("monitor"), signal.SIGKILL)
    code, err = up.finish()
    assert code == 1, err
    up.assert_no_orphan()


@pytest.mark.daemons
def test_no_orphan_after_a_launcher_sigkill(tmp_path: Path) -> None:
    up = Up(tmp_path)
    up.proc.kill()  # SIGKILL: no handler, no cleanup; the kernel's PR_SET_PDEATHSIG does it
    up.finish()
    up.assert_no_orphan(within_s=15.0)
