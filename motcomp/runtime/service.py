"""The real-time compensator service: ``motcomp run``.

Lifecycle::

    start    read config -> open zenoh (before any real-time priority) -> declare input
             subscriber, output publisher(s), status publisher and queryables -> CAN bus if
             configured -> build the compensator at neutral
    loop     a thread at a fixed rate on absolute deadlines (a short scheduler slice, or
             optionally SCHED_FIFO; optionally pinned),
             the heap frozen while it runs (frozen_heap); each tick: apply queued commands,
             take the newest input frame (never blocks), run :func:`motcomp.core.tick.step` on
             it (validation, reference, catch-up, compensator, verdict: the whole per-tick
             policy), send the
             output on every port; count, never log
    main     the main thread: signals, status at 1 Hz (and on query, from a copy at most
             STATUS_MAX_AGE_S old), the systemd watchdog (only while the loop ticks), the
             motion-quality figures (:mod:`motcomp.runtime.monitor`: the loop records r and u
             per tick, the feedback subscriber queues each frame with its arrival instant, the
             main thread decodes and estimates when it builds the status); admin requests and
             SIGHUP are handed to the admin worker, or answered ``busy`` at once
    admin    one worker thread: reloads, profile switches, bypass toggles, from a queue of at
             most ADMIN_QUEUE requests, started at most ADMIN_RATE_HZ a second
    stop     SIGTERM/SIGINT -> park (ramp to neutral within the limits) -> exit 0; exit 1 if
             parking did not finish within park_timeout_s.  The loop thread parks on its own:
             the stop never waits for the admin worker (a reload being read, a queue)

Everything the loop needs from the outside world comes through two non-blocking doors: the
input source's ``drain()`` and a command queue (a deque: appends and pops are atomic) through
which the main thread hands it closures to run between two ticks -- bypass toggles and config
swaps.  The loop thread is the only one that touches the tick's state.  Reloads are validated
in the admin worker (:mod:`motcomp.runtime.reload`) and swapped in by :meth:`Service.apply_config`.

The loop comes first: the interpreter's switch interval is set to SWITCH_INTERVAL_S, so that a
loop thread waking at its deadline gets the interpreter lock within that time from a thread
parsing a config or building a status (the default, 5 ms, cost several ticks each time).
Measured cost of admin work to the loop: docs/BENCHMARKS.md ("admin").
"""

from __future__ import annotations

import logging
import math
import os
import queue
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import msgpack

from motcomp import __version__
from motcomp.config import (
    SUPERVISION_PERIOD_MAX_S,
    ServiceConfig,
    config_hash,
    config_sources,
    new_tick,
    resolve_axes,
)
from motcomp.core import native
from motcomp.core.axes import AXES
from motcomp.core.tick import (
    MAX_ERROR_CHARS,
    TickParams,
    TickState,
    is_parked,
    park,
    prediction_status,
    set_bypass,
    step,
)
from motcomp.errors import ConfigError, MotcompError, ServiceError
from motcomp.io.ports import InputPort, OutputPort
from motcomp.io.zenoh_io import ZenohEndpoints, ZenohSink, ZenohSource, open_session
from motcomp.runtime.clock import DEGRADED_MISSED_SHARE, DeadlineClock, frozen_heap
from motcomp.runtime.confine import Confinement
from motcomp.runtime.monitor import (
    BIN_S,
    COMMAND_WINDOW_S,
    FEEDBACK_STALE_S,
    LAG_RANGE_S,
    MotionMonitor,
    starved_out,
)
from motcomp.runtime.reload import Prepared, Preparer
from motcomp.runtime.rt import schedule_loop
from motcomp.runtime.stats import LoopStats
from motcomp.runtime.supervise import Supervisor
from motcomp.runtime.systemd import Notifier

__all__ = ["DegradedLog", "Service"]

log = logging.getLogger("motcomp.service")

STAT_SERIES = ("tick", "compute", "io", "late")
"""What the loop times, per tick (us): ``tick`` from waking at the deadline to the end of the
tick; ``io`` the part of it spent in the ports (taking the newest input; encoding and sending
the outputs); ``compute`` the rest (commands, :func:`motcomp.core.tick.step`: catch-up steps,
validation, reference, compensator, saturation verdicts); ``late`` waking after the deadline."""


ENVELOPE_LOG_S = 10.0
"""The envelope guard's actions are logged (ERROR) at most this often, with their count."""
PLATFORM_FIGURES = ("setpoint_age_ms", "setpoint_age_mean_ms", "ticks", "missed_ticks",
                    "missed_waiting_cpu")
"""The numbers the service takes from the platform's status frames (docs/WIRE.md) ..."""
MAX_PLATFORM_STATUS_BYTES = 65536
"""... of at most this size (a larger frame is not decoded)."""
DEADLINE_WINDOW_S = 10.0
"""The status' ``deadlines`` block counts the deadlines missed over windows this long; one
with more than :data:`~motcomp.runtime.clock.DEGRADED_MISSED_SHARE` of them missed is logged
at WARNING (:class:`DegradedLog`)."""
REPEAT_WARNING_S = 60.0
"""A WARNING about a condition that goes on or comes back is repeated at most this often: the
degraded deadline windows (:class:`DegradedLog`, which counts those not logged) and the loss of
the platform's feedback (a loss within this of the last warning is logged at DEBUG)."""


class DegradedLog:
    """Which degraded deadline windows are logged: the first at once, then at most one a
    :data:`REPEAT_WARNING_S` while they go on, saying how many were not logged in between;
    and, when a window holds again after unlogged ones, one line saying so.  A host that
    starves the loop for an hour logs 60 lines, not 360; the status counts every window."""

    def __init__(self) -> None:
        self.logged_at = -math.inf
        self.unlogged = 0

    def window(self, degraded: bool, now: float) -> tuple[str, int] | None:
        """``("warning" | "kept", unlogged windows before it)`` to log for a window closed at
        ``now`` (monotonic s), or None."""
        if degraded:
            if now - self.logged_at < REPEAT_WARNING_S:
                self.unlogged += 1
                return None
            before, self.unlogged, self.logged_at = self.unlogged, 0, now
            return "warning", before
        before, self.unlogged, self.logged_at = self.unlogged, 0, -math.inf
        return ("kept", before) if before else None


