"""``motcomp hil``: the simulated platform on the wire (hardware-in-the-loop stub).

Consumes corrected setpoints (zenoh ``platform/setpoint`` or the CAN frames of the DBC), holds
the latest one per axis, advances :class:`~motcomp.sim.platform.PlatformSimulator` (true
dynamics per axis, which may differ from the compensator's model) at its own fixed rate on wall
time (periods its loop missed are simulated afterwards: see :class:`HilPlatform`), enforces its
own hard limits (violations are counted, logged and published), and publishes feedback
``{"t", "pos", "acc"}`` with accelerometer imperfections on ``platform/feedback``.  Its counters
go to ``platform/status`` at 1 Hz.  It logs its start-up (endpoints, the true model and hard
limits of each axis, the input transport) and, when stopped, a summary of its counters.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import signal
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from motcomp.core.axes import AXES
from motcomp.core.fpmode import subnormals_flushed
from motcomp.core.models import ProcessModel, parse_model
from motcomp.errors import ConfigError, FrameError
from motcomp.io.wire import decode_output, encode_feedback
from motcomp.io.zenoh_io import ZenohEndpoints, ZenohSink, open_session
from motcomp.presets import load_preset
from motcomp.runtime.clock import DeadlineClock, frozen_heap
from motcomp.sim.platform import Accelerometer, PlatformSimulator

__all__ = ["Drift", "HilConfig", "HilPlatform", "default_truth", "parse_drift", "run_hil",
           "summary_text"]

log = logging.getLogger("motcomp.hil")

AXIS_INDEX = {axis: i for i, axis in enumerate(AXES)}
AGE_WINDOW_S = 10.0
"""The setpoint age's figures are over the frames applied in the last this many seconds (up to
the newest: docs/WIRE.md, "the last seconds")."""
AGE_RING = 1 << 15
"""Frames whose age is kept (10 s of setpoints at up to 3.2 kHz; beyond, the newest)."""


def default_truth() -> tuple[list[ProcessModel], np.ndarray, np.ndarray, np.ndarray]:
    """Truth models and soft limits of the 8 axes from the ``rails`` and ``hexapod`` presets."""
    rails, hexapod = load_preset("rails"), load_preset("hexapod")
    models: list[ProcessModel] = []
    rows = []
    for axis in AXES:
        preset = rails if axis in rails.axes else hexapod
        models.append(preset.model)
        lim = preset.axis_limits(axis)
        rows.append((lim.p_min[0], lim.p_max[0], lim.v_max[0]))
    arr = np.array(rows)
    return models, arr[:, 0], arr[:, 1], arr[:, 2]


DRIFT_STEP_S = 0.05
"""A ramped drift updates the axis' model this often."""


@dataclass(frozen=True)
class Drift:
    """The truth of one axis changes during a run: to ``model`` at ``at_s`` after the start,
    or, with ``ramp_s``, linearly (every parameter) from the truth in force at ``at_s`` to
    ``model`` over ``ramp_s``."""

    axis: str
    model: ProcessModel
    at_s: float
    ramp_s: float = 0.0


def parse_drift(text: str) -> Drift:
    """``AXIS=SPEC@T`` or ``AXIS=SPEC@T+RAMP`` (seconds), e.g.
    ``rails_y=p1d:K=1,Td=0.0275,Tp1=0.1858@60`` (a step at 60 s) or ``...@60+30`` (a ramp from
    60 s to 90 s).

    Raises
    ------
    ConfigError
        Naming the part that is wrong.
    """
    head, at, when = text.rpartition("@")
    axis, sep, spec = head.partition("=")
    if not at or not sep or axis not in AXES:
        raise ConfigError(f"--drift {text!r}: expected AXIS=SPEC@T[+RAMP] with AXIS in "
                          f"{', '.join(AXES)}")
    start, plus, ramp = when.partition("+")
    try:
        at_s, ramp_s = float(start), float(ramp) if plus else 0.0
    except ValueError:
        raise ConfigError(f"--drift {text!r}: T and RAMP must be seconds, got {when!r}") from None
    if not (math.isfinite(at_s) and at_s >= 0 and math.isfinite(ramp_s) and ramp_s >= 0):
        raise ConfigError(f"--drift {text!r}: T and RAMP must be finite and >= 0")
    try:
        model = parse_model(spec)
    except ConfigError as e:
        raise ConfigError(f"--drift {text!r}: {e}") from None
    return Drift(axis, model, at_s, ramp_s)


