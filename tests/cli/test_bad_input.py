"""Bad input as a new user types it: one line naming the problem, exit code 2, no work done.

Each case runs the real command line as a subprocess (``python -m
services.cli.main``) in an empty working directory and checks that stderr holds
exactly one line ``crosspath <command>: <option>: <reason>``, stdout is empty,
and nothing under the test's directory changed (no result file, no run
directory, no ``./results``, an existing file left as it was).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli.main import build_parser

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"
KEPT = "an existing file: keep me\n"


def _snapshot(root: Path) -> dict[str, str]:
    """Every path under ``root`` with its content (``<dir>`` for directories)."""
    return {
        str(p.relative_to(root)): "<dir>" if p.is_dir() else p.read_text()
        for p in sorted(root.rglob("*"))
    }


def crosspath(cwd: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "services.cli.main", *argv],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"},
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.fixture
def place(tmp_path: Path) -> Path:
    """An empty working directory ``cwd`` and an existing file ``file.txt``."""
    (tmp_path / "cwd").mkdir()
    (tmp_path / "file.txt").write_text(KEPT)
    return tmp_path


S = str(PAPER)
CASES = [
    # (id, argv with {tmp}, command, option, part of the reason)
    ("sim-seed", ["sim", S, "--seed", "-1", "--json", "{tmp}/r.json"], "sim", "--seed", ">= 0"),
    ("sim-json-dir", ["sim", S, "--json", "{tmp}"], "sim", "--json", "is a directory"),
    (
        "sim-json-under-a-file",
        ["sim", S, "--json", "{tmp}/file.txt/r.json"],
        "sim",
        "--json",
        "not a directory",
    ),
    ("sim-trace-dir", ["sim", S, "--trace", "{tmp}"], "sim", "--trace", "is a directory"),
    ("sim-jitter-nan", ["sim", S, "--jitter-ms", "nan"], "sim", "--jitter-ms", "finite"),
    ("sim-latency-negative", ["sim", S, "--latency-ms", "-2"], "sim", "--latency-ms", ">= 0"),
    ("sim-latency-nan", ["sim", S, "--latency-ms", "nan"], "sim", "--latency-ms", "finite"),
    ("sim-loss-percent", ["sim", S, "--loss", "30"], "sim", "--loss", "fraction within 0..1"),
    ("sim-loss-above-one", ["sim", S, "--loss", "1.5"], "sim", "--loss", "fraction within 0..1"),
    ("sim-mode", ["sim", S, "--mode", "bogus"], "sim", "--mode", "invalid choice"),
    ("sim-unknown-option", ["sim", S, "--sed", "1"], "sim", "--sed 1", "unrecognized"),
    ("sim-no-scenario", ["sim"], "sim", "scenario", "required"),
    (
        "paper-out-is-a-file",
        ["experiment", "paper", "--out", "{tmp}/file.txt"],
        "experiment paper",
        "--out",
        "not a directory",
    ),
    (
        "paper-trials",
        ["experiment", "paper", "--trials", "0", "--out", "{tmp}/paper"],
        "experiment paper",
        "--trials",
        ">= 1",
    ),
    (
        "bench-rsu-cars",
        ["bench", "rsu", "--cars", "-5", "--json", "{tmp}/b.json"],
        "bench rsu",
        "--cars",
        ">= 0",
    ),
    (
        "bench-codec-points",
        ["bench", "codec", "--points", "500", "--json", "{tmp}/c.json"],
        "bench codec",
        "--points",
        "<= ",
    ),
    (
        "up-timeout-zero",
        ["up", S, "--timeout", "0", "--run-dir", "{tmp}/run", "--json", "{tmp}/r.json"],
        "up",
        "--timeout",
        "> 0",
    ),
    ("up-json-dir", ["up", S, "--json", "{tmp}"], "up", "--json", "is a directory"),
    ("up-speed", ["up", S, "--speed", "5000"], "up", "--speed", "<= 1000"),
    (
        "up-run-dir-is-a-file",
        ["up", S, "--run-dir", "{tmp}/file.txt"],
        "up",
        "--run-dir",
        "not a directory",
    ),
    (
        "lab-run-loss-percent",
        ["lab", "run", S, "--loss", "30", "--run-dir", "{tmp}/lab", "--json", "{tmp}/l.json"],
        "lab run",
        "--loss",
        "(30 % is 0.3)",
    ),
    ("lab-up-burst", ["lab", "up", S, "--burst", "0.5"], "lab up", "--burst", ">= 1"),
    (
        "loss-sweep-percent",
        ["experiment", "loss-sweep", "--losses", "0,30", "--out", "{tmp}/sweep"],
        "experiment loss-sweep",
        "--losses",
        "fraction within 0..1",
    ),
    ("monitor-seed", ["monitor", "--seed", "-3"], "monitor", "--seed", ">= 0"),
]


@pytest.mark.parametrize(
    ("argv", "command", "option", "reason"),
    [pytest.param(argv, cmd, opt, why, id=case) for case, argv, cmd, opt, why in CASES],
)
def test_bad_input_is_one_line_and_exit_2_before_any_work(
    place: Path, argv: list[str], command: str, option: str, reason: str
) -> None:
    before = _snapshot(place)
    proc = crosspath(place / "cwd", *(a.replace("{tmp}", str(place)) for a in argv))
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"crosspath {command}: {option}: "), lines[0]
    assert reason in lines[0], lines[0]
    assert proc.stdout == ""
    assert _snapshot(place) == before  # nothing written, no run dir, no ./results
    assert (place / "file.txt").read_text() == KEPT


def test_a_scenario_that_fails_validation_is_one_line(place: Path) -> None:
    bad = place / "bad.toml"
    bad.write_text(PAPER.read_text().replace('route = "north"', 'route = "nowhere"'))
    proc = crosspath(place / "cwd", "sim", str(bad), "--json", str(place / "r.json"))
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("crosspath sim: "), proc.stderr
    assert "route" in lines[0]
    assert not (place / "r.json").exists()


@pytest.mark.parametrize(
    ("text", "value"), [("0", 0.0), ("0.3", 0.3), ("30%", 0.3), ("1", 1.0), ("100%", 1.0)]
)
def test_loss_is_a_fraction_in_every_command(text: str, value: float) -> None:
    parser = build_parser()
    assert parser.parse_args(["sim", S, "--loss", text]).loss == pytest.approx(value)
    assert parser.parse_args(["lab", "run", S, "--loss", text]).loss == pytest.approx(value)
    assert parser.parse_args(["lab", "up", S, "--loss", text]).loss == pytest.approx(value)
    sweep = parser.parse_args(["experiment", "loss-sweep", "--losses", f"0.05,{text}"])
    assert sweep.losses == pytest.approx((0.05, value))


def test_the_loss_sweep_default_losses_are_fractions() -> None:
    args = build_parser().parse_args(["experiment", "loss-sweep"])
    assert args.losses == (0.0, 0.1, 0.3, 0.5, 0.8, 1.0)


FLOWS = REPO / "scenarios" / "four-way-flows.toml"


@pytest.mark.parametrize(
    "argv",
    [
        ["rsu", "--scenario", str(FLOWS), "--id", "rsu1"],
        ["vehicle", "--scenario", str(FLOWS), "--id", "we-0"],
    ],
    ids=["rsu-daemon", "vehicle-daemon"],
)
def test_daemon_harnesses_refuse_flows_in_one_line(place: Path, argv: list[str]) -> None:
    """A daemon refuses a flow scenario before starting anything (issue 12: `crosspath up`
    and `crosspath lab run` expand flows for their seed, tests/supervise/test_up_flows.py
    and tests/supervise/lab/test_lab_tls.py; a daemon loads that plain file), instead of
    running with no cars."""
    before = _snapshot(place)
    proc = crosspath(place / "cwd", *argv)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "flows" in lines[0] and "crosspath up" in lines[0], lines[0]
    assert _snapshot(place) == before
