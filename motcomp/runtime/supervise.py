"""Supervision of the platform model in the running service: :class:`Supervisor`.

Every ``supervision.period_s`` the service's main thread hands the outputs and feedback of the
last period (:meth:`motcomp.runtime.monitor.MotionMonitor.chunk`) to a process of its own,
which keeps the last ``window_s`` (:class:`motcomp.runtime.estimate.LiveWindow`) and estimates
each driven axis' platform (:func:`motcomp.runtime.estimate.estimate_axis`) at low priority; the
loop thread does none of it.  The main thread judges the answers (:class:`DriftJudge`) and
shows them in the status' ``model_mismatch`` block; an alarm is logged at WARNING (at its
start, then at most every :data:`ALARM_LOG_S`) and, through the status frames, recorded.

Layout of the block, the rules and what an alarm means: docs/SUPERVISION.md.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import math
import os
import pickle
import queue
import subprocess
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from motcomp.config import ResolvedAxes, SupervisionConfig
from motcomp.core.axes import AXES
from motcomp.core.models import ProcessModel
from motcomp.runtime import child
from motcomp.runtime.estimate import EstimateSettings, LiveWindow
from motcomp.runtime.monitor import MAX_JUDGED_MISSED_SHARE

__all__ = ["ALARM_LOG_S", "BLIND_AFTER_S", "CONFIDENCE_Z", "CPU_SHARE_MAX", "MIN_RUN",
           "DriftJudge", "Supervisor", "settings_of"]

log = logging.getLogger("motcomp.supervise")

ALARM_LOG_S = 60.0
"""An alarm still on is logged again after this long."""
WORKER_NICE = 19
"""The estimator process' niceness: the lowest weight of the ordinary scheduler, so the loop's
CPU comes first and the estimator still gets its share on a saturated host (``SCHED_IDLE``,
tried first, starved it there: no estimate in 120 s at load 18 on 2 cores)."""
ESTIMATE_TIMEOUT_S = 30.0
"""An estimate not answered within this long: the estimator process is stopped (a new one
starts with the next period)."""
CONFIDENCE_Z = 2.0
"""An estimate exceeds a bound when it does by this many of its standard errors."""
MIN_RUN = 3
"""Fewest informative estimates that start (or clear) an alarm, however long the hold."""
KEEP_MARGIN_S = 5.0
"""The estimator keeps this much more than a window."""
BLIND_AFTER_S = 120.0
"""An axis none of whose windows of motion was judged for this long is *unsupervised*: said in
its status and, once, in the log (docs/SUPERVISION.md)."""
CPU_SHARE_MAX = 0.10
"""The estimator process' CPU time is at most this share of the wall time: the next chunk is
sent no sooner than the last estimate's CPU time over this share after the one before."""


def _p1d_spec(model: ProcessModel) -> str | None:
    """The spec of ``model``'s P1D reduction (what an OE model is judged through), if any."""
    try:
        return model.to_p1d().spec()
    except Exception:  # a model without one is judged in its own form
        return None


def settings_of(cfg: SupervisionConfig) -> EstimateSettings:
    """The estimator's settings from the config's ``[supervision]``."""
    return EstimateSettings(window_s=cfg.window_s, band_hz=tuple(cfg.band_hz),  # type: ignore[arg-type]
                            min_motion=cfg.min_motion, max_delay_se_ms=cfg.max_delay_se_ms)


# --- the estimator process --------------------------------------------------------------------
_WINDOW: LiveWindow | None = None


