"""Daemon settings: pydantic models and one loader with a fixed precedence.

Every daemon (vehicle, RSU, monitor) reads a model derived from
:class:`CommonDaemonConfig`. Values come from, lowest precedence first:

1. the model's defaults;
2. a TOML file (``--config FILE``);
3. environment variables ``CROSSPATH_<FIELD>``, ``__`` (double underscore)
   separating nested fields, e.g. ``CROSSPATH_ZENOH__LISTEN='["udp/0.0.0.0:7447"]'``;
4. command-line overrides: dotted keys, e.g. ``--set zenoh.max_links=4``,
   ``--listen``, ``--connect``, ``--prefix``, ``--log-level``.

Environment and ``--set`` values are parsed as JSON when they are valid JSON
(``2``, ``true``, ``null``, ``["udp/0.0.0.0:7447"]``, ``"text"``) and kept as
text otherwise (``udp/0.0.0.0:7447``, ``car-1``); a value that starts like a JSON
list, object or string but does not parse is an error. Numbers given for text
fields are accepted as text (``--set node_id=7`` gives ``"7"``).
Environment variables whose first field is not a field of the model are ignored
(other crosspath tools may set ``CROSSPATH_*`` variables); unknown nested
fields and unknown keys anywhere else are errors (``extra="forbid"``).

Any problem raises :class:`ConfigError` naming the field and the reason;
:func:`exit_on_config_error` turns it into the CLI's message and exit code 2.

This module imports no zenoh: :class:`ZenohSettings` is turned into a
``zenoh.Config`` by ``services.edge.transport.zenoh_config``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, TextIO, TypeVar

from pydantic import BaseModel, ConfigDict, Field, JsonValue, ValidationError, field_validator

from protocol import keys

ENV_PREFIX = "CROSSPATH_"
"""Environment variables with this prefix override configuration fields."""

CONFIG_ERROR_EXIT = 2
"""Exit code of a command whose configuration is invalid (as argparse uses)."""

LogLevel = Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"]


class ConfigError(ValueError):
    """Invalid configuration: ``problems`` lists (field path, reason) pairs."""

    def __init__(self, problems: Sequence[tuple[str, str]]) -> None:
        if not problems:
            raise ValueError("ConfigError needs at least one problem")
        self.problems: tuple[tuple[str, str], ...] = tuple(problems)
        super().__init__("; ".join(f"{field}: {reason}" for field, reason in self.problems))

    @property
    def field(self) -> str:
        """Path of the first offending field (dotted), or a source such as ``--set``."""
        return self.problems[0][0]

    @property
    def reason(self) -> str:
        """Why the first offending field was rejected."""
        return self.problems[0][1]


class ZenohSettings(BaseModel):
    """How a daemon joins the Zenoh network.

    ``config_file`` (a Zenoh JSON5 file) is applied first; then the explicit
    fields here override it. Without a ``config_file`` every field applies,
    defaults included (so multicast scouting is off unless asked for). With one,
    only the fields set explicitly (in TOML, environment or command line) override
    the file. See ``deploy/zenoh/README.md`` for the UDP/TCP setup.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True)

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=list)
    """Endpoints to listen on; empty: none. A peer should listen on one ``udp/`` and one
    ``tcp/`` endpoint that the others can reach (gossip passes them on)."""
    connect: list[str] = Field(default_factory=list)
    """Endpoints to connect to (both endpoints of the rendezvous RSU or router)."""
    multicast_scouting: bool = False
    max_links: Annotated[int, Field(ge=1, le=64)] = 2
    """Links per peer pair: 2 or more lets a UDP and a TCP link coexist."""
    config_file: Path | None = None
    options: dict[str, JsonValue] = Field(default_factory=dict)
    """Raw Zenoh settings applied last: Zenoh config path (``a/b/c``) -> JSON value."""

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, value: list[str]) -> list[str]:
        for endpoint in value:
            proto, sep, address = endpoint.partition("/")
            if not sep or not proto or not address:
                raise ValueError(f"endpoint {endpoint!r} is not <proto>/<address>")
        return value


class TimeSettings(BaseModel):
    """The run's shared time base (see ``services.edge.clock.RunClock``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True)

    epoch_unix: float | None = None
    """Wall-clock time (Unix seconds) of run time 0; None: the daemon's start."""
    speed: Annotated[float, Field(gt=0.0, le=1000.0)] = 1.0
    """Run seconds per wall second (2.0 runs twice as fast as real time)."""


class CommonDaemonConfig(BaseModel):
    """Settings every daemon shares; daemon models subclass this."""

    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True)

    node_id: str
    """This daemon's id: the vehicle or RSU id, or a node name (1..32 of [A-Za-z0-9_-])."""
    key_prefix: str = keys.DEFAULT_PREFIX
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    log_level: LogLevel = "INFO"
    log_json: bool = False
    time: TimeSettings = Field(default_factory=TimeSettings)
    stats_period_s: Annotated[float, Field(gt=0.0)] = 1.0

    @field_validator("node_id")
    @classmethod
    def _node_id(cls, value: str) -> str:
        return keys.validate_id(value, "node id")

    @field_validator("key_prefix")
    @classmethod
    def _key_prefix(cls, value: str) -> str:
        return keys.validate_prefix(value)

    @field_validator("log_level", mode="before")
    @classmethod
    def _log_level(cls, value: object) -> object:
        return value.upper() if isinstance(value, str) else value


