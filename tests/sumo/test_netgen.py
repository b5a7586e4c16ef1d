"""The demand experiment's 4-way as a SUMO network (``services.sumo.netgen``)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from services.sumo.netgen import ROUTES, Control, build_network, write_routes
from tests.sumo.conftest import require_sumo


def _lane_shape(root: ET.Element, lane_id: str) -> list[tuple[float, float]]:
    lane = next(el for el in root.iter("lane") if el.get("id") == lane_id)
    return [(float(a), float(b)) for a, b in (p.split(",") for p in lane.get("shape", "").split())]


@pytest.mark.parametrize("control", list(Control))
def test_network_has_the_crosspath_geometry(tmp_path: Path, control: Control) -> None:
    require_sumo()
    net = build_network(tmp_path, control)
    root = ET.parse(net).getroot()
    centre = next(j for j in root.iter("junction") if j.get("id") == "c")
    assert centre.get("type") == control.value
    # one lane per approach, right-hand traffic 1.75 m off the axis, 150 m from the centre
    assert _lane_shape(root, "w_in_0")[0] == (-150.0, -1.75)
    assert _lane_shape(root, "e_out_0")[-1] == (150.0, -1.75)
    assert _lane_shape(root, "s_in_0")[0] == (1.75, -150.0)
    assert _lane_shape(root, "n_in_0")[0] == (-1.75, 150.0)
    normal = [e for e in root.iter("edge") if e.get("function") != "internal"]
    assert sorted(e.get("id", "") for e in normal) == sorted(
        f"{s}_{d}" for s in "wesn" for d in ("in", "out")
    )
    assert all(len(e.findall("lane")) == 1 for e in normal)
    tls = list(root.iter("tlLogic"))
    if control is Control.TRAFFIC_LIGHT:
        assert [t.get("type") for t in tls] == ["actuated"]
    else:
        assert tls == []
    # every route's two edges are connected (no turnarounds)
    conns = {(c.get("from"), c.get("to")) for c in root.iter("connection")}
    assert all(edges in conns for edges in ROUTES.values())
    assert ("w_in", "w_out") not in conns


def test_routes_file_lists_every_departure_in_time_order(tmp_path: Path) -> None:
    path = tmp_path / "d.rou.xml"
    n = write_routes(path, {"we": [5.0, 1.0], "sn": [3.0]})
    assert n == 3
    root = ET.parse(path).getroot()
    cars = [
        (v.get("id"), v.get("route"), float(v.get("depart", "nan"))) for v in root.iter("vehicle")
    ]
    # a route's n-th departure is car <route>-<n>, whatever order the times came in
    assert cars == [("we-1", "we", 1.0), ("sn-0", "sn", 3.0), ("we-0", "we", 5.0)]
    vtype = next(root.iter("vType"))
    assert vtype.get("sigma") == "0" and vtype.get("tau") == "1.0"


def test_unknown_route_and_bad_approach_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown route 'xx'"):
        write_routes(tmp_path / "r.rou.xml", {"xx": [0.0]})
    with pytest.raises(ValueError, match="approach_m"):
        build_network(tmp_path, Control.PRIORITY, approach_m=5.0)
