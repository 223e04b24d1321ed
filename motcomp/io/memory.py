"""In-memory twins of the transport adapters, for tests and offline runs.

:class:`MemorySource` hands out the queued payloads one per ``drain()`` call (or all at once, as
the zenoh source does, with ``burst=True``); :class:`MemorySink` keeps what it was given.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

from motcomp.core.tick import TickOutput
from motcomp.io.wire import encode_output

__all__ = ["MemorySink", "MemorySource"]


class MemorySource:
    """A source fed by the test: ``push(payload)``; ``drain()`` never blocks."""

    def __init__(self, payloads: Iterable[bytes] = (), burst: bool = False) -> None:
        self._queue: deque[bytes] = deque(payloads)
        self.burst = burst

    def push(self, payload: bytes) -> None:
        self._queue.append(payload)

    def drain(self) -> list[bytes]:
        if not self._queue:
            return []
        if self.burst:
            out = list(self._queue)
            self._queue.clear()
            return out
        return [self._queue.popleft()]

    def close(self) -> None:
        self._queue.clear()


class MemorySink:
    """Keeps every payload put (or only the last ``keep``)."""

    def __init__(self, keep: int | None = None) -> None:
        self.payloads: deque[bytes] = deque(maxlen=keep)
        self.sent = 0
        self.errors = 0

    def send(self, out: TickOutput, t: float) -> None:
        """An :class:`~motcomp.io.ports.OutputPort`: keeps the encoded output frame."""
        self.put(encode_output(out.seq, t, out.src_seq, out.u, out.flags, out.rx_ns))
        self.sent += 1

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)

    def close(self) -> None:
        pass
