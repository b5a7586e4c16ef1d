"""systemd's readiness protocol (``sd_notify``), stdlib only.

A unit with ``Type=notify`` is "started" only once the service sends ``READY=1``
on the datagram socket named by ``$NOTIFY_SOCKET``: for a crosspath daemon that is
after its transport is open, its subscriptions and liveliness token are declared
and its metrics endpoint listens (:func:`services.edge.lifecycle.serve` sends it
when ``startup`` returns), so ``systemctl start`` returns when the daemon can take
part in a run and units ordered ``After=`` it start after that.

Outside systemd (no ``NOTIFY_SOCKET``) every call is a no-op. A socket that
cannot be reached is logged once at WARNING and otherwise ignored: the daemon
works without a service manager, and systemd notices a missing ``READY=1``
itself (``TimeoutStartSec``).
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

logger = logging.getLogger("crosspath.notify")

__all__ = ["notify", "notify_socket_address"]


def notify_socket_address(environ: Mapping[str, str] = os.environ) -> str | bytes | None:
    """The address of ``$NOTIFY_SOCKET``: a path, or bytes for the Linux abstract
    namespace (a leading ``@`` becomes a NUL byte); None when unset or unusable."""
    name = environ.get("NOTIFY_SOCKET", "")
    if name.startswith("@"):
        return b"\0" + name[1:].encode()
    if name.startswith("/"):
        return name
    return None  # empty, or a vsock address (not used for services on this host)


def notify(state: str, environ: Mapping[str, str] = os.environ) -> bool:
    """Send ``state`` (newline-separated ``KEY=VALUE`` lines, e.g. ``READY=1``) to the
    service manager; whether it was sent (False without ``$NOTIFY_SOCKET``)."""
    address = notify_socket_address(environ)
    if address is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(state.encode())
    except OSError as exc:
        logger.warning("cannot notify the service manager at %r: %s", address, exc)
        return False
    return True
