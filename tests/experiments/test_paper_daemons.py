"""``experiment paper --daemons``: real daemons through the Python API keep the speed profiles;
and the API's own daemon run (``services.api.run_daemons``, which every trial calls) gives
the in-process harness's result, with its provenance, network and trace."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from services.api import simulate
from services.experiments.paper import COLUMNS, run_paper_experiment
from services.model.results import RunResult
from services.model.types import Policy

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
    # the API's daemon run (run_daemons, trace on) against the in-process harness
    result = RunResult.model_validate(run["result"])
    reference = simulate(PAPER, mode="rsu", seed=2)
    assert result.ok and result.collisions == 0 and result.all_finished
    assert result.start_times == reference.start_times
    for vid, ref in reference.vehicles.items():
        got = result.vehicles[vid].passing_time_s
        assert got == pytest.approx(ref.passing_time_s, rel=0.10), vid
    assert result.network is not None
    fp = result.network.stream("fp")
    assert fp is not None and fp.delivery_ratio is not None and fp.delivery_ratio > 0.9
    prov = result.provenance
    assert prov is not None and prov.channel.kind == "zenoh" and prov.policy is Policy.PAPER
    assert prov.scenario_sha256 == hashlib.sha256(PAPER.read_bytes()).hexdigest()
    on_disk = (tmp_path / "daemons" / "rsu-paper-seed2" / "result.json").read_text()
    assert RunResult.model_validate_json(on_disk).vehicles == result.vehicles
