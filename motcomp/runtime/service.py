"""The real-time compensator service: ``motcomp run``.

Lifecycle::

    start    read config -> open zenoh (before any real-time priority) -> declare input
             subscriber, output publisher(s), status publisher and queryables -> CAN bus if
             configured -> build the compensator at neutral
    loop     a thread at a fixed rate on absolute deadlines (a short scheduler slice, or
             optionally SCHED_FIFO; optionally pinned),
             gc.freeze() at its start; each tick: apply queued commands, take the newest input
             frame (never blocks), validate it, shape the reference, step the compensator,
             publish; count, never log
    main     the main thread: signals, status at 1 Hz (and on query), admin requests, the
             systemd watchdog (only while the loop ticks), reloads
    stop     SIGTERM/SIGINT -> park (ramp to neutral within the limits) -> exit 0; exit 1 if
             parking did not finish within park_timeout_s

Everything the loop needs from the outside world comes through two non-blocking doors: the
input source's ``latest()`` and a command queue (a deque: appends and pops are atomic) through
which the main thread hands it closures to run between two ticks -- bypass toggles and config
swaps.  The loop thread is the only one that touches the compensator.
"""

from __future__ import annotations

import gc
import logging
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from motcomp import __version__
from motcomp.config import ResolvedAxes, ServiceConfig, config_hash, resolve_axes
from motcomp.core.axes import AXES
from motcomp.core.compensator import Compensator
from motcomp.core.saturation import POS, VEL
from motcomp.errors import ConfigError, MotcompError, ServiceError
from motcomp.io.wire import InputValidator, encode_output
from motcomp.io.zenoh_io import ZenohEndpoints, ZenohSink, ZenohSource, open_session
from motcomp.resources import config_file
from motcomp.runtime.clock import DeadlineClock
from motcomp.runtime.rt import pin_to_cpu, set_realtime, set_slice
from motcomp.runtime.shaper import ReferenceShaper
from motcomp.runtime.stats import LoopStats
from motcomp.runtime.systemd import Notifier

__all__ = ["Service", "build_compensator"]

log = logging.getLogger("motcomp.service")

_HARD_BITS = POS | VEL
MAX_CATCH_UP = 20
"""Longest stall (in periods) whose samples are computed afterwards (see Service._catch_up)."""
_SAT_FLAGS = tuple(f"sat:{a}" for a in AXES)
_BYPASS_FLAGS = tuple(f"bypass:{a}" for a in AXES)
STAT_SERIES = ("tick", "compute", "io", "late")
"""What the loop times, per tick (us): ``tick`` from waking at the deadline to the end of the
tick; ``io`` the part of it spent in transport calls (taking the newest input, sending the
outputs); ``compute`` the rest (commands, catch-up steps, validation, reference, compensator,
saturation verdicts, encoding); ``late`` waking after the deadline."""


def build_compensator(cfg: ServiceConfig, axes: ResolvedAxes) -> Compensator:
    """The compensator of a config, at rest at neutral."""
    comp = Compensator(axes.models, axes.gains, axes.limits, cfg.loop.rate_hz,
                       fade_s=cfg.loop.bypass_fade_s, history_s=0.5)
    comp.set_bypass(axes.bypass)
    return comp


@dataclass
class _Counters:
    """Written by the loop thread only."""

    ticks: int = 0
    sat: list[int] = field(default_factory=lambda: [0] * len(AXES))
    src_seq: int = -1
    superseded: int = 0  # source frames skipped (a newer one arrived first, or lost)
    last_tick_mono: float = 0.0
    mode: str = "startup"


