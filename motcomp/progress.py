"""A minimal progress bar on stderr for long jobs (no dependency).

On a terminal (or with ``force``): a bar redrawn at most ten times a second.  On a stream that
is not a terminal (a log file, journald, CI): a plain line every ``every_s`` seconds
(:data:`PLAIN_EVERY_S` by default) while the job runs, from a thread of its own, so that even a
step that reports nothing in between is never silent; and, if it said anything, one line when
it ends, with its duration.  A job shorter than ``every_s`` prints nothing there.  Nothing at
all with ``quiet``.
"""

from __future__ import annotations

import sys
import threading
import time
from types import TracebackType
from typing import TextIO

__all__ = ["PLAIN_EVERY_S", "Progress"]

PLAIN_EVERY_S = 10.0
"""Plain progress lines come at most this often on a stream that is not a terminal."""


class Progress:
    """``with Progress("fitting", total=4) as p: ... p.advance()``."""

    def __init__(self, label: str, total: float, quiet: bool = False, force: bool = False,
                 stream: TextIO | None = None, unit: str = "",
                 every_s: float = PLAIN_EVERY_S) -> None:
        self.label = label
        self.total = max(float(total), 1e-12)
        self.done = 0.0
        self.note = ""
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = not quiet and (force or self.stream.isatty())
        self.plain = not quiet and not self.enabled and every_s > 0
        self.every_s = every_s
        self._last = 0.0
        self._t0 = time.monotonic()
        self._said = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> Progress:
        self._t0 = time.monotonic()
        if self.plain:
            self._thread = threading.Thread(target=self._lines, name="progress", daemon=True)
            self._thread.start()
        else:
            self._draw(force=True)
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.done = self.total
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            if self._said:
                how = "done" if exc_type is None else "stopped"
                self._write(f"{self.label}: {how} after {time.monotonic() - self._t0:.1f} s")
        self._draw(force=True, final=True)

    def advance(self, amount: float = 1.0, note: str = "") -> None:
        self.done = min(self.done + amount, self.total)
        self.note = note
        self._draw(note=note)

    def update(self, done: float, note: str = "") -> None:
        self.done = min(max(done, 0.0), self.total)
        self.note = note
        self._draw(note=note)

    def _draw(self, force: bool = False, final: bool = False, note: str = "") -> None:
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

    def _lines(self) -> None:
        """The plain lines' thread: one line every ``every_s`` until the job ends."""
        while not self._stop.wait(self.every_s):
            unit = f" {self.unit}" if self.unit else ""
            note = f" {self.note}" if self.note else ""
            self._write(f"{self.label}: {self.done:.1f} of {self.total:.1f}{unit} "
                        f"({self.done / self.total * 100:.0f} %) after "
                        f"{time.monotonic() - self._t0:.0f} s{note}")
            self._said = True

    def _write(self, line: str) -> None:
        try:
            self.stream.write(line + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # a closed stream: the job goes on
            pass
