"""The view's pure fold: decoded messages and trace rows into a JSON-able world."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from protocol import encode
from protocol import keys as pkeys
from protocol.messages import FuturePath, Header, Mode
from services.daemons.steplog import StepLog
from services.edge.plumbing import StartRun, TruthReport
from services.model.catalog import resolve_scenario
from services.model.kinematics import TruthState
from services.model.scenario import load_scenario
from services.model.types import Policy, RunMode
from services.view.state import (
    MAX_DRAWN_POINTS,
    SPARK_SAMPLES,
    Replay,
    TraceRow,
    ViewState,
    rows_from_trace_csv,
    scenario_map,
)
from services.view.traces import TraceError, load_trace
from tests.view.helpers import RUN_ID, beacon, cp, fp, start, terminate, truth


def car(snap: dict[str, Any], vid: str) -> dict[str, Any]:
    cars = snap["cars"]
    assert isinstance(cars, list)
    (found,) = [c for c in cars if c["id"] == vid]
    assert isinstance(found, dict)
    return found


def test_future_path_puts_a_car_with_its_path_and_mode() -> None:
    state = ViewState()
    assert state.on_datagram(*fp("A", 1.0, -50.0, -1.75))
    snap = state.snapshot()
    a = car(snap, "A")
    assert (a["x"], a["y"], a["v"], a["mode"]) == (-50.0, -1.75, 10.0, "AUTO")
    assert isinstance(a["fp"], list) and len(a["fp"]) == 30 and a["fp"][1] == [-49.0, -1.75]
    assert snap["t"] == 1.0
    json.dumps(snap, allow_nan=False)  # JSON-able, no NaN


def test_truth_wins_over_the_future_path_position() -> None:
    state = ViewState()
    state.on_datagram(*start())
    state.on_datagram(*truth("A", 20, 1.0, -40.0, -1.75, mode="C_SLOW"))
    state.on_datagram(*fp("A", 1.05, -99.0, -1.75, mode=Mode.C_FAST))
    a = car(state.snapshot(), "A")
    assert a["x"] == -40.0  # ground truth, not the path's position
    assert a["mode"] == "C_FAST"  # the latest word of the car
    assert len(a["fp"]) == 30


def test_coordinated_path_shown_until_terminated_or_stale() -> None:
    state = ViewState()
    state.on_datagram(*fp("B", 2.0, 1.75, -40.0))
    state.on_datagram(*cp("rsu1", "B", 2.0, 1.75, -40.0))
    b = car(state.snapshot(), "B")
    assert len(b["cp"]) == 20 and b["cp_mode"] == "C_SLOW" and b["cp_rsu"] == "rsu1"
    state.on_datagram(*terminate("rsu1", "B", 2.1))
    assert car(state.snapshot(), "B")["cp"] == []
    state.on_datagram(*cp("rsu1", "B", 3.0, 1.75, -30.0))
    state.on_datagram(*fp("B", 4.5, 1.75, -20.0))  # 1.5 s without a repeat: stale
    assert car(state.snapshot(), "B")["cp"] == []


def test_beacon_and_start_and_run_info() -> None:
    state = ViewState()
    state.on_datagram(*start())
    state.on_datagram(*beacon("rsu1", 0.5))
    snap = state.snapshot()
    assert snap["run"]["run_id"] == RUN_ID and snap["run"]["mode"] == "rsu"
    assert snap["rsus"] == [
        {"id": "rsu1", "intersection": "X1", "x": 0.0, "y": 0.0, "r": 150.0, "t": 0.5}
    ]


def test_hostile_datagrams_are_counted_and_dropped() -> None:
    state = ViewState()
    key, good = fp("A", 1.0, 0.0, 0.0)
    assert not state.on_datagram(key, b"\x00garbage")
    assert not state.on_datagram(key, good[:-7])  # truncated
    assert not state.on_datagram("crosspath/v2x/fp/B", good)  # sender is not the key's
    assert not state.on_datagram("elsewhere/v2x/fp/A", good)
    assert not state.on_datagram("crosspath/sim/truth/A", b"\xff\xfe")
    assert not state.on_datagram(truth("B", 1, 1.0, 0.0, 0.0)[0], truth("A", 1, 1.0, 0, 0)[1])
    c = state.counters
    assert (c["malformed"], c["mismatched"], c["bad_key"]) == (3, 2, 1)
    assert c["received"] == 6 and c["applied"] == 0
    assert state.snapshot()["cars"] == []


def test_a_forged_far_future_time_does_not_stop_the_clock() -> None:
    state = ViewState()
    state.on_datagram(*fp("A", 1.0, 0.0, 0.0))
    assert not state.on_datagram(*fp("A", 5000.0, 9.0, 9.0))
    assert state.counters["implausible_time"] == 1
    assert state.on_datagram(*fp("A", 1.1, 1.0, 0.0))
    assert state.snapshot()["t"] == 1.1


def test_per_sender_state_is_bounded() -> None:
    state = ViewState(max_cars=4)
    for i in range(10):
        state.on_datagram(*fp(f"car{i}", 1.0 + i * 0.01, float(i), 0.0))
    snap = state.snapshot()
    assert [c["id"] for c in snap["cars"]] == ["car6", "car7", "car8", "car9"]
    assert state.counters["evicted"] == 6
    for k in range(SPARK_SAMPLES * 2):  # sparkline bounded too
        state.on_truth(TraceRow(2.0 + k * 0.5, "car9", float(k), 0.0, 5.0))
    assert len(car(state.snapshot(), "car9")["spark"]) == SPARK_SAMPLES


def test_cars_not_heard_for_long_are_forgotten_and_faded() -> None:
    state = ViewState()
    state.on_truth(TraceRow(0.0, "A", 0.0, 0.0, 1.0))
    state.on_truth(TraceRow(2.0, "B", 0.0, 0.0, 1.0))
    assert car(state.snapshot(), "A")["stale"] is True
    assert car(state.snapshot(), "B")["stale"] is False
    state.on_truth(TraceRow(12.0, "B", 1.0, 0.0, 1.0))
    assert [c["id"] for c in state.snapshot()["cars"]] == ["B"]


def test_paths_are_thinned_for_the_page() -> None:
    pts = np.array([[float(i), 0.0, 0.05 * i] for i in range(200)])
    msg = FuturePath(Header("A", 1, 0), 0.0, 0.0, 1.0, 0.0, 4.5, 1.8, Mode.AUTO, pts)
    state = ViewState()
    assert state.on_datagram(pkeys.future_path("A"), encode(msg))
    drawn = car(state.snapshot(), "A")["fp"]
    assert len(drawn) == MAX_DRAWN_POINTS and drawn[0] == [0.0, 0.0] and drawn[-1] == [199.0, 0.0]


def test_replay_scrubs_forwards_and_backwards() -> None:
    rows = [
        TraceRow(0.1 * k, vid, 2.0 * k, y, 20.0) for k in range(100) for vid, y in (("A", 0.0),)
    ]
    rows += [TraceRow(0.1 * k, "B", 0.0, float(k), 10.0) for k in range(50, 100)]
    state = ViewState()
    replay = Replay(rows, state)
    replay.seek(5.0)
    snap = state.snapshot()
    assert car(snap, "A")["x"] == 100.0 and snap["t"] == 5.0
    assert car(snap, "A")["h"] == 0.0  # heading from the motion (east)
    assert car(snap, "B")["h"] == round(math.pi / 2, 3)
    replay.seek(2.0)  # back: folded again from the start
    snap = state.snapshot()
    assert car(snap, "A")["x"] == 40.0 and [c["id"] for c in snap["cars"]] == ["A"]
    replay.seek(1e9)
    assert state.snapshot()["t"] == pytest.approx(9.9) and state.ended
    with pytest.raises(ValueError):
        replay.seek(math.nan)
    with pytest.raises(ValueError):
        Replay([], ViewState())


def test_scenario_map_of_the_paper_scenario() -> None:
    m = scenario_map(load_scenario("paper-blind-intersection"))
    assert {la["id"] for la in m["lanes"]} == {"eb", "wb", "nb", "sb"}
    assert len(m["buildings"]) == 4
    assert m["intersections"][0]["zone"][0] == [-3.5, -3.5]
    assert m["rsus"][0]["r"] > 0
    assert m["focus"] == [-83.5, -83.5, 83.5, 83.5]
    assert m["bounds"][0] <= -200.0
    json.dumps(m, allow_nan=False)


def test_trace_files(tmp_path: Path) -> None:
    csv_path = tmp_path / "trace.csv"
    csv_path.write_text(
        "t,vehicle,s,x,y,speed,accel,reason,detail,mode\n"
        "0.0,A,0.0,-200.0,-1.75,0.0,0.0,cruise,,AUTO\n"
        "0.05,A,0.0,-199.9,-1.75,0.5,0.2,coordinated,,C_SLOW\n"
    )
    loaded = load_trace(csv_path)
    assert loaded.kind == "csv" and loaded.scenario is None
    assert loaded.rows[1] == TraceRow(0.05, "A", -199.9, -1.75, 0.5, "C_SLOW", "coordinated")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vehicle,x,y,speed\n0.0,A,nan,0,0\n")
    with pytest.raises(TraceError, match="not finite"):
        load_trace(bad)
    with pytest.raises(ValueError, match="line 2"):
        rows_from_trace_csv([{"t": "x"}])
    with pytest.raises(TraceError, match="no step log"):
        load_trace(tmp_path)
    # a monitor step log, found in its run dir, names its scenario file
    run_dir = tmp_path / "run"
    scenario_file = str(resolve_scenario(Path("paper-blind-intersection")))
    log = StepLog(run_dir / "result.steps.jsonl")
    log.start(
        StartRun(
            RUN_ID,
            "paper-blind-intersection",
            RunMode.RSU,
            Policy.PAPER,
            1,
            {"A": 0.0},
            1e9,
            1.0,
            60.0,
            "monitor",
            ("A",),
        ),
        scenario_file,
        [],
    )
    for n in range(3):
        st = TruthState("A", 0.05 * n, -200.0 + n, -1.75, 0.0, 1.0, 0.0, float(n), 4.5, 1.8)
        log.truth(1e9 + n, TruthReport(RUN_ID, n, st, "AUTO", "cruise"))
    log.close()
    loaded = load_trace(run_dir)
    assert loaded.kind == "steplog" and loaded.scenario == scenario_file
    assert [r.x for r in loaded.rows] == [-200.0, -199.0, -198.0]
    assert loaded.rows[0].length == 4.5


def test_signed_plumbing_is_opened_and_its_signer_checked() -> None:
    """With an opener (the run's root key), truth counts only when signed by its car
    and a start only when signed by the run's monitor; what does not open is dropped."""
    signed: dict[bytes, tuple[bytes, str]] = {}

    def seal(item: tuple[str, bytes], signer: str) -> tuple[str, bytes]:
        blob = b"SIG" + bytes([len(signed)]) + item[1]
        signed[blob] = (item[1], signer)
        return item[0], blob

    def opener(blob: bytes) -> tuple[bytes, str]:
        if blob not in signed:
            raise ValueError("bad_signature")
        return signed[blob]

    state = ViewState(opener=opener)
    assert not state.on_datagram(*seal(start(), "A"))  # a car cannot start a run
    assert state.on_datagram(*seal(start(), "monitor"))
    assert not state.on_datagram(*seal(truth("A", 1, 0.05, -50.0, -1.75), "B"))  # B lies
    assert not state.on_datagram(*truth("A", 1, 0.05, -50.0, -1.75))  # unsigned
    assert state.on_datagram(*seal(truth("A", 1, 0.05, -50.0, -1.75), "A"))
    assert state.counters["unauthenticated"] == 3
    assert [c["id"] for c in state.snapshot()["cars"]] == ["A"]
    assert state.snapshot()["run"]["monitor"] == "monitor"