class Service:
    """See the module docstring.  ``run()`` blocks until stopped and returns the exit code."""

    def __init__(self, cfg: ServiceConfig, endpoints: ZenohEndpoints,
                 config_path: Path | None = None, *, shadow: bool = False) -> None:
        """``shadow``: a copy for :meth:`warm_up` (no warnings logged, no systemd socket)."""
        self.cfg = cfg
        self.endpoints = endpoints
        self.config_path = config_path
        self.axes = resolve_axes(cfg)
        for w in self.axes.warnings if not shadow else ():
            log.warning("%s", w)
        self.comp = build_compensator(cfg, self.axes)
        self.validator = InputValidator(list(self.axes.limits.p_min), list(self.axes.limits.p_max),
                                        cfg.input.reject_beyond_fraction)
        self.shaper = ReferenceShaper(self.axes.driven, self._ramp_speeds(cfg, self.axes),
                                      cfg.loop.stale_after_s, cfg.loop.hold_s, cfg.loop.rejoin_s,
                                      cfg.loop.startup_s, cfg.input.reconstruction == "linear",
                                      cfg.input.max_extrapolation_s)
        self.stats = LoopStats(round(cfg.status.window_s * cfg.loop.rate_hz), STAT_SERIES)
        self.counters = _Counters()
        self.notifier = Notifier("" if shadow else None)
        self.commands: deque[Callable[[], None]] = deque()
        self.stop_event = threading.Event()
        self.reload_event = threading.Event()
        self.loop_done = threading.Event()
        self.exit_code = 0
        self.config_version = 1
        self.config_id = config_hash(cfg)
        self.reloads: list[dict[str, Any]] = []
        self.rt_report = ""
        self._loop_error: BaseException | None = None
        self._pending: bytes | None = None
        self._seq = 0
        self._source: ZenohSource | None = None
        self._sinks: list[Any] = []
        self._can: Any = None
        self._clock: DeadlineClock | None = None
        self._t_wall0 = 0.0
        self._t_mono0 = 0
        self._bypass_flags: list[str] = []
        self._dev_lp = [0.0] * len(AXES)
        self._dev_alpha = min(1.0, 1.0 / (0.02 * cfg.loop.rate_hz))
        self.io_ns = 0
        self._last_payload: bytes | None = None
        self._last_tick_ns = 0
        self._shadow: Service | None = None
        """Time the last :meth:`tick` spent in transport calls (input take, sends)."""
        self._perf = time.perf_counter_ns

    @staticmethod
    def _ramp_speeds(cfg: ServiceConfig, axes: ResolvedAxes) -> list[float]:
        return [cfg.loop.ramp_speed_fraction * float(v) for v in axes.limits.v_max]

    # --- the loop thread ------------------------------------------------------------------
    def attach(self, source: Any, sinks: list[Any]) -> None:
        """Use these adapters (e.g. the in-memory twins of :mod:`motcomp.io.memory`) instead of
        opening transports: then :meth:`tick` can be driven directly with a given time."""
        self._source = source
        self._sinks = list(sinks)
        self._set_bypass_flags()

    def _poll_input(self) -> bool:
        assert self._source is not None
        payload = self._source.latest()
        if payload is None:
            return False
        self._pending = payload
        return True

    def tick(self, now_ns: int) -> None:
        """One tick at the sample instant ``now_ns`` (the deadline: the reference is evaluated
        on the ideal, uniform time grid the compensator assumes, not at the jittered moment the
        thread woke up)."""
        commands = self.commands
        while commands:
            commands.popleft()()
        now = now_ns / 1e9
        payload = self._pending
        self._pending = None
        perf = self._perf
        io = 0
        if payload is None and self._source is not None:
            t_io = perf()
            payload = self._source.latest()
            io = perf() - t_io
        shaper = self.shaper
        if payload is not None:
            self._last_payload = payload
            res = self.validator.accept(payload, after_stale=shaper.is_stale(now))
            if res is not None:
                c = self.counters
                gap = res[0] - c.src_seq - 1
                if c.src_seq >= 0 and 0 < gap < 1_000_000:  # a regress is a source restart
                    c.superseded += gap
                c.src_seq = res[0]
                shaper.on_input(res[2], now, res[1])
        ref, mode = shaper.reference(now)
        comp = self.comp
        u = comp.step(ref)
        flags = [mode] if mode else []
        sat = self.counters.sat
        limited = [False] * len(u)
        tol = self.cfg.status.saturation_tolerance
        dev = comp.deviation
        lp = self._dev_lp
        alpha, keep = self._dev_alpha, 1.0 - self._dev_alpha
        for i, f in enumerate(comp.flags):
            # a position or velocity bound, or a *sustained* departure from the target (its
            # 20 ms average): the limiter absorbing zero-mean jitter noise that the compensator
            # amplifies is not a saturation of the motion.  (Written as lfilter computes it, so
            # that an offline replay reproduces the verdicts exactly.)
            if not f and lp[i] == 0.0:  # the common case: nothing to average
                continue
            lp[i] = alpha * dev[i] + keep * lp[i]
            if f & _HARD_BITS or (f and abs(lp[i]) > tol):
                sat[i] += 1
                limited[i] = True
                flags.append(_SAT_FLAGS[i])
        flags.extend(self._bypass_flags)
        t_wall = self._t_wall0 + (now_ns - self._t_mono0) / 1e9
        out = encode_output(self._seq, t_wall, self.counters.src_seq, u, flags)
        t_io = perf()
        for sink in self._sinks:
            sink.put(out)
        if self._can is not None:
            self._can.send(self._seq, u, limited, mode == "stale", mode == "parking")
        self.io_ns = io + perf() - t_io
        self._seq += 1
        self._last_tick_ns = now_ns
        self.counters.mode = mode or "running"
        self.counters.ticks += 1

    # --- cache warming --------------------------------------------------------------------
    def make_shadow(self) -> Service:
        """A copy of this service without transports, for :meth:`warm_up`: same config, its
        own compensator, shaper and validator, an in-memory input and no output."""
        from motcomp.io.memory import MemorySource

        shadow = Service(self.cfg, self.endpoints, shadow=True)
        shadow.attach(MemorySource(latest_only=True), [])
        return shadow

    def warm_up(self) -> None:
        """Run the tick's code on the shadow service, one tick behind this one: the payload
        this service took last (if new) at the instant of its last tick.  Nothing leaves the
        shadow; its only effect is on the CPU's caches and predictors, which a sleep through
        the kernel's idle path leaves cold (docs/BENCHMARKS.md: the real tick then costs
        about a third)."""
        shadow = self._shadow
        if shadow is None:
            return
        payload, self._last_payload = self._last_payload, None
        try:
            if payload is not None:
                shadow._source.push(payload)  # type: ignore[union-attr]
            shadow.tick(self._last_tick_ns)
        except Exception as exc:  # never let the warm-up stop the loop: drop the shadow
            self._shadow = None
            log.error("cache warm-up failed and is off from now on: %r", exc)

    def _catch_up(self, deadline_ns: int, skipped: int) -> None:
        """Step the compensator (no input, no output) at the ``skipped`` deadlines before this
        one: its discrete dynamics stay on the real time grid, instead of seeing the reference
        jump by several samples at once (which a high-gain tuning amplifies).  At most
        :data:`MAX_CATCH_UP` periods; a longer stall is left to the stale-input logic."""
        period = round(1e9 / self.cfg.loop.rate_hz)
        for j in range(min(skipped, MAX_CATCH_UP), 0, -1):
            ref, _ = self.shaper.reference((deadline_ns - j * period) / 1e9)
            self.comp.step(ref)

    def _parked(self) -> bool:
        if not self.shaper.parked:
            return False
        st = self.comp.state()
        return bool(max(abs(x) for x in st.u) < 1e-6 and max(abs(x) for x in st.v) < 1e-4)

    def _loop(self) -> None:
        try:
            loop = self.cfg.loop
            naps = (f"naps of {loop.sleep_max_us:g} us" if loop.sleep_max_us > 0
                    else "one sleep per tick")
            self.rt_report = (f"{set_realtime(loop.realtime_priority)}; "
                              f"{set_slice(loop.slice_us)}; {naps}; {pin_to_cpu(loop.cpu)}")
            warm = self.warm_up if loop.warm_up else None
            if warm is not None:
                self._shadow = self.make_shadow()
            gc.collect()
            gc.freeze()
            clock = DeadlineClock(loop.rate_hz, loop.spin_us, sleep_max_us=loop.sleep_max_us)
            self._clock = clock
            self._t_mono0 = time.perf_counter_ns()
            self._t_wall0 = time.time()
            park_deadline: float | None = None
            record = self.stats.record
            perf = time.perf_counter_ns
            while True:
                if loop.sync_to_input:
                    deadline, now, _ = clock.wait_or_poll(self._poll_input, loop.poll_us, warm)
                else:
                    deadline, now = clock.wait(warm)
                if clock.skipped:
                    self._catch_up(deadline, clock.skipped)
                self.tick(deadline)
                tick_ns = perf() - now
                io_ns = self.io_ns
                record(tick_ns / 1e3, (tick_ns - io_ns) / 1e3, io_ns / 1e3,
                       (now - deadline) / 1e3)
                self.counters.last_tick_mono = time.monotonic()
                if self.stop_event.is_set():
                    if park_deadline is None:
                        self.shaper.park(now / 1e9)
                        park_deadline = time.monotonic() + loop.park_timeout_s
                    elif self._parked():
                        break
                    elif time.monotonic() > park_deadline:
                        log.error("parking did not finish within %.1f s", loop.park_timeout_s)
                        self.exit_code = 1
                        break
        except BaseException as exc:  # pragma: no cover - reported by the main thread
            self._loop_error = exc
            self.exit_code = 1
        finally:
            self.loop_done.set()

    # --- configuration changes (main thread builds, loop thread swaps) ---------------------
    def _set_bypass_flags(self) -> None:
        """Recompute the per-axis "bypass:" flags (loop thread, after a bypass change)."""
        bypass = self.comp.bypass
        self._bypass_flags = [_BYPASS_FLAGS[i] for i in range(len(AXES))
                              if bypass[i] and self.axes.driven[i]]

    def request_bypass(self, on: bool, axes: list[str] | None = None) -> list[str]:
        """Queue a bumpless bypass change for the given driven axes (all when None)."""
        names = axes or [a for a, d in zip(AXES, self.axes.driven, strict=True) if d]
        unknown = [a for a in names if a not in AXES]
        if unknown:
            raise ConfigError(f"unknown axis {unknown[0]!r}")
        done = threading.Event()

        def apply() -> None:
            mask = list(self.comp.bypass)
            for a in names:
                i = AXES.index(a)
                if self.axes.driven[i]:
                    mask[i] = on
            self.comp.set_bypass(mask)
            self._set_bypass_flags()
            done.set()

        self.commands.append(apply)
        if not done.wait(1.0):
            raise ServiceError("the loop did not apply the bypass change within 1 s")
        return [a for a, b in zip(AXES, self.comp.bypass, strict=True) if b]

    # --- status ---------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        now = self._t_mono_s()
        c = self.counters
        v = self.validator
        clock = self._clock
        return {
            "t": time.time(),
            "version": __version__,
            "mode": c.mode,
            "config": {"hash": self.config_id, "version": self.config_version,
                       "path": str(self.config_path) if self.config_path else None},
            "rate_hz": self.cfg.loop.rate_hz,
            "sync_to_input": self.cfg.loop.sync_to_input,
            "ticks": c.ticks,
            "kernel": self.kernels(),
            "missed_ticks": clock.missed if clock else 0,
            "loop": self.stats.snapshot(),
            "loop_window_s": self.cfg.status.window_s,
            "frames": {"received": v.received, "accepted": v.accepted, "rejected": v.rejected,
                       "rejected_by_reason": dict(v.counts), "last_reject": v.last_error,
                       "superseded": c.superseded},
            "stale_s": self.shaper.stale_time(now),
            "stale_total_s": self.shaper.stale_total_s,
            "stale_episodes": self.shaper.stale_episodes,
            "saturation": dict(zip(AXES, c.sat, strict=True)),
            "bypass": [a for a, b in zip(AXES, self.comp.bypass, strict=True) if b],
            "profile": self.cfg.profile,
            "profiles": sorted(self.cfg.profiles),
            "driven": [a for a, d in zip(AXES, self.axes.driven, strict=True) if d],
            "src_seq": c.src_seq,
            "can": ({"sent": self._can.sent, "errors": self._can.errors}
                    if self._can is not None else None),
            "reloads": self.reloads[-10:],
            "realtime": self.rt_report,
            "clock": self.tick_clock(),
        }

    def kernels(self) -> str:
        """Which code runs the tick's hot path: ``c`` (the compiled compensator, shaper loops
        and wire codec), ``python`` (none of them: not built, or ``MOTCOMP_KERNEL=python``),
        or which part runs which."""
        from motcomp.io import wire
        from motcomp.runtime import shaper

        parts = {"compensator": self.comp.kernel,
                 "shaper": "c" if shaper._cshaper is not None else "python",
                 "wire": "c" if wire._cwire is not None else "python"}
        kinds = set(parts.values())
        if len(kinds) == 1:
            return kinds.pop()
        return ", ".join(f"{k} {v}" for k, v in parts.items())

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
    def _serve_admin(self, query: Any) -> None:
        name = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            body = query.payload.to_bytes() if query.payload is not None else b""
            req = msgpack.unpackb(body) if body else {}
            if not isinstance(req, dict):
                raise ConfigError("admin request must be a msgpack map")
            if name == "bypass":
                on = req.get("on")
                if not isinstance(on, bool):
                    raise ConfigError("bypass request needs {'on': true|false, 'axes': [...]}")
                axes = req.get("axes")
                result: dict[str, Any] = {"ok": True, "bypass": self.request_bypass(on, axes)}
            elif name == "reload":
                result = self.reload(req.get("path"))
            elif name == "profile":
                from motcomp.runtime.reload import switch_profile

                pname = req.get("name")
                if pname is not None and not isinstance(pname, str):
                    raise ConfigError("profile request needs {'name': str | None}")
                result = switch_profile(self, pname)
            else:
                raise ConfigError(f"unknown admin command {name!r}; commands: bypass, reload, "
                                  "profile")
        except MotcompError as exc:
            result = {"ok": False, "error": str(exc)}
        query.reply(str(query.key_expr), msgpack.packb(result))

    def reload(self, path: str | None = None) -> dict[str, Any]:
        """Reload the config (see :mod:`motcomp.runtime.reload`)."""
        from motcomp.runtime.reload import reload_service

        return reload_service(self, path)

    def run(self) -> int:
        """Start, loop until SIGTERM/SIGINT, park, stop; returns the exit code."""
        cfg = self.cfg
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stop_event.set())
        signal.signal(signal.SIGHUP, lambda *_: self.reload_event.set())
        import zenoh

        with open_session(self.endpoints) as session:
            self._source = ZenohSource(session, cfg.input.key)
            if cfg.output.transport in ("zenoh", "both"):
                self._sinks.append(ZenohSink(session, cfg.output.key))
            if cfg.output.transport in ("can", "both"):
                self._can = self._open_can()
            status_pub = session.declare_publisher(cfg.status.key)
            status_q = session.declare_queryable(cfg.status.key, zenoh.handlers.FifoChannel(16))
            admin_q = (session.declare_queryable(f"{cfg.admin.key}/**",
                                                 zenoh.handlers.FifoChannel(16))
                       if cfg.admin.enabled else None)
            self._set_bypass_flags()
            thread = threading.Thread(target=self._loop, name="motcomp-loop", daemon=True)
            thread.start()
            try:
                return self._main(thread, status_pub, status_q, admin_q)
            finally:
                self.stop_event.set()
                thread.join(timeout=cfg.loop.park_timeout_s + 2.0)
                self.notifier.stopping()
                for q in (status_q, admin_q):
                    if q is not None:
                        q.undeclare()
                status_pub.undeclare()
                for sink in self._sinks:
                    sink.close()
                if self._source is not None:
                    self._source.close()
                if self._can is not None:
                    self._can.close()
                self.notifier.close()

    def _open_can(self) -> Any:
        from motcomp.io.can_io import CanSink, load_layouts, open_bus

        c = self.cfg.output.can
        dbc = Path(c.dbc)
        if not dbc.is_absolute():
            base = self.config_path.parent if self.config_path else None
            dbc = base / dbc if base and (base / dbc).is_file() else config_file(c.dbc)
        layouts, _ = load_layouts(dbc)
        return CanSink(open_bus(c.interface, c.channel, c.bitrate_bps), layouts, c.send_every)

    def _main(self, thread: threading.Thread, status_pub: Any, status_q: Any,
              admin_q: Any) -> int:
        cfg = self.cfg
        next_status = time.monotonic() + cfg.status.period_s
        next_dog = 0.0
        dog_every = (self.notifier.watchdog_usec / 2e6) if self.notifier.watchdog_usec else 1.0
        ready = False
        while not self.loop_done.is_set():
            self.loop_done.wait(0.02)
            now = time.monotonic()
            healthy = self.counters.ticks > 0 and now - self.counters.last_tick_mono < 0.25
            if healthy and not ready:
                ready = True
                self.notifier.ready(f"running at {cfg.loop.rate_hz:g} Hz")
                kernels = self.kernels()
                log.info("running: %g Hz, config %s, %s; tick kernels: %s",
                         cfg.loop.rate_hz, self.config_id, self.rt_report, kernels)
                if kernels != "c":
                    log.warning("the tick's compiled kernels are not all in use (%s; not built, "
                                "or MOTCOMP_KERNEL=python): a tick costs up to 4x more CPU",
                                kernels)
            if healthy and now >= next_dog:
                self.notifier.watchdog()
                next_dog = now + dog_every
            if self.reload_event.is_set():
                self.reload_event.clear()
                self.reload()
            while (q := status_q.try_recv()) is not None:
                q.reply(cfg.status.key, msgpack.packb(self.status()))
                q.drop()
            while admin_q is not None and (q := admin_q.try_recv()) is not None:
                self._serve_admin(q)
                q.drop()
            if now >= next_status:
                status_pub.put(msgpack.packb(self.status()))
                next_status = now + cfg.status.period_s
        if self._loop_error is not None:
            log.error("loop failed: %r", self._loop_error)
            return 1
        st = self.status()
        log.info("stopped after %d ticks (%d missed); exit %d", st["ticks"], st["missed_ticks"],
                 self.exit_code)
        return self.exit_code

