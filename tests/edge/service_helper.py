"""A tiny service for the lifecycle tests, run as ``python -m tests.edge.service_helper``.

``MODE`` (argv[1]) is ``cooperative`` (run returns when stop is set), ``frozen`` (the
same, first printing ``frozen <count>``: the objects ``gc.freeze`` holds as ``run``
starts) or ``stubborn`` (run ignores stop: only a forced exit ends it). Markers go to
stdout, one per line, so the test can follow the service's steps; logs go to stderr.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import sys

from services.edge.lifecycle import run_service
from services.edge.logs import configure_logging

logger = logging.getLogger("crosspath.helper")


def mark(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


class HelperService:
    def __init__(self, mode: str) -> None:
        self.stubborn = mode == "stubborn"
        self.frozen = mode == "frozen"

    async def startup(self) -> None:
        mark("startup")

    async def run(self, stop: asyncio.Event) -> None:
        if self.frozen:
            mark(f"frozen {gc.get_freeze_count()}")
        logger.info("running")
        mark("running")
        if self.stubborn:
            watcher = asyncio.ensure_future(self._report_stop(stop))
            try:
                await asyncio.sleep(3600)
            finally:
                watcher.cancel()
        else:
            await stop.wait()
            mark("stopping")

    async def _report_stop(self, stop: asyncio.Event) -> None:
        await stop.wait()
        mark("stop ignored")

    async def shutdown(self) -> None:
        mark("shutdown")


def main() -> int:
    configure_logging("INFO", "helper-node")
    return run_service(HelperService(sys.argv[1]))


if __name__ == "__main__":
    sys.exit(main())