def _hand_over() -> None:
    """Between two axes of the motion-quality figures: sleep briefly, so that a loop thread
    waiting for the interpreter lock takes it now rather than at the end of the switch interval
    (:data:`SWITCH_INTERVAL_S` while the service runs)."""
    time.sleep(0.0002)


class ModeLog:
    """Logs the loop's mode switches (start-up, running, stale, rejoin, parking) with their
    reasons, from the main thread: the loop itself counts and never logs.  Polled every 20 ms;
    switches between two polls are counted (``stale_episodes``), and said at the next one."""

    def __init__(self, state: TickState) -> None:
        self.mode = state.mode
        self.episodes = state.shaper.stale_episodes
        self.waiting = False
        """No input frame yet, since the start-up went stale."""

    def update(self, state: TickState, p: TickParams) -> None:
        mode, episodes = state.mode, state.shaper.stale_episodes
        if mode == self.mode and episodes == self.episodes:
            return
        if episodes > self.episodes and mode != "stale":
            log.warning("input was stale %d time(s) briefly (no valid frame for %.3f s)",
                        episodes - self.episodes, p.shaper.stale_after_s)
        if mode == "stale" and state.received == 0:  # nothing yet: a sender not started
            log.info("waiting for input: no frame received yet, holding the start position "
                     "(the input goes stale after %.3f s without a valid frame once it runs)",
                     p.shaper.stale_after_s)
        elif mode == "stale":
            log.warning("input stale: no valid frame for %.3f s (%d received, %d rejected, "
                        "last rejection: %s); holding %.2f s, then ramping to neutral",
                        p.shaper.stale_after_s, state.received, state.rejected,
                        state.last_reject or "none", p.shaper.hold_s)
        elif mode == "rejoin":
            log.info("input %s: blending to the live input over at least %.2f s",
                     "started" if self.mode == "startup" or self.waiting else "resumed",
                     state.shaper.blend_s)
        elif mode == "parking":
            log.info("stop requested: parking (ramping every axis to neutral)")
        elif mode == "running" and self.mode != "startup":
            log.info("running on live input")
        self.mode, self.episodes = mode, episodes
        self.waiting = mode == "stale" and state.received == 0


FEEDBACK_RING = 256
"""Feedback frames kept between two polls of the main thread (every 20 ms)."""
QUERY_CHANNEL = 1024
"""Status and admin queries kept between two polls of the main thread; beyond, a burst's oldest
are dropped (their askers get no reply) rather than held: a full FIFO would hold up zenoh's
thread, and with it the input and the output."""
QUERIES_PER_POLL = 64
"""Status queries, and admin queries, taken from their channels per poll (every 20 ms): a burst
is answered over several polls, the main thread never holds the interpreter long."""
ADMIN_QUEUE = 16
"""Admin requests waiting for the worker; one more is answered ``{"ok": False, "error":
"busy"}`` at once."""
ADMIN_RATE_HZ = 10.0
"""The admin worker starts at most this many requests a second."""
STATUS_MAX_AGE_S = 0.1
"""A status query is answered with a status at most this old (rebuilt after an admin change)."""
BUILD_CHECK_S = 5.0
"""The installed build is looked at (:func:`motcomp.core.native.status`: a few dozen ``stat``
calls, each a hand-over of the interpreter lock) this often, not at each status."""
SWITCH_INTERVAL_S = 0.0002
"""The interpreter's switch interval while the service runs (``sys.setswitchinterval``)."""
RELOADS_KEPT = 10
"""Reload attempts kept for the status."""
BUSY = msgpack.packb({"ok": False, "error": "busy"})
ADMIN_OFF = msgpack.packb({"ok": False, "error": "admin off"})

def _answer(query: Any, key: str, result: dict[str, Any] | bytes) -> None:
    """Reply to an admin query and release it (never raises: the session may be closing)."""
    try:
        query.reply(key, result if isinstance(result, bytes) else msgpack.packb(result))
        query.drop()
    except Exception as exc:  # pragma: no cover - a closed session
        log.debug("admin reply on %s failed: %r", key, exc)


