"""Logging setup of the daemons: one named logger per service, the node id on every line.

Loggers are named ``crosspath.<service>`` (``crosspath.rsu``, ``crosspath.vehicle``,
``crosspath.transport``...). :func:`configure_logging` sends every record to
stderr (stdout stays free for a command's results) with wall time, level,
logger name and the node id; ``json=True`` writes one JSON object per line
instead, for collecting logs of many daemons.

Zenoh's own (Rust) logs are separate: see ``services.edge.transport.init_zenoh_logging``.
"""

from __future__ import annotations

import json as jsonlib
import logging
import logging.config
from typing import Any

ROOT_LOGGER = "crosspath"

TEXT_FORMAT = "%(asctime)s %(levelname)-7s %(name)s [%(node)s] %(message)s"

_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


class NodeFilter(logging.Filter):
    """Stamps every record with the node id (attribute ``node``)."""

    def __init__(self, node: str) -> None:
        super().__init__()
        self.node = node

    def filter(self, record: logging.LogRecord) -> bool:
        record.node = self.node
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per record: time (Unix s), level, logger, node, message."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": record.created,
            "level": record.levelname,
            "logger": record.name,
            "node": getattr(record, "node", ""),
            "message": record.getMessage(),
        }
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return jsonlib.dumps(entry, ensure_ascii=False)


def _node_filter(node: str) -> NodeFilter:
    return NodeFilter(node)


def configure_logging(level: str, node: str, json: bool = False) -> None:
    """Configure the ``crosspath`` loggers (and the root logger, for libraries) via dictConfig.

    ``level`` is a stdlib level name (case-insensitive); raises ValueError otherwise.
    """
    name = level.upper()
    if name not in _LEVELS:
        raise ValueError(f"unknown log level {level!r}; expected one of {', '.join(_LEVELS)}")
    formatter: dict[str, Any] = {"()": JsonFormatter} if json else {"format": TEXT_FORMAT}
    logging.config.dictConfig(
        {
            "version": 1,
            "disable_existing_loggers": False,
            "filters": {"node": {"()": _node_filter, "node": node}},
            "formatters": {"default": formatter},
            "handlers": {
                "stderr": {
                    "class": "logging.StreamHandler",
                    "stream": "ext://sys.stderr",
                    "formatter": "default",
                    "filters": ["node"],
                }
            },
            "loggers": {ROOT_LOGGER: {"level": name, "handlers": ["stderr"], "propagate": False}},
            "root": {"level": "WARNING", "handlers": ["stderr"]},
        }
    )


def get_logger(service: str) -> logging.Logger:
    """The logger ``crosspath.<service>``."""
    return logging.getLogger(f"{ROOT_LOGGER}.{service}")