def _between(a: ProcessModel, b: ProcessModel, f: float) -> ProcessModel:
    """``a``'s parameters moved the fraction ``f`` of the way to ``b``'s (same kind)."""
    pa, pb = a.params(), b.params()
    return dataclasses.replace(a, **{k: pa[k] + f * (pb[k] - pa[k]) for k in pa})  # type: ignore[type-var]


@dataclass
class HilConfig:
    """Settings of the simulated platform."""

    models: Sequence[ProcessModel]
    p_min: np.ndarray
    p_max: np.ndarray
    v_max: np.ndarray | None
    rate_hz: float = 1000.0
    transport: str = "zenoh"
    setpoint_key: str = "platform/setpoint"
    feedback_key: str = "platform/feedback"
    status_key: str = "platform/status"
    feedback_every: int = 1
    accelerometer: Accelerometer = field(default_factory=Accelerometer)
    seed: int = 0
    can_interface: str = "udp_multicast"
    can_channel: str = "239.74.163.2"
    dbc: str = ""
    spin_us: float = 20.0
    duration_s: float = math.inf
    drifts: Sequence[Drift] = ()


class HilPlatform:
    """The simulated platform's work at each of its ticks, apart from the transports and the
    clock (so that tests can drive it tick by tick).

    The platform lives on wall time: a real one keeps moving while the simulator's thread is
    stalled, and its drives take each setpoint when it comes.  So frames are queued as they
    arrive (:meth:`take_frame`), and after a stall the skipped periods are simulated first
    (:meth:`catch_up`, at most :attr:`max_catch_up_s` of them), each with the frames stamped
    before its start -- what the platform would have had then -- and then the tick's own period
    with every frame received (:meth:`step`).  Without that, every missed tick would freeze the
    simulated platform for a period: under a few percent of missed ticks its dynamics would
    look that much slower (the rails' 186 ms lag becoming 195 ms or more), which no compensator
    tuned on the true model can cancel.  Frames from CAN carry no time: a stall is simulated on
    the setpoint held before it.
    """

    max_catch_up_s = 1.0

    def __init__(self, cfg: HilConfig) -> None:
        # position limits are enforced by the simulator at every tick; the velocity limit is
        # judged between consecutive frames with their own timestamps (the two clocks are not in
        # step, so one tick may see two frames' worth of motion)
        self.sim = PlatformSimulator(cfg.models, cfg.rate_hz, cfg.p_min, cfg.p_max, None,
                                     cfg.accelerometer, seed=cfg.seed)
        self.v_hard = None if cfg.v_max is None else [float(v) for v in cfg.v_max]
        self.setpoint = [0.0] * len(AXES)
        self.frames = 0
        self.bad = 0
        self.caught_up = 0
        """Periods simulated after a stall of the simulator's own loop."""
        self.age_n = 0
        """Setpoint frames whose age was counted, since the start."""
        self._age_at = np.full(AGE_RING, -np.inf)
        self._ages = np.zeros(AGE_RING)
        """A ring of when the newest frames were applied and their ages: the age is the
        period's start minus the frame's ``t`` (the service's tick), i.e. the
        transport and this loop's tick phase that the platform adds to the delay of its truth
        model, as the service's stamps see it."""
        self._max_catch_up = max(1, round(self.max_catch_up_s * cfg.rate_hz))
        self._period_s = 1.0 / cfg.rate_hz
        self._queue: deque[tuple[float, dict[str, float]]] = deque()
        self._prev_t: float | None = None
        self._prev = [0.0] * len(AXES)
        for d in cfg.drifts:  # each drift checked now, on a simulator of its axis alone
            truth = cfg.models[AXES.index(d.axis)]
            if d.model.kind != truth.kind:
                raise ConfigError(f"drift of {d.axis}: {d.model} is not of the kind of its "
                                  f"truth {truth}")
            PlatformSimulator([truth], cfg.rate_hz, [-1.0], [1.0]).set_model(0, d.model)
        self._drifts = sorted(cfg.drifts, key=lambda d: d.at_s)
        self._ramp_from: dict[int, ProcessModel] = {}
        self._next_drift_s = 0.0

    def drift_to(self, elapsed_s: float) -> None:
        """Apply the drifts due ``elapsed_s`` after the start (each start and end is logged at
        WARNING: the platform changed under the service)."""
        if elapsed_s < self._next_drift_s or not self._drifts:
            return
        self._next_drift_s = elapsed_s + DRIFT_STEP_S
        for j, d in enumerate(self._drifts):
            if elapsed_s < d.at_s or self._ramp_from.get(j) is d.model:
                continue  # not yet, or done
            i = AXES.index(d.axis)
            if j not in self._ramp_from:
                self._ramp_from[j] = self.sim.models[i]
                if d.ramp_s > 0:
                    log.warning("%s: the simulated platform drifts (--drift): truth ramping from "
                                "%s to %s over %g s (%.1f s after the start)", d.axis,
                                self.sim.models[i].spec(), d.model.spec(), d.ramp_s, elapsed_s)
            f = 1.0 if d.ramp_s <= 0 else min((elapsed_s - d.at_s) / d.ramp_s, 1.0)
            if f >= 1.0:
                was = self.sim.models[i].spec() if d.ramp_s <= 0 else self._ramp_from[j].spec()
                self.sim.set_model(i, d.model)
                self._ramp_from[j] = d.model
                log.warning("%s: the simulated platform drifted (--drift): truth now %s, was %s "
                            "(%.1f s after the start)", d.axis, d.model.spec(), was, elapsed_s)
            else:
                self.sim.set_model(i, _between(self._ramp_from[j], d.model, f))

    def take_frame(self, payload: bytes) -> None:
        """A setpoint frame of the service (zenoh), queued until the period it belongs to."""
        self.frames += 1
        try:
            frame = decode_output(payload)
            pos = {axis: float(v) for axis, v in frame["pos"].items()
                   if axis in AXES and isinstance(v, int | float)}
            t_frame = float(frame["t"])
        except (FrameError, AttributeError, TypeError, ValueError):
            self.bad += 1
            return
        self._queue.append((t_frame, pos))

    def _apply(self, until_t: float, tick_t: float | None = None) -> None:
        """Apply the queued frames stamped up to ``until_t``, in order (their axes replace the
        held setpoint; the velocity limit is judged between consecutive frames), at the period
        starting at wall time ``tick_t`` (their ages are counted, if given)."""
        queue = self._queue
        at = until_t if tick_t is None else tick_t
        while queue and queue[0][0] <= until_t:
            t_frame, pos = queue.popleft()
            self.take_axes(pos)
            self._judge_speed(t_frame)
            if math.isfinite(at):
                k = self.age_n % AGE_RING
                self._age_at[k] = at
                self._ages[k] = at - t_frame
                self.age_n += 1

    @property
    def setpoint_age_s(self) -> float:
        """Median age of the setpoint frames applied over the last :data:`AGE_WINDOW_S` (nan
        before any): the typical delay the stack adds, which a fit sees; a stall's few late
        frames move the mean, not this."""
        recent = self._recent_ages()
        return float(np.median(recent)) if recent.size else math.nan

    @property
    def setpoint_age_mean_s(self) -> float:
        """Mean age of the setpoint frames applied over the last :data:`AGE_WINDOW_S` (nan
        before any)."""
        recent = self._recent_ages()
        return float(np.mean(recent)) if recent.size else math.nan

    def _recent_ages(self) -> np.ndarray:
        """The ages of the frames applied over the last :data:`AGE_WINDOW_S` up to the newest."""
        if not self.age_n:
            return self._ages[:0]
        newest = self._age_at[(self.age_n - 1) % AGE_RING]
        return self._ages[self._age_at >= newest - AGE_WINDOW_S]

    def _judge_speed(self, t_frame: float) -> None:
        now_sp = list(self.setpoint)
        if self.v_hard is not None and self._prev_t is not None and t_frame > self._prev_t:
            dt = t_frame - self._prev_t
            for i, (v, was, v_max) in enumerate(zip(now_sp, self._prev, self.v_hard,
                                                    strict=True)):
                if abs(v - was) > v_max * dt * (1 + 1e-6):
                    self.sim.violations[i] += 1
        self._prev_t, self._prev = t_frame, now_sp

    def take_axes(self, got: dict[str, float]) -> None:
        """Setpoints by axis (decoded from CAN frames, or a queued frame's): they replace the
        held setpoint at once (names not in :data:`AXES` are ignored)."""
        for axis, value in got.items():
            if (i := AXIS_INDEX.get(axis)) is not None:
                self.setpoint[i] = value

    def catch_up(self, skipped: int, tick_t: float | None = None) -> None:
        """Simulate the ``skipped`` periods before the tick at wall time ``tick_t`` that the
        loop did not tick (a stall), each with the frames stamped before its start (none if
        ``tick_t`` is None: the held setpoint)."""
        n = min(skipped, self._max_catch_up)
        for j in range(n, 0, -1):
            if tick_t is not None:
                self._apply(tick_t - j * self._period_s)
            self.sim.step(self.setpoint)
        self.caught_up += n

    def step(self, tick_t: float | None = None) -> np.ndarray:
        """Simulate this tick's period (starting at wall time ``tick_t``, if known) with every
        frame received; returns the acceleration measured at its start."""
        self._apply(math.inf, tick_t)
        _, acc, _ = self.sim.step(self.setpoint)
        return acc


