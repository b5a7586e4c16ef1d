"""``crosspath bench codec``: crosspath's binary codec against the paper's JSON.

One realistic future path (a car at 12 m/s decelerating at 1 m/s² along a
straight lane, points 0.084 s apart, full-precision floats as a planner emits
them) goes message → bytes → message in every format, in the same run:

``crosspath``
    ``protocol.encode`` / ``protocol.decode``, with the C speed-ups of
    ``protocol/_speedups.c`` when they were built (``c_speedups`` says whether).
``crosspath_numpy``
    the same functions on their numpy path (``protocol.codec.use_speedups(False)``):
    what a machine without a C compiler at install runs, and the codec before the C
    speed-ups; same bytes. ``speedup_c_vs_numpy`` is their ratio.
``paper_json``
    what the paper sent (60 KB per 120-point path): an Autoware 1.x lane dump
    as ``rospy_message_converter`` + ``json.dumps`` (default separators)
    produce it. Per point an ``autoware_msgs/Waypoint`` without its ``dtlane``
    and ``wpstate`` sub-messages: ``gid``, ``lid``, a stamped pose (header with
    seq, stamp = pass time as secs/nsecs, frame_id; position x/y/z; orientation
    quaternion), a twist (linear and angular x/y/z, linear x = speed), lane ids,
    costs, direction; plus a lane header. This lands near the paper's figure
    (the full Waypoint message would be about 60 % bigger).
``json``
    compact stdlib JSON of exactly the fields crosspath carries, one object
    ``{"x":..,"y":..,"t":..}`` per point, separators ``(",", ":")``. The
    baseline of ``speedup_vs_json``.
``json_arrays``
    the same with each point as a ``[x, y, t]`` array.
``msgpack``
    the same fields, points as a list of ``[x, y, t]`` float lists.

Every format includes building its dict from the message and the message
from its dict (numpy arrays and all), so all do the same job. Times are
medians over ``repeat`` rounds of ``number`` calls each of the process's CPU
time (``time.process_time``: on a shared 2-core machine wall time also counts
other processes' turns); the formats take turns inside every round so they
share the machine's state. ``encode_decode_us_p50`` is crosspath's median
round, ``speedup_vs_json`` the ratio of medians against compact JSON.

``path_sizes_bytes``: crosspath's size of three realistic 120-point future
paths, since the delta widths depend on the direction of travel: along an
axis (the sample above: y never changes), diagonal (the same motion at 45°:
both x and y change) and turning (a left turn through a 4-way intersection,
12 m/s slowing to 7 m/s on a 15 m radius arc, then straight on).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from protocol import (
    MAX_DATAGRAM,
    AutonomousPath,
    Command,
    CoordinatedPath,
    FuturePath,
    Header,
    Kind,
    Message,
    Mode,
    ModeCommand,
    RsuBeacon,
    decode,
    encode,
    max_points,
)
from protocol.codec import speedups_available, use_speedups
from protocol.messages import FloatArray
from services.edge.args import output_file, positive_int
from services.edge.progress import Ticker

FORMATS: dict[str, str] = {
    "crosspath": "crosspath binary codec (protocol/SPEC.md)",
    "crosspath_numpy": "the same codec on its numpy path (no C speed-ups)",
    "paper_json": "Autoware lane dump as JSON, one Waypoint object per point (the paper)",
    "json": "compact stdlib JSON, one {x,y,t} object per point",
    "json_arrays": "compact stdlib JSON, one [x,y,t] array per point",
    "msgpack": "msgpack, points as [x,y,t] float lists",
}
"""Format name -> what it is."""

TARGET_US_P50 = 8.0
"""Issue 14: encode + decode of a 120-point future path [µs]."""

TARGET_SPEEDUP_VS_JSON = 25.0
"""Issue 14: at least this many times faster than compact stdlib JSON."""

TARGET_PATH_BYTES = 450
"""Issue 14: most bytes of a 120-point future path on any realistic path."""

PAPER_JSON_BYTES = 60_000
"""What the paper reports for one 120-point path (§V, 60 KB)."""

SPACING_S = 0.084
"""Time between future-path points of the sample path [s]."""


def sample_future_path(points: int = 120, sender: str = "car-a") -> FuturePath:
    """A car at 12 m/s decelerating at 1 m/s² eastbound on y = -1.75 m (paper scenario lane)."""
    t_rel = np.arange(points) * SPACING_S
    decel = min(1.0, 12.0 / max(t_rel[-1], 1e-9)) if points > 1 else 1.0
    x = -60.0 + 12.0 * t_rel - 0.5 * decel * t_rel**2
    now = 12.345
    path = np.column_stack([x, np.full(points, -1.75), now + t_rel])
    return FuturePath(
        Header(sender, 7, round(now * 1e6)),
        float(x[0]),
        -1.75,
        12.0,
        0.0,
        4.5,
        1.8,
        Mode.AUTO,
        path,
    )


def _path_message(points: FloatArray) -> FuturePath:
    now = float(points[0, 2])
    (x0, y0), (x1, y1) = points[0, :2], points[1, :2]
    return FuturePath(
        Header("car-a", 7, round(now * 1e6)),
        float(x0),
        float(y0),
        12.0,
        math.atan2(y1 - y0, x1 - x0),
        4.5,
        1.8,
        Mode.AUTO,
        points,
    )


def diagonal_future_path(points: int = 120) -> FuturePath:
    """The sample path's motion at 45°: both coordinates change at every point."""
    axis = sample_future_path(points).points
    s = axis[:, 0] - axis[0, 0]
    c = math.sqrt(0.5)
    return _path_message(np.column_stack([-40.0 + c * s, -45.0 + c * s, axis[:, 2]]))