def _estimate(request: tuple[dict[str, np.ndarray], list[str], dict[str, ProcessModel],
                             EstimateSettings]) -> tuple[str, Any]:
    """In the estimator process: add the chunk (columns: ``axes``) to the window, estimate;
    ``("ok", (results, CPU seconds it took))`` or ``("error", text)``."""
    global _WINDOW
    chunk, axes, models, settings = request
    cpu0 = time.process_time()
    try:
        keep = settings.window_s + KEEP_MARGIN_S
        if _WINDOW is None or _WINDOW.keep_s != keep or _WINDOW.axes != axes or chunk["lost"]:
            _WINDOW = LiveWindow(keep, axes)  # a gap in what was sent: the window starts again
        _WINDOW.add(chunk["t_out"], chunk["u"], chunk["t_fb"], chunk["acc"])
        res = _WINDOW.estimate(models, settings)
    except Exception as exc:  # a bug: said, the process goes on
        return ("error", f"{type(exc).__name__}: {str(exc)[:120]}")
    return ("ok", (res, time.process_time() - cpu0))


def serve() -> None:
    """The estimator process' main: answer chunks until stdin closes, at niceness
    :data:`WORKER_NICE` (its CPU time bounded by the supervisor's budget,
    :data:`CPU_SHARE_MAX`)."""
    with contextlib.suppress(AttributeError, OSError):  # the ordinary scheduler, lowest weight
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError):  # not permitted: the service's priority
        os.nice(WORKER_NICE - os.nice(0))
    for name in ("scipy.optimize", "scipy.signal"):  # once, before the first estimate's CPU
        importlib.import_module(name)  # time is counted against its budget
    child.serve(_estimate)


# --- the judge --------------------------------------------------------------------------------
@dataclass
class _AxisState:
    alarm: bool = False
    exceeding_since: float | None = None
    """Frame-clock instant of the first of the informative estimates beyond a bound in a row."""
    exceeding_n: int = 0
    within_since: float | None = None
    within_n: int = 0
    alarm_since: float | None = None
    alarms: int = 0
    logged: float = -math.inf
    last: dict[str, Any] = field(default_factory=dict)
    last_informative: dict[str, Any] | None = None
    """The figures of the last informative window (what a retune takes when the latest window
    told nothing)."""
    informative: int = 0
    judged: int = 0
    last_t: float | None = None
    """The end of the last window judged (frame clock)."""
    blind_s: float = 0.0
    """Time of motion since the last informative window."""
    blind: Counter[str] = field(default_factory=Counter)
    """Why the windows of that time were not judged: a count per kind of reason."""
    last_reason: dict[str, str] = field(default_factory=dict)
    """The latest reason of each kind."""
    unsupervised: bool = False
    verdict: str = ""
    """The last informative estimate's: ``within``, ``exceeds`` or ``at the bound``."""


# what each kind of reason a window is not judged for asks of the host or of the driving
_NEEDS = (
    ("stalls", "a host that keeps the service's and the platform's deadlines: the stalls cut "
               "out most of each window (docs/DEPLOYMENT.md: a core of its own, "
               "real-time priority)"),
    ("uncertain", "driving that moves the axis in the band for longer: the delay was not "
                  "determined to the bound (more slaloms and lane changes, or a longer "
                  "supervision.window_s; the host's stalls that are not cut widen it too)"),
    ("limiter", "a command within the axis' limits: the limiter acted on most ticks"),
    ("explains", "a model of the platform's kind: the model explains too little of the "
                 "measured acceleration (or the accelerometer does not measure this axis)"),
    ("feedback", "the platform's measured acceleration of this axis in its feedback "
                 "(acc, docs/WIRE.md)"),
)


def _still(reason: str) -> bool:
    """Whether a window was not judged because the axis did not move (nothing to see there:
    not a blind window)."""
    return reason.startswith(("too little motion", "the command is constant"))


def _kind(reason: str) -> str:
    """The kind of a reason a window was not judged for (a key of :data:`_NEEDS`), or
    ``"other"``."""
    for key, words in (("stalls", ("stalls of the host", "of its deadlines")),
                       ("uncertain", ("uncertain",)),
                       ("limiter", ("the limiter acted",)), ("explains", ("explains",)),
                       ("feedback", ("feedback", "no outputs"))):
        if any(w in reason for w in words):
            return key
    return "other"


