"""A sd_notify listener for tests: a datagram socket drained by a thread."""

from __future__ import annotations

import socket
import threading
from pathlib import Path


class NotifyListener:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.messages: list[str] = []
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.settimeout(0.1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.messages.append(self._sock.recv(4096).decode())
            except (TimeoutError, OSError):
                continue

    def close(self) -> str:
        self._stop.set()
        self._thread.join()
        self._sock.close()
        return "\n".join(self.messages)