def turning_future_path(points: int = 120) -> FuturePath:
    """A left turn: 12 m/s slowing to 7 m/s on a 15 m radius quarter circle, then straight."""
    t = np.arange(points) * SPACING_S
    v = np.maximum(12.0 - 2.0 * t, 7.0)
    s = np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2 * SPACING_S)])
    radius, approach = 15.0, 25.0
    arc = math.pi / 2 * radius
    on_arc = np.clip(s - approach, 0.0, arc) / radius  # angle turned [rad]
    x = np.where(s < approach, s - approach, radius * np.sin(on_arc))
    y = np.where(s < approach, 0.0, radius * (1.0 - np.cos(on_arc)))
    after = np.maximum(s - approach - arc, 0.0)  # straight on, northbound
    x, y = x + 3.0, y - 1.75 + after
    return _path_message(np.column_stack([x, y, 12.345 + t]))


PATHS: dict[str, Callable[[int], FuturePath]] = {
    "axis": sample_future_path,
    "diagonal": diagonal_future_path,
    "turning": turning_future_path,
}
"""Realistic future paths whose sizes the README quotes."""


def sample_messages(points: int = 120) -> dict[str, Message]:
    """One realistic message of every kind; paths have ``points`` points."""
    fp = sample_future_path(points)
    speeds = np.maximum(12.0 - (fp.points[:, 2] - fp.points[0, 2]) * 1.0, 0.0)
    rsu = Header("rsu-1", 3, fp.header.time_us + 2_000)
    return {
        "future_path": fp,
        "autonomous_path": AutonomousPath(
            fp.header,
            fp.x,
            fp.y,
            fp.speed,
            fp.heading,
            fp.length,
            fp.width,
            Mode.C_SLOW,
            fp.points,
        ),
        "coordinated_path": CoordinatedPath(rsu, "car-a", Mode.C_SLOW, fp.points, speeds),
        "mode_command": ModeCommand(rsu, "car-a", Command.INITIATE, Mode.C_SLOW),
        "rsu_beacon": RsuBeacon(rsu, "x-0", 5.0, -5.0, 150.0),
    }


