"""A crosspath scenario from a SUMO network (``crosspath scenario from-sumo NET.net.xml``).

Reads the ``.net.xml`` with the standard library (no SUMO needed) and builds:

- **intersections**: every junction that has internal lanes (not ``dead_end`` or
  ``internal``); its conflict zone is the convex hull of SUMO's junction shape (the
  scenario format wants convex zones; the hull also covers SUMO's rounded corners),
  its centre the junction's position, the stop line ``stop_line_offset_m`` before it;
- **lanes**: SUMO's normal lanes chained through their straight (``dir="s"``)
  connections, so a lane runs through a junction as crosspath's lanes do (the
  blind-corner caution watches the lanes that cross a route); a chain stops before
  it would pass a junction twice. A lane's id is that of its first SUMO lane;
- **routes**: from every entry lane (a normal lane no connection leads to) through
  one or several junctions to an exit lane (one with no connection onward), along
  SUMO's connections (turnarounds left out) and their internal lane(s) (``via``,
  followed through internal junctions), never through a junction twice; id
  ``<first edge>-<last edge>`` (lane ids when an edge pair has several routes). At most
  ``max_routes``, taken round robin over the entries (each entry's routes through more
  junctions first), so a cap keeps every entry. A closed network (no entry lane) gets
  one route per connection;
- **cars**: one ``[[vehicles]]`` per route, started ``stagger_s`` apart in route
  order, or with ``vehicles_per_hour`` one ``[[flows]]`` per route for ``flow_end_s``;
- **RSUs**: one per intersection at its centre (coverage ``rsu_coverage_m``), unless
  ``rsus=False``; ``[params].v_max_mps`` is the fastest normal lane's speed;
- **priority roads**: at a ``priority`` junction whose incoming edges differ in SUMO
  ``priority``, the lanes coming in on the highest are the intersection's
  ``priority_lanes`` (the planner's rule 5: a connected car on a minor road gives way
  to an unconnected car on them, as SUMO's drivers expect).

SUMO ids become crosspath ids (``[A-Za-z0-9_-]{1,32}``): other characters turn into
``_``, long ids are cut, clashes get ``-2``, ``-3``... Points closer than 0.5 m to the
previous one are dropped: SUMO repeats a point where two shapes meet, and splits a
turn at its internal junction a few decimetres further on, a kink that as a 0.2 m
segment reads as a 0.5 m radius (a left turn then crawled through the junction at
1 m/s; 3.75 m/s without it, netgen's 4-way). Decisions
where the issue is silent: no buildings (a ``.net.xml`` has none); ``max_sim_s`` is
the last start plus twice the longest route at half the speed limit plus 60 s.
"""

from __future__ import annotations

import itertools
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.model.scenario import Scenario, ScenarioFile
from services.supervise.expand import scenario_toml

__all__ = ["SumoNetError", "SumoNetwork", "read_net", "scenario_from_net", "write_scenario"]

Point = tuple[float, float]
_ID_BAD = re.compile(r"[^A-Za-z0-9_-]")
_MIN_STEP_M = 0.5
PRIORITY_JUNCTIONS = ("priority", "priority_stop")
"""SUMO junction types where a road has priority (its incoming edges' ``priority``)."""
_MAX_PATHS_PER_ENTRY = 1000
"""Routes enumerated from one entry lane at most (a grid has very many)."""


class SumoNetError(ValueError):
    """The file is not a SUMO network crosspath can use (names the file and why)."""


@dataclass(frozen=True, slots=True)
class Connection:
    from_lane: str
    to_lane: str
    via: str | None
    direction: str


@dataclass(slots=True)
class SumoNetwork:
    """What crosspath needs of a ``.net.xml``: lane shapes and speeds, junctions with
    shapes, and connections (keyed by SUMO lane id)."""

    lanes: dict[str, list[Point]] = field(default_factory=dict)
    lane_speed: dict[str, float] = field(default_factory=dict)
    lane_edge: dict[str, str] = field(default_factory=dict)
    edge_to: dict[str, str] = field(default_factory=dict)
    junctions: dict[str, tuple[Point, list[Point]]] = field(default_factory=dict)
    junction_type: dict[str, str] = field(default_factory=dict)
    edge_priority: dict[str, int] = field(default_factory=dict)
    connections: list[Connection] = field(default_factory=list)
    internal_next: dict[str, str] = field(default_factory=dict)

    def via_chain(self, via: str | None) -> list[str]:
        """The internal lanes a connection drives through, in order."""
        out: list[str] = []
        while via is not None and via not in out:
            out.append(via)
            via = self.internal_next.get(via)
        return out


