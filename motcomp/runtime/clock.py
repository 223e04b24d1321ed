"""Absolute-deadline pacing: the one place that reads the clock in the loop.

``time.sleep()`` until shortly before the deadline, then spin on ``perf_counter_ns``.  The
clock sets its thread's timer slack to :data:`TIMER_SLACK_NS` (``prctl(PR_SET_TIMERSLACK)``, no
privilege needed): with the kernel's default of 50 us for a normal thread a sleep ends up to
50 us late, and the spin before the deadline then never happens; with 1 us a sleep ends as late
as the machine wakes a thread (15-70 us on a virtual machine), and the spin absorbs the rest.
How long before the deadline the sleep ends is learned (:class:`SleepLead`): the
:data:`LEAD_QUANTILE` quantile of the sleeps' own lateness, at most ``spin_us`` -- so the loop
spins only as long as this machine's wake-ups need, and is on time at that share of its ticks.
Deadlines are absolute (``t0 + k * period``), so errors do not accumulate; a late tick is
counted as missed periods and the schedule skips ahead instead of catching up in a burst.

``sleep_max_us`` (0 by default: one sleep) cuts the sleep into naps.  On a virtual machine a
virtual CPU that stays idle longer than the hypervisor's halt-polling window (KVM: 200 us by
default) is given back to the host, and under load on the host it can come back milliseconds
late; naps shorter than the window keep it, at a price: measured here, the clock alone at 1 kHz
takes 2-4 % of a core in one sleep and 14-22 % in naps of 100 us (docs/BENCHMARKS.md).  Use
naps where the host probe (:mod:`motcomp.runtime.probe`) shows such stalls.

Each missed deadline is also attributed: the clock reads its thread's *run delay* (Linux
``/proc/thread-self/schedstat``: the time the thread was runnable but waiting for a CPU) at
every tick, and of the periods missed at a late tick it counts as *waiting for a CPU* those
that this wait accounts for (:attr:`DeadlineClock.missed_waiting`).  A loop kept from its CPU by
other threads is the host's doing; the other misses are the loop's own work, a lock it waited
for, or the machine stopping it outright (a virtual CPU the hypervisor took: the host probe,
:mod:`motcomp.runtime.probe`, sees those) -- docs/DEPLOYMENT.md, "Missed deadlines".
"""

from __future__ import annotations

import gc
import os
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["DEGRADED_MISSED_SHARE", "INPUT_GRACE", "LEAD_QUANTILE", "TIMER_SLACK_NS",
           "WATCH_STEP_NS", "DeadlineClock", "SleepLead", "frozen_heap", "run_delay_reader",
           "set_timer_slack", "sleep_until"]

TIMER_SLACK_NS = 1000
"""Timer slack of the thread that waits (ns): how late the kernel may end its sleeps."""
LEAD_QUANTILE = 0.9
"""The share of a waiting thread's sleeps that end before their deadline (:class:`SleepLead`)."""
LEAD_STEP_NS = 1000
"""How fast :class:`SleepLead` follows its quantile (ns a sleep, at most)."""
WATCH_STEP_NS = 10_000
"""How fast the input-synchronous wait's watch follows its quantile (ns a tick, at most):
from half a period of 1 kHz to the transport's spread in about half a second."""

DEGRADED_MISSED_SHARE = 0.02
"""A loop that missed more than this share of its deadlines over a stretch is degraded there:
the service logs it (a WARNING, at most one a minute while it lasts; its status' ``deadlines``
counts every window) and an identification of
that stretch warns (docs/DEPLOYMENT.md, docs/IDENTIFICATION.md)."""
INPUT_GRACE = 25
"""Input-synchronous mode: after a tick on an input, the own clock waits this percentage of a
period beyond the period for the next input before it ticks without one."""


@contextmanager
def frozen_heap() -> Iterator[None]:
    """While a deadline loop runs: collect once, then keep every object alive at the start out
    of the cyclic collector's reach (``gc.freeze``; ``gc.unfreeze`` at the end), so that its
    full collections scan only what the loop allocates -- one full collection of a process'
    imports holds the interpreter for tens of milliseconds on a loaded host, whichever thread
    runs it (docs/REPLAY.md, "Real time").  The freeze is the process'."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def set_timer_slack(ns: int) -> bool:
    """The calling thread's timer slack (Linux ``prctl(PR_SET_TIMERSLACK)``); False where it
    cannot be set (another OS)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0) == 0)
    except (OSError, AttributeError):
        return False


