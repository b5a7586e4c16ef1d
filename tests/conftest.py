"""Test-wide settings.

Hypothesis: on CI (``CI`` set) every property runs a fixed, derandomised set of
examples, so a submission's result does not depend on which examples a random search
happened to find; locally the search is random and wider, which is where new failures
are found (and then pinned with ``@example``).

Serial tests: ``make test`` runs the pure tests in parallel (pytest-xdist), then the
``serial`` ones one at a time. A test is serial when it is marked ``daemons`` or ``lab``,
or lives where tests use real time, sockets or processes (:data:`SERIAL_PATHS`): sharing
the CPU with another test would make their timing, not the code, decide the result. The
``packaging`` test (a wheel built and installed in a fresh venv) keeps no time: it runs in
the parallel pass."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

_TESTS = Path(__file__).resolve().parent
SERIAL_PATHS = ("bench", "daemons", "deploy", "edge", "security", "supervise", "view")
"""Folders under tests/ whose tests are all serial."""
SERIAL_MARKS = ("daemons", "lab")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        try:
            top = item.path.resolve().relative_to(_TESTS).parts[0]
        except ValueError:
            continue
        if top in SERIAL_PATHS or any(item.get_closest_marker(m) for m in SERIAL_MARKS):
            item.add_marker(pytest.mark.serial)