def run_hil(cfg: HilConfig, endpoints: ZenohEndpoints,
            stop: threading.Event | None = None) -> int:
    """Run until SIGTERM/SIGINT (or ``stop``, or ``duration_s``); returns the exit code."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    import zenoh

    plat = HilPlatform(cfg)
    sim = plat.sim
    receiver: Any = None
    if cfg.transport == "can":
        from motcomp.io.can_io import CanSetpointReceiver, open_bus
        from motcomp.resources import config_file

        receiver = CanSetpointReceiver(open_bus(cfg.can_interface, cfg.can_channel),
                                       cfg.dbc or config_file("motcomp.dbc"))
    with open_session(endpoints) as session, subnormals_flushed() as flushed, frozen_heap():
        _log_startup(cfg, endpoints, plat, flushed)
        # every frame, in order (a ring: never blocks zenoh, keeps the newest 4096)
        source = (session.declare_subscriber(cfg.setpoint_key, zenoh.handlers.RingChannel(4096))
                  if cfg.transport == "zenoh" else None)
        feedback = ZenohSink(session, cfg.feedback_key)
        status_pub = session.declare_publisher(cfg.status_key)
        clock = DeadlineClock(cfg.rate_hz, cfg.spin_us)
        t_wall0, t_mono0 = time.time(), time.perf_counter_ns()
        t_end = time.monotonic() + cfg.duration_s
        next_status = time.monotonic() + 1.0
        reported = np.zeros(len(AXES), dtype=np.int64)
        try:
            while not stop.is_set() and time.monotonic() < t_end:
                deadline, now = clock.wait()
                if source is not None:
                    while (sample := source.try_recv()) is not None:
                        plat.take_frame(sample.payload.to_bytes())
                    if clock.skipped:
                        plat.catch_up(clock.skipped, t_wall0 + (deadline - t_mono0) / 1e9)
                else:
                    got = receiver.poll()
                    if clock.skipped:
                        plat.catch_up(clock.skipped)
                    plat.take_axes(got)
                t = t_wall0 + (now - t_mono0) / 1e9
                plat.drift_to((now - t_mono0) / 1e9)
                acc = plat.step(t if cfg.transport == "zenoh" else None)
                if clock.ticks % cfg.feedback_every == 0:
                    # position and acceleration at the instant of this setpoint (the start of
                    # the period), stamped with it
                    y = sim.position_at_start
                    feedback.put(encode_feedback(t, dict(zip(AXES, y.tolist(), strict=True)),
                                                 dict(zip(AXES, acc.tolist(), strict=True))))
                if time.monotonic() >= next_status:
                    next_status += 1.0
                    new = sim.violations - reported
                    for j in np.nonzero(new)[0]:
                        log.warning("hard-limit violations on %s: %d", AXES[j], int(new[j]))
                    reported = sim.violations.copy()
                    status_pub.put(msgpack.packb(_status(plat, clock, receiver)))
        finally:
            final = _status(plat, clock, receiver)
            status_pub.put(msgpack.packb(final))
            log.info("%s", summary_text(final, "stopped" if stop.is_set() else "finished"))
            status_pub.undeclare()
            feedback.close()
            if source is not None:
                source.undeclare()
            if receiver is not None:
                receiver.close()
    return 0


def _log_startup(cfg: HilConfig, endpoints: ZenohEndpoints, plat: HilPlatform,
                 flushed: str) -> None:
    where = (f"CAN {cfg.can_interface} {cfg.can_channel} (DBC {cfg.dbc or 'shipped'})"
             if cfg.transport == "can" else f"zenoh {cfg.setpoint_key}")
    log.info("simulated platform at %g Hz; zenoh %s; setpoints from %s; feedback on %s, "
             "counters on %s at 1 Hz; %s", cfg.rate_hz, endpoints.describe(), where,
             cfg.feedback_key, cfg.status_key, flushed)
    v_hard = plat.v_hard
    for i, axis in enumerate(AXES):
        log.info("  %-9s truth %s; hard limits [%g, %g]%s", axis, cfg.models[i],
                 cfg.p_min[i], cfg.p_max[i],
                 "" if v_hard is None else f", |v| <= {v_hard[i]:g}")
    for d in cfg.drifts:
        log.info("  %-9s drifts to %s %g s after the start%s", d.axis, d.model.spec(), d.at_s,
                 f" (a ramp over {d.ramp_s:g} s)" if d.ramp_s else "")
    a = cfg.accelerometer
    log.info("accelerometer: %s", f"noise {a.noise_std:g}, bias {a.bias:g}, tremor {a.tremor_amp:g}"
             f" at {a.tremor_hz:g} Hz, quantum {a.lsb:g}" if (a.noise_std or a.bias or a.tremor_amp
                                                              or a.lsb) else "ideal")


def summary_text(status: dict[str, Any], how: str = "stopped") -> str:
    """One line of the platform's counters (from :func:`_status`'s map), said at exit."""
    viol = {a: n for a, n in status.get("violations", {}).items() if n}
    text = (f"{how}: {status['ticks']} ticks, {status['missed_ticks']} missed, "
            f"{status['caught_up']} periods caught up; setpoint frames received "
            f"{status['frames']} ({status['bad_frames']} bad)")
    age = status.get("setpoint_age_ms", math.nan)
    if math.isfinite(age):
        text += (f", applied {age:.2f} ms after their t (median of the last "
                 f"{AGE_WINDOW_S:g} s; mean "
                 f"{status.get('setpoint_age_mean_ms', math.nan):.2f} ms)")
    can = status.get("can")
    if can is not None:
        text += (f"; CAN frames {can['received']} (CRC errors {can['crc_errors']}, alive "
                 f"errors {can['alive_errors']}, unknown {can['unknown']})")
    return text + "; hard-limit violations: " + (
        ", ".join(f"{a} {n}" for a, n in viol.items()) if viol else "none")


def _status(plat: HilPlatform, clock: DeadlineClock, receiver: Any) -> dict[str, Any]:
    sim = plat.sim
    out: dict[str, Any] = {
        "t": time.time(), "ticks": clock.ticks, "missed_ticks": clock.missed,
        "missed_waiting_cpu": clock.missed_waiting,
        "caught_up": plat.caught_up, "frames": plat.frames, "bad_frames": plat.bad,
        "setpoint_age_ms": plat.setpoint_age_s * 1e3,
        "setpoint_age_mean_ms": plat.setpoint_age_mean_s * 1e3,
        "violations": dict(zip(AXES, sim.violations.tolist(), strict=True)),
        "position": dict(zip(AXES, sim.position.tolist(), strict=True)),
        "truth": {a: m.spec() for a, m in zip(AXES, sim.models, strict=True)},
    }
    if receiver is not None:
        out["can"] = {"received": receiver.received, "crc_errors": receiver.crc_errors,
                      "alive_errors": receiver.alive_errors, "unknown": receiver.unknown}
    return out
