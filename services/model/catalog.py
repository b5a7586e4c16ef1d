"""The scenarios shipped with crosspath, found by name wherever the package is installed.

The top-level ``scenarios/`` folder of the source tree is also an importable data
package (``scenarios``, its ``*.toml`` files as package data), so a wheel carries
the default scenarios and this module finds them through :mod:`importlib.resources`,
never relative to a checkout (``scenarios/README.md``, "Packaged scenarios").

A scenario argument is a path or the name of a packaged scenario:
:func:`resolve_scenario` decides which, and :func:`~services.model.scenario.load_scenario`
calls it, so every command and daemon that takes a scenario accepts both.
"""

from __future__ import annotations

import os
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Final

__all__ = [
    "DEFAULT_SCENARIO_NAME",
    "PACKAGE",
    "default_scenario",
    "packaged_names",
    "packaged_scenario",
    "resolve_scenario",
]

PACKAGE: Final = "scenarios"
"""The data package holding the packaged scenario files."""

SUFFIX: Final = ".toml"

DEFAULT_SCENARIO_NAME: Final = "paper-blind-intersection"
"""The paper's scenario: the default of ``demo``, ``experiment paper``/``loss-sweep`` and
``bench sim``."""


@cache
def _folder() -> Path:
    """The packaged scenarios' folder on the file system (pip installs wheels unpacked;
    the daemons get the file's path on their command line, so it must be a real file)."""
    try:
        folder = resources.files(PACKAGE)
    except ModuleNotFoundError as exc:
        raise RuntimeError(
            f"the {PACKAGE!r} data package is missing: crosspath is not installed properly"
        ) from exc
    if not isinstance(folder, Path):
        raise RuntimeError(f"packaged scenarios must be files on disk, got {folder!r}")
    return folder


@cache
def packaged_names() -> tuple[str, ...]:
    """Names of the packaged scenarios (file names without ``.toml``), sorted."""
    return tuple(sorted(p.stem for p in _folder().glob(f"*{SUFFIX}") if p.is_file()))


def packaged_scenario(name: str) -> Path:
    """The file of packaged scenario ``name`` (``.toml`` optional); ``LookupError`` naming the
    packaged ones when there is none."""
    stem = name.removesuffix(SUFFIX)
    if stem not in packaged_names():
        known = ", ".join(packaged_names()) or "none"
        raise LookupError(f"no packaged scenario {name!r} (packaged: {known})")
    return _folder() / f"{stem}{SUFFIX}"


def default_scenario() -> Path:
    """The file of the default scenario, :data:`DEFAULT_SCENARIO_NAME`."""
    return packaged_scenario(DEFAULT_SCENARIO_NAME)


def resolve_scenario(ref: str | os.PathLike[str]) -> Path:
    """The scenario file ``ref`` means: an existing path as given; otherwise a bare name
    (no directory part) of a packaged scenario, with or without ``.toml``; otherwise
    ``ref`` as a path, which the caller then fails to read. A file in the working
    directory wins over a packaged scenario of the same name. Raises
    ``FileNotFoundError`` for a bare name that is neither, listing the packaged names."""
    path = Path(ref)
    text = os.fspath(ref)
    if path.is_file() or not text or path.name != text:
        return path
    try:
        return packaged_scenario(text)
    except LookupError as exc:
        if path.exists():
            return path  # e.g. a directory: reading it says what is wrong
        raise FileNotFoundError(f"no file {text!r} and {exc}") from None