class DriftJudge:
    """Turns estimates into alarms, per axis.

    An estimate *exceeds* when it is informative and its residual delay lies beyond
    ``delay_bound_ms``, or its gain error beyond ``gain_bound``, by more than
    :data:`CONFIDENCE_Z` standard errors (the 95 % interval is outside the bound); it is
    *within* when both intervals lie inside their bounds.  An alarm starts when the informative
    estimates over ``hold_s`` -- at least :data:`MIN_RUN` of them, the first at least
    ``hold_s`` before the last -- all exceeded; it clears when they were all within.  An
    estimate that is neither (its interval holds a bound) restarts both runs; one that is not
    informative tells nothing either way and changes neither run.  An alarm stays as it is
    until it clears.  An axis' state is ``drift`` while its alarm is on, else the last
    estimate's verdict: ``within``, ``exceeds`` (no alarm yet: the run is shorter than
    ``hold_s``), ``at the bound`` (neither), or ``not informative``.

    An axis whose windows with motion in the band were not informative for
    :data:`BLIND_AFTER_S` is *unsupervised* (its state; a WARNING once, with the reasons and
    what the host or the driving would need) until a window is informative again.
    """

    def __init__(self, cfg: SupervisionConfig) -> None:
        self.cfg = cfg
        self.axes: dict[str, _AxisState] = {}

    def update(self, axis: str, fig: dict[str, Any], t: float | None, now: float
               ) -> str | None:
        """Judge one estimate of ``axis`` whose window ends at ``t`` (frame clock, s; None: a
        window without its end, which adds no time); returns a WARNING text when an alarm
        starts, or is still on after :data:`ALARM_LOG_S` (``now``: monotonic s), else None."""
        cfg = self.cfg
        st = self.axes.setdefault(axis, _AxisState())
        st.judged += 1
        st.last = fig
        since = 0.0 if st.last_t is None or t is None else max(t - st.last_t, 0.0)
        if t is not None:
            st.last_t = t
        if not fig.get("informative"):
            reason = str(fig.get("reason") or "")
            if _still(reason):
                return None  # the axis did not move: nothing to see, not blind
            st.blind_s += since
            st.blind[_kind(reason)] += 1
            st.last_reason[_kind(reason)] = reason
            if not st.unsupervised and st.blind_s >= BLIND_AFTER_S:
                st.unsupervised = True
                return self.blind_text(axis, st)
            return None
        st.informative += 1
        st.last_informative = fig
        if st.unsupervised:
            log.info("%s: supervised again: a window was judged after %.0f s of motion without",
                     axis, st.blind_s)
        st.blind_s, st.unsupervised = 0.0, False
        st.blind.clear()
        st.last_reason.clear()
        delay, gain = fig["residual_delay_ms"], fig["gain_error"]
        z_delay = CONFIDENCE_Z * fig["residual_delay_se_ms"]
        z_gain = CONFIDENCE_Z * fig["gain_error_se"]
        exceeds = (abs(delay) - z_delay > cfg.delay_bound_ms
                   or abs(gain) - z_gain > cfg.gain_bound)
        within = (abs(delay) + z_delay <= cfg.delay_bound_ms
                  and abs(gain) + z_gain <= cfg.gain_bound)
        st.verdict = "exceeds" if exceeds else "within" if within else "at the bound"
        if st.last_t is None:  # informative, but nowhere in time yet: nothing to hold
            return None
        t = st.last_t
        if not exceeds and not within:  # the interval holds a bound: neither run goes on
            st.exceeding_since = st.within_since = None
            st.exceeding_n = st.within_n = 0
        elif exceeds:
            st.within_since, st.within_n = None, 0
            if st.exceeding_since is None:
                st.exceeding_since = t
            st.exceeding_n += 1
            if (not st.alarm and t - st.exceeding_since >= cfg.hold_s
                    and st.exceeding_n >= MIN_RUN):
                st.alarm, st.alarm_since = True, t
                st.alarms += 1
                st.logged = now
                return self.text(axis, fig, "starts")
        else:
            st.exceeding_since, st.exceeding_n = None, 0
            if st.within_since is None:
                st.within_since = t
            st.within_n += 1
            if st.alarm and t - st.within_since >= cfg.hold_s and st.within_n >= MIN_RUN:
                st.alarm, st.alarm_since = False, None
                log.info("%s: model mismatch cleared: residual delay %.2f ms, gain error "
                         "%+.1f %% in the band", axis, delay, 100 * gain)
        if st.alarm and now - st.logged >= ALARM_LOG_S:
            st.logged = now
            return self.text(axis, fig, "still on")
        return None

    def text(self, axis: str, fig: dict[str, Any], how: str) -> str:
        """The alarm's WARNING, with the numbers behind it."""
        e = fig["estimate"]
        return (f"{axis}: model mismatch {how}: the platform now delivers the compensated "
                f"motion {fig['residual_delay_ms']:+.2f} +- {fig['residual_delay_se_ms']:.2f} ms "
                f"late with a gain error of {100 * fig['gain_error']:+.1f} % at "
                f"{fig['at_hz']:.2f} Hz (bounds {self.cfg.delay_bound_ms:g} ms, "
                f"{100 * self.cfg.gain_bound:g} %, held {self.cfg.hold_s:g} s): estimate "
                f"{e['spec']} (Td {e['Td_ms']:.2f} +- {e['Td_se_ms']:.2f} ms; identified "
                f"{e['identified']}) against the model {fig['model']}; retune: motcomp "
                f"identify --from-status --axis {axis}")

    def blind_text(self, axis: str, st: _AxisState) -> str:
        """The WARNING of an axis that became unsupervised: why, and what would help."""
        whys = "; ".join(f"{n} x {st.last_reason[k]!r}" for k, n in st.blind.most_common())
        needs = [need for key, need in _NEEDS if key in st.blind]
        return (f"{axis}: unsupervised: no window was judged in {st.blind_s:.0f} s of motion "
                f"({whys}); a drift of the platform would not be seen.  It needs "
                + ("; or ".join(needs) if needs else "the reasons above addressed") + ".")

    def block(self, axis: str) -> dict[str, Any]:
        st = self.axes.get(axis)
        if st is None:
            return {"state": "waiting", "alarm": False, "alarms": 0, "blind_s": 0.0,
                    "unsupervised": False}
        fig = st.last
        state = ("drift" if st.alarm else "unsupervised" if st.unsupervised
                 else st.verdict if fig.get("informative") else "not informative")
        return {"state": state, "alarm": st.alarm, "alarm_since_t": st.alarm_since,
                "alarms": st.alarms, "windows": st.judged, "informative_windows": st.informative,
                "blind_s": st.blind_s, "unsupervised": st.unsupervised, **fig,
                "last_informative": st.last_informative if st.last_informative is not fig
                else None}


