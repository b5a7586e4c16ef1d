"""The ``crosspath`` front-end: ``--version``, help with defaults, one-line errors, run dirs."""

from __future__ import annotations

import argparse
import importlib.metadata
import io
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import redirect_stdout
from pathlib import Path

import pytest

from services.cli.main import COMMANDS, HelpFormatter, build_parser, one_line

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"


def crosspath(cwd: Path, *argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "services.cli.main", *argv],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_version_is_the_package_version(tmp_path: Path) -> None:
    proc = crosspath(tmp_path, "--version")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == f"crosspath {importlib.metadata.version('crosspath')}\n"


def test_sim_help_shows_the_defaults(tmp_path: Path) -> None:
    proc = crosspath(tmp_path, "sim", "--help")
    assert proc.returncode == 0, proc.stderr
    lines: dict[str, str] = {}  # option -> its whole entry, continuation lines joined
    option = ""
    for line in proc.stdout.splitlines():
        if line.startswith("  -"):
            option = line.split()[0]
            lines[option] = line.strip()
        elif option and line.startswith("    "):
            lines[option] += " " + line.strip()
        else:
            option = ""
    assert lines["--seed"].endswith("(default: 0)")
    assert lines["--loss"].endswith("(default: 0.0)")
    assert lines["--latency-ms"].endswith("(default: 2.0)")
    assert lines["--jitter-ms"].endswith("(default: 1.0)")
    assert "(default: rsu)" in lines["--mode"]
    assert "default" not in lines["--json"]  # no default to show: nothing, not "None"


def _commands(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield sub
                yield from _commands(sub)


def test_every_command_shows_every_default_in_its_help() -> None:
    parser = build_parser()
    seen = 0
    for command in _commands(parser):
        assert command.formatter_class is HelpFormatter, command.prog
        text = command.format_help()
        for action in command._actions:
            default = action.default
            if (
                not action.option_strings
                or default in (None, False, argparse.SUPPRESS, [], ())
                or isinstance(action, argparse._HelpAction)
            ):
                continue
            seen += 1
            assert action.help, f"{command.prog} {action.option_strings[0]}: no help"
            shown = (
                " ".join(str(v) for v in default)
                if isinstance(default, list | tuple)
                else str(default)
            )
            assert f"(default: {shown})" in " ".join(text.split()) or "default" in action.help, (
                f"{command.prog} {action.option_strings[0]}"
            )
    assert seen > 40  # every command was walked
    words = {tuple(c.prog.split()[1:]) for c in _commands(parser)}
    assert set(COMMANDS) <= words


def test_help_of_every_command_works() -> None:
    parser = build_parser()
    for words in COMMANDS:
        out = io.StringIO()
        with redirect_stdout(out), pytest.raises(SystemExit) as exc:
            parser.parse_args([*words, "--help"])
        assert exc.value.code == 0
        assert out.getvalue().startswith(f"usage: crosspath {' '.join(words)}")


@pytest.mark.parametrize(
    ("message", "line"),
    [
        ("argument --seed: must be >= 0, got -1", "--seed: must be >= 0, got -1"),
        ("the following arguments are required: scenario", "scenario: required"),
        ("unrecognized arguments: --x 1", "--x 1: unrecognized arguments"),
        ("unrecognized arguments: --x", "--x: unrecognized argument"),
        ("argument --mode: bad 'a'\n (choose 'b')", "--mode: bad 'a' (choose 'b')"),
    ],
)  # fmt: skip
def test_argparse_complaints_become_one_line(message: str, line: str) -> None:
    assert one_line(message) == line


def test_no_command_is_one_line(tmp_path: Path) -> None:
    proc = crosspath(tmp_path)
    assert proc.returncode == 2
    assert proc.stderr == "crosspath: COMMAND: required\n"


@pytest.mark.daemons
def test_up_writes_its_logs_beside_its_result_not_in_the_working_directory(
    tmp_path: Path,
) -> None:
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    out = tmp_path / "out" / "run.json"
    proc = crosspath(
        cwd, "up", str(PAPER), "--mode", "standalone", "--speed", "20", "--json", str(out),
        timeout=180,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert out.is_file()
    logs = tmp_path / "out" / "run-logs"
    assert {p.name for p in logs.iterdir()} >= {"monitor.log", "A.log", "B.log", "result.json"}
    assert list(cwd.iterdir()) == []  # no ./results
    assert proc.stderr == ""  # not a terminal: no status line


def test_help_never_breaks_a_default_path_or_name() -> None:
    """CI checks out under a long directory: a default path must stay one word."""
    parser = argparse.ArgumentParser(prog="x", formatter_class=HelpFormatter)
    long_path = "/check/work/some-long-directory-name/scenarios/paper-blind-intersection.toml"
    parser.add_argument("--scenario", default=long_path, help="TOML file or packaged name")
    words = parser.format_help().split()
    assert f"{long_path})" in words
