"""Daemon settings: where and how a daemon runs, one loader with a fixed precedence.

Every daemon (vehicle, RSU, monitor) reads a model derived from
:class:`CommonDaemonConfig`, a pydantic-settings ``BaseSettings``. What the
experiment *is* (map, cars, RSU and vehicle knobs) belongs to the scenario file
(``services.model.scenario``), not here. Values come from, lowest precedence first:

1. the model's defaults;
2. a TOML file (``--config FILE``);
3. environment variables ``CROSSPATH_<FIELD>``, ``__`` (double underscore)
   separating nested fields, e.g. ``CROSSPATH_ZENOH__LISTEN='["udp/0.0.0.0:7447"]'``,
   read by pydantic-settings' ``EnvSettingsSource`` with the prefix and delimiter the
   model declares: lists and tables are JSON, ``null`` is None, anything else is
   text for pydantic to validate (``4`` for a float, ``true`` for a bool);
4. command-line overrides: dotted keys, e.g. ``--set zenoh.max_links=4``,
   ``--listen``, ``--connect``, ``--prefix``, ``--log-level``.

``--set`` values are parsed as JSON when they are valid JSON (``2``, ``true``,
``null``, ``["udp/0.0.0.0:7447"]``, ``"text"``) and kept as text otherwise
(``udp/0.0.0.0:7447``, ``car-1``); a value that starts like a JSON list, object or
string but does not parse is an error, as is an environment value that is not the
JSON its list or table field needs. Numbers given for text fields are accepted as
text (``--set node_id=7`` gives ``"7"``). Environment variables whose first field
is not a field of the model are ignored (other crosspath tools may set
``CROSSPATH_*`` variables); unknown nested fields and unknown keys anywhere else
are errors (``extra="forbid"``). Each layer replaces what it sets: a table given
whole (``CROSSPATH_ZENOH__OPTIONS='{...}'``) replaces that table.

Any problem raises :class:`ConfigError` naming the field, the reason and, for a
bad value, where it came from (``(from CROSSPATH_TIME__SPEED)``, the file, or the
command line); :func:`exit_on_config_error` turns it into the CLI's message and
exit code 2. Built directly (``RsuDaemonConfig(node_id=...)``) a model reads only
its arguments: the layering is :func:`load_config`'s job alone.

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
from pydantic.fields import FieldInfo
from pydantic_settings import (
    BaseSettings,
    EnvSettingsSource,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    SettingsError,
)

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
    connect_in_turn: bool = False
    """Open connects to the reliable ``connect`` endpoints (``tcp/``, ``tls/``) one after
    another, waiting for each (at most ``connect_timeout_s`` in all), and then to the
    others (``udp/``, ``quic/``) in the background; off: Zenoh's default, every endpoint
    in the background at once, so start order does not matter. For set-ups that start
    nodes in order, each connecting to nodes already up (``crosspath up``, the lab): a
    pair's UDP and TCP links opened at once were seen to lose declarations (tokens,
    subscribers) for good (``services.edge.transport.zenoh_config``)."""
    connect_timeout_s: Annotated[float, Field(gt=0.0, le=3600.0)] = 30.0
    """With ``connect_in_turn``: how long open waits for the reliable endpoints in all
    [s] before it fails (an endpoint that never answers)."""
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


def background_endpoint(endpoint: str) -> str:
    """``endpoint`` marked for Zenoh to connect to in the background even with
    ``ZenohSettings.connect_in_turn`` (its own ``exit_on_failure=false`` option); one that
    says ``exit_on_failure`` already is returned as it is."""
    if "exit_on_failure=" in endpoint.partition("#")[2]:
        return endpoint
    return f"{endpoint}{';' if '#' in endpoint else '#'}exit_on_failure=false"


class SecuritySettings(BaseModel):
    """A daemon's credentials (issue 13; files written by ``crosspath keys``).

    With ``key``, ``certificate`` and ``root`` set, the daemon signs every V2X
    datagram it sends and refuses (counts and drops) every one not signed by a
    key the root certified for its sender and role (``services.edge.trust``).
    With none of them set the daemon sends unsigned and accepts anything, and says
    so loudly at start (``insecure = true`` states that this is meant)."""

    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True)

    key: Path | None = None
    """This daemon's Ed25519 private key (PEM, ``<id>.key``); ``{node}`` stands for the
    node id (``keys/{node}.key`` serves every car of a multi-car host)."""
    certificate: Path | None = None
    """Its certificate (``<id>.cert``, ``{node}`` as for ``key``)."""
    root: Path | None = None
    """The authority's public key every certificate must be signed by (``root.pub``)."""
    revocation: Path | None = None
    """Revoked key ids, one hex per line (``revoked.txt``), re-read when it changes."""
    insecure: bool = False
    """Run without signatures on purpose (comparison runs); refused with credentials set."""

    @property
    def enabled(self) -> bool:
        """Whether credentials are configured (signing and verification on)."""
        return self.key is not None

    def model_post_init(self, context: Any, /) -> None:
        named = [self.key, self.certificate, self.root]
        if any(p is not None for p in named) and not all(p is not None for p in named):
            raise ValueError("security needs key, certificate and root together")
        if self.insecure and self.key is not None:
            raise ValueError("security.insecure with credentials set: choose one")


class TimeSettings(BaseModel):
    """The run's shared time base (see ``services.edge.clock.RunClock``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, coerce_numbers_to_str=True)

    epoch_unix: float | None = None
    """Wall-clock time (Unix seconds) of run time 0; None: the daemon's start."""
    speed: Annotated[float, Field(gt=0.0, le=1000.0)] = 1.0
    """Run seconds per wall second (2.0 runs twice as fast as real time)."""