# ---------------------------------------------------------------- baselines


def _fields(m: FuturePath) -> dict[str, Any]:
    h = m.header
    return {
        "kind": "future_path",
        "sender": h.sender,
        "seq": h.seq,
        "time": h.time_s,
        "x": m.x,
        "y": m.y,
        "speed": m.speed,
        "heading": m.heading,
        "length": m.length,
        "width": m.width,
        "mode": m.mode.name,
    }


def _from_fields(d: dict[str, Any], points: Any) -> FuturePath:
    return FuturePath(
        Header(d["sender"], d["seq"], round(d["time"] * 1e6)),
        d["x"],
        d["y"],
        d["speed"],
        d["heading"],
        d["length"],
        d["width"],
        Mode[d["mode"]],
        np.array(points, dtype=np.float64).reshape(-1, 3),
    )


def json_encode(m: FuturePath) -> bytes:
    d = _fields(m)
    d["points"] = [{"x": x, "y": y, "t": t} for x, y, t in m.points.tolist()]
    return json.dumps(d, separators=(",", ":")).encode()


def json_decode(data: bytes) -> FuturePath:
    d = json.loads(data)
    return _from_fields(d, [(p["x"], p["y"], p["t"]) for p in d["points"]])


def json_arrays_encode(m: FuturePath) -> bytes:
    d = _fields(m)
    d["points"] = m.points.tolist()
    return json.dumps(d, separators=(",", ":")).encode()


def json_arrays_decode(data: bytes) -> FuturePath:
    d = json.loads(data)
    return _from_fields(d, d["points"])


def msgpack_encode(m: FuturePath) -> bytes:
    d = _fields(m)
    d["points"] = m.points.tolist()
    packed: bytes = msgpack.packb(d)
    return packed


def msgpack_decode(data: bytes) -> FuturePath:
    d = msgpack.unpackb(data)
    return _from_fields(d, d["points"])


