"""SUMO comes from the ``eclipse-sumo`` wheel (extra ``sumo``, in ``dev``): the tests
skip without it locally and fail on CI, where ``make test`` installs it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.sumo.netgen import (
    Control,
    SumoNotFound,
    build_corridor,
    build_network,
    sumo_binary,
)


def require_sumo() -> None:
    """Skip (fail on CI) when SUMO or libsumo/traci is missing."""
    try:
        sumo_binary("sumo")
        sumo_binary("netconvert")
        from services.sumo.baseline import sumo_api

        sumo_api()
    except SumoNotFound as exc:
        if os.environ.get("CI"):
            pytest.fail(f"SUMO is missing on CI (pip install '.[dev]' installs it): {exc}")
        pytest.skip(str(exc))


@pytest.fixture(scope="session")
def short_nets(tmp_path_factory: pytest.TempPathFactory) -> dict[Control, Path]:
    """The 4-way with 40 m approaches, one network per control (quick to drive)."""
    require_sumo()
    d = tmp_path_factory.mktemp("nets")
    return {c: build_network(d / c.value, c, approach_m=40.0) for c in Control}


@pytest.fixture(scope="session")
def corridors(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """Priority corridors of 2 and 3 junctions (``j0``, ``j1``...) 40 m apart, arms and
    ends of 20 m (quick to drive), keyed by their number of junctions."""
    require_sumo()
    d = tmp_path_factory.mktemp("corridors")
    return {n: build_corridor(d, junctions=n, spacing_m=40.0, arm_m=20.0) for n in (2, 3)}