class CommonDaemonConfig(BaseSettings):
    """Settings every daemon shares; daemon models subclass this.

    The model declares its environment (prefix ``CROSSPATH_``, ``__`` between nested
    fields); :func:`load_config` layers file < environment < command line.
    """

    model_config = SettingsConfigDict(
        extra="forbid",
        frozen=True,
        coerce_numbers_to_str=True,
        validate_default=False,
        env_prefix=ENV_PREFIX,
        env_nested_delimiter="__",
        case_sensitive=False,
    )

    node_id: str
    """This daemon's id: the vehicle or RSU id, or a node name (1..32 of [A-Za-z0-9_-])."""
    key_prefix: str = keys.DEFAULT_PREFIX
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    log_level: LogLevel = "INFO"
    log_json: bool = False
    time: TimeSettings = Field(default_factory=TimeSettings)
    stats_period_s: Annotated[float, Field(gt=0.0)] = 1.0
    metrics_port: Annotated[int, Field(ge=0, le=65535)] | None = None
    """Serve Prometheus metrics on this TCP port (0: any free one); None: no endpoint
    (``services.edge.metrics``)."""
    metrics_host: str = "0.0.0.0"
    """Address the metrics endpoint listens on."""
    security: SecuritySettings = Field(default_factory=SecuritySettings)

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

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Only the arguments when built directly (see the module doc)."""
        return (init_settings,)


T = TypeVar("T", bound=BaseSettings)


def parse_value(text: str) -> object:
    """Turn a ``--set`` value into Python (JSON-or-string, see module doc)."""
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


class _EnvSource(EnvSettingsSource):
    """pydantic-settings' environment source over a given mapping rather than
    ``os.environ`` (tests and callers pass their own), naming the variable of a value
    that is not valid JSON."""

    def __init__(self, settings_cls: type[BaseSettings], env: Mapping[str, str]) -> None:
        self._environ = env  # read by _load_env_vars, which the base __init__ calls
        super().__init__(settings_cls)

    def _load_env_vars(self) -> Mapping[str, str | None]:
        return {name.lower(): value for name, value in self._environ.items()}

    def decode_complex_value(self, field_name: str, field: FieldInfo | None, value: Any) -> Any:
        try:
            return super().decode_complex_value(field_name, field, value)  # type: ignore[arg-type]
        except json.JSONDecodeError as exc:
            suffix = field_name.upper()
            names = sorted(
                name
                for name, text in self._environ.items()
                if text == value
                and name.upper().startswith(ENV_PREFIX)
                and name.upper().endswith(suffix)
            )
            name = names[0] if names else ENV_PREFIX + suffix
            raise ConfigError([(name, f"invalid JSON ({exc.msg} at column {exc.colno})")]) from None


def _env_layer(
    model: type[BaseSettings], env: Mapping[str, str]
) -> list[tuple[list[str], object, str]]:
    """(field path, value, variable) of each ``CROSSPATH_*`` variable that names a field of
    ``model``, in name order, its value parsed by pydantic-settings (``null`` is None)."""
    try:
        parsed = _EnvSource(model, env)()
    except SettingsError as exc:
        if isinstance(exc.__cause__, ConfigError):
            raise exc.__cause__ from None
        raise ConfigError([(f"{ENV_PREFIX}*", str(exc))]) from None
    layer: list[tuple[list[str], object, str]] = []
    for name in sorted(env):
        if not name.upper().startswith(ENV_PREFIX):
            continue
        path = [part.lower() for part in name[len(ENV_PREFIX) :].split("__")]
        node: object = parsed
        for part in path:
            if not isinstance(node, dict) or part not in node:
                break
            node = node[part]
        else:
            layer.append((path, None if env[name].strip() == "null" else node, name))
    return layer


def _leaves(tree: Mapping[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Paths of the values of a TOML document (tables walked into, the rest leaves)."""
    out: list[tuple[str, ...]] = []
    for key, value in tree.items():
        here = (*prefix, key)
        out.extend(_leaves(value, here) if isinstance(value, dict) and value else [here])
    return out


def _origin(loc: Sequence[object], sources: Sequence[tuple[tuple[str, ...], str]]) -> str | None:
    """Where the value at ``loc`` came from: the last layer that set it or a table above it."""
    parts = tuple(str(part) for part in loc)
    for path, source in reversed(sources):
        if parts[: len(path)] == path:
            return source
    return None


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

    Raises :class:`ConfigError` (with the dotted field path, the reason and the source
    of the bad value) on any problem.
    """
    tree: dict[str, Any] = read_toml(path) if path is not None else {}
    sources = [(leaf, str(path)) for leaf in _leaves(tree)]
    for env_path, value, name in _env_layer(model, env):
        _set_path(tree, env_path, value, name)
        sources.append((tuple(env_path), name))
    for key, value in overrides.items():
        _set_path(tree, key.split("."), value, key)
        sources.append((tuple(key.split(".")), "the command line"))
    try:
        return model.model_validate(tree)
    except ValidationError as exc:
        problems = []
        for error in exc.errors():
            origin = _origin(error["loc"], sources)
            reason = error["msg"] if origin is None else f"{error['msg']} (from {origin})"
            problems.append((".".join(str(part) for part in error["loc"]) or "<root>", reason))
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
    group.add_argument(
        "--metrics-port", type=int, metavar="PORT", help="serve Prometheus metrics on PORT"
    )


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
    if getattr(args, "metrics_port", None) is not None:
        overrides["metrics_port"] = args.metrics_port
    return overrides


def config_from_args(
    model: type[T], args: argparse.Namespace, env: Mapping[str, str] = os.environ
) -> T:
    """:func:`load_config` from the options of :func:`add_common_arguments`."""
    path: Path | None = getattr(args, "config", None)
    return load_config(model, path, overrides_from_args(args), env)
