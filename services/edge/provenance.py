"""Where a run's code and scenario came from: the I/O half of a run result's provenance.

The run result (``services.model.results``) and the harness are pure; what needs
the file system or a subprocess is found here and handed down as an
:class:`~services.model.results.Origin`:

- the package version from the installed distribution's metadata
  (:func:`importlib.metadata.version`), or :data:`UNKNOWN_VERSION` when
  ``crosspath`` runs from a source tree that was never installed;
- the git commit of the source tree (``git rev-parse HEAD``) when the package
  runs from a checkout (a ``.git`` right beside ``services/``); None for an
  installed wheel or without git. Uncommitted changes are not flagged;
- the sha256 of the scenario file's bytes (None when it cannot be read).

Version and commit are looked up once per process.
"""

from __future__ import annotations

import hashlib
import logging
import os
import subprocess
from functools import cache
from importlib import metadata
from pathlib import Path
from typing import Final

from services.model.catalog import resolve_scenario
from services.model.results import Origin

__all__ = ["UNKNOWN_VERSION", "file_sha256", "git_commit", "origin", "package_version"]

log = logging.getLogger("crosspath.provenance")

DISTRIBUTION: Final = "crosspath"
UNKNOWN_VERSION: Final = "0+unknown"
"""The version reported when the package's metadata is not installed."""
SOURCE_ROOT: Final = Path(__file__).resolve().parents[2]
"""The folder holding ``services/`` (a checkout, or site-packages for a wheel)."""
GIT_TIMEOUT_S: Final = 5.0


@cache
def package_version() -> str:
    """The installed ``crosspath`` version, or :data:`UNKNOWN_VERSION`."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return UNKNOWN_VERSION


@cache
def git_commit(root: Path = SOURCE_ROOT) -> str | None:
    """The commit checked out in ``root`` (40 hex digits), or None when ``root`` is not a
    git checkout or git is unavailable."""
    if not (root / ".git").exists():
        return None
    try:
        done = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        log.debug("no git commit for %s: %s", root, exc)
        return None
    commit = done.stdout.strip()
    if done.returncode != 0 or len(commit) != 40:
        return None
    return commit


def file_sha256(path: str | os.PathLike[str]) -> str | None:
    """sha256 (hex) of the file's bytes, or None when it cannot be read."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        log.debug("no digest of %s: %s", path, exc)
        return None
    return hashlib.sha256(data).hexdigest()


def origin(scenario_file: str | os.PathLike[str] | None) -> Origin:
    """Version, commit and the scenario file's path and digest, for a run result
    (``scenario_file`` may name a packaged scenario: its file is the one hashed)."""
    if scenario_file is None:
        return Origin(version=package_version(), commit=git_commit())
    try:
        path = resolve_scenario(scenario_file)
    except OSError:
        path = Path(scenario_file)
    return Origin(
        version=package_version(),
        commit=git_commit(),
        scenario_file=str(path),
        scenario_sha256=file_sha256(path),
    )
