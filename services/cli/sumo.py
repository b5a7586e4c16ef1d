"""``crosspath sumo NET.net.xml ROUTES.rou.xml``: co-simulation, SUMO's world and crosspath's
connected cars and RSUs (``services.sumo.cosim`` says who does what).

Options: ``--connected-share`` (fraction of SUMO's cars crosspath drives, drawn per car
from ``--seed``), ``--mode``/``--policy`` as ``crosspath sim``, ``--loss``, ``--no-rsu``,
``--max-sim`` [s], ``--json OUT`` (the run result, with the ``sumo`` section: SUMO's own
``timeLoss`` per car beside crosspath's ``delay_s``).

``--daemons``: every RSU is a ``crosspath rsu`` daemon process and V2X travels over Zenoh
(``services.sumo.daemons``); this process stays SUMO's world, paced on the run clock at
``--speed`` run seconds per wall second (default 1). ``--run-dir`` holds the daemons'
logs, the scenario and the run's keys (default ``<OUT>-logs`` beside ``--json OUT``, else
``results/sumo/<time>-<id>``); ``--insecure`` leaves V2X unsigned (comparison only). The
result's ``harness`` is ``daemons``, with the ``network`` and ``actors`` sections of a
daemon run. Exit 0 when the run completed, 1 when a daemon failed, 2 for unusable input (a
file that is not a SUMO network or route file, SUMO missing, ``--speed`` or
``--run-dir`` without ``--daemons``), 128 + the signal on Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from services.edge.args import (
    add_mode_and_policy,
    fraction,
    non_negative_int,
    output_dir,
    output_file,
    positive_float,
    run_speed,
)

__all__ = ["configure", "run"]


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath sumo``."""
    parser.add_argument("net", type=Path, help="the SUMO network (.net.xml)")
    parser.add_argument("routes", type=Path, help="SUMO's demand (.rou.xml: vehicles, flows)")
    parser.add_argument(
        "--connected-share",
        type=fraction,
        default=1.0,
        help="share of SUMO's cars that crosspath drives, a fraction 0..1 (or 50%%)",
    )
    add_mode_and_policy(parser)
    parser.add_argument(
        "--seed", type=non_negative_int, default=0, help="seed of SUMO, the share draw, the channel"
    )
    parser.add_argument(
        "--loss", type=fraction, default=0.0, help="V2X loss probability per receiver, 0..1"
    )
    parser.add_argument(
        "--max-sim", type=positive_float, default=3600.0, help="stop at this run time [s]"
    )
    parser.add_argument("--no-rsu", action="store_true", help="no RSU at the junctions")
    parser.add_argument(
        "--json", type=output_file, default=None, metavar="OUT", help="write the run result here"
    )
    parser.add_argument(
        "--daemons",
        action="store_true",
        help="the RSUs as daemon processes, V2X over Zenoh, on the run clock",
    )
    parser.add_argument(
        "--speed",
        type=run_speed,
        default=None,
        help="with --daemons: run seconds per wall second (default 1)",
    )
    parser.add_argument(
        "--run-dir",
        type=output_dir,
        default=None,
        help="with --daemons: logs, scenario, keys (default: <OUT>-logs beside --json OUT)",
    )
    parser.add_argument(
        "--insecure", action="store_true", help="with --daemons: V2X unsigned (comparison only)"
    )


def run(args: argparse.Namespace) -> int:
    """One co-simulation; prints the summary and SUMO's figures beside ours."""
    from services.model.scenario import ScenarioError
    from services.sim.membus import ChannelModel
    from services.sim.results import format_summary
    from services.sumo.cosim import CosimOptions
    from services.sumo.daemons import DaemonsError
    from services.sumo.from_sumo import SumoNetError
    from services.sumo.netgen import SumoNotFound
    from services.sumo.run import cosimulate

    name = "crosspath sumo"
    daemons: bool = args.daemons
    if not daemons and (args.speed is not None or args.run_dir is not None or args.insecure):
        print(f"{name}: --speed, --run-dir and --insecure need --daemons", file=sys.stderr)
        return 2
    run_dir: Path | None = args.run_dir
    if daemons and run_dir is None and args.json is not None:
        run_dir = args.json.with_name(f"{args.json.stem}-logs")
    try:
        options = CosimOptions(
            mode=args.mode,
            policy=args.policy,
            seed=args.seed,
            connected_share=args.connected_share,
            channel=ChannelModel(loss=args.loss),
            max_sim_s=args.max_sim,
            rsus=not args.no_rsu,
            daemons=daemons,
            speed=1.0 if args.speed is None else args.speed,
            run_dir=run_dir,
            insecure=args.insecure,
        )
        result = cosimulate(args.net, args.routes, options)
    except (SumoNetError, ScenarioError, SumoNotFound, ValueError) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    except DaemonsError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        if not daemons:
            raise
        signum = exc.args[0] if exc.args and isinstance(exc.args[0], int) else 2
        print(f"{name}: interrupted, daemons stopped", file=sys.stderr)
        return 128 + signum
    except Exception as exc:  # SUMO's own errors (a bad route file) come as its exceptions
        if type(exc).__module__.split(".")[0] in ("libsumo", "traci"):
            print(f"{name}: SUMO: {exc}", file=sys.stderr)
            return 2
        raise
    print(format_summary(result))
    sumo, summary = result.sumo, result.summary
    if sumo is not None and summary is not None:
        ours = summary.mean_delay_s
        theirs = sumo.mean_time_loss_s
        print(
            f"SUMO: {sumo.connected} of {len(sumo.vehicles)} cars connected, "
            f"{summary.vehicles_finished} arrived, SUMO collisions {sumo.collisions}; "
            f"mean delay {'-' if ours is None else f'{ours:.2f} s'} "
            f"(SUMO timeLoss {'-' if theirs is None else f'{theirs:.2f} s'})"
        )
    if result.network is not None:
        from services.daemons.monitor import format_degraded, format_network

        print(format_network(result.network))
        if (degraded := format_degraded(result)) is not None:
            print(degraded)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(result.to_json() + "\n")
    return 0