# --- the service's side ------------------------------------------------------------------------
class _Estimator:
    """The estimator process, spoken to by a thread of its own: the pipe's writes and reads
    block there, never in the service's main thread (a child still importing, or a large
    chunk, would otherwise stall it).  :meth:`ask` hands a request over; :meth:`answer` takes
    the reply, ``("ok", value)`` or ``("error", text)``, without waiting."""

    def __init__(self) -> None:
        self._requests: queue.Queue[Any] = queue.Queue()
        self._replies: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="motcomp-supervise",
                                        daemon=True)
        self._thread.start()

    def ask(self, request: Any) -> None:
        self._requests.put(request)

    def answer(self) -> tuple[str, Any] | None:
        try:
            return self._replies.get_nowait()
        except queue.Empty:
            return None

    def kill(self) -> None:
        """Stop the process now (a write or read the thread is blocked in fails, and the
        request is answered with an error); the next request starts a new one."""
        with self._lock:
            proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()

    def close(self) -> None:
        self._requests.put(None)
        self.kill()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while (request := self._requests.get()) is not None:
            with self._lock:
                proc = self._proc
                if proc is None or proc.poll() is not None:
                    proc = self._proc = child.spawn(
                        "from motcomp.runtime.supervise import serve; serve()")
            try:
                reply = child.ask(proc, request, ESTIMATE_TIMEOUT_S)
            except (OSError, EOFError, ValueError, pickle.PickleError, TimeoutError) as exc:
                proc.kill()
                proc.wait()
                for f in (proc.stdin, proc.stdout):
                    if f is not None:
                        f.close()
                what = (f"an estimate took longer than {ESTIMATE_TIMEOUT_S:g} s"
                        if isinstance(exc, TimeoutError)
                        else f"the estimator process stopped ({type(exc).__name__})")
                reply = ("error", what)
            self._replies.put(reply)
        with self._lock:
            proc, self._proc = self._proc, None
        if proc is not None:
            proc.kill()
            proc.wait()


