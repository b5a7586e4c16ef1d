"""``crosspath scenario from-sumo NET.net.xml``: write a crosspath scenario from a SUMO network.

The conversion is :func:`services.sumo.from_sumo.scenario_from_net` (its docstring says
what becomes what); this is the command line around it. The written file is loaded back
with ``load_scenario`` before the command reports success, so it runs in ``crosspath
sim`` as written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.edge.args import non_negative_float, output_file, positive_float, positive_int

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath scenario from-sumo``."""
    parser.add_argument("net", type=Path, help="the SUMO network (.net.xml)")
    parser.add_argument(
        "-o",
        "--out",
        type=output_file,
        default=None,
        help="scenario file to write (default: NET's name with .toml, in the working dir)",
    )
    parser.add_argument("--name", default=None, help="scenario name (default: sumo-<net name>)")
    parser.add_argument(
        "--stagger",
        type=non_negative_float,
        default=4.0,
        help="one car per route, started this many s apart",
    )
    parser.add_argument(
        "--vehicles-per-hour",
        type=positive_float,
        default=None,
        help="instead of one car per route, a flow of this many veh/h on every route",
    )
    parser.add_argument(
        "--flow-end", type=positive_float, default=300.0, help="flows end at this run time [s]"
    )
    parser.add_argument(
        "--stop-line-offset",
        type=non_negative_float,
        default=1.0,
        help="stop line this far before each junction's zone [m]",
    )
    parser.add_argument("--no-rsu", action="store_true", help="no RSU at the junctions")
    parser.add_argument(
        "--max-routes",
        type=positive_int,
        default=200,
        help="at most this many entry-to-exit routes, round robin over the entries",
    )


def run(args: argparse.Namespace) -> int:
    """Write the scenario; 0 on success, 2 when the network cannot be converted."""
    from services.model.scenario import ScenarioError, load_scenario
    from services.sumo.from_sumo import SumoNetError, scenario_from_net, write_scenario

    name = "crosspath scenario from-sumo"
    out: Path = args.out or Path(args.net.name.removesuffix(".xml").removesuffix(".net") + ".toml")
    try:
        sc = scenario_from_net(
            args.net,
            name=args.name,
            stagger_s=args.stagger,
            vehicles_per_hour=args.vehicles_per_hour,
            flow_end_s=args.flow_end,
            stop_line_offset_m=args.stop_line_offset,
            rsus=not args.no_rsu,
            max_routes=args.max_routes,
        )
        write_scenario(sc, out)
        back = load_scenario(out)
    except (SumoNetError, ScenarioError, ValueError) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    print(
        f"wrote {out}: {len(back.lane_ids)} lanes, {len(back.intersections)} intersection(s), "
        f"{len(back.route_ids)} routes, {len(back.vehicles)} cars, {len(back.spec.flows)} flows"
    )
    return 0
