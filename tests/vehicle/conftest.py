from __future__ import annotations

from pathlib import Path

import pytest

from services.model.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"


@pytest.fixture(scope="session")
def paper() -> Scenario:
    return load_scenario(PAPER)
