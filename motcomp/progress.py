"""A minimal progress bar on stderr for long jobs (no dependency).

On a terminal (or with ``force``): a bar redrawn at most ten times a second.  On a stream that
is not a terminal (a log file, journald, CI): a plain line every ``every_s`` seconds
(:data:`PLAIN_EVERY_S` by default) while the job runs, from a thread of its own, so that even a
step that reports nothing in between is never silent; and, if it said anything, one line when
it ends, with its duration.  A job shorter than ``every_s`` prints nothing there.  Nothing at
all with ``quiet``.

:class:`Stages` turns a job of several stages (each reporting its own ``done of total``) into
one progress: the stage's name and number, its own progress, and the whole job's share done,
from the stages' estimated weights.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TextIO

__all__ = ["PLAIN_EVERY_S", "Progress", "ProgressCallback", "Stages"]

ProgressCallback = Callable[[float, float, str], None]
"""``callback(done, total, note)``: how far a job got, and what it is doing."""

PLAIN_EVERY_S = 10.0
"""Plain progress lines come at most this often on a stream that is not a terminal."""


class Progress:
    """``with Progress("fitting", total=4) as p: ... p.advance()``."""

    def __init__(self, label: str, total: float, quiet: bool = False, force: bool = False,
                 stream: TextIO | None = None, unit: str = "",
                 every_s: float = PLAIN_EVERY_S, counts: bool = True) -> None:
        self.label = label
        self.counts = counts  # False: the share done only (weights, not counts of anything)
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
        self._interrupted = False
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
        if exc_type is None and not self._interrupted:
            self.done = self.total
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            if self._said:
                how = "done" if exc_type is None and not self._interrupted else "stopped"
                self._write(f"{self.label}: {how} after {time.monotonic() - self._t0:.1f} s")
        self._draw(force=True, final=True)

    def interrupted(self) -> None:
        """The job ended before its end without raising (a signal it handled): the last line
        says "stopped", and the bar stays where it was."""
        self._interrupted = True

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
        columns = max(shutil.get_terminal_size((120, 24)).columns - 1, 40)
        width = 30 if columns >= 120 else 20
        filled = round(frac * width)
        bar = "#" * filled + "-" * (width - filled)
        elapsed = now - self._t0
        text = f"{self.label:<18} [{bar}] {frac * 100:5.1f}% {elapsed:6.1f}s {note}"
        self.stream.write("\r" + text[:columns].ljust(columns))
        if final:
            self.stream.write("\n")
        self.stream.flush()

    def _lines(self) -> None:
        """The plain lines' thread: one line every ``every_s`` until the job ends."""
        while not self._stop.wait(self.every_s):
            unit = f" {self.unit}" if self.unit else ""
            note = f" {self.note}" if self.note else ""
            share = f"{self.done / self.total * 100:.0f} %"
            head = f"{self.done:.1f} of {self.total:.1f}{unit} ({share})" if self.counts \
                else share
            self._write(f"{self.label}: {head} after {time.monotonic() - self._t0:.0f} s{note}")
            self._said = True

    def _write(self, line: str) -> None:
        try:
            self.stream.write(line + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # a closed stream: the job goes on
            pass


class Stages:
    """One progress for a job of stages: ``Stages(report, [("optimising the PID", 1.0),
    ("designing the prefilter", 3.0)])``, then ``stages.start("designing the prefilter")``
    returns the ``(done, total, note)`` callback of that stage (or None without ``report``).

    ``report(done, total, note)`` receives the share of the job done in weight units (the
    finished stages' weights plus the running one's share of its own) and a note such as
    ``stage 2 of 3, designing the prefilter: 4 of 14, 0.912 ms met``.  :meth:`plan` replaces the
    stages still to come when what remains becomes known; the share done never goes back.
    """

    def __init__(self, report: ProgressCallback | None,
                 plan: Sequence[tuple[str, float]]) -> None:
        self.report = report
        self.stages: list[tuple[str, float]] = list(plan)
        self.index = -1
        self.done = 0.0  # the weight of the finished stages
        self._shown = 0.0

    def plan(self, remaining: Sequence[tuple[str, float]]) -> None:
        """The stages after the running one are ``remaining``."""
        self.stages = self.stages[: self.index + 1] + list(remaining)

    def start(self, name: str, weight: float | None = None
              ) -> Callable[[int, int, str], None] | None:
        """Finish the running stage and start ``name`` (the next planned one, or a new one of
        ``weight``)."""
        if self.index >= 0:
            self.done += self.stages[self.index][1]
        self.index += 1
        if self.index < len(self.stages) and self.stages[self.index][0] == name:
            if weight is not None:
                self.stages[self.index] = (name, weight)
        else:
            self.stages.insert(self.index, (name, 1.0 if weight is None else weight))
        self._emit(0.0, "")
        if self.report is None:
            return None

        def update(done: int, total: int, note: str) -> None:
            frac = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
            self._emit(frac, f": {done} of {total}, {note}" if note else f": {done} of {total}")

        return update

    def _emit(self, frac: float, detail: str) -> None:
        if self.report is None:
            return
        name, weight = self.stages[self.index]
        total = sum(w for _, w in self.stages)
        self._shown = max(self._shown, self.done + frac * weight)
        self.report(min(self._shown, total), total,
                    f"stage {self.index + 1} of {len(self.stages)}, {name}{detail}")
