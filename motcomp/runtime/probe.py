"""The host's own deadline misses: a bare loop clock in a child process, run beside a session.

A real-time figure (a delay, the command's smoothness) says something about motcomp only if the
host could hold the loop's rate while it was measured.  :class:`HostProbe` runs the loop's clock
(:class:`~motcomp.runtime.clock.DeadlineClock`, the config's loop settings, no work, no I/O) in
a process of its own for as long as its ``with`` block lasts, and returns what the machine
itself imposed on it: deadlines missed, lateness percentiles, the longest stall.  A test or a
benchmark then judges its real-time figures only if :meth:`HostClock.holds`, and otherwise
reports them as not judged, with these figures (docs/TESTING.md).

The probe costs what the loop's clock costs: its spin before each deadline (at most
``spin_us`` of each period) and its naps.  ``python -m motcomp.runtime.probe RATE SPIN_US
SLEEP_MAX_US`` runs it until SIGTERM and prints one JSON line.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import numpy as np

from motcomp.errors import ServiceError

__all__ = ["MAX_MISSED_SHARE", "MAX_STALL_MS", "HostClock", "HostProbe", "loop_kept_from_cpu",
           "measure_clock"]

MAX_MISSED_SHARE = 0.05
"""The host holds a 1 kHz loop if its bare clock missed at most this share of the deadlines
(measured on 2 cores: alone on a quiet host 0-0.03 %; beside the demo's four processes, which
the test itself runs, 0.6 %) ..."""
MAX_STALL_MS = 50.0
"""... and never stalled it longer than this (the service's default ``stale_after_s``: a
longer stall holds the reference, which no real-time figure survives)."""


@dataclass(frozen=True)
class HostClock:
    """What the bare clock met: ``ticks`` it ran, deadlines ``missed``, lateness (us)."""

    ticks: int
    missed: int
    late_p99_us: float
    late_p999_us: float
    late_max_us: float

    @property
    def missed_share(self) -> float:
        total = self.ticks + self.missed
        return self.missed / total if total else math.nan

    def holds(self) -> bool:
        """The host held the loop rate (:data:`MAX_MISSED_SHARE`, :data:`MAX_STALL_MS`)."""
        return (self.ticks > 0 and self.missed_share <= MAX_MISSED_SHARE
                and self.late_max_us <= MAX_STALL_MS * 1e3)

    def describe(self) -> str:
        return (f"the host's bare loop clock missed {self.missed} of {self.ticks + self.missed} "
                f"deadlines ({100 * self.missed_share:.2f} %; a host that holds the rate: <= "
                f"{100 * MAX_MISSED_SHARE:g} %), lateness p99 {self.late_p99_us:.0f} us, "
                f"p99.9 {self.late_p999_us:.0f} us, longest {self.late_max_us / 1e3:.1f} ms "
                f"(<= {MAX_STALL_MS:g} ms)")


def loop_kept_from_cpu(status: Mapping[str, Any], since: Mapping[str, Any] | None = None
                       ) -> str | None:
    """Why the host did not hold the rate of a service's loop or of its platform's, from the
    service's status (counts since start; with ``since``, an earlier status of the same
    service, the deadlines between the two), or None if it held both or the status cannot tell:
    the loop missed more than :data:`MAX_MISSED_SHARE` of its deadlines while it waited for a
    CPU that other threads held (``missed_waiting_cpu``,
    :attr:`motcomp.runtime.clock.DeadlineClock.missed_waiting`), or the platform's loop did
    (the same figures in the status' ``platform`` block, where the platform reports them, as
    ``motcomp hil`` does).

    The bare clock of :class:`HostProbe` needs next to no CPU, so a scheduler that shares a
    saturated CPU fairly still gives it its deadlines; a loop that needs a third of a CPU then
    waits.  Misses of a loop's own (its work, a lock) do not count here."""
    before = since or {}
    for who, counts, base in (
            ("the service's loop", status, before),
            ("the platform's loop", status.get("platform") or {}, before.get("platform") or {})):
        waiting = counts.get("missed_waiting_cpu")
        if waiting is not None:
            waiting -= base.get("missed_waiting_cpu") or 0
        missed = int(counts.get("missed_ticks") or 0) - int(base.get("missed_ticks") or 0)
        due = int(counts.get("ticks") or 0) - int(base.get("ticks") or 0) + missed
        if waiting is not None and due > 0 and waiting > MAX_MISSED_SHARE * due:
            return (f"{who} missed {waiting:g} of {due} deadlines ({100 * waiting / due:.1f} %)"
                    f" waiting for a CPU that other threads held (a host that holds the rate: "
                    f"<= {100 * MAX_MISSED_SHARE:g} %; {missed} missed in all)")
    return None


class HostProbe:
    """``with HostProbe(rate_hz, spin_us, sleep_max_us) as probe: ...``; then ``probe.result``
    (:class:`HostClock`).

    Raises
    ------
    ServiceError
        On exit, if the probe process failed or printed no result.
    """

    def __init__(self, rate_hz: float = 1000.0, spin_us: float = 50.0,
                 sleep_max_us: float = 0.0) -> None:
        self.args = [str(rate_hz), str(spin_us), str(sleep_max_us)]
        self._proc: subprocess.Popen[str] | None = None
        self.result: HostClock | None = None

    def __enter__(self) -> HostProbe:
        self._proc = subprocess.Popen([sys.executable, "-m", "motcomp.runtime.probe", *self.args],
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self._proc.stdout.readline() if self._proc.stdout else ""
        if line.strip() != "ready":
            self._proc.kill()
            raise ServiceError(f"host probe did not start: {line!r} "
                               f"{self._proc.stderr.read() if self._proc.stderr else ''}")
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        proc = self._proc
        assert proc is not None
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
        if kind is not None:
            return
        try:
            self.result = HostClock(**json.loads(out))
        except (ValueError, TypeError) as e:
            raise ServiceError(f"host probe exited {proc.returncode} without a result: "
                               f"{out!r} {err[-500:]!r}") from e


def measure_clock(rate_hz: float, spin_us: float, sleep_max_us: float,
                  ticks: int | None = None, stop: threading.Event | None = None) -> HostClock:
    """The loop's clock alone (sleep, then spin to each deadline; no work, no I/O) for
    ``ticks`` deadlines or until ``stop`` is set, in the calling thread: what the machine
    itself imposes on a loop scheduled as this thread is (``tools/bench_service.py`` schedules
    it as the service's loop first)."""
    from motcomp.runtime.clock import DeadlineClock

    late: list[int] = []
    clock = DeadlineClock(rate_hz, spin_us, sleep_max_us=sleep_max_us)
    while not (stop is not None and stop.is_set()) and (ticks is None or len(late) < ticks):
        deadline, now = clock.wait()
        late.append(now - deadline)
    a = np.asarray(late, dtype=float) / 1e3 if late else np.zeros(1)
    return HostClock(clock.ticks, clock.missed, float(np.percentile(a, 99)),
                     float(np.percentile(a, 99.9)), float(a.max()))


def _main(rate_hz: float, spin_us: float, sleep_max_us: float) -> None:
    """The probe's process: the bare clock until SIGTERM, then its result as one JSON line."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print("ready", flush=True)
    r = measure_clock(rate_hz, spin_us, sleep_max_us, stop=stop)
    print(json.dumps(r.__dict__), flush=True)


if __name__ == "__main__":
    _main(*(float(x) for x in sys.argv[1:4]))