def _shape(text: str | None, where: str) -> list[Point]:
    if not text:
        raise SumoNetError(f"{where}: no shape")
    try:
        pts = [(float(a), float(b)) for a, b, *_ in (p.split(",") for p in text.split())]
    except ValueError:
        raise SumoNetError(f"{where}: bad shape {text[:60]!r}") from None
    if any(not (math.isfinite(x) and math.isfinite(y)) for x, y in pts):
        raise SumoNetError(f"{where}: shape has a non-finite coordinate")
    return pts


def read_net(path: Path) -> SumoNetwork:
    """Parse ``path``; :class:`SumoNetError` if it is not a readable SUMO network."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise SumoNetError(f"{path}: {exc}") from None
    if root.tag != "net":
        raise SumoNetError(f"{path}: not a SUMO network (root <{root.tag}>, want <net>)")
    net = SumoNetwork()
    for edge in root.iter("edge"):
        eid = edge.get("id", "")
        internal = edge.get("function") == "internal"
        if not internal and edge.get("to"):
            net.edge_to[eid] = edge.get("to", "")
            try:
                net.edge_priority[eid] = int(edge.get("priority", "-1"))
            except ValueError:
                raise SumoNetError(f"{path}: edge {eid}: bad priority") from None
        for lane in edge.iter("lane"):
            lid = lane.get("id", "")
            net.lanes[lid] = _shape(lane.get("shape"), f"{path}: lane {lid}")
            net.lane_speed[lid] = float(lane.get("speed", "13.89"))
            net.lane_edge[lid] = eid
    for j in root.iter("junction"):
        if j.get("type") in ("internal", "dead_end") or not (j.get("intLanes") or "").strip():
            continue
        jid = j.get("id", "")
        centre = (float(j.get("x", "nan")), float(j.get("y", "nan")))
        net.junctions[jid] = (centre, _shape(j.get("shape"), f"{path}: junction {jid}"))
        net.junction_type[jid] = j.get("type", "")
    for c in root.iter("connection"):
        f, t = c.get("from", ""), c.get("to", "")
        from_lane, to_lane = f"{f}_{c.get('fromLane')}", f"{t}_{c.get('toLane')}"
        via = c.get("via")
        if f.startswith(":"):
            if via is not None:
                net.internal_next[from_lane] = via
            continue
        if from_lane in net.lanes and to_lane in net.lanes:
            net.connections.append(Connection(from_lane, to_lane, via, c.get("dir", "s")))
    if not net.connections:
        raise SumoNetError(f"{path}: no connections between lanes: nothing to route")
    return net


def _hull(points: Iterable[Point]) -> list[Point]:
    """Convex hull, counter-clockwise (Andrew's monotone chain)."""
    pts = sorted(set(points))
    if len(pts) < 3:
        return pts

    def cross(o: Point, a: Point, b: Point) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[Point] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 1e-9:
            lower.pop()
        lower.append(p)
    upper: list[Point] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 1e-9:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _join(shapes: Sequence[Sequence[Point]]) -> list[Point]:
    """Shapes end to end, points under 1 cm from the previous one dropped."""
    out: list[Point] = []
    for shape in shapes:
        for p in shape:
            if not out or math.dist(out[-1], p) >= _MIN_STEP_M:
                out.append((round(p[0], 3), round(p[1], 3)))
    return out


class _Ids:
    """SUMO ids made valid and unique crosspath ids."""

    def __init__(self) -> None:
        self.used: set[str] = set()

    def __call__(self, raw: str) -> str:
        base = _ID_BAD.sub("_", raw).strip("_") or "x"
        base = base[:28]
        ident, n = base, 1
        while ident in self.used:
            n += 1
            ident = f"{base}-{n}"
        self.used.add(ident)
        return ident


def _lane_chains(net: SumoNetwork) -> list[list[str]]:
    """Normal lanes chained through straight connections (each lane in one chain)."""
    straight: dict[str, Connection] = {}
    has_pred: set[str] = set()
    for c in net.connections:
        if c.direction == "s" and c.from_lane not in straight:
            straight[c.from_lane] = c
            has_pred.add(c.to_lane)
    normal = [lid for lid in net.lanes if not lid.startswith(":")]
    done: set[str] = set()
    chains: list[list[str]] = []
    for start in [lid for lid in normal if lid not in has_pred] + normal:
        if start in done:
            continue
        chain, junctions = [start], set()
        done.add(start)
        cur = start
        while cur in straight:
            nxt = straight[cur].to_lane
            junction = net.edge_to.get(net.lane_edge[cur], "")
            if nxt in done or junction in junctions:
                break
            junctions.add(junction)
            chain += [*net.via_chain(straight[cur].via), nxt]
            done.add(nxt)
            cur = nxt
        chains.append(chain)
    return chains


def _route_paths(net: SumoNetwork) -> list[list[Connection]]:
    """Every route as its connections: from each entry lane (a normal lane no connection
    leads to) through junctions to an exit lane (one with no connection onward), never
    through a junction twice; per entry, routes through more junctions first. Without
    entry lanes (a closed network), one route per connection."""
    out_of: dict[str, list[Connection]] = {}
    into: set[str] = set()
    for c in net.connections:
        if c.direction in ("t", "T"):
            continue
        out_of.setdefault(c.from_lane, []).append(c)
        into.add(c.to_lane)
    entries = [lid for lid in out_of if lid not in into]
    if not entries:
        return [[c] for conns in out_of.values() for c in conns]
    per_entry: list[list[list[Connection]]] = []
    for entry in entries:
        found: list[list[Connection]] = []
        stack: list[tuple[str, list[Connection], frozenset[str]]] = [(entry, [], frozenset())]
        while stack and len(found) < _MAX_PATHS_PER_ENTRY:
            lane, path, seen = stack.pop()
            junction = net.edge_to.get(net.lane_edge[lane], "")
            onward = out_of.get(lane, [])
            if not onward:
                if path:
                    found.append(path)
                continue
            if junction in seen:
                continue  # it would pass that junction twice
            for c in reversed(onward):
                stack.append((c.to_lane, [*path, c], seen | {junction}))
        found.sort(key=len, reverse=True)
        per_entry.append(found)
    # round robin over the entries, so a cap keeps routes from every entry
    return [p for group in itertools.zip_longest(*per_entry) for p in group if p is not None]


def _routes(net: SumoNetwork, max_routes: int) -> list[tuple[str, list[str]]]:
    """(raw id, SUMO lanes in order) of the first ``max_routes`` routes of
    :func:`_route_paths`; raw id ``<first edge>-<last edge>`` (lane ids when an edge pair
    has several routes)."""
    paths = _route_paths(net)[:max_routes]
    ends = [(net.lane_edge[p[0].from_lane], net.lane_edge[p[-1].to_lane]) for p in paths]
    out: list[tuple[str, list[str]]] = []
    for path, (fe, te) in zip(paths, ends, strict=True):
        lanes = [path[0].from_lane]
        for c in path:
            lanes += [*net.via_chain(c.via), c.to_lane]
        unique = ends.count((fe, te)) == 1
        out.append((f"{fe}-{te}" if unique else f"{path[0].from_lane}-{path[-1].to_lane}", lanes))
    return out


def _priority_lanes(net: SumoNetwork, jid: str, lane_of_sumo: dict[str, str]) -> list[str]:
    """The scenario lanes that come in to junction ``jid`` on its priority road: at a
    ``priority`` (or ``priority_stop``) junction whose incoming edges differ in SUMO
    priority, the lanes of the highest; else none."""
    if net.junction_type.get(jid) not in PRIORITY_JUNCTIONS:
        return []
    incoming = {e: p for e, p in net.edge_priority.items() if net.edge_to.get(e) == jid}
    if not incoming or max(incoming.values()) == min(incoming.values()):
        return []
    top = max(incoming.values())
    out = {
        lane_of_sumo[lid]
        for lid, edge in net.lane_edge.items()
        if incoming.get(edge) == top and lid in lane_of_sumo
    }
    return sorted(out)


def scenario_from_net(
    path: Path,
    *,
    name: str | None = None,
    stagger_s: float = 4.0,
    vehicles_per_hour: float | None = None,
    flow_end_s: float = 300.0,
    stop_line_offset_m: float = 1.0,
    rsus: bool = True,
    rsu_coverage_m: float = 150.0,
    max_routes: int = 200,
) -> Scenario:
    """The crosspath scenario of the network at ``path`` (see the module docstring),
    validated; :class:`SumoNetError` or ``ScenarioError`` if it cannot be built."""
    if not (math.isfinite(stagger_s) and stagger_s >= 0):
        raise ValueError(f"stagger_s must be >= 0, got {stagger_s!r}")
    if isinstance(max_routes, bool) or not isinstance(max_routes, int) or max_routes < 1:
        raise ValueError(f"max_routes must be an int >= 1, got {max_routes!r}")
    net = read_net(path)
    ids = _Ids()
    doc: dict[str, Any] = {}
    stem = path.name.removesuffix(".xml").removesuffix(".net")
    doc["scenario"] = {
        "name": (name or f"sumo-{stem}")[:100],
        "description": f"from the SUMO network {path.name} (crosspath scenario from-sumo)",
    }
    lanes = []
    lane_of_sumo: dict[str, str] = {}
    for chain in _lane_chains(net):
        pts = _join([net.lanes[lid] for lid in chain])
        if len(pts) >= 2:
            lane_id = ids(chain[0])
            lanes.append({"id": lane_id, "points": [list(p) for p in pts]})
            lane_of_sumo.update((lid, lane_id) for lid in chain)
    doc["lanes"] = lanes
    inter_ids: dict[str, str] = {}
    intersections = []
    for jid, (centre, shape) in net.junctions.items():
        hull = _hull(shape)
        if len(hull) < 3:
            continue
        inter_ids[jid] = ids(jid)
        intersections.append(
            {
                "id": inter_ids[jid],
                "center": list(centre),
                "conflict_zone": [list(p) for p in hull],
                "stop_line_offset_m": stop_line_offset_m,
                "priority_lanes": _priority_lanes(net, jid, lane_of_sumo),
            }
        )
    doc["intersections"] = intersections
    routes = []
    longest = 0.0
    for raw, lane_path in _routes(net, max_routes):
        pts = _join([net.lanes[lid] for lid in lane_path])
        if len(pts) >= 2:
            routes.append({"id": ids(raw), "points": [list(p) for p in pts]})
            longest = max(longest, sum(math.dist(a, b) for a, b in itertools.pairwise(pts)))
    if not routes:
        raise SumoNetError(f"{path}: no route through any junction")
    doc["routes"] = routes
    v_max = max(s for lid, s in net.lane_speed.items() if not lid.startswith(":"))
    if vehicles_per_hour is None:
        doc["vehicles"] = [
            {"id": ids(f"v-{r['id']}"), "route": r["id"], "start_time_s": round(i * stagger_s, 3)}
            for i, r in enumerate(routes)
        ]
        last = stagger_s * (len(routes) - 1)
    else:
        doc["flows"] = [
            {
                "id": ids(f"f-{r['id']}")[:27],
                "route": r["id"],
                "vehicles_per_hour": vehicles_per_hour,
                "end_s": flow_end_s,
            }
            for r in routes
        ]
        last = flow_end_s
    doc["params"] = {
        "v_max_mps": round(v_max, 4),
        "max_sim_s": round(last + 2.0 * longest / (0.5 * v_max) + 60.0, 1),
    }
    if rsus:
        doc["rsus"] = [
            {
                "id": ids(f"rsu-{jid}"),
                "intersection": inter_ids[jid],
                "position": list(net.junctions[jid][0]),
                "coverage_m": rsu_coverage_m,
            }
            for jid in inter_ids
        ]
    spec = ScenarioFile.model_validate(doc)
    return Scenario(spec, str(path))


def write_scenario(scenario: Scenario, out: Path) -> Path:
    """Write ``scenario`` as TOML to ``out``; ``out``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"# {scenario.description}\n\n" + scenario_toml(scenario), encoding="utf-8")
    return out
