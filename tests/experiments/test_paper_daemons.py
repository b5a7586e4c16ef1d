"""``experiment paper --daemons``: real daemons through the Python API keep the speed profiles."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.experiments.paper import COLUMNS, run_paper_experiment

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"


@pytest.mark.daemons
def test_daemon_trials_have_traces_profiles_and_behaviour(tmp_path: Path) -> None:
    rsu = next(c for c in COLUMNS if c.key == "rsu-paper")
    doc = run_paper_experiment(
        PAPER, 1, 2, tmp_path, daemons=True, progress=False, speed=2.0, columns=[rsu]
    )
    assert doc["harness"] == "daemons"
    assert (tmp_path / "speed_profiles.png").read_bytes()[:4] == b"\x89PNG"
    run = doc["runs"]["rsu-paper"][0]
    assert run["result"]["harness"] == "daemons" and "trace" not in run["result"]
    assert set(run["behaviour"]) == {"A", "B"}  # analysed from the monitor's trace
    assert doc["aggregates"]["rsu-paper"]["behaviour"] is not None
    report = (tmp_path / "REPORT.md").read_text()
    assert "(speed_profiles.png)" in report and "No planner trace" not in report
    assert (tmp_path / "daemons" / "rsu-paper-seed2" / "monitor.log").exists()
    assert json.loads((tmp_path / "results.json").read_text())["runs"] == doc["runs"]
