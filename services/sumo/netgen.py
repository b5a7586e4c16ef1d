"""The demand experiment's 4-way intersection as a SUMO network, and its demand as routes.

Same geometry as ``scenarios/four-way-flows.toml``: one lane per approach, 3.5 m wide,
right-hand traffic (a lane's centre 1.75 m right of the road axis), approaches of
150 m from the centre, 13.89 m/s (50 km/h). :func:`build_network` writes plain
``.nod.xml``/``.edg.xml`` and runs ``netconvert`` from the ``eclipse-sumo`` wheel.

Decisions where the issue is silent:

- Junction controls: ``priority`` (the east-west road is the major road, priority 2
  against 1: with equal priorities SUMO's choice of major road is not stated),
  ``allway_stop``, ``traffic_light`` with ``tlType="actuated"`` (netconvert's default
  programme, default detectors), and ``unregulated`` (no right of way: used only for
  the free-flow reference of each route, where one car drives alone).
- Corner radius 2 m (``radius`` of the centre node; crosspath's right turns use 2 m).
- Edge and route ids follow crosspath: edge ``w_in`` enters from the west, ``e_out``
  leaves to the east; route ``we`` enters from the west and leaves east.
- The vehicle type mirrors crosspath's car and ``[params]`` defaults: 4.5 x 1.8 m,
  accel 1.5, decel 2.0, emergency decel 5.0 m/s², v_max 13.89 m/s, ``tau`` 1.0 s
  (``headway_s``), minGap 2.5 m (the insertion gap), Krauss with ``sigma`` 0 and no
  speed deviation (crosspath's cars are deterministic); cars depart at rest
  (``departSpeed="0"``), as crosspath's start.
"""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from xml.sax.saxutils import quoteattr

__all__ = [
    "APPROACH_M",
    "JUNCTION_TYPES",
    "ROUTES",
    "Control",
    "SumoNotFound",
    "VehicleTypeSpec",
    "build_corridor",
    "build_network",
    "sumo_binary",
    "sumo_home",
    "write_routes",
]

APPROACH_M = 150.0
"""Distance from the centre to each approach's end [m]."""
LANE_WIDTH_M = 3.5
SPEED_MPS = 13.8889
CORNER_RADIUS_M = 2.0

_SIDES: dict[str, tuple[float, float]] = {
    "w": (-1.0, 0.0),
    "e": (1.0, 0.0),
    "s": (0.0, -1.0),
    "n": (0.0, 1.0),
}
"""Side -> unit vector from the centre to its approach's end."""

ROUTES: dict[str, tuple[str, str]] = {
    f"{a}{b}": (f"{a}_in", f"{b}_out") for a in "wesn" for b in "wesn" if a != b
}
"""Route id (``<from side><to side>``) -> its two SUMO edges."""


class Control(StrEnum):
    """A SUMO junction control (netconvert node ``type``)."""

    PRIORITY = "priority"
    ALLWAY_STOP = "allway_stop"
    TRAFFIC_LIGHT = "traffic_light"
    UNREGULATED = "unregulated"

    @property
    def label(self) -> str:
        """The control's name in tables and figures."""
        return {
            Control.PRIORITY: "SUMO priority",
            Control.ALLWAY_STOP: "SUMO all-way stop",
            Control.TRAFFIC_LIGHT: "SUMO actuated TL",
            Control.UNREGULATED: "SUMO unregulated",
        }[self]


JUNCTION_TYPES: tuple[Control, ...] = (Control.PRIORITY, Control.ALLWAY_STOP, Control.TRAFFIC_LIGHT)
"""The baselines of the demand experiment."""


class SumoNotFound(RuntimeError):
    """SUMO (the ``eclipse-sumo`` wheel or ``SUMO_HOME``) is not installed."""


def sumo_home() -> Path:
    """SUMO's home: the ``eclipse-sumo`` wheel's, else ``$SUMO_HOME``."""
    try:
        import sumo

        return Path(sumo.SUMO_HOME)
    except ImportError:
        env = os.environ.get("SUMO_HOME")
        if env:
            return Path(env)
    raise SumoNotFound(
        "SUMO is not installed: pip install 'crosspath[sumo]' (the eclipse-sumo wheel)"
    )


