"""A minimal progress bar on stderr for long offline jobs (no dependency).

Shown only when stderr is a terminal or ``force`` is set; silent with ``quiet``.  Redraws at most
ten times a second.  With ``every_s`` > 0, a stream that is not a terminal (a log file, journald)
gets a plain line at most every ``every_s`` seconds instead.
"""

from __future__ import annotations

import sys
import time
from types import TracebackType
from typing import TextIO

__all__ = ["Progress"]


class Progress:
    """``with Progress("fitting", total=4) as p: ... p.advance()``."""

    def __init__(self, label: str, total: float, quiet: bool = False, force: bool = False,
                 stream: TextIO | None = None, unit: str = "", every_s: float = 0.0) -> None:
        self.label = label
        self.total = max(float(total), 1e-12)
        self.done = 0.0
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = not quiet and (force or self.stream.isatty())
        self.every_s = every_s if not quiet and not self.enabled else 0.0
        self._last = 0.0
        self._t0 = time.monotonic()
        self._last_line = self._t0

    def __enter__(self) -> Progress:
        self._draw(force=True)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.done = self.total
        self._draw(force=True, final=True)

    def advance(self, amount: float = 1.0, note: str = "") -> None:
        self.done = min(self.done + amount, self.total)
        self._draw(note=note)

    def update(self, done: float, note: str = "") -> None:
        self.done = min(max(done, 0.0), self.total)
        self._draw(note=note)

    def _draw(self, force: bool = False, final: bool = False, note: str = "") -> None:
        if self.every_s > 0:
            self._line(final, note)
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        frac = self.done / self.total
        width = 30
        filled = round(frac * width)
        bar = "#" * filled + "-" * (width - filled)
        elapsed = now - self._t0
        text = f"\r{self.label:<18} [{bar}] {frac * 100:5.1f}% {elapsed:6.1f}s {note}"
        self.stream.write(text[:120].ljust(100))
        if final:
            self.stream.write("\n")
        self.stream.flush()

    def _line(self, final: bool, note: str) -> None:
        now = time.monotonic()
        if final or now - self._last_line < self.every_s:
            return
        self._last_line = now
        unit = f" {self.unit}" if self.unit else ""
        self.stream.write(f"{self.label}: {self.done:.1f} of {self.total:.1f}{unit} "
                          f"({self.done / self.total * 100:.0f} %) after {now - self._t0:.0f} s"
                          f"{' ' + note if note else ''}\n")
        self.stream.flush()
