"""``crosspath bench latency``: transport latency and age at use of V2X messages, per stream.

Issue 14: the one-way ``fp`` latency the runs report is measured from the planning
instant (the header's generation time), so it includes the sender's own work;
Zenoh's share was not measured. This bench splits it, on loopback, with two real
Zenoh sessions in one process (scouting off: the receiver connects to the
sender's ``tcp/`` and ``udp/`` endpoints, as the daemons do):

``transport``
    publish call -> handler on the receiving asyncio loop. The wire format has no
    send timestamp, so the sender stamps the instant of each ``publish`` call in a
    side table keyed by (key, sequence number) that the handler looks up.
``age``
    planning instant (the header's generation time, stamped when the message is
    built) -> handler, after the handler decoded the datagram: what a receiver
    sees as the age of the data it is about to use.

Load: ``cars`` cars each publish a 120-point future path (``Stream.FP``) and the
RSU sends each a 120-point coordinated path (``Stream.CMD``) at ``rate_hz``,
spread evenly over each period, from a sender thread; the receiving side runs
the handlers on an asyncio loop as the daemons do. Both clocks are this
process's ``perf_counter_ns``. Only the transport is timed: no planning, no RSU.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import socket
import threading
import time
from typing import Any

import numpy as np

from protocol import CoordinatedPath, FuturePath, Header, Mode, decode, encode, keys
from protocol.keys import QOS, Stream
from services.edge.args import output_file, positive_int
from services.edge.progress import Ticker
from services.edge.settings import ZenohSettings
from services.edge.transport import ZenohTransport

logger = logging.getLogger(__name__)

STREAMS: tuple[Stream, ...] = (Stream.FP, Stream.CMD)
"""The streams measured: future paths (car -> all) and coordinated paths (RSU -> car)."""

RSU_ID = "rsu-1"
POINTS = 120
TARGET_TRANSPORT_P99_MS = 2.0
"""Issue 14: transport p99 on loopback with 40 cars running [ms]."""


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _paths(now_us: int, seq: int, car: str) -> tuple[FuturePath, CoordinatedPath]:
    t = now_us / 1e6 + np.arange(POINTS) * 0.084
    x = -60.0 + 12.0 * (t - t[0])
    points = np.column_stack([x, np.full(POINTS, -1.75), t])
    header = Header(car, seq, now_us)
    fp = FuturePath(header, float(x[0]), -1.75, 12.0, 0.0, 4.5, 1.8, Mode.AUTO, points)
    cp = CoordinatedPath(
        Header(RSU_ID, seq, now_us), car, Mode.C_SLOW, points, np.full(POINTS, 12.0)
    )
    return fp, cp


def _percentiles_ms(samples_ns: list[int]) -> dict[str, float | int | None]:
    if not samples_ns:
        return {"n": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    a = np.asarray(samples_ns, dtype=np.float64) / 1e6
    return {
        "n": len(samples_ns),
        "p50_ms": round(float(np.percentile(a, 50)), 4),
        "p99_ms": round(float(np.percentile(a, 99)), 4),
        "max_ms": round(float(a.max()), 4),
    }


def _sender(
    tx: ZenohTransport,
    cars: int,
    rate_hz: float,
    duration_s: float,
    sent: dict[tuple[str, int], int],
    stop: threading.Event,
) -> None:
    """Publish every car's paths at ``rate_hz``, evenly spread; stamp each publish call."""
    clock = time.perf_counter_ns
    period_ns = round(1e9 / rate_hz)
    slot_ns = period_ns // max(cars, 1)
    fp_qos, cmd_qos = QOS[Stream.FP], QOS[Stream.CMD]
    names = [f"car-{i}" for i in range(cars)]
    fp_keys = [keys.future_path(n) for n in names]
    cmd_keys = [keys.rsu_command(RSU_ID, n) for n in names]
    start = clock()
    rounds = max(1, round(duration_s * rate_hz))
    for r in range(rounds):
        for i, name in enumerate(names):
            due = start + r * period_ns + i * slot_ns
            while (wait := due - clock()) > 0:
                if stop.is_set():
                    return
                time.sleep(min(wait / 1e9, 0.01))
            fp, cp = _paths(clock() // 1000, r + 1, name)  # planning instant = header time
            fp_data, cp_data = encode(fp), encode(cp)
            sent[(fp_keys[i], r + 1)] = clock()
            tx.publish(fp_keys[i], fp_data, fp_qos)
            sent[(cmd_keys[i], r + 1)] = clock()
            tx.publish(cmd_keys[i], cp_data, cmd_qos)


async def _measure(cars: int, rate_hz: float, duration_s: float, settle_s: float) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    tcp, udp = _free_port(socket.SOCK_STREAM), _free_port(socket.SOCK_DGRAM)
    endpoints = [f"tcp/127.0.0.1:{tcp}", f"udp/127.0.0.1:{udp}"]
    tx = ZenohTransport(ZenohSettings(listen=endpoints), loop)
    rx = ZenohTransport(ZenohSettings(connect=endpoints), loop)
    await tx.open_async()
    await rx.open_async()
    sent: dict[tuple[str, int], int] = {}
    transport: dict[Stream, list[int]] = {s: [] for s in STREAMS}
    age: dict[Stream, list[int]] = {s: [] for s in STREAMS}
    unmatched = 0
    clock = time.perf_counter_ns

    def handler(key: str, data: bytes) -> None:
        nonlocal unmatched
        now = clock()
        message = decode(data)
        stream = Stream.FP if isinstance(message, FuturePath) else Stream.CMD
        stamp = sent.get((key, message.header.seq))
        if stamp is None:
            unmatched += 1
            return
        transport[stream].append(now - stamp)
        age[stream].append(clock() - message.header.time_us * 1000)

    subs = [
        rx.subscribe(keys.all_future_paths(), handler),
        rx.subscribe(keys.all_commands(), handler),
    ]
    stop = threading.Event()
    try:
        await asyncio.sleep(settle_s)  # links and subscriptions propagate
        worker = asyncio.to_thread(_sender, tx, cars, rate_hz, duration_s, sent, stop)
        await worker
        await asyncio.sleep(0.2)  # the last datagrams arrive
    finally:
        stop.set()
        for sub in subs:
            sub.close()
        rx.close()
        tx.close()
    streams = {
        str(s): {"transport": _percentiles_ms(transport[s]), "age": _percentiles_ms(age[s])}
        for s in STREAMS
    }
    received = sum(len(v) for v in transport.values())
    p99s = [v["transport"]["p99_ms"] for v in streams.values()]
    met = all(p is not None and p <= TARGET_TRANSPORT_P99_MS for p in p99s)
    return {
        "bench": "latency",
        "cars": cars,
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "points": POINTS,
        "endpoints": endpoints,
        "sent": len(sent),
        "received": received,
        "unmatched": unmatched,
        "clock": "perf_counter_ns",
        "streams": streams,
        "targets": {"transport_p99_ms": TARGET_TRANSPORT_P99_MS, "met": {"transport_p99": met}},
    }


def measure(
    cars: int = 40, rate_hz: float = 10.0, duration_s: float = 5.0, settle_s: float = 1.0
) -> dict[str, Any]:
    """Run the load (module docstring) and return the JSON document ``bench latency`` writes."""
    if cars < 1 or not rate_hz > 0 or not duration_s > 0 or settle_s < 0:
        raise ValueError("cars >= 1, rate_hz > 0, duration_s > 0 and settle_s >= 0 needed")
    return asyncio.run(_measure(cars, rate_hz, duration_s, settle_s))


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench latency``; bad values are refused while parsing."""
    parser.add_argument("--json", metavar="OUT", type=output_file, help="write the results as JSON")
    parser.add_argument("--cars", type=positive_int, default=40, help="cars publishing")
    parser.add_argument("--rate", type=positive_int, default=10, help="messages per car [Hz]")
    parser.add_argument("--seconds", type=positive_int, default=5, help="duration of the load")


def run(args: argparse.Namespace) -> int:
    """Measure and print; a status line on stderr while it runs (on a terminal only)."""
    label = f"{args.cars} cars at {args.rate} Hz for {args.seconds} s"
    with Ticker("crosspath bench latency", lambda: label):
        doc = measure(args.cars, float(args.rate), float(args.seconds))
    print(f"sent {doc['sent']}, received {doc['received']} ({label}, loopback)")
    print(f"{'stream':<8}{'transport p50':>15}{'p99 [ms]':>10}{'age p50':>10}{'p99 [ms]':>10}")
    for name, s in doc["streams"].items():
        tr, ag = s["transport"], s["age"]
        print(
            f"{name:<8}{tr['p50_ms'] or 0:>15.3f}{tr['p99_ms'] or 0:>10.3f}"
            f"{ag['p50_ms'] or 0:>10.3f}{ag['p99_ms'] or 0:>10.3f}"
        )
    for name, ok in doc["targets"]["met"].items():
        print(f"target {name}: {'met' if ok else 'NOT met'}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0
