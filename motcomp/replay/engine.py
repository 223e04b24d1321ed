"""Two ways to run the compensator over a :class:`~motcomp.replay.plan.TickPlan`.

:func:`run_ticks` -- the reference
    The service itself (:class:`~motcomp.runtime.service.Service` with in-memory adapters),
    driven tick by tick: ``_catch_up`` and ``tick(now_ns)`` with the recorded frames, bypass
    changes queued as commands, parking requested between ticks.  About 25 us a tick.

:func:`run_fast` -- the offline engine, ~100x faster, same numbers to ~1e-11
    The reference comes from :func:`~motcomp.replay.reference.reconstruct`.  Per axis, the
    compensator is split where its structure allows:

    * With model-recovery anti-windup the PID and its model see ``M v`` (the *raw* output), so
      the raw output is a linear function of the reference whatever the limiter does:
      ``v = F r`` with ``F = Cr / (1 + Cy M)`` (:mod:`motcomp.core.loop`).  A stretch without
      bypass changes runs the kernel's own recursion (:func:`_loop_step`, a copy of
      ``Compensator.step`` without the limiter) for ``order + 2`` samples, then
      ``scipy.signal.lfilter`` on ``F`` with the initial conditions of those samples
      (``lfiltic``): the difference equation of ``F`` holds once ``order`` samples of the same
      dynamics are behind.
    * The limiter (:func:`~motcomp.core.saturation.limit_axis`) passes a feasible target
      through bit-exactly, and feasibility of sample ``k`` depends only on the two samples
      before: it is evaluated for the whole stretch at once, assuming passthrough; at each
      infeasible sample the exact ``limit_axis`` runs sample by sample until two samples in a
      row pass through again, after which the assumption holds again.  The target tracker
      (a linear filter of the clamped target) is computed with ``lfilter`` for the stretch.
    * Bypassed axes: the target is the reference (plus the minimum-jerk fade after a switch),
      through the same limiter; the PID state at the end of a bypass stretch (needed only if
      compensation is switched back on) is rebuilt from its difference equations in bulk.

    Differences from the service's numbers come only from floating-point ordering inside
    ``lfilter`` (about 1e-11 m on a ZN rails axis); the engine itself is deterministic.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig
from motcomp.core.axes import AXES
from motcomp.core.compensator import p1d_coefficients
from motcomp.core.loop import model_tf, pid_tf
from motcomp.core.saturation import POS, VEL, axis_constants, limit_axis
from motcomp.record.session import InputStream
from motcomp.replay.plan import TickPlan

__all__ = ["EngineResult", "initial_position", "run_fast", "run_ticks", "saturated"]

_HARD = POS | VEL


@dataclass
class EngineResult:
    """Per row of the plan: the reference, the command and the limiter flags (rows x 8)."""

    ref: np.ndarray
    u: np.ndarray
    flags: np.ndarray
    target: np.ndarray
    """What the limiter was asked for (the raw PID output, or the bypass target)."""
    mode: np.ndarray
    bypass: np.ndarray
    """Per row and axis: compensation off (the service's bypass mask at that step)."""
    emit: np.ndarray
    """Per row: an output was sent (False for the steps computed to catch up after a stall)."""
    timings: dict[str, float] = field(default_factory=dict)


def saturated(res: EngineResult, tol: float, rate_hz: float = 1000.0) -> np.ndarray:
    """Rows x axes: the service's "sat:<axis>" rule -- a position or velocity limit acted, or
    the command departs from its target by more than ``tol`` on a 20 ms average (the service's
    recursion, which ``lfilter`` reproduces operation for operation)."""
    from scipy.signal import lfilter

    out = np.zeros(res.flags.shape, dtype=bool)
    alpha = min(1.0, 1.0 / (0.02 * rate_hz))
    # the average runs on the ticks that sent an output (views when all did)
    rows = None if bool(res.emit.all()) else np.flatnonzero(res.emit)
    for a in range(res.flags.shape[1]):
        flags = res.flags[:, a] if rows is None else res.flags[rows, a]
        acted = np.flatnonzero(flags)
        if acted.size == 0:
            continue
        first = int(acted[0])  # before the first action the average is exactly zero
        f = flags[first:]
        u = res.u[first:, a] if rows is None else res.u[rows[first:], a]
        target = res.target[first:, a] if rows is None else res.target[rows[first:], a]
        avg = lfilter([alpha], [1.0, -(1.0 - alpha)], np.where(f != 0, u - target, 0.0))
        k = acted - first
        verdict = ((f[k] & _HARD) != 0) | (np.abs(avg[k]) > tol)
        out[acted if rows is None else rows[acted], a] = verdict
    return out


def initial_position(plan: TickPlan, inp: InputStream, axes: ResolvedAxes) -> np.ndarray:
    """Where a warm start puts the compensator at rest: the first consumed frame, within the
    limits (neutral for axes it does not carry and undriven axes); zeros for a cold start."""
    p = np.zeros(len(AXES))
    if not plan.warm:
        return p
    f = int(plan.frame[np.flatnonzero(plan.frame >= 0)[0]])
    row = inp.pos[f]
    for a in range(len(AXES)):
        if axes.driven[a] and not math.isnan(row[a]):
            p[a] = min(max(float(row[a]), float(axes.limits.p_min[a])),
                       float(axes.limits.p_max[a]))
    return p


# --- the reference: the service, tick by tick -------------------------------------------------
def run_ticks(plan: TickPlan, inp: InputStream, cfg: ServiceConfig, progress: Any = None
              ) -> EngineResult:
    """Run the plan through the service's own ``tick`` (see the module docstring); catch-up
    rows are stepped as ``Service._catch_up`` steps them."""
    from motcomp.io.memory import MemorySink, MemorySource
    from motcomp.io.wire import decode_output, encode_input
    from motcomp.io.zenoh_io import ZenohEndpoints
    from motcomp.runtime.service import Service

    svc = Service(cfg, ZenohEndpoints())
    src, sink = MemorySource(), MemorySink()
    svc.attach(src, [sink])
    axes = svc.axes
    loop = cfg.loop
    if plan.warm:
        svc.comp.reset(initial_position(plan, inp, axes))
        svc.shaper.configure(svc.shaper.ramp_speed, loop.stale_after_s, loop.hold_s,
                             loop.rejoin_s, 0.0)
    known = _recorded_bypass_axes(plan, axes)
    _apply_bypass(svc, plan.bypass0, known)
    events = dict(plan.bypass_events)
    n = plan.rows
    u = np.full((n, len(AXES)), np.nan)
    flags = np.zeros((n, len(AXES)), dtype=np.int8)
    target = np.full((n, len(AXES)), np.nan)
    ref = np.full((n, len(AXES)), np.nan)
    mode = np.zeros(n, dtype=np.int8)
    bypass = np.zeros((n, len(AXES)), dtype=bool)
    first_seen = not plan.warm
    period = plan.period_ns
    j = 0
    while j < n:
        if progress is not None and j % 4096 == 0:
            progress(j / n)
        # catch-up rows precede their tick; the service computes their instants itself
        k = j
        while k < n and not plan.emit[k]:
            k += 1
        if k >= n:
            break
        if plan.park is not None and j <= plan.park[0] <= k:
            svc.shaper.park(plan.park[1])
        if k > j:  # Service._catch_up, step by step (to keep each step's numbers)
            assert int(plan.now_ns[k] - plan.now_ns[j]) == (k - j) * period
            for c in range(j, k):
                r_c, _ = svc.shaper.reference(int(plan.now_ns[c]) / 1e9)
                u[c] = svc.comp.step(r_c)
                ref[c], target[c], flags[c] = r_c, svc.comp.raw_output, svc.comp.flags
                bypass[c] = svc.comp.bypass
        if k in events:
            svc.commands.append(_bypass_command(svc, events[k], known))
        f = int(plan.frame[k])
        if f >= 0:
            row = inp.pos[f]
            pos = {AXES[a]: float(row[a]) for a in np.flatnonzero(~np.isnan(row))}
            t = float(inp.t[f])
            if math.isnan(t):
                src.push(msgpack.packb({"seq": int(inp.seq[f]), "pos": pos}))
            else:
                src.push(encode_input(int(inp.seq[f]), t, pos))
        svc.tick(int(plan.now_ns[k]))
        if not first_seen and f >= 0:
            first_seen = True
            svc.shaper.configure(svc.shaper.ramp_speed, loop.stale_after_s, loop.hold_s,
                                 loop.rejoin_s, loop.startup_s)
        frame = decode_output(sink.payloads.pop())
        u[k] = [frame["pos"][a] for a in AXES]
        fl = set(frame["flags"])
        flags[k] = [(POS | VEL) if f"sat:{a}" in fl else 0 for a in AXES]
        target[k] = svc.comp.raw_output
        ref[k] = svc.shaper.ref
        bypass[k] = svc.comp.bypass
        mode[k] = next((i for i, m in enumerate(("", "rejoin", "stale", "parking"))
                        if m and m in fl), 0)
        j = k + 1
    return EngineResult(ref, u, flags, target, mode, bypass, plan.emit.copy())


def _recorded_bypass_axes(plan: TickPlan, axes: ResolvedAxes) -> tuple[bool, ...]:
    """Axes the recorded bypass applies to: driven here, and driven by the recorded service."""
    known = plan.bypass_axes if plan.bypass_axes is not None else [True] * len(AXES)
    return tuple(bool(d and k) for d, k in zip(axes.driven, known, strict=True))


def _bypass_command(svc: Any, mask: np.ndarray, driven: tuple[bool, ...]
                    ) -> Callable[[], None]:
    def apply() -> None:
        _apply_bypass(svc, mask, driven)
    return apply


def _apply_bypass(svc: Any, mask: np.ndarray | None, driven: tuple[bool, ...]) -> None:
    if mask is None:
        return
    new = [bool(m) if d else b for m, d, b in zip(mask, driven, svc.comp.bypass, strict=True)]
    if new != svc.comp.bypass.tolist():
        svc.comp.set_bypass(new)
        svc._set_bypass_flags()


# --- the offline engine ------------------------------------------------------------------------
@dataclass
class _Params:
    kp: float
    kih: float
    ad: float
    bd: float
    b: float
    c: float
    phi: float
    g0: float
    g1: float
    d: int
    K: float
    lim: tuple[float, ...]
    fade_step: float
    hist_len: int
    bF: np.ndarray
    aF: np.ndarray


def _params(cfg: ServiceConfig, axes: ResolvedAxes) -> list[_Params]:
    """Per axis: the kernel's constants exactly as :class:`Compensator` computes them."""
    rate = float(cfg.loop.rate_hz)
    h = 1.0 / rate
    lims = axis_constants(axes.limits, h)
    fade_s = cfg.loop.bypass_fade_s
    fade_step = h / fade_s if fade_s > 0 else 1.0
    max_td = max(m.Td for m in axes.models)
    hist_s = 0.5  # as build_compensator asks
    if hist_s < max_td:
        hist_s = max_td
    length = 1
    while length < math.ceil(hist_s * rate) + 2:
        length *= 2
    out = []
    for m, g, lim in zip(axes.models, axes.gains, lims, strict=True):
        phi, g0, g1, d = p1d_coefficients(m, h)
        (nr, dc), (ny, _) = pid_tf(g, h)
        nm, dm = model_tf(m, h)
        num = np.polymul(nr, dm)
        den = np.polyadd(np.polymul(dc, dm), np.polymul(ny, nm))
        size = max(num.size, den.size)
        num = np.concatenate([np.zeros(size - num.size), num])
        den = np.concatenate([np.zeros(size - den.size), den])
        out.append(_Params(g.kp, g.ki * h, g.tf / (g.tf + h), g.kd / (g.tf + h), g.b, g.c,
                           phi, g0, g1, d, m.K, lim, fade_step, length,
                           num / den[0], den / den[0]))
    return out


class _State:
    """One axis of the kernel's state (the variables of ``Compensator.step``)."""

    def __init__(self, p: float, prm: _Params) -> None:
        self.r = p
        self.u = p
        self.vel = 0.0
        self.track = (p, 0.0, 0.0)  # the limiter's target tracker
        self.xc = prm.K * p
        self.y = self.xc
        self.hist: deque[float] = deque([p] * prm.hist_len, maxlen=prm.hist_len)
        self.D = 0.0
        self.w_prev = prm.c * p - self.xc
        self.I = p - prm.kp * (prm.b * p - self.y) - self.D  # Compensator._reseed
        self.bypass = False
        self.fade_offset = 0.0
        self.fade_progress = 1.0

    def set_bypass(self, on: bool) -> None:
        """``Compensator.set_bypass`` for this axis."""
        if on == self.bypass:
            return
        if on:
            self.fade_offset = self.u - self.r
            self.fade_progress = 0.0
        self.bypass = on


def _loop_step(st: _State, prm: _Params, r: float) -> float:
    """One step of the kernel's PID and model, compensation on (``Compensator.step`` minus the
    limiter); returns the raw output ``v``."""
    y = st.xc
    st.y = y
    w = prm.c * r - y
    d = prm.ad * st.D + prm.bd * (w - st.w_prev)
    st.D = d
    st.w_prev = w
    v = prm.kp * (prm.b * r - y) + st.I + d
    st.I += prm.kih * (r - y)
    hist = st.hist
    hist.append(v)
    h0 = hist[-prm.d] if prm.d > 0 else hist[0]
    st.xc = prm.phi * y + prm.g0 * h0 + prm.g1 * hist[-prm.d - 1]
    st.r = r
    return v


def _raw_output(r: np.ndarray, st: _State, prm: _Params, need_state: bool) -> np.ndarray:
    """``v`` for a stretch with compensation on (see the module docstring); the PID/model state
    is carried to the end of the stretch only if ``need_state``."""
    from scipy.signal import lfilter, lfiltic

    n = r.size
    order = prm.aF.size - 1
    warm = min(n, order + 2)
    v = np.empty(n)
    for k, rk in enumerate(r[:warm].tolist()):
        v[k] = _loop_step(st, prm, rk)
    if n > warm:
        zi = lfiltic(prm.bF, prm.aF, v[warm - 1::-1][:order], r[warm - 1::-1][:order])
        v[warm:], _ = lfilter(prm.bF, prm.aF, r[warm:], zi=zi)
        if need_state:
            _advance(st, prm, r[warm:], v[warm:])
    return v


def _advance(st: _State, prm: _Params, r: np.ndarray, v: np.ndarray) -> None:
    """The PID/model state after a stretch, from the kernel's difference equations in bulk.
    ``v`` is what the model was fed (the raw output, or the command while bypassed)."""
    from scipy.signal import lfilter

    n = r.size
    if n == 0:
        return
    L, d = prm.hist_len, prm.d
    past = np.fromiter(st.hist, dtype=np.float64, count=L)
    ext = np.concatenate([past, v])
    k = np.arange(n)
    h0 = ext[L + k + 1 - d] if d > 0 else ext[k + 1]
    h1 = ext[L + k - d]
    xin = prm.g0 * h0 + prm.g1 * h1
    xc, _ = lfilter([1.0], [1.0, -prm.phi], xin, zi=[prm.phi * st.xc])
    y = np.concatenate([[st.xc], xc[:-1]])
    w = prm.c * r - y
    D, _ = lfilter([prm.bd, -prm.bd], [1.0, -prm.ad], w, zi=[prm.ad * st.D - prm.bd * st.w_prev])
    # the integrator from v = kp (b r - y) + I + D at the last step (summing its increments
    # would integrate the rounding of y, ~1e-9 after a second), then its own update; while
    # bypassed (tracking) the raw output equals the command, so the same relation holds
    rl, yl, Dl = float(r[-1]), float(y[-1]), float(D[-1])
    st.I = (float(v[-1]) - (prm.kp * (prm.b * rl - yl) + Dl)) + prm.kih * (rl - yl)
    st.hist.extend(v[-L:].tolist())
    st.xc = float(xc[-1])
    st.y = float(y[-1])
    st.D = float(D[-1])
    st.w_prev = float(w[-1])
    st.r = float(r[-1])


def _tracker_tf(lim: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Transfer functions from the clamped target to the three tracker states after each update
    ``s[k] = F s[k-1] + G x[k]`` (``(3, 4)`` numerators, common denominator)."""
    from scipy.signal import ss2tf

    f = np.array(lim[12:21]).reshape(3, 3)
    g = np.array(lim[21:24]).reshape(3, 1)
    num, den = ss2tf(f, g, f, g)  # q[k+1] = F q[k] + G x[k], s[k] = F q[k] + G x[k]
    return np.asarray(num), np.asarray(den)


def _tracker(x: np.ndarray, s0: tuple[float, float, float], lim: tuple[float, ...]
             ) -> np.ndarray:
    """The limiter's target tracker over ``x`` (clamped targets) from state ``s0``: ``(3, n)``.
    The first samples run the kernel's own recursion, the rest ``lfilter`` from them."""
    from scipy.signal import lfilter, lfiltic

    f00, f01, f02, f10, f11, f12, f20, f21, f22, g0, g1, g2 = lim[12:24]
    n = x.size
    out = np.empty((3, n))
    warm = min(n, 3)
    sp, sv, sa = s0
    for k in range(warm):
        t = float(x[k])
        sp, sv, sa = (f00 * sp + f01 * sv + f02 * sa + g0 * t,
                      f10 * sp + f11 * sv + f12 * sa + g1 * t,
                      f20 * sp + f21 * sv + f22 * sa + g2 * t)
        out[:, k] = (sp, sv, sa)
    if n > warm:
        num, den = _tracker_tf(lim)
        for j in range(3):
            zi = lfiltic(num[j], den, out[j, warm - 1::-1], x[warm - 1::-1])
            out[j, warm:], _ = lfilter(num[j], den, x[warm:], zi=zi)
    return out


def _limit(target: np.ndarray, st: _State, lim: tuple[float, ...], need_state: bool = True
           ) -> tuple[np.ndarray, np.ndarray]:
    """``limit_axis`` over a stretch (see the module docstring): ``(u, flags)``.

    Feasibility is evaluated with the same comparisons as ``limit_axis``; the braking test
    only where the axis is within twice the worst braking distance of an end stop (elsewhere it
    holds with a wide margin), and the position test only at the first sample (later ones
    follow clamped targets).  The target tracker is run only if the limiter acts, or if the
    state is needed after the stretch."""
    (h, inv_h, p_min, p_max, v_max, ah, _ah2, _two_a, inv_two_a, *_rest) = lim
    n = target.size
    tc = np.clip(target, p_min, p_max)
    vel = np.empty(n)
    vel[0] = (tc[0] - st.u) * inv_h
    np.subtract(tc[1:], tc[:-1], out=vel[1:])
    vel[1:] *= inv_h
    v_prev = np.empty(n)
    v_prev[0] = st.vel
    v_prev[1:] = vel[:-1]
    ok = v_prev - ah <= vel
    ok &= vel <= v_prev + ah
    del v_prev
    ok &= np.abs(vel) <= v_max
    ok[0] &= p_min <= st.u <= p_max
    margin = 2.0 * v_max * (h + v_max * inv_two_a)
    near = np.flatnonzero((tc > p_max - margin) | (tc < p_min + margin)) + 1
    near = np.concatenate([[0], near[near < n]])
    up_ = np.concatenate([[st.u], tc[near[1:] - 1]])
    vn = vel[near]
    up = vn * (h + vn * inv_two_a) <= p_max - up_
    down = -vn * (h - vn * inv_two_a) <= up_ - p_min
    ok[near] &= np.where(vn > 0.0, up, down)
    flags = np.zeros(n, dtype=np.int8)
    bad = np.flatnonzero(~ok)
    u = tc
    if bad.size or need_state:
        trk = _tracker(tc, st.track, lim)
    u0, v0 = st.u, st.vel
    pos = 0
    nb = bad.size
    b = 0
    while b < nb:
        k = int(bad[b])
        if k > pos:
            u0, v0 = float(tc[k - 1]), float(vel[k - 1])
        sp, sv, sa = ((float(trk[0, k - 1]), float(trk[1, k - 1]), float(trk[2, k - 1]))
                      if k > 0 else st.track)
        run = 0
        i = k
        while i < n:
            ti = float(target[i])
            ui, vi, sp, sv, sa, fl = limit_axis(ti, u0, v0, sp, sv, sa, lim)
            u[i] = ui
            flags[i] = fl
            u0, v0 = ui, vi
            i += 1
            run = run + 1 if fl == 0 else 0
            if run >= 2:
                break
        pos = i
        b = int(np.searchsorted(bad, pos))
    if pos < n or nb == 0:  # ended in a passthrough stretch
        st.u, st.vel = float(tc[-1]), float(vel[-1])
    else:
        st.u, st.vel = u0, v0
    if bad.size or need_state:
        st.track = (float(trk[0, -1]), float(trk[1, -1]), float(trk[2, -1]))
    return u, flags


def _bypass_targets(r: np.ndarray, st: _State, fade_step: float) -> np.ndarray:
    """The bypass target: the reference, plus the minimum-jerk fade of the offset at the switch
    (``Compensator.step``, bypass branch)."""
    out = r.copy()
    p = st.fade_progress
    off = st.fade_offset
    n = r.size
    k = 0
    while p < 1.0 and k < n:
        out[k] = float(r[k]) + off * (1.0 - p**3 * (10.0 - 15.0 * p + 6.0 * p * p))
        p = min(p + fade_step, 1.0)
        k += 1
    st.fade_progress = p
    return out


def run_fast(plan: TickPlan, inp: InputStream, cfg: ServiceConfig, axes: ResolvedAxes,
             progress: Any = None) -> EngineResult:
    """Run the plan through the offline engine (see the module docstring)."""
    import time

    from motcomp.replay.reference import reconstruct

    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    def sub(lo: float, hi: float) -> Any:
        return None if progress is None else (lambda x: progress(lo + (hi - lo) * x))

    ref, mode = reconstruct(plan, inp, cfg, axes, sub(0.0, 0.4))
    timings["reference_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    n = plan.rows
    prms = _params(cfg, axes)
    p0 = initial_position(plan, inp, axes)
    known = _recorded_bypass_axes(plan, axes)
    u = np.empty((n, len(AXES)), order="F")
    flags = np.zeros((n, len(AXES)), dtype=np.int8, order="F")
    target = np.empty((n, len(AXES)), order="F")
    bypass = np.zeros((n, len(AXES)), dtype=bool, order="F")
    for a in range(len(AXES)):
        prm = prms[a]
        st = _State(float(p0[a]), prm)
        on0 = bool(axes.bypass[a])
        st.set_bypass(on0)
        if plan.warm:  # reset after the config's bypass: no fade
            st.fade_offset, st.fade_progress = 0.0, 1.0
        if plan.bypass0 is not None and known[a]:
            st.set_bypass(bool(plan.bypass0[a]))
        changes = [(r_, bool(m[a])) for r_, m in plan.bypass_events if known[a]]
        bounds = [0] + [r_ for r_, on in changes] + [n]
        states = [st.bypass] + [on for _, on in changes]
        for s in range(len(bounds) - 1):
            lo, hi = bounds[s], bounds[s + 1]
            st.set_bypass(states[s])
            if hi <= lo:
                continue
            rr = ref[lo:hi, a]
            bypass[lo:hi, a] = st.bypass
            more = s + 2 < len(bounds)  # the PID state is needed after this stretch
            if st.bypass:
                tgt = _bypass_targets(rr, st, prm.fade_step)
                u[lo:hi, a], flags[lo:hi, a] = _limit(tgt, st, prm.lim, more)
                if more:
                    _advance(st, prm, rr, u[lo:hi, a])
            else:
                tgt = _raw_output(rr, st, prm, more)
                u[lo:hi, a], flags[lo:hi, a] = _limit(tgt, st, prm.lim, more)
            target[lo:hi, a] = tgt
        if progress is not None:
            progress(0.4 + 0.6 * (a + 1) / len(AXES))
    timings["compensator_s"] = time.perf_counter() - t1
    return EngineResult(ref, u, flags, target, mode, bypass, plan.emit.copy(), timings)