class Supervisor:
    """The estimator process and the judge (:meth:`poll`, :meth:`status`: main thread).

    :meth:`poll` is called by the service's main thread often (every 20 ms): it collects a
    finished estimate (without waiting) and, every ``period_s``, sends the next chunk (or keeps
    it for the next, while the estimator is busy).  Nothing here raises or blocks: a failed or
    hung estimator process (no answer within :data:`ESTIMATE_TIMEOUT_S`) is stopped, restarted
    with the next period and said in the block and the log.  The process ends with the service,
    also when the service dies (its stdin closes)."""

    def __init__(self, cfg: SupervisionConfig, axes: ResolvedAxes) -> None:
        self.cfg = cfg
        self.judge = DriftJudge(cfg)
        self.set_axes(axes)
        self._estimator: _Estimator | None = None
        self._busy_since: float | None = None
        """When the request the estimator works on was handed over (None: idle)."""
        self._sent_at = -math.inf
        """When the last request was handed over."""
        self._send_after = -math.inf
        """The CPU budget: no request before this."""
        self._started: float | None = None
        """When the first chunk was taken (for the estimator's CPU share)."""
        self._now = 0.0
        self._answered: float | None = None
        """When the last estimate was answered (or the first request sent)."""
        self.starved = False
        """No estimate answered for :data:`BLIND_AFTER_S`: every axis is unsupervised."""
        self._cursor = (0, 0)
        self._next = 0.0
        self._pending: list[dict[str, Any]] = []
        self.cpu_s = 0.0
        self.estimates = 0
        self.errors = 0
        self.last_error = ""
        self._shares: deque[tuple[float, int, tuple[int, ...], int]] = deque()
        """``(now, ticks, acted, missed)`` at each chunk: the window's conditions."""

    def set_axes(self, axes: ResolvedAxes) -> None:
        """The config's models in force (at start and after each accepted reload): each axis'
        ``model`` as written, a P2UZD as a P2UZD (:func:`~motcomp.runtime.estimate.estimate_axis`
        says how each kind is judged).  An axis whose model a reload replaced is judged anew
        against it (its alarm, runs and blindness start over): the estimate of the platform is
        the compensator's business no more than before, the model it is judged against is."""
        old = getattr(self, "models", {})
        self.models = {a: axes.plants[i] for i, a in enumerate(AXES) if axes.driven[i]}
        # the specs an estimate may name (the model's own, or its P1D reduction's), computed
        # once here: not at each judgement, on the service's main thread
        self._specs = {a: {m.spec(), _p1d_spec(m)} - {None} for a, m in self.models.items()}
        for axis, model in self.models.items():
            before = old.get(axis)
            if before is None or before.spec() == model.spec():
                continue
            st = self.judge.axes.pop(axis, None)
            if st is not None:
                log.info("%s: the model is now %s (was %s)%s: supervision judges against it "
                         "from the next estimate", axis, model.spec(), before.spec(),
                         ", its model mismatch alarm ends with the model it was raised on"
                         if st.alarm else "")

    def reconfigure(self, cfg: SupervisionConfig, axes: ResolvedAxes) -> None:
        """A reload's ``[supervision]`` and models (``window_s`` is a restart key)."""
        self.cfg = cfg
        self.judge.cfg = cfg
        self.set_axes(axes)

    def close(self) -> None:
        """Stop the estimator process and its thread (safe to call twice)."""
        est, self._estimator = self._estimator, None
        self._busy_since = None
        if est is not None:
            est.close()

    def poll(self, monitor: Any, to_frame_s: Any, now: float, ticks: int, acted: list[int],
             missed: int) -> list[str]:
        """Collect, judge and send; returns the WARNING texts to log (alarms, an axis become
        unsupervised).

        ``to_frame_s(ns)`` maps loop instants to the outputs' ``t``; ``ticks``, ``acted`` and
        ``missed`` are the loop's counters (for the window's limiter share and deadlines).
        Every ``period_s`` the new outputs and feedback are taken from ``monitor``; they are
        sent to the estimator when it is idle and its CPU budget allows
        (:data:`CPU_SHARE_MAX`), kept meanwhile."""
        if not self.cfg.enabled or not self.models:
            if self._estimator is not None:  # turned off by a reload: nothing is judged
                self.close()
                self.judge = DriftJudge(self.cfg)
                self._pending, self._cursor = [], monitor.chunk((0, 0))[0]
            return []
        self._now = now
        warnings: list[str] = []
        est = self._estimator
        if self._busy_since is not None and est is not None:
            reply = est.answer()
            if reply is None and now - self._busy_since > ESTIMATE_TIMEOUT_S + 5.0:
                est.kill()  # a write the thread is blocked in: it answers with an error
            elif reply is not None:
                self._busy_since = None
                kind, value = reply
                if kind != "ok":
                    self._failed(str(value)[:160])
                else:
                    results, cpu = value
                    self.cpu_s += float(cpu)
                    self.estimates += 1
                    self._answered = now
                    if self.starved:
                        self.starved = False
                        log.info("model supervision: estimates again")
                    # the budget: this estimate's CPU time is at most CPU_SHARE_MAX of the
                    # time from its request to the next
                    self._send_after = self._sent_at + float(cpu) / CPU_SHARE_MAX
                    warnings = self._judge(results, now)
        if (self._answered is not None and not self.starved
                and now - self._answered >= BLIND_AFTER_S):
            self.starved = True
            warnings.append(
                f"model supervision: unsupervised: no estimate in {now - self._answered:.0f} s "
                f"({self.errors} failed: {self.last_error or 'none answered'}); its process gets "
                "no CPU time on this host, so no drift of any axis would be seen.  It needs a "
                "host with CPU to spare for it (at most "
                f"{100 * CPU_SHARE_MAX:g} % of a core): stop other work on this one")
        if now >= self._next:
            if self._started is None:
                self._started = self._answered = now
            self._next = now + self.cfg.period_s
            self._take(monitor, to_frame_s, now, ticks, acted, missed)
        if self._pending and self._busy_since is None and now >= self._send_after:
            merged: dict[str, Any] = {k: np.concatenate([c[k] for c in self._pending])
                                      for k in self._pending[0] if k != "lost"}
            merged["lost"] = any(c["lost"] for c in self._pending)
            self._pending = []
            if self._estimator is None:
                self._estimator = _Estimator()
            self._estimator.ask((merged, list(self.models), dict(self.models),
                                 settings_of(self.cfg)))
            self._busy_since = self._sent_at = now
        return warnings

    def _take(self, monitor: Any, to_frame_s: Any, now: float, ticks: int, acted: list[int],
              missed: int) -> None:
        """The outputs and feedback since the last chunk, kept until they are sent."""
        self._shares.append((now, ticks, tuple(acted), missed))
        self._cursor, raw = monitor.chunk(self._cursor)
        cols = [AXES.index(a) for a in self.models]
        fb_t = np.where(np.isfinite(raw["fb_sent"]), raw["fb_sent"], to_frame_s(raw["fb_ns"]))
        self._pending.append({"t_out": to_frame_s(raw["t_ns"]), "u": raw["u"][:, cols],
                              "t_fb": fb_t, "acc": raw["acc"][:, cols], "lost": raw["lost"]})
        # what the estimator keeps at most: older chunks are of no use to it
        keep = max(1, math.ceil((self.cfg.window_s + KEEP_MARGIN_S) / self.cfg.period_s))
        if len(self._pending) > keep:
            del self._pending[:-keep]
            self._pending[0]["lost"] = True

    def _failed(self, text: str) -> None:
        self.errors += 1
        self.last_error = text
        log.error("model supervision: %s (a new estimator process starts with the next "
                  "period)", text)

    def _window_conditions(self, now: float) -> tuple[list[float] | None, float | None]:
        """The limiter share per axis and the missed-deadline share over the last window."""
        shares = self._shares
        horizon = now - self.cfg.window_s
        while len(shares) > 2 and shares[1][0] <= horizon:
            shares.popleft()
        if len(shares) < 2:
            return None, None
        (_, t0, a0, m0), (_, t1, a1, m1) = shares[0], shares[-1]
        if t1 <= t0:
            return None, None
        limited = [(x - y) / (t1 - t0) for x, y in zip(a1, a0, strict=True)]
        return limited, (m1 - m0) / (t1 - t0 + m1 - m0)

    def _judge(self, results: dict[str, dict[str, Any]], now: float) -> list[str]:
        limited, missed = self._window_conditions(now)
        out = []
        for axis, fig in results.items():
            if fig.get("model") not in self._specs.get(axis, ()):
                continue  # estimated against a model a reload has replaced meanwhile
            fig["missed_share"] = missed  # the loop's stalls are cut out of the estimate
            own = str(fig.get("reason") or "")
            if missed is not None and missed > MAX_JUDGED_MISSED_SHARE and not _still(own):
                # the host's stalls first: they are why the estimate is uncertain, if it is
                fig["reason"] = (f"the loop missed {100 * missed:.0f} % of its deadlines "
                                 f"over the window (more than {100 * MAX_JUDGED_MISSED_SHARE:g}"
                                 " %): the figures carry its stalls"
                                 + (f" (and {own})" if own and not fig.get("informative")
                                    else ""))
                fig["informative"] = False
            elif fig.get("informative"):
                share = limited[AXES.index(axis)] if limited else 0.0
                if share > self.cfg.max_limited_share:
                    fig["informative"] = False
                    fig["reason"] = (f"the limiter acted on {100 * share:.0f} % of the ticks "
                                     f"(more than {100 * self.cfg.max_limited_share:g} %)")
            to_t = fig.get("to_t")
            text = self.judge.update(axis, fig, None if to_t is None else float(to_t), now)
            if text is not None:
                out.append(text)
        return out

    def status(self) -> dict[str, Any]:
        """The status' ``model_mismatch`` block."""
        cfg = self.cfg
        return {"enabled": cfg.enabled, "window_s": cfg.window_s, "period_s": cfg.period_s,
                "band_hz": list(cfg.band_hz), "delay_bound_ms": cfg.delay_bound_ms,
                "gain_bound": cfg.gain_bound, "hold_s": cfg.hold_s,
                "estimates": self.estimates, "cpu_s": self.cpu_s,
                "cpu_share": (self.cpu_s / (self._now - self._started)
                              if self._started is not None and self._now > self._started
                              else None),
                "errors": self.errors,
                "last_error": self.last_error,
                "alarm": any(self.judge.block(a)["alarm"] for a in self.models),
                "starved": self.starved,
                "axes": {a: self._block(a) for a in self.models}}

    def _block(self, axis: str) -> dict[str, Any]:
        block = self.judge.block(axis)
        if self.starved and not block["alarm"]:
            block.update(state="unsupervised", unsupervised=True)
        return block