T = TypeVar("T", bound=BaseModel)


def parse_value(text: str) -> object:
    """Turn an environment or ``--set`` value into Python (JSON-or-string, see module doc)."""
    stripped = text.strip()
    try:
        value: object = json.loads(stripped)
    except json.JSONDecodeError as exc:
        if stripped[:1] in ("[", "{", '"'):
            raise ValueError(f"invalid JSON ({exc.msg} at column {exc.colno})") from None
        return text
    return value


def _set_path(tree: dict[str, Any], path: Sequence[str], value: object, source: str) -> None:
    """Set ``tree[path[0]][path[1]]... = value``, creating tables on the way."""
    if not path or any(not part for part in path):
        raise ConfigError([(source, "empty field name")])
    node = tree
    for depth, part in enumerate(path[:-1]):
        child = node.get(part)
        if child is None:
            child = {}
            node[part] = child
        elif not isinstance(child, dict):
            where = ".".join(path[: depth + 1])
            raise ConfigError([(where, f"is not a table, cannot set {'.'.join(path)}")])
        node = child
    node[path[-1]] = value


def _env_layer(model: type[BaseModel], env: Mapping[str, str]) -> list[tuple[list[str], object]]:
    fields = set(model.model_fields)
    layer: list[tuple[list[str], object]] = []
    for name in sorted(env):
        if not name.startswith(ENV_PREFIX):
            continue
        path = [part.lower() for part in name[len(ENV_PREFIX) :].split("__")]
        if path[0] not in fields:
            continue
        try:
            value = parse_value(env[name])
        except ValueError as exc:
            raise ConfigError([(name, str(exc))]) from None
        layer.append((path, value))
    return layer


def read_toml(path: Path) -> dict[str, Any]:
    """The TOML file as a dict; unreadable or invalid files raise :class:`ConfigError`."""
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except OSError as exc:
        raise ConfigError([(str(path), exc.strerror or str(exc))]) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([(str(path), f"invalid TOML: {exc}")]) from None


def load_config(
    model: type[T],
    path: Path | None,
    overrides: Mapping[str, object],
    env: Mapping[str, str] = os.environ,
) -> T:
    """Build ``model`` from a TOML file, then ``CROSSPATH_*`` env vars, then dotted overrides.

    Raises :class:`ConfigError` (with the dotted field path and reason) on any problem.
    """
    tree: dict[str, Any] = read_toml(path) if path is not None else {}
    for env_path, value in _env_layer(model, env):
        _set_path(tree, env_path, value, ENV_PREFIX)
    for key, value in overrides.items():
        _set_path(tree, key.split("."), value, key)
    try:
        return model.model_validate(tree)
    except ValidationError as exc:
        problems = [
            (".".join(str(part) for part in error["loc"]) or "<root>", error["msg"])
            for error in exc.errors()
        ]
        raise ConfigError(problems) from None


def exit_on_config_error(command: str, error: ConfigError, stream: TextIO | None = None) -> int:
    """Report ``error`` as ``crosspath <command>: config error: <field>: <reason>``; return 2."""
    out = sys.stderr if stream is None else stream
    for field, reason in error.problems:
        out.write(f"crosspath {command}: config error: {field}: {reason}\n")
    out.flush()
    return CONFIG_ERROR_EXIT


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options every daemon command shares (see :func:`overrides_from_args`)."""
    group = parser.add_argument_group("configuration")
    group.add_argument("--config", type=Path, metavar="FILE", help="TOML configuration file")
    group.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one field (dotted key, JSON-or-string value); repeatable",
    )
    group.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, e.g. udp/0.0.0.0:7447; repeatable",
    )
    group.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint to connect to, e.g. tcp/192.0.2.1:7447; repeatable",
    )
    group.add_argument("--prefix", metavar="PREFIX", help="key expression prefix (crosspath)")
    group.add_argument("--log-level", metavar="LEVEL", help="DEBUG, INFO, WARNING or ERROR")


def overrides_from_args(args: argparse.Namespace) -> dict[str, object]:
    """Dotted-key overrides from the options of :func:`add_common_arguments`.

    ``--set`` items come first, so the dedicated options win over them.
    """
    overrides: dict[str, object] = {}
    for item in getattr(args, "set", None) or []:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError([("--set", f"expected KEY=VALUE, got {item!r}")])
        try:
            overrides[key] = parse_value(text)
        except ValueError as exc:
            raise ConfigError([(key, str(exc))]) from None
    if getattr(args, "listen", None):
        overrides["zenoh.listen"] = list(args.listen)
    if getattr(args, "connect", None):
        overrides["zenoh.connect"] = list(args.connect)
    if getattr(args, "prefix", None):
        overrides["key_prefix"] = args.prefix
    if getattr(args, "log_level", None):
        overrides["log_level"] = args.log_level
    return overrides


def config_from_args(
    model: type[T], args: argparse.Namespace, env: Mapping[str, str] = os.environ
) -> T:
    """:func:`load_config` from the options of :func:`add_common_arguments`."""
    path: Path | None = getattr(args, "config", None)
    return load_config(model, path, overrides_from_args(args), env)