class Service:
    """See the module docstring.  ``run()`` blocks until stopped and returns the exit code."""

    def __init__(self, cfg: ServiceConfig, endpoints: ZenohEndpoints,
                 config_path: Path | None = None) -> None:
        self.cfg = cfg
        self.endpoints = endpoints
        self.config_path = config_path
        """The config in force: the start-up file, then the file of the last accepted
        ``reload --config`` (what SIGHUP and ``reload`` re-read, and the status shows)."""
        self.confinement = self._confine(config_path)
        self.preparer = Preparer()
        self.live_profile: str | None = None
        """The profile an operator chose with ``motcomp profile`` (None: none chosen live):
        a reload of a file that sets no profile keeps it while the file still defines it."""
        self.axes = resolve_axes(cfg)
        for w in self.axes.warnings:
            log.warning("%s", w)
        self.params: TickParams
        self.params, self.state = new_tick(cfg, self.axes)
        self.stats = LoopStats(round(cfg.status.window_s * cfg.loop.rate_hz), STAT_SERIES)
        # the rings also hold what supervision reads between two of its periods, with margin
        self.monitor = MotionMonitor(cfg.loop.rate_hz, cfg.status.window_s,
                                     min_span_s=2.0 * SUPERVISION_PERIOD_MAX_S + 5.0)
        self.supervisor = Supervisor(cfg.supervision, self.axes)
        self.last_tick_mono = 0.0
        self.notifier = Notifier(None)
        self.commands: deque[Callable[[], None]] = deque()
        self.stop_event = threading.Event()
        self.reload_event = threading.Event()
        self.loop_done = threading.Event()
        self.exit_code = 0
        self.config_version = 1
        self.config_id = config_hash(cfg)
        self.reloads: list[dict[str, Any]] = []
        self._deadlines: dict[str, Any] = {"window_s": DEADLINE_WINDOW_S, "due": 0, "missed": 0,
                                           "missed_waiting_cpu": 0, "share": 0.0,
                                           "degraded": False, "windows_degraded": 0}
        """The last closed window's deadlines (:meth:`_judge_deadlines`)."""
        self._deadline_window = (time.monotonic(), 0, 0, 0)
        """The open window's start: instant, ticks, missed and waiting."""
        self._degraded_log = DegradedLog()
        self.rt_report = ""
        self._loop_error: BaseException | None = None
        self._source: InputPort | None = None
        self._ports: list[OutputPort] = []
        self._can: Any = None
        self._clock: DeadlineClock | None = None
        self._t_wall0 = 0.0
        self._t_mono0 = 0
        self.io_ns = 0
        """Time the last :meth:`tick` spent in transport calls (input take, sends)."""
        self._pending: list[bytes] = []
        self._feedback: Any = None  # the feedback subscriber (a ring), polled by _main
        self._fb_warned_ns = -(2**62)  # the last WARNING of a feedback loss (perf clock)
        self._platform_sub: Any = None  # the platform's status (a ring of 1), polled by _main
        self._platform: dict[str, Any] | None = None
        """The platform's own figures from its last status frame (:meth:`_poll_platform`)."""
        self._perf = time.perf_counter_ns
        self._clocked = False
        """The ticks run on the loop's own clock (:meth:`_loop`): input frames are stamped with
        the instant they were taken; with an instant given by a caller (:meth:`attach`), with it."""
        self._admin_q: queue.Queue[tuple[str, Any] | None] = queue.Queue(ADMIN_QUEUE)
        # the packed status: (admin generation, built at, bytes); a cache built before the
        # newest admin change is stale whatever its age
        self._status_cache: tuple[int, float, bytes] | None = None
        self._admin_gen = 0
        self._build = native.status()
        """What runs, and a reinstall since: the status' ``tick`` (every BUILD_CHECK_S)."""

    @staticmethod
    def _confine(path: Path | None) -> Confinement | None:
        """Where reloads may read (see :mod:`motcomp.runtime.confine`): None without a file."""
        if path is None:
            return None
        try:
            files: tuple[Path, ...] = config_sources(path).files
        except MotcompError:  # read at start by the caller; only its directory then
            files = ()
        return Confinement(path, files)

    # --- the loop thread ------------------------------------------------------------------
    def attach(self, source: InputPort, ports: list[OutputPort], *, wall0: float | None = None,
               mono0_ns: int | None = None) -> None:
        """Use these ports (e.g. the in-memory twins of :mod:`motcomp.io.memory`) instead of
        opening transports: then :meth:`tick` can be driven directly with a given time;
        ``wall0``/``mono0_ns`` map tick instants to output ``t`` (see :meth:`tick_clock`)."""
        self._source = source
        self._ports = list(ports)
        if wall0 is not None:
            self._t_wall0 = wall0
        if mono0_ns is not None:
            self._t_mono0 = mono0_ns

    def _poll_input(self) -> bool:
        assert self._source is not None
        frames = self._source.drain()
        if not frames:
            return False
        self._pending.extend(frames)
        return True

    def tick(self, now_ns: int, skipped: int = 0) -> None:
        """One tick at the sample instant ``now_ns`` (the deadline: the reference is evaluated
        on the ideal, uniform time grid the compensator assumes, not at the jittered moment the
        thread woke up), after ``skipped`` missed deadlines."""
        commands = self.commands
        while commands:
            commands.popleft()()
        payload = self._pending
        self._pending = []
        perf = self._perf
        io = 0
        taken = now_ns  # when the frames were taken: on the loop's clock, or the tick's instant
        if self._source is not None:
            t_io = perf()
            payload.extend(self._source.drain())
            t_end = perf()
            io = t_end - t_io
            if self._clocked:
                taken = t_end
        state = self.state
        out = step(state, self.params, now_ns, payload, skipped, taken)
        shaper = state.shaper
        self.monitor.record(now_ns, shaper.played, out.u, round(shaper.played_lag_s * 1e9),
                            not out.mode, state.moving)
        t_wall = self._t_wall0 + (now_ns - self._t_mono0) / 1e9
        t_io = perf()
        for port in self._ports:
            port.send(out, t_wall)
        self.io_ns = io + perf() - t_io

    def _loop(self) -> None:
        with frozen_heap():
            self._run_loop()

    def _run_loop(self) -> None:
        latency_fd: int | None = None
        try:
            loop = self.cfg.loop
            self.rt_report, latency_fd = schedule_loop(loop)
            clock = DeadlineClock(loop.rate_hz, loop.spin_us, sleep_max_us=loop.sleep_max_us)
            self._clock = clock
            self._clocked = True
            self._t_mono0 = time.perf_counter_ns()
            self._t_wall0 = time.time()
            park_deadline: float | None = None
            record = self.stats.record
            perf = time.perf_counter_ns
            while True:
                if loop.sync_to_input:
                    deadline, now, _ = clock.wait_or_poll(self._poll_input, loop.poll_us)
                else:
                    deadline, now = clock.wait()
                self.tick(deadline, clock.skipped)
                tick_ns = perf() - now
                io_ns = self.io_ns
                record(tick_ns / 1e3, (tick_ns - io_ns) / 1e3, io_ns / 1e3,
                       (now - deadline) / 1e3)
                self.last_tick_mono = time.monotonic()
                if self.stop_event.is_set():
                    if park_deadline is None:
                        park(self.state, self.params, now)
                        park_deadline = time.monotonic() + loop.park_timeout_s
                    elif is_parked(self.state):
                        break
                    elif time.monotonic() > park_deadline:
                        log.error("parking did not finish within %.1f s", loop.park_timeout_s)
                        self.exit_code = 1
                        break
        except BaseException as exc:  # pragma: no cover - reported by the main thread
            self._loop_error = exc
            self.exit_code = 1
        finally:
            if latency_fd is not None:
                os.close(latency_fd)
            self.loop_done.set()

    # --- configuration changes (main thread builds, loop thread swaps) ---------------------
    def request_bypass(self, on: bool, axes: list[str] | None = None) -> list[str]:
        """Queue a bumpless bypass change for the given driven axes; returns the axes in bypass
        once the loop applied it.  Bypass on turns the axis' PID and its prediction off.  Bypass
        off gives an axis its prediction back and turns its PID on -- except on an axis whose
        PID the config bypasses while it predicts (a delay-dominated one): there compensation
        is the prediction, and the PID stays bypassed.  Without ``axes``: bypass on for every
        driven axis, bypass off only for the driven axes that the running config compensates
        (by its PID or by prediction)."""
        cfg_axes = self.axes
        names = list(axes) if axes is not None else [
            a for a, d, b, p in zip(AXES, cfg_axes.driven, cfg_axes.bypass, cfg_axes.predict,
                                    strict=True)
            if d and (on or not b or p)]
        unknown = [a for a in names if a not in AXES]
        if unknown:
            raise ConfigError(f"unknown axis {str(unknown[0])[:40]!r}; axes: {', '.join(AXES)}")
        result: list[str] = []
        done = threading.Event()

        def apply() -> None:
            # compensation off: PID and prediction; back on: prediction, and the PID unless
            # the config bypasses it (and predicts, or no axis was named)
            pid = list(self.state.comp.bypass)
            off = list(self.state.prediction_off)
            for i, a in enumerate(AXES):
                if a in names:
                    off[i] = on
                    pid[i] = on or (cfg_axes.bypass[i]
                                    and (axes is None or cfg_axes.predict[i]))
            result.extend(self._set_bypass(pid, off))
            done.set()

        self.run_between_ticks(apply, done, "the bypass change")
        by_prediction = [a for a in names if not on and a in result]
        log.info("bypass %s for %s: compensation %s (admin request)%s", "on" if on else "off",
                 ", ".join(names) or "no axis", "off" if on else "on",
                 f"; {', '.join(by_prediction)}: by prediction alone, the PID bypassed by the "
                 "config" if by_prediction else "")
        return result

    def _set_bypass(self, pid: Sequence[object], off: Sequence[object]) -> list[str]:
        """:func:`set_bypass` (on the loop thread, between ticks), the delay monitor told
        which axes it changed."""
        st = self.state
        before = list(zip(st.comp.bypass, st.prediction_off, strict=True))
        result = set_bypass(st, pid, off)
        after = list(zip(st.comp.bypass, st.prediction_off, strict=True))
        self.monitor.changed(sum(1 << i for i, (was, now) in enumerate(zip(before, after,
                                                                            strict=True))
                                 if was != now))
        return result

    def run_between_ticks(self, fn: Callable[[], None], done: threading.Event, what: str,
                          timeout_s: float = 2.0) -> None:
        """Queue ``fn`` to the loop thread (it runs between two ticks and sets ``done``).

        Raises
        ------
        ServiceError
            If the loop did not run it within ``timeout_s``.
        """
        if self.stop_event.is_set():
            raise ServiceError(f"stopping: {what} was not applied")
        self.commands.append(fn)
        if not done.wait(timeout_s):
            raise ServiceError(f"the loop did not apply {what} within {timeout_s:g} s")

    def apply_config(self, new: Prepared) -> None:
        """Swap a validated config in between two ticks, bumplessly (see
        :mod:`motcomp.runtime.reload`)."""
        done = threading.Event()

        def swap() -> None:
            comp = self.state.comp
            models, gains = new.axes.models, new.axes.gains
            if tuple(models) == comp.models:  # each call checks the stability of every pair:
                if tuple(gains) != comp.gains:  # the least of them (a few ms of the loop's)
                    comp.set_gains(gains)
                comp.set_limits(new.axes.limits)
            else:
                comp.reconfigure(models, gains, new.axes.limits)
            comp.set_fade(new.cfg.loop.bypass_fade_s)
            self._set_bypass(new.axes.bypass, [False] * len(AXES))
            if new.digest != self.config_id:  # the delay is measured afresh on every axis
                self.monitor.changed((1 << len(AXES)) - 1)
            self.params = new.params
            self.cfg = new.cfg
            self.axes = new.axes
            done.set()

        self.run_between_ticks(swap, done, "the new config")
        self.supervisor.reconfigure(new.cfg.supervision, new.axes)
        self.config_version += 1
        self.config_id = new.digest

    # --- status ---------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        now = self._t_mono_s()
        st = self.state
        shaper = st.shaper
        clock = self._clock
        return {
            "t": time.time(),
            "version": __version__,
            "mode": st.mode,
            "config": {"hash": self.config_id, "version": self.config_version,
                       "path": str(self.config_path) if self.config_path else None},
            "rate_hz": self.cfg.loop.rate_hz,
            "sync_to_input": self.cfg.loop.sync_to_input,
            "ticks": st.ticks,
            "missed_ticks": clock.missed if clock else 0,
            "missed_waiting_cpu": clock.missed_waiting if clock else 0,
            "deadlines": (dict(self._deadlines) if self._deadlines["due"] or clock is None else
                          {**self._window_figures(self._deadline_window, time.monotonic())[0],
                           "windows_degraded": 0, "open": True}),
            "loop": self.stats.snapshot(),
            "loop_window_s": self.cfg.status.window_s,
            "frames": {"received": st.received, "accepted": st.accepted,
                       "rejected": st.rejected, "rejected_by_reason": dict(st.rejected_by_reason),
                       "last_reject": st.last_reject, "superseded": st.superseded},
            "input": {"reconstruction": self.params.shaper.reconstruction,
                      "period_ms": shaper.period_s * 1e3, "lag_ms": shaper.lag_s * 1e3,
                      "playback_lag_ms": self.params.shaper.playback_lag_s * 1e3,
                      "lag_excess_ms": self._lag_excess_ms(),
                      "lead_ms": self.params.shaper.lead_s * 1e3,
                      "band": {a: {"band_hz": b.band_hz, "delay_ms": b.delay_s * 1e3}
                               for a, b in zip(AXES, self.params.shaper.band, strict=False)
                               if b is not None}},
            "envelope": {"clamps": st.envelope_clamps,
                         "acted": dict(zip(AXES, st.envelope_acted, strict=True))},
            "stale_s": shaper.stale_time(now),
            "stale_total_s": shaper.stale_total_s,
            "stale_episodes": shaper.stale_episodes,
            "saturation": dict(zip(AXES, st.sat, strict=True)),
            "bypass": [a for a, b in zip(AXES, st.comp.bypass, strict=True) if b],
            "prediction": prediction_status(st),
            "profile": self.cfg.profile,
            "profiles": sorted(self.cfg.profiles),
            "driven": [a for a, d in zip(AXES, self.axes.driven, strict=True) if d],
            "src_seq": st.src_seq,
            "can": ({"sent": self._can.sent, "errors": self._can.errors}
                    if self._can is not None else None),
            "reloads": self.reloads[-RELOADS_KEPT:],
            "realtime": self.rt_report,
            "tick": self._build,
            "clock": self.tick_clock(),
            "platform": self._platform,
            "model_mismatch": self.supervisor.status(),
            **self._quality(),
        }

    def _lag_excess_ms(self) -> float | None:
        """How much longer the input's reconstruction lags than ``input.playback_lag_s``, the
        lag the design cancels (ms; None before the playback starts): a sender whose samples
        lie further apart than that (a slow or irregular one, less its lead) is late by this
        much; 0 for a regular 1 kHz sender."""
        shaper, sp = self.state.shaper, self.params.shaper
        if sp.reconstruction != "smooth" or shaper.playback_delay_s is None:
            return None
        return (shaper.lag_s - sp.playback_lag_s) * 1e3

    def _quality(self) -> dict[str, Any]:
        """The status' ``feedback``, ``quality`` and ``axes_quality`` blocks (layout in
        docs/DEPLOYMENT.md, "Motion quality"); never raises."""
        st, axes = self.state, self.axes
        window: dict[str, Any] = {"window_s": self.monitor.window_s,
                                  "command_window_s": COMMAND_WINDOW_S, "bin_s": BIN_S,
                                  "lag_range_s": list(LAG_RANGE_S), "from_t": None,
                                  "to_t": None}
        try:
            rep = self.monitor.report(time.perf_counter_ns(), st.ticks, list(st.acted),
                                      axes.driven, axes.limits.p_min, axes.limits.p_max,
                                      pause=_hand_over)
        except Exception as exc:  # pragma: no cover - report() catches its own
            log.error("motion-quality figures failed: %r", exc)
            return {"quality": window, "axes_quality": {}}
        starved_out(rep["axes"], float(self._deadlines.get("share") or 0.0))
        span = rep["span_ns"]
        if span is not None and self._t_wall0 and self._t_mono0:
            window["from_t"], window["to_t"] = (self._t_wall0 + (x - self._t_mono0) / 1e9
                                                for x in span)
        return {"feedback": {"key": self.cfg.feedback.key, **rep["feedback"]},
                "quality": window, "axes_quality": rep["axes"]}

    def _window_figures(self, window: tuple[float, int, int, int], now: float
                        ) -> tuple[dict[str, Any], tuple[float, int, int, int]]:
        """The deadlines of the window that began at ``window`` (instant, ticks, missed and
        waiting then) up to ``now``, and the counts at ``now`` (the next window's start)."""
        t0, ticks0, missed0, waiting0 = window
        clock = self._clock
        ticks, missed = self.state.ticks, clock.missed if clock else 0
        waiting = (clock.missed_waiting or 0) if clock else 0
        due = (ticks - ticks0) + (missed - missed0)
        share = (missed - missed0) / due if due > 0 else 0.0
        known = clock is not None and clock.missed_waiting is not None
        return ({"window_s": round(now - t0, 3), "due": due, "missed": missed - missed0,
                 "missed_waiting_cpu": waiting - waiting0 if known else None,
                 "share": share, "degraded": share > DEGRADED_MISSED_SHARE},
                (now, ticks, missed, waiting))

    def _judge_deadlines(self, window: tuple[float, int, int, int], now: float
                         ) -> tuple[float, int, int, int]:
        """Close a deadline window: the status' ``deadlines`` block, and, as :class:`DegradedLog`
        says, a WARNING when more than :data:`~motcomp.runtime.clock.DEGRADED_MISSED_SHARE` of
        its deadlines were missed, saying how many of them the loop spent waiting for a CPU (the
        host's doing)."""
        fig, then = self._window_figures(window, now)
        self._deadlines = {**fig, "windows_degraded": self._deadlines.get("windows_degraded", 0)
                           + int(fig["degraded"])}
        said = self._degraded_log.window(fig["degraded"], now)
        if said is not None and said[0] == "warning":
            waiting = fig["missed_waiting_cpu"]
            why = (f", {waiting} of them while the loop waited for a CPU that other threads "
                   "held (docs/DEPLOYMENT.md, \"Missed deadlines\")" if waiting is not None
                   else "")
            more = (f" ({said[1]} more degraded window(s) of {DEADLINE_WINDOW_S:g} s since the "
                    "last such warning)" if said[1] else "")
            log.warning("missed %d of %d deadlines over the last %.0f s (%.1f %%: more than "
                        "%g %%)%s: the host does not give the loop its CPU; delays, command "
                        "smoothness and identification are degraded until it does%s",
                        fig["missed"], fig["due"], now - window[0], 100 * fig["share"],
                        100 * DEGRADED_MISSED_SHARE, why, more)
        elif said is not None:
            log.info("the loop kept its deadlines again over the last %.0f s (%.1f %% missed), "
                     "after %d degraded window(s) not logged since the last warning",
                     now - window[0], 100 * fig["share"], said[1])
        return then

    def tick_clock(self) -> dict[str, Any] | None:
        """How output ``t`` maps back to the loop's own tick instants (None before the loop
        starts): ``t = wall0 + (tick_ns - mono0_ns) / 1e9``, and without ``sync_to_input`` every
        tick instant lies on the grid ``grid0_ns + m * period_ns``.  A replay uses this to
        rebuild the exact ``tick_ns`` the loop computed with (see docs/REPLAY.md)."""
        clock = self._clock
        if clock is None or not self._t_mono0 or not self._t_wall0:
            return None
        return {"wall0": self._t_wall0, "mono0_ns": self._t_mono0,
                "grid0_ns": None if self.cfg.loop.sync_to_input else clock.start_ns,
                "period_ns": clock.period_ns}

    def _t_mono_s(self) -> float:
        return time.perf_counter_ns() / 1e9

    # --- main thread ----------------------------------------------------------------------
    def submit(self, kind: str, item: Any) -> bool:
        """Hand a request to the admin worker (``("query", zenoh query)`` or ``("sighup",
        None)``); False if its queue is full (the caller answers ``busy``)."""
        try:
            self._admin_q.put_nowait((kind, item))
        except queue.Full:
            return False
        return True

    def _admin_worker(self) -> None:
        """The admin worker thread: serves the queue, at most ADMIN_RATE_HZ requests a second,
        until a None; after a stop request, answers what is left ``stopping``."""
        gap = 1.0 / ADMIN_RATE_HZ
        next_start = 0.0
        while (item := self._admin_q.get()) is not None:
            kind, obj = item
            wait = next_start - time.monotonic()
            if wait > 0:
                self.stop_event.wait(wait)
            next_start = time.monotonic() + gap
            try:
                if kind == "sighup":
                    if not self.stop_event.is_set():
                        self.reload()
                    self._admin_gen += 1
                else:
                    self._serve_admin(obj)
            except Exception as exc:  # never let a request stop the worker
                log.error("admin request failed: %r", exc)
                self._admin_gen += 1

    def _serve_admin(self, query: Any) -> None:
        key = str(query.key_expr)
        name = key.rsplit("/", 1)[-1]
        if self.stop_event.is_set():
            result: dict[str, Any] = {"ok": False, "error": "stopping"}
        else:
            try:
                body = query.payload.to_bytes() if query.payload is not None else b""
                result = self.admin(name, body)
            except Exception as exc:  # never let a request stop the worker
                result = {"ok": False, "error": f"internal error: {type(exc).__name__}"}
        self._admin_gen += 1  # before the answer: a status asked after it shows the change
        _answer(query, key, result)

    def admin(self, name: str, body: bytes) -> dict[str, Any]:
        """Answer one admin request (``bypass``, ``reload``, ``profile``; msgpack ``body``):
        ``{"ok": True, ...}`` or ``{"ok": False, "error": text}`` for any failure."""
        try:
            if len(body) > 65536:
                raise ConfigError(f"admin request of {len(body)} bytes (at most 65536)")
            req = msgpack.unpackb(body) if body else {}
            if not isinstance(req, dict):
                raise ConfigError("admin request must be a msgpack map")
            if name == "bypass":
                on, axes = req.get("on"), req.get("axes")
                if not isinstance(on, bool) or not (
                        axes is None or (isinstance(axes, list)
                                         and all(isinstance(a, str) for a in axes))):
                    raise ConfigError("bypass request needs {'on': true|false, 'axes': [str]}")
                bypassed = self.request_bypass(on, axes)
                off, cfg_axes = self.state.prediction_off, self.axes
                return {"ok": True, "bypass": bypassed,
                        "predicted": [a for i, a in enumerate(AXES)
                                      if cfg_axes.driven[i] and cfg_axes.predict[i]
                                      and not off[i]]}
            if name == "reload":
                path = req.get("path")
                if path is not None and not isinstance(path, str):
                    raise ConfigError("reload request needs {'path': str | None}")
                return self.reload(path)
            if name == "profile":
                pname = req.get("name")
                if pname is not None and not isinstance(pname, str):
                    raise ConfigError("profile request needs {'name': str | None}")
                return self.switch_profile(pname)
            raise ConfigError(f"unknown admin command {name[:40]!r}; commands: bypass, reload, "
                              "profile")
        except Exception as exc:
            text = str(exc) if isinstance(exc, MotcompError) else \
                f"internal error: {type(exc).__name__}: {exc}"
            return {"ok": False, "error": text[:MAX_ERROR_CHARS * 5]}

    def reload(self, path: str | None = None) -> dict[str, Any]:
        """Validate and apply a config file (default: the config in force), read only as
        :attr:`confinement` allows; returns ``{"ok": bool, ...}`` and never raises for a bad
        config or a refused file.  An accepted ``path`` becomes the config in force."""
        source = self.config_path
        if path:  # relative: to the config directory
            source = Path(path)
            if self.confinement is not None and not source.is_absolute():
                source = self.confinement.root / source
        attempt: dict[str, Any] = {"t": time.time(), "kind": "reload",
                                   "path": str(source) if source else None}

        file_sets = [False]

        def prepare() -> Prepared:
            new = self.preparer.prepare_config(self.cfg, self.axes, source, self.confinement)
            live = self.live_profile
            file_sets[0] = new.cfg.profile is not None
            if live is None or file_sets[0]:
                return new  # none chosen live, or the file names its own
            if live not in new.cfg.profiles:
                log.warning("profile %s (chosen live) is not defined in the reloaded config: "
                            "dropped, no profile active", live)
                return new
            try:
                kept = self.preparer.prepare_profile(new.cfg, new.axes, live)
            except ConfigError as exc:
                log.warning("profile %s (chosen live) does not fit the reloaded config (%s): "
                            "dropped, the file's settings apply", live, exc)
                return new
            log.warning("profile %s (chosen live) applied over the reloaded config, which sets "
                        "none (`motcomp profile none` returns to the file's tuning)", live)
            return kept

        out = self._attempt(attempt, prepare, "reload")
        if out["ok"] and (file_sets[0] or self.cfg.profile is None):
            self.live_profile = None  # the file's choice (or none) is in force now
        if out["ok"] and path and source != self.config_path:
            log.info("config in force is now %s (was %s): SIGHUP and reload re-read it",
                     source, self.config_path)
            self.config_path = source
        return out

    def switch_profile(self, name: str | None) -> dict[str, Any]:
        """Make ``name`` the active scenario profile (None: none), bumplessly."""
        attempt: dict[str, Any] = {"t": time.time(), "kind": "profile", "path": None}
        out = self._attempt(
            attempt, lambda: self.preparer.prepare_profile(self.cfg, self.axes, name),
            f"switch to profile {name}" if name else "switch to no profile")
        if out["ok"]:
            self.live_profile = name
        return out

    def _attempt(self, attempt: dict[str, Any], prepare: Callable[[], Prepared], what: str
                 ) -> dict[str, Any]:
        self.notifier.reloading()
        try:
            new = prepare()
            attempt["hash"] = new.digest
            before = self.config_id
            self.apply_config(new)
            attempt.update(ok=True, version=self.config_version, profile=new.cfg.profile,
                           unchanged=new.digest == before)
            for w in new.axes.warnings:
                log.warning("%s", w)
            log.info("%s ok%s (hash %s, version %d, %s)", what,
                     f": {attempt['path']}" if attempt.get("path") else "", new.digest,
                     self.config_version,
                     f"profile {new.cfg.profile}" if new.cfg.profile else "no profile")
        except MotcompError as exc:
            attempt.update(ok=False, error=str(exc))
            log.error("%s rejected: %s (running config %s kept)", what, exc, self.config_id)
        finally:
            self.notifier.ready()
        self.reloads.append(attempt)
        del self.reloads[:-RELOADS_KEPT]
        return {"ok": attempt["ok"], **{k: v for k, v in attempt.items() if k != "ok"}}

    def run(self) -> int:
        """Start, loop until SIGTERM/SIGINT, park, stop; returns the exit code."""
        cfg = self.cfg
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stop_event.set())
        signal.signal(signal.SIGHUP, lambda *_: self.reload_event.set())
        import zenoh

        switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)

        with open_session(self.endpoints) as session:
            self._source = ZenohSource(session, cfg.input.key)
            if cfg.output.transport in ("zenoh", "both"):
                self._ports.append(ZenohSink(session, cfg.output.key))
            if cfg.output.transport in ("can", "both"):
                self._can = self._open_can()
                self._ports.append(self._can)
            # feedback: a ring polled by the main thread (no Python callback on a zenoh thread:
            # it would contend with the loop thread for the interpreter 1000 times a second)
            feedback_sub = session.declare_subscriber(cfg.feedback.key,
                                                      zenoh.handlers.RingChannel(FEEDBACK_RING))
            self._feedback = feedback_sub
            self._platform_sub = session.declare_subscriber(cfg.feedback.status_key,
                                                            zenoh.handlers.RingChannel(1))
            status_pub = session.declare_publisher(cfg.status.key)
            status_q = session.declare_queryable(cfg.status.key,
                                                 zenoh.handlers.RingChannel(QUERY_CHANNEL))
            # declared with admin off too, to answer ``admin off`` at once (not a silence
            # that reads as an unreachable service after the command's whole timeout)
            admin_q = session.declare_queryable(f"{cfg.admin.key}/**",
                                                zenoh.handlers.RingChannel(QUERY_CHANNEL))
            thread = threading.Thread(target=self._loop, name="motcomp-loop", daemon=True)
            worker = threading.Thread(target=self._admin_worker, name="motcomp-admin",
                                      daemon=True)
            thread.start()
            worker.start()
            try:
                return self._main(thread, status_pub, status_q, admin_q)
            finally:
                self.stop_event.set()
                thread.join(timeout=cfg.loop.park_timeout_s + 2.0)
                self.notifier.stopping()
                self._stop_worker(worker)
                self.preparer.close()
                self.supervisor.close()
                sys.setswitchinterval(switch)
                for q in (status_q, admin_q, feedback_sub, self._platform_sub):
                    if q is not None:
                        q.undeclare()
                status_pub.undeclare()
                for port in self._ports:
                    port.close()
                if self._source is not None:
                    self._source.close()
                self.notifier.close()

    def _stop_worker(self, worker: threading.Thread) -> None:
        """Answer what is still queued ``stopping`` and end the admin worker (a request it is
        busy with gets a second to finish; the worker is a daemon)."""
        while True:
            try:
                item = self._admin_q.get_nowait()
            except queue.Empty:
                break
            if item is not None and item[0] == "query":
                _answer(item[1], str(item[1].key_expr), {"ok": False, "error": "stopping"})
        self._admin_q.put_nowait(None)  # empty now: only this thread submits
        worker.join(timeout=1.0)

    def _status_bytes(self, now: float, max_age_s: float = STATUS_MAX_AGE_S) -> bytes:
        """The packed status, rebuilt when older than ``max_age_s`` or after an admin change;
        never raises.

        The status reads the loop's state while the loop changes it: a read that catches a
        structure half rebuilt (a prediction reconfigured by a swap) raises, and is tried again
        (three times, 1 ms apart), then the previous status is served, or a minimal one."""
        cached = self._status_cache
        gen = self._admin_gen  # read before the status: a change after it makes this stale
        if cached is not None and cached[0] == gen and now - cached[1] <= max_age_s:
            return cached[2]
        error: Exception | None = None
        for _ in range(3):
            try:
                data = msgpack.packb(self.status())
            except Exception as exc:
                error = exc
                time.sleep(0.001)
                continue
            self._status_cache = (gen, now, data)
            return data
        log.warning("status failed three times: %r", error)
        if cached is not None:
            return cached[2]
        return msgpack.packb({"t": time.time(), "version": __version__, "mode": self.state.mode,
                              "ticks": self.state.ticks, "error": f"status failed: {error!r}"})

    def _poll_feedback(self) -> None:
        """Hand the feedback frames received since the last poll to the monitor, each stamped
        when taken from the channel (never before it arrived: the monitor's smallest transit
        must not be shortened by a frame that came in while this poll was preempted; the
        monitor times frames by their own ``t``; never raises)."""
        sub = self._feedback
        if sub is None:
            return
        perf = time.perf_counter_ns
        while (sample := sub.try_recv()) is not None:
            t_ns = perf()
            try:
                payload = sample.payload.to_bytes()
            except Exception:  # counted as a bad frame by the monitor
                payload = b""
            self.monitor.on_feedback(t_ns, payload)

    def to_frame_s(self, t_ns: Any) -> Any:
        """Loop instants (ns, scalar or array) as the outputs' ``t`` (s)."""
        return self._t_wall0 + (t_ns - self._t_mono0) / 1e9

    def _supervise(self, now: float) -> None:
        """The model supervision's turn (:class:`~motcomp.runtime.supervise.Supervisor`)."""
        st = self.state
        for text in self.supervisor.poll(self.monitor, self.to_frame_s, now, st.ticks,
                                         list(st.acted),
                                         self._clock.missed if self._clock else 0):
            log.warning("%s", text)

    def _watch_feedback(self, lost_ns: int | None) -> int | None:
        """Log when no good feedback frame came for :data:`FEEDBACK_STALE_S` (WARNING; a
        loss within :data:`REPEAT_WARNING_S` of the last warning, and its end, at DEBUG) and
        when it comes back (INFO); returns the arrival of the last good frame before the loss,
        or None while the feedback comes (or never came)."""
        now = time.perf_counter_ns()
        mon = self.monitor
        age = mon.feedback_age_s(now)
        if age is None:
            return None
        if lost_ns is None and age > FEEDBACK_STALE_S:
            again = now - self._fb_warned_ns < REPEAT_WARNING_S * 1e9
            self._fb_warned_ns = self._fb_warned_ns if again else now
            log.log(logging.DEBUG if again else logging.WARNING,
                    "platform feedback: no good frame for %.1f s (%d good, %d bad so far): the "
                    "apparent delay and the model supervision wait for it", age,
                    mon.fb_received - mon.fb_bad, mon.fb_bad)
            return now - round(age * 1e9)
        if lost_ns is not None and age <= FEEDBACK_STALE_S:
            said = self._fb_warned_ns >= lost_ns
            log.log(logging.INFO if said else logging.DEBUG, "platform feedback: back after "
                    "%.1f s", (now - lost_ns) / 1e9 - age)
            return None
        return lost_ns

    def _poll_platform(self) -> None:
        """Keep the figures of the platform's newest status frame (docs/WIRE.md: those it
        reports of ``PLATFORM_FIGURES``, numbers only), with the instant it arrived."""
        sub = self._platform_sub
        if sub is None or (sample := sub.try_recv()) is None:
            return
        try:
            payload = sample.payload.to_bytes()
            if len(payload) > MAX_PLATFORM_STATUS_BYTES:
                return
            st = msgpack.unpackb(payload, raw=False)
        except Exception:  # not a status frame: nothing to show
            return
        if isinstance(st, dict):
            self._platform = {"received_t": time.time(), **{
                k: st[k] for k in PLATFORM_FIGURES
                if isinstance(st.get(k), int | float) and not isinstance(st.get(k), bool)}}

    def _open_can(self) -> Any:
        from motcomp.io.can_io import open_can_output

        return open_can_output(self.cfg.output.can, self.config_path)

    def _main(self, thread: threading.Thread, status_pub: Any, status_q: Any,
              admin_q: Any) -> int:
        cfg = self.cfg
        admin_on = cfg.admin.enabled
        next_status = time.monotonic() + cfg.status.period_s
        next_build = time.monotonic() + BUILD_CHECK_S
        next_dog = 0.0
        dog_every = (self.notifier.watchdog_usec / 2e6) if self.notifier.watchdog_usec else 1.0
        ready = False
        seen = ModeLog(self.state)
        clamps, clamps_logged = 0, -math.inf
        feedback_lost: int | None = None
        window = self._deadline_window = (time.monotonic(), 0, 0, 0)
        while not self.loop_done.is_set():
            self.loop_done.wait(0.02)
            now = time.monotonic()
            self._poll_feedback()
            self._poll_platform()
            self.monitor.drain()
            feedback_lost = self._watch_feedback(feedback_lost)
            if ready and self._t_mono0:
                self._supervise(now)
            seen.update(self.state, self.params)
            if self.state.envelope_clamps > clamps and now - clamps_logged >= ENVELOPE_LOG_S:
                log.error("the hardware envelope's guard changed %d command(s) (per axis %s): "
                          "the limiter let a command out of the envelope -- a bug upstream",
                          self.state.envelope_clamps - clamps,
                          {a: n for a, n in zip(AXES, self.state.envelope_acted, strict=True)
                           if n})
                clamps, clamps_logged = self.state.envelope_clamps, now
            if now - window[0] >= DEADLINE_WINDOW_S and self._clock is not None:
                window = self._deadline_window = self._judge_deadlines(window, now)
            healthy = self.state.ticks > 0 and now - self.last_tick_mono < 0.25
            if healthy and not ready:
                ready = True
                self.notifier.ready(f"running at {cfg.loop.rate_hz:g} Hz")
                log.info("running: %g Hz, config %s, %s; tick %s", cfg.loop.rate_hz,
                         self.config_id, self.rt_report, native.ACTIVE)
                self.preparer.start()  # the reloads' reader, once start-up is done
            if healthy and now >= next_dog:
                self.notifier.watchdog()
                next_dog = now + dog_every
            if self.reload_event.is_set() and self.submit("sighup", None):
                self.reload_event.clear()  # else: kept for the next poll
            for _ in range(QUERIES_PER_POLL):
                if (q := status_q.try_recv()) is None:
                    break
                q.reply(cfg.status.key, self._status_bytes(time.monotonic()))
                q.drop()
            for _ in range(QUERIES_PER_POLL):
                if (q := admin_q.try_recv()) is None:
                    break
                if not admin_on:  # [restart]: the config the service started with
                    _answer(q, str(q.key_expr), ADMIN_OFF)
                elif not self.submit("query", q):
                    _answer(q, str(q.key_expr), BUSY)
            if now >= next_build:
                self._build, next_build = native.status(), now + BUILD_CHECK_S
            if now >= next_status:
                status_pub.put(self._status_bytes(time.monotonic(), 0.0))
                next_status = now + cfg.status.period_s
        if self._loop_error is not None:
            log.error("loop failed: %r", self._loop_error)
            return 1
        log.info("stopped after %d ticks (%d missed); exit %d", self.state.ticks,
                 self._clock.missed if self._clock else 0, self.exit_code)
        return self.exit_code

