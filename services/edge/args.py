"""Argparse value types shared by every ``crosspath`` command: bad input fails at parsing.

Each function here is an argparse ``type=``: it turns the option's text into a
value or raises :class:`argparse.ArgumentTypeError` with a short reason, so a
bad value is refused before any work starts (the CLI's parser prints it as one
line, ``crosspath <cmd>: <option>: <reason>``, and exits 2). They live in the
edge layer, not in ``services.cli``, because the daemons, the launcher, the
benches and the experiments define their own options and may only import
downwards.

Units rule: a probability or share (loss, ...) is a fraction 0..1 everywhere;
:func:`fraction` also takes an explicit percentage (``30%`` is 0.3), never a
bare number above 1.

Output paths are checked the same way: :func:`output_file` refuses a directory
and a parent that cannot be created or written, :func:`output_dir` refuses an
existing file. (Root passes every permission check; the checks still catch the
common mistakes.)
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path

from services.edge.plumbing import MAX_SPEED
from services.model.catalog import DEFAULT_SCENARIO_NAME
from services.model.types import Policy, RunMode

__all__ = [
    "add_mode_and_policy",
    "finite_float",
    "float_at_least",
    "fraction",
    "int_at_least",
    "non_negative_float",
    "non_negative_int",
    "output_dir",
    "output_file",
    "positive_float",
    "positive_int",
    "run_speed",
]


def _bad(reason: str) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(reason)


def _int(text: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise _bad(f"must be an integer, got {text!r}") from None


def finite_float(text: str) -> float:
    """A real number (no ``nan``, no ``inf``)."""
    try:
        value = float(text.strip())
    except ValueError:
        raise _bad(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise _bad(f"must be a finite number, got {text!r}")
    return value


def int_at_least(low: int) -> Callable[[str], int]:
    """An integer ``>= low``."""

    def parse(text: str) -> int:
        value = _int(text)
        if value < low:
            raise _bad(f"must be >= {low}, got {value}")
        return value

    parse.__name__ = f"int_at_least_{low}"
    return parse


def float_at_least(low: float, *, strict: bool = False) -> Callable[[str], float]:
    """A finite number ``>= low`` (``> low`` with ``strict``)."""

    def parse(text: str) -> float:
        value = finite_float(text)
        if value < low or (strict and value == low):
            raise _bad(f"must be {'>' if strict else '>='} {low:g}, got {text.strip()}")
        return value

    parse.__name__ = f"float_{'above' if strict else 'at_least'}_{low:g}"
    return parse


non_negative_int = int_at_least(0)
"""An integer >= 0 (seeds, counts that may be empty)."""
positive_int = int_at_least(1)
"""An integer >= 1 (trials, jobs, repetitions)."""
non_negative_float = float_at_least(0.0)
"""A finite number >= 0 (latencies, jitter, delays)."""
positive_float = float_at_least(0.0, strict=True)
"""A finite number > 0 (timeouts, rates, time limits)."""


def run_speed(text: str) -> float:
    """Run seconds per wall second, in (0, :data:`~services.edge.plumbing.MAX_SPEED`]."""
    value = positive_float(text)
    if value > MAX_SPEED:
        raise _bad(f"must be <= {MAX_SPEED:g}, got {text.strip()}")
    return value


def fraction(text: str) -> float:
    """A probability or share, 0..1; ``30%`` is accepted as 0.3, a bare ``30`` is not."""
    raw = text.strip()
    percent = raw.endswith("%")
    value = finite_float(raw[:-1] if percent else raw)
    if percent:
        if not 0.0 <= value <= 100.0:
            raise _bad(f"must be within 0..100 %, got {raw}")
        return value / 100.0
    if not 0.0 <= value <= 1.0:
        hint = f" ({value:g} % is {value / 100.0:g})" if 1.0 < value <= 100.0 else ""
        raise _bad(f"must be a fraction within 0..1{hint}, got {raw}")
    return value


def _nearest_existing(path: Path) -> Path:
    """``path`` or its closest ancestor that exists (``.`` for a relative path at worst)."""
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return Path(".")


def _creatable_under(directory: Path, target: Path) -> None:
    """Refuse when ``target``'s missing parents cannot be created under ``directory``."""
    existing = _nearest_existing(directory)
    if not existing.is_dir():
        raise _bad(f"{existing} is not a directory, cannot create {target}")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise _bad(f"cannot write in {existing}")


def output_file(text: str) -> Path:
    """A file to write: not a directory; its directory exists or can be created, writable."""
    if not text.strip():
        raise _bad("must be a file path, got an empty string")
    path = Path(text)
    if path.is_dir():
        raise _bad(f"{path} is a directory, expected a file path")
    if path.exists() and not os.access(path, os.W_OK):
        raise _bad(f"{path} is not writable")
    _creatable_under(path.parent, path)
    return path


def output_dir(text: str) -> Path:
    """A directory to write into: an existing writable directory, or one that can be created."""
    if not text.strip():
        raise _bad("must be a directory path, got an empty string")
    path = Path(text)
    if path.exists():
        if not path.is_dir():
            raise _bad(f"{path} exists and is not a directory")
        if not os.access(path, os.W_OK | os.X_OK):
            raise _bad(f"cannot write in {path}")
        return path
    _creatable_under(path.parent, path)
    return path


def add_mode_and_policy(parser: argparse.ArgumentParser) -> None:
    """``--mode`` and ``--policy``, the same in every command that runs the scenario."""
    parser.add_argument(
        "--mode",
        choices=[m.value for m in RunMode],
        default=RunMode.RSU.value,
        help="standalone (no V2X), fp-only (future paths), rsu (future paths and the RSU)",
    )
    parser.add_argument(
        "--policy",
        choices=[p.value for p in Policy],
        default=Policy.PAPER.value,
        help="the RSU's velocity manager (rsu mode)",
    )


def add_scenario_option(parser: argparse.ArgumentParser) -> None:
    """``--scenario``, defaulting to the paper's scenario by its packaged name (a name,
    not a path, so the help shows it whole wherever the package is installed)."""
    parser.add_argument(
        "--scenario",
        type=Path,
        default=Path(DEFAULT_SCENARIO_NAME),
        help="TOML file or packaged name",
    )