class SleepLead:
    """How long before a deadline a waiting thread's sleep should end: a running estimate of
    the :data:`LEAD_QUANTILE` quantile of its sleeps' lateness (the time from the instant a
    sleep was asked to end to the instant the thread ran again), at most ``max_ns``.

    Each lateness moves the estimate by at most :data:`LEAD_STEP_NS` -- up by that times the
    quantile when the lateness exceeds it, down by that times its complement otherwise -- so it
    settles where that share of the sleeps end before it and one stall moves it by a step.  It
    starts at ``max_ns`` and never exceeds it, so after any stretch of late sleeps it comes
    down again within ``max_ns`` / (step x (1 - quantile)) sleeps that end on time."""

    __slots__ = ("_down", "_q", "_up", "max_ns", "ns")

    def __init__(self, max_ns: int, step_ns: int = LEAD_STEP_NS) -> None:
        self.max_ns = max(0, int(max_ns))
        self._q = self.max_ns
        self.ns = self.max_ns
        self._up = round(step_ns * LEAD_QUANTILE)
        self._down = round(step_ns * (1 - LEAD_QUANTILE))

    def learn(self, late_ns: int) -> None:
        self.learn_exceeded(late_ns > self._q)

    def learn_exceeded(self, exceeded: bool) -> None:
        """One sample, told only whether it exceeded the estimate."""
        if exceeded:
            self._q = min(self._q + self._up, self.max_ns)
        else:
            self._q = max(0, self._q - self._down)
        self.ns = self._q


def sleep_until(due_ns: int, lead: SleepLead, nap_ns: int = 0,
                clock: Callable[[], int] = time.perf_counter_ns) -> None:
    """Sleep until ``lead.ns`` before ``due_ns`` on ``clock`` -- in one sleep, or in naps of at
    most ``nap_ns`` if > 0 --, then spin until ``due_ns``; ``lead`` learns how late the sleep
    ended.  The sleeps end within the calling thread's timer slack (:func:`set_timer_slack`)
    after the machine wakes the thread."""
    wake = due_ns - lead.ns
    slept = False
    while (rest := wake - clock()) > 0:
        time.sleep((nap_ns if 0 < nap_ns < rest else rest) / 1e9)
        slept = True
    if slept:
        lead.learn(-rest)
    while clock() < due_ns:
        pass


def run_delay_reader() -> Callable[[], int] | None:
    """A function returning the calling thread's run delay so far (ns: time runnable but not
    running, ``/proc/thread-self/schedstat``'s second field), or None where the kernel does
    not account it.  The file stays open until the function is collected."""
    try:
        fd = os.open(f"/proc/self/task/{threading.get_native_id()}/schedstat", os.O_RDONLY)
    except OSError:
        return None

    def read() -> int:
        return int(os.pread(fd, 64, 0).split()[1])

    try:
        read()
    except (OSError, IndexError, ValueError):
        os.close(fd)
        return None
    weakref.finalize(read, os.close, fd)
    return read