def _ros_header(seq: int, t: float) -> dict[str, Any]:
    secs = int(t // 1)
    stamp = {"secs": secs, "nsecs": round((t - secs) * 1e9)}
    return {"seq": seq, "stamp": stamp, "frame_id": "map"}


def paper_json_encode(m: FuturePath) -> bytes:
    """The Autoware-style lane dump described in the module docstring."""
    waypoints: list[dict[str, Any]] = []
    cos_half, sin_half = math.cos(m.heading / 2), math.sin(m.heading / 2)
    pts = m.points.tolist()
    # speed at each point from the next point (the last repeats the one before)
    speeds = [
        math.hypot(nx - x, ny - y) / (nt - t) if nt > t else 0.0
        for (x, y, t), (nx, ny, nt) in itertools.pairwise(pts)
    ]
    speeds.append(speeds[-1] if speeds else m.speed)
    for i, ((x, y, t), v) in enumerate(zip(pts, speeds, strict=True)):
        waypoints.append(
            {
                "gid": i,
                "lid": i,
                "pose": {
                    "header": _ros_header(0, t),
                    "pose": {
                        "position": {"x": x, "y": y, "z": 0.0},
                        "orientation": {"x": 0.0, "y": 0.0, "z": sin_half, "w": cos_half},
                    },
                },
                "twist": {
                    "linear": {"x": v, "y": 0.0, "z": 0.0},
                    "angular": {"x": 0.0, "y": 0.0, "z": 0.0},
                },
                "lane_id": 0,
                "left_lane_id": 0,
                "right_lane_id": 0,
                "stop_line_id": 0,
                "cost": 0.0,
                "time_cost": 0.0,
                "direction": 0,
            }
        )
    lane = {
        "header": _ros_header(m.header.seq, m.header.time_s),
        "sender": m.header.sender,
        "increment": 0,
        "lane_id": 0,
        "waypoints": waypoints,
        "lane_index": 0,
        "cost": 0.0,
        "closest_object_distance": 0.0,
        "closest_object_velocity": 0.0,
        "is_blocked": False,
        "current_pose": {"x": m.x, "y": m.y, "heading": m.heading},
        "current_speed": m.speed,
        "vehicle": {"length": m.length, "width": m.width},
        "mode": m.mode.name,
    }
    return json.dumps(lane).encode()


def paper_json_decode(data: bytes) -> FuturePath:
    d = json.loads(data)
    stamp = d["header"]["stamp"]
    pose = d["current_pose"]
    points = []
    for w in d["waypoints"]:
        s = w["pose"]["header"]["stamp"]
        p = w["pose"]["pose"]["position"]
        points.append((p["x"], p["y"], s["secs"] + s["nsecs"] * 1e-9))
    return FuturePath(
        Header(d["sender"], d["header"]["seq"], stamp["secs"] * 1_000_000 + stamp["nsecs"] // 1000),
        pose["x"],
        pose["y"],
        d["current_speed"],
        pose["heading"],
        d["vehicle"]["length"],
        d["vehicle"]["width"],
        Mode[d["mode"]],
        np.array(points, dtype=np.float64).reshape(-1, 3),
    )


CODECS: dict[str, tuple[Callable[[FuturePath], bytes], Callable[[bytes], Any]]] = {
    "crosspath": (encode, decode),
    "crosspath_numpy": (encode, decode),  # timed with use_speedups(False)
    "paper_json": (paper_json_encode, paper_json_decode),
    "json": (json_encode, json_decode),
    "json_arrays": (json_arrays_encode, json_arrays_decode),
    "msgpack": (msgpack_encode, msgpack_decode),
}


# ---------------------------------------------------------------- measurement


def _time_per_call(fn: Callable[[Any], Any], arg: Any, number: int) -> float:
    """CPU seconds per call of ``fn(arg)`` over ``number`` calls."""
    clock = time.process_time
    start = clock()
    for _ in range(number):
        fn(arg)
    return (clock() - start) / number


def measure(points: int = 120, repeat: int = 25, number: int = 200) -> dict[str, Any]:
    """Sizes and median encode+decode times [µs] of every format for one ``points``-point path."""
    if repeat < 1 or number < 1:
        raise ValueError("repeat and number must be at least 1")
    message = sample_future_path(points)
    payloads = {name: enc(message) for name, (enc, _) in CODECS.items()}
    for name, (_, dec) in CODECS.items():
        back = dec(payloads[name])
        if back.points.shape != message.points.shape:
            raise RuntimeError(f"{name} round trip lost points")
    enc_us: dict[str, list[float]] = {name: [] for name in CODECS}
    dec_us: dict[str, list[float]] = {name: [] for name in CODECS}
    with_c = use_speedups(True)
    try:
        for _ in range(repeat):
            for name, (enc, dec) in CODECS.items():
                use_speedups(with_c and name != "crosspath_numpy")
                enc_us[name].append(_time_per_call(enc, message, number) * 1e6)
                dec_us[name].append(_time_per_call(dec, payloads[name], number) * 1e6)
    finally:
        use_speedups(with_c)
    encode_us = {name: statistics.median(v) for name, v in enc_us.items()}
    decode_us = {name: statistics.median(v) for name, v in dec_us.items()}
    both_us = {
        name: statistics.median(e + d for e, d in zip(enc_us[name], dec_us[name], strict=True))
        for name in CODECS
    }
    sizes = {name: len(p) for name, p in payloads.items()}
    path_sizes = {name: len(encode(make(points))) for name, make in PATHS.items()}
    p50 = both_us["crosspath"]
    speedup = both_us["json"] / p50
    kinds = {
        kind: {"bytes": len(encode(m)), "max_points": max_points(m.kind)}
        for kind, m in sample_messages(points).items()
    }
    return {
        "points": points,
        "repeat": repeat,
        "number": number,
        "formats": dict(FORMATS),
        "sizes_bytes": sizes,
        "encode_decode_us": both_us,
        "encode_us": encode_us,
        "decode_us": decode_us,
        "encode_decode_us_p50": p50,
        "speedup_vs_json": speedup,
        "speedup_vs_json_arrays": both_us["json_arrays"] / both_us["crosspath"],
        "speedup_vs_msgpack": both_us["msgpack"] / both_us["crosspath"],
        "c_speedups": speedups_available(),
        "speedup_c_vs_numpy": both_us["crosspath_numpy"] / both_us["crosspath"],
        "size_ratio_vs_paper_json": sizes["paper_json"] / sizes["crosspath"],
        "paper_reported_bytes": PAPER_JSON_BYTES,
        "max_datagram": MAX_DATAGRAM,
        "kinds": kinds,
        "max_points": {k.name.lower(): max_points(k) for k in Kind},
        "path_sizes_bytes": path_sizes,
        "targets": {
            "encode_decode_us_p50": TARGET_US_P50,
            "speedup_vs_json": TARGET_SPEEDUP_VS_JSON,
            "path_bytes": TARGET_PATH_BYTES,
            "met": {
                "encode_decode_us_p50": p50 <= TARGET_US_P50,
                "speedup_vs_json": speedup >= TARGET_SPEEDUP_VS_JSON,
                "path_bytes": max(path_sizes.values()) <= TARGET_PATH_BYTES,
            },
        },
    }


# ---------------------------------------------------------------- CLI


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench codec``; bad values are refused while parsing."""
    most = max_points(Kind.FUTURE_PATH)

    def points(text: str) -> int:
        value = positive_int(text)
        if value > most:
            raise argparse.ArgumentTypeError(f"must be <= {most} (one datagram), got {value}")
        return value

    parser.add_argument("--json", metavar="OUT", type=output_file, help="write the results as JSON")
    parser.add_argument("--points", type=points, default=120, help="points per path")
    parser.add_argument("--repeat", type=positive_int, default=25, help="timed rounds (median)")
    parser.add_argument("--number", type=positive_int, default=200, help="calls per round")


def run(args: argparse.Namespace) -> int:
    """Measure and print; a status line on stderr while it runs (on a terminal only)."""
    with Ticker("crosspath bench codec", lambda: f"{len(FORMATS)} formats"):
        result = measure(args.points, repeat=args.repeat, number=args.number)
    print(
        f"future path, {result['points']} points; median of {args.repeat} x {args.number} calls "
        "(CPU time)"
    )
    print(f"{'format':<16} {'bytes':>8} {'enc+dec µs':>11} {'vs crosspath':>13}")
    ours = result["encode_decode_us"]["crosspath"]
    for name in FORMATS:
        us = result["encode_decode_us"][name]
        print(f"{name:<16} {result['sizes_bytes'][name]:>8} {us:>11.1f} {us / ours:>12.1f}x")
    print(
        f"crosspath encode+decode p50 {result['encode_decode_us_p50']:.1f} µs; "
        f"speedup vs compact JSON: {result['speedup_vs_json']:.1f}x; "
        f"size ratio vs paper JSON: {result['size_ratio_vs_paper_json']:.0f}x; "
        + (
            f"C speed-ups {result['speedup_c_vs_numpy']:.1f}x the numpy path"
            if result["c_speedups"]
            else "C speed-ups NOT built: numpy path"
        )
    )
    print(
        f"{result['points']}-point future path: "
        + ", ".join(f"{k} {v} B" for k, v in result["path_sizes_bytes"].items())
    )
    for name, ok in result["targets"]["met"].items():
        print(f"target {name}: {'met' if ok else 'NOT met'}")
    print(
        "per kind: "
        + ", ".join(
            f"{k} {v['bytes']} B (max {v['max_points']} points)"
            if v["max_points"]
            else f"{k} {v['bytes']} B"
            for k, v in result["kinds"].items()
        )
    )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0
