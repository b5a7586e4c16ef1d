"""``crosspath bench sim``: cases and keys (never timings), and the scaled traffic scenario."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from services.bench import sim
from services.model import geometry
from services.model.types import Policy, RunMode

KEYS = {"scenario", "mode", "cars", "x_real_time"}

SHORT_CASES = (
    ("standalone", RunMode.STANDALONE, Policy.PAPER),
    ("rsu-slot", RunMode.RSU, Policy.SLOT),
)
"""Two of the paper cases, to keep these tests short."""


def test_every_mode_and_policy_is_a_paper_case() -> None:
    assert {(mode, policy) for _, mode, policy in sim.CASES} == {
        (RunMode.STANDALONE, Policy.PAPER),
        (RunMode.FP_ONLY, Policy.PAPER),
        (RunMode.RSU, Policy.PAPER),
        (RunMode.RSU, Policy.SLOT),
    }


def test_scaled_traffic_has_about_the_cars_asked() -> None:
    for cars in (50, 200):
        scenario = sim.scaled_traffic(cars)
        assert scenario.name == f"four-way-flows-40-x{cars}"
        assert abs(sim._cars(scenario) - cars) <= 0.15 * cars
    with pytest.raises(ValueError):
        sim.scaled_traffic(0)


def test_measure_paper_and_a_short_traffic_window(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sim, "CASES", SHORT_CASES)
    doc = sim.measure(seeds=1, traffic_cars=(10,), window_s=2.0)
    cases = doc["cases"]
    assert [c["case"] for c in cases] == [
        "standalone",
        "rsu-slot",
        "traffic-10-standalone",
        "traffic-10-fp-only",
        "traffic-10-rsu",
    ]
    for c in cases:
        assert set(c) >= KEYS
        assert c["x_real_time"] > 0 and c["sim_s"] > 0 and c["cpu_s"] > 0
    paper = [c for c in cases if c["scenario"] == doc["scenario"]]
    assert [(c["mode"], c["policy"]) for c in paper] == [("standalone", "paper"), ("rsu", "slot")]
    assert all(c["cars"] == 2 for c in paper)
    traffic = cases[-1]
    assert traffic["sim_s"] == pytest.approx(2.0, abs=0.1)  # the window, not the whole run
    assert traffic["cars_started"] <= traffic["cars"]
    assert set(doc["targets"]["met"]) == {"paper_every_mode"}
    assert doc["c_geometry"] is geometry.kernel_available()
    json.dumps(doc)


def test_run_writes_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sim, "CASES", SHORT_CASES[:1])
    parser = argparse.ArgumentParser()
    sim.configure(parser)
    out = tmp_path / "sim.json"
    args = parser.parse_args(["--seeds", "1", "--traffic-cars", "--json", str(out)])
    assert sim.run(args) == 0
    doc = json.loads(out.read_text())
    assert [c["case"] for c in doc["cases"]] == ["standalone"]
    assert "x real time" in capsys.readouterr().out