class DeadlineClock:
    """Paces a loop at ``rate_hz``.

    ``wait()`` blocks until the next deadline and returns ``(deadline_ns, now_ns)``;
    :attr:`missed` counts the periods skipped because a tick overran, and :attr:`skipped` the
    deadlines skipped just before the one returned (so the caller can account for them).  With
    ``poll`` (input-synchronous mode, :meth:`wait_or_poll`) the wait also ends early, at least
    half a period after the last tick, when ``poll()`` returns True; it is called from
    :attr:`watch` before the input is expected, every ``poll_us``.  :attr:`lead` says how long
    before a deadline ``wait()``'s sleep ends (learned, at most ``spin_us``).

    :attr:`missed_waiting` is the part of :attr:`missed` that the thread's wait for a CPU
    accounts for (None without ``run_delay``): at a tick ``L`` late after a wait ``W`` for a CPU
    since the tick before, the periods that a tick ``L - W`` late would still have missed are
    the loop's own, the others the host's.  ``run_delay`` (ns so far) is the waiting thread's;
    by default the creating thread's (:func:`run_delay_reader`).
    """

    def __init__(self, rate_hz: float, spin_us: float = 50.0,
                 clock: Callable[[], int] = time.perf_counter_ns,
                 sleep_max_us: float = 0.0,
                 run_delay: Callable[[], int] | None = None) -> None:
        set_timer_slack(TIMER_SLACK_NS)
        self.period_ns = round(1e9 / rate_hz)
        self.spin_ns = int(spin_us * 1000)
        self.lead = SleepLead(self.spin_ns)
        self.watch = SleepLead(self.period_ns // 2, WATCH_STEP_NS)
        self._landed = False
        self.nap_ns = int(sleep_max_us * 1000)
        self._clock = clock
        self.start_ns = clock()
        self.next_ns = self.start_ns + self.period_ns
        self.missed = 0
        self.skipped = 0
        self._skip_next = 0
        self.ticks = 0
        self._last_tick_ns = self.start_ns
        self._grace_ns = 0
        self._run_delay = run_delay or run_delay_reader()
        self._waited_ns = self._run_delay() if self._run_delay else 0
        self.missed_waiting: int | None = 0 if self._run_delay else None

    def wait(self) -> tuple[int, int]:
        deadline = self.next_ns
        sleep_until(deadline, self.lead, self.nap_ns, self._clock)
        return self._advance(deadline)

    def wait_or_poll(self, poll: Callable[[], bool], poll_us: float) -> tuple[int, int, bool]:
        """Like :meth:`wait`, but tick early when ``poll()`` says an input has arrived.

        Returns ``(deadline_ns, now_ns, polled)``; after an early tick the schedule is re-phased
        to it, so a source at the loop rate drives the loop: the next input is expected a period
        later, and the own clock waits :data:`INPUT_GRACE` of a period more for it before it
        ticks without (a frame a few microseconds late would otherwise cost an extra tick on
        stale input, and another half a period later on the frame).

        The wait sleeps until it watches, then polls every ``poll_us`` until ``spin_us`` before
        the input is expected, and from there without sleeping, as :meth:`wait` spins: the
        input is seen as it lands.  After a tick on an input seen landing, it watches from
        :attr:`watch` before the next one is expected; after any other tick (the own clock's,
        or on an input found waiting) from half a period after it, as at the start.
        :attr:`watch` is learned as :class:`SleepLead` learns its lead, from whether the input
        was already there when the watch began: it settles where that holds at
        1 - :data:`LEAD_QUANTILE` of the ticks (those inputs are taken when the watch begins),
        so a loop driven by a steady source wakes about once a period instead of polling half
        of it.  It starts at half a period, and moves by at most :data:`WATCH_STEP_NS` a tick.
        """
        clock = self._clock
        deadline = self.next_ns
        expected = deadline - self._grace_ns
        earliest = self._last_tick_ns + self.period_ns // 2
        spin_at = expected - self.spin_ns
        step = poll_us / 1e6
        # the watch holds where the last tick was an input's landing (its instant the input's);
        # after any other tick the input's instant is not known: watch from half a period
        anchored = self._landed
        watch_at = max(earliest, expected - self.watch.ns) if anchored else earliest
        learn = False
        if (rest := watch_at - clock()) > 0:
            time.sleep(rest / 1e9)
            learn = anchored
        first = True
        while True:
            now = clock()
            if now >= earliest:
                arrived = poll()
                if first:  # the first look: was the input already there?
                    if learn:
                        self.watch.learn_exceeded(arrived)
                    self._landed = False
                if arrived:
                    self._landed = not first  # seen landing, not found waiting
                    d, n = self._advance(now)
                    self._grace_ns = self.period_ns * INPUT_GRACE // 100
                    self.next_ns += self._grace_ns
                    return d, n, True
                first = False
            if now >= deadline:
                d, n = self._advance(deadline)
                self._grace_ns = 0
                self._landed = False
                return d, n, False
            if now < spin_at:
                time.sleep(min(step, (spin_at - now) / 1e9))

    def _advance(self, deadline: int) -> tuple[int, int]:
        now = self._clock()
        self.ticks += 1
        self._last_tick_ns = now
        self.skipped = self._skip_next
        self._skip_next = 0
        nxt = deadline + self.period_ns
        waited = 0
        if self._run_delay is not None:
            total = self._run_delay()
            waited, self._waited_ns = total - self._waited_ns, total
        if now >= nxt:  # overran one or more whole periods: skip them, do not burst
            skipped = int((now - deadline) // self.period_ns)
            self.missed += skipped
            if self.missed_waiting is not None:
                own = max(0, int((now - deadline - waited) // self.period_ns))
                self.missed_waiting += skipped - min(own, skipped)
            self._skip_next = skipped
            nxt = deadline + (skipped + 1) * self.period_ns
        self.next_ns = nxt
        return deadline, now
