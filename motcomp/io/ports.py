"""The two small protocols every transport adapter implements (zenoh, CAN, in-memory twins).

An input port hands the loop every input frame that arrived since the last call, never
blocking; an output port takes the
tick's :class:`~motcomp.core.tick.TickOutput` and its time ``t`` (wall-clock seconds), encodes
it for its medium and sends it without blocking, counting what it could not send instead of
raising.  The service keeps a list of output ports and knows nothing of their media.
"""

from __future__ import annotations

from typing import Protocol

from motcomp.core.tick import TickOutput

__all__ = ["InputPort", "OutputPort"]


class InputPort(Protocol):
    def drain(self) -> list[bytes]:
        """The frames since the last call, oldest first (a bounded number: the newest)."""

    def close(self) -> None: ...


class OutputPort(Protocol):
    sent: int
    errors: int

    def send(self, out: TickOutput, t: float) -> None:
        """Encode and send one tick's output; never blocks, never raises for the transport."""

    def close(self) -> None: ...