def sumo_binary(name: str = "sumo") -> Path:
    """A SUMO program (``sumo``, ``netconvert``) from :func:`sumo_home`, else on PATH."""
    candidate = sumo_home() / "bin" / name
    if candidate.is_file():
        return candidate
    found = shutil.which(name)
    if found is None:
        raise SumoNotFound(f"{name} not found in {candidate.parent} nor on PATH")
    return Path(found)


def _nodes_xml(control: Control, approach_m: float) -> str:
    extra = ' tlType="actuated"' if control is Control.TRAFFIC_LIGHT else ""
    lines = [
        "<nodes>",
        f'  <node id="c" x="0.0" y="0.0" type="{control.value}"'
        f' radius="{CORNER_RADIUS_M}"{extra}/>',
    ]
    lines += [
        f'  <node id="{k}" x="{x * approach_m}" y="{y * approach_m}" type="dead_end"/>'
        for k, (x, y) in _SIDES.items()
    ]
    return "\n".join([*lines, "</nodes>", ""])


def _edges_xml() -> str:
    lines = ["<edges>"]
    for side in _SIDES:
        prio = 2 if side in "we" else 1
        common = f'numLanes="1" speed="{SPEED_MPS}" width="{LANE_WIDTH_M}" priority="{prio}"'
        lines.append(f'  <edge id="{side}_in" from="{side}" to="c" {common}/>')
        lines.append(f'  <edge id="{side}_out" from="c" to="{side}" {common}/>')
    return "\n".join([*lines, "</edges>", ""])


def build_network(directory: Path, control: Control, approach_m: float = APPROACH_M) -> Path:
    """Write ``four-way-<control>.net.xml`` in ``directory`` with netconvert; its path.
    ``approach_m`` [m] from the centre to each approach's end (tests use short ones).

    Raises :class:`SumoNotFound` without SUMO, ``RuntimeError`` when netconvert fails.
    """
    directory.mkdir(parents=True, exist_ok=True)
    stem = directory / f"four-way-{control.value}"
    nod, edg = stem.with_suffix(".nod.xml"), stem.with_suffix(".edg.xml")
    net = stem.with_suffix(".net.xml")
    if not (approach_m > 3 * LANE_WIDTH_M and approach_m < 1e6):
        raise ValueError(f"approach_m must be > {3 * LANE_WIDTH_M} m, got {approach_m!r}")
    nod.write_text(_nodes_xml(control, approach_m))
    edg.write_text(_edges_xml())
    _netconvert(nod, edg, net)
    return net


def _netconvert(nod: Path, edg: Path, net: Path) -> Path:
    """Run netconvert on plain node and edge files (no turnarounds, coordinates kept)."""
    cmd = [
        str(sumo_binary("netconvert")),
        "--node-files",
        str(nod),
        "--edge-files",
        str(edg),
        "--output-file",
        str(net),
        "--no-turnarounds",
        "true",
        "--offset.disable-normalization",
        "true",
        "--no-warnings",
        "true",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=120)
    if proc.returncode != 0 or not net.is_file():
        raise RuntimeError(f"netconvert failed ({proc.returncode}): {proc.stderr.strip()}")
    return net


