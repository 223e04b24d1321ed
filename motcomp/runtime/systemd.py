"""systemd readiness and watchdog notifications, without a dependency.

Writes ``KEY=VALUE`` lines to the datagram socket named by ``$NOTIFY_SOCKET`` (an abstract
socket when it starts with ``@``); does nothing when the variable is absent.  Sends never
block: a Unix datagram queue holds ~10 messages, and a reader that stops reading must not
freeze the service.  systemd 252 (these
machines) does not accept ``Type=notify-reload``: the unit uses ``Type=notify`` with
``ExecReload=/bin/kill -HUP $MAINPID`` and the service sends ``RELOADING=1`` +
``MONOTONIC_USEC`` then ``READY=1`` around a reload.
"""

from __future__ import annotations

import os
import socket
import time

__all__ = ["Notifier"]


class Notifier:
    """``notify("READY=1")`` etc.; silently inactive outside systemd."""

    def __init__(self, address: str | None = None) -> None:
        addr = address if address is not None else os.environ.get("NOTIFY_SOCKET", "")
        self.address = addr
        self._sock: socket.socket | None = None
        if addr:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # never block the service: a full queue (a reader that does not read) drops the
            # notification instead
            self._sock.setblocking(False)
        self.dropped = 0
        self.watchdog_usec = int(os.environ.get("WATCHDOG_USEC", "0") or 0)

    @property
    def active(self) -> bool:
        return self._sock is not None

    def notify(self, *lines: str) -> bool:
        if self._sock is None:
            return False
        target = "\0" + self.address[1:] if self.address.startswith("@") else self.address
        try:
            self._sock.sendto("\n".join(lines).encode(), target)
        except OSError:  # BlockingIOError (queue full) included
            self.dropped += 1
            return False
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def reloading(self) -> bool:
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify("RELOADING=1", f"MONOTONIC_USEC={usec}")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