def build_corridor(
    directory: Path,
    junctions: int = 3,
    spacing_m: float = 100.0,
    arm_m: float = 40.0,
    control: Control = Control.PRIORITY,
) -> Path:
    """Write ``corridor-<n>.net.xml`` in ``directory``: a west-east main road (priority 2)
    through ``junctions`` 4-way junctions ``j0``, ``j1``... ``spacing_m`` apart, each with a
    north and a south arm (priority 1) of ``arm_m``; the main road runs ``arm_m`` beyond
    the first and last junction. One 3.5 m lane per direction, 13.89 m/s; node ids ``w``,
    ``e``, ``n<k>``, ``s<k>``, edge ids ``<from node>_<to node>``. Its path; raises as
    :func:`build_network`."""
    if not 1 <= junctions <= 50:
        raise ValueError(f"junctions must be within 1..50, got {junctions!r}")
    if not (spacing_m > 3 * LANE_WIDTH_M and arm_m > 3 * LANE_WIDTH_M):
        raise ValueError(f"spacing_m and arm_m must be > {3 * LANE_WIDTH_M} m")
    directory.mkdir(parents=True, exist_ok=True)
    stem = directory / f"corridor-{junctions}"
    xs = [k * spacing_m for k in range(junctions)]
    nodes = [(f"j{k}", x, 0.0, control.value) for k, x in enumerate(xs)]
    nodes += [("w", -arm_m, 0.0, "dead_end"), ("e", xs[-1] + arm_m, 0.0, "dead_end")]
    for k, x in enumerate(xs):
        nodes += [(f"n{k}", x, arm_m, "dead_end"), (f"s{k}", x, -arm_m, "dead_end")]
    extra = ' tlType="actuated"' if control is Control.TRAFFIC_LIGHT else ""
    nod_lines = ["<nodes>"] + [
        f'  <node id="{i}" x="{x}" y="{y}" type="{t}"'
        + (f' radius="{CORNER_RADIUS_M}"{extra}' if i.startswith("j") else "")
        + "/>"
        for i, x, y, t in nodes
    ]
    main = ["w", *(f"j{k}" for k in range(junctions)), "e"]
    pairs = [(a, b, 2) for a, b in itertools.pairwise(main)]
    pairs += [(f"{arm}{k}", f"j{k}", 1) for k in range(junctions) for arm in "ns"]
    edg_lines = ["<edges>"]
    for a, b, prio in pairs:
        common = f'numLanes="1" speed="{SPEED_MPS}" width="{LANE_WIDTH_M}" priority="{prio}"'
        edg_lines.append(f'  <edge id="{a}_{b}" from="{a}" to="{b}" {common}/>')
        edg_lines.append(f'  <edge id="{b}_{a}" from="{b}" to="{a}" {common}/>')
    nod, edg = stem.with_suffix(".nod.xml"), stem.with_suffix(".edg.xml")
    nod.write_text("\n".join([*nod_lines, "</nodes>", ""]))
    edg.write_text("\n".join([*edg_lines, "</edges>", ""]))
    return _netconvert(nod, edg, stem.with_suffix(".net.xml"))


@dataclass(frozen=True, slots=True)
class VehicleTypeSpec:
    """The SUMO vType of every car [m, m/s, m/s², s] (crosspath's defaults)."""

    length_m: float = 4.5
    width_m: float = 1.8
    accel_mps2: float = 1.5
    decel_mps2: float = 2.0
    emergency_decel_mps2: float = 5.0
    v_max_mps: float = SPEED_MPS
    tau_s: float = 1.0
    min_gap_m: float = 2.5

    def xml(self) -> str:
        return (
            f'  <vType id="car" length="{self.length_m}" width="{self.width_m}"'
            f' accel="{self.accel_mps2}" decel="{self.decel_mps2}"'
            f' emergencyDecel="{self.emergency_decel_mps2}" maxSpeed="{self.v_max_mps}"'
            f' tau="{self.tau_s}" minGap="{self.min_gap_m}" sigma="0" speedFactor="1"'
            ' speedDev="0"/>'
        )


def write_routes(
    path: Path,
    departures: Mapping[str, Sequence[float]],
    vtype: VehicleTypeSpec | None = None,
) -> int:
    """Write a ``.rou.xml``: the 12 routes and one vehicle per departure.

    ``departures`` maps a route id of :data:`ROUTES` to departure times [s]; vehicle
    ``<route>-<n>`` departs at its n-th time (crosspath's flow car ids when the keys
    are flow ids named after their routes). Returns the number of vehicles.
    """
    vt = vtype if vtype is not None else VehicleTypeSpec()
    rows: list[tuple[float, str, str]] = []
    for route, times in departures.items():
        if route not in ROUTES:
            raise ValueError(f"unknown route {route!r} (known: {', '.join(ROUTES)})")
        for n, t in enumerate(times):
            rows.append((float(t), f"{route}-{n}", route))
    rows.sort()
    lines = ["<routes>", vt.xml()]
    lines += [f'  <route id="{r}" edges="{a} {b}"/>' for r, (a, b) in ROUTES.items()]
    lines += [
        f'  <vehicle id={quoteattr(vid)} type="car" route="{route}" depart="{t:.3f}"'
        ' departSpeed="0" departLane="first" departPos="base"/>'
        for t, vid, route in rows
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join([*lines, "</routes>", ""]))
    return len(rows)
