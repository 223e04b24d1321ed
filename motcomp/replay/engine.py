"""The replay's engine: the service's own tick over a :class:`~motcomp.replay.plan.TickPlan`.

:func:`run_ticks` calls :func:`motcomp.core.tick.step` -- the function the service calls every
tick -- once per tick of the plan, at the tick's instant, with the recorded bytes of the input
frame the tick read (the tick checks them itself) and the number of deadlines missed before it
(the tick computes the catch-up steps itself).  Between ticks it does what the service does
between ticks: bypass switches (:func:`~motcomp.core.tick.set_bypass`) and the parking request
(:func:`~motcomp.core.tick.park`).  The same function on the same bytes at the same instants
gives the same numbers (in the same floating-point mode: subnormals flushed to zero where the
service's loop flushed them): a replay with the recorded config reproduces the recorded outputs
bit for bit (docs/REPLAY.md says when the instants are known exactly).

Catch-up rows of the plan are not stepped here: they are the ``skipped`` of the tick that
follows them, and their columns in :class:`EngineResult` are NaN (nothing was sent).
"""

from __future__ import annotations

import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig, new_tick, resolve_axes
from motcomp.core.axes import AXES
from motcomp.core.fpmode import subnormals_flushed
from motcomp.core.tick import TickParams, TickState, park, set_bypass, step, warm_start
from motcomp.record.frames import FLAG_BITS
from motcomp.record.session import InputStream
from motcomp.replay.plan import TickPlan, first_position

__all__ = ["MODES", "EngineResult", "initial_position", "run_ticks"]

MODES: tuple[str, ...] = ("", "rejoin", "stale", "parking")
"""Values of :attr:`EngineResult.mode`: index of the tick's mode (``TickOutput.mode``)."""
_MODE_INDEX = {m: i for i, m in enumerate(MODES)}
_BLOCK = 1 << 15  # ticks whose results are gathered before they are stored in the arrays


@dataclass
class EngineResult:
    """Per row of the plan (rows x 8 in :data:`~motcomp.core.axes.AXES` order where 2-D)."""

    ref: np.ndarray
    """The reference of the tick (NaN at catch-up rows)."""
    u: np.ndarray
    """The command sent (NaN at catch-up rows)."""
    limited: np.ndarray
    """The tick's own saturation verdict (``TickOutput.limited``, the ``sat:<axis>`` flags)."""
    mode: np.ndarray
    """Index in :data:`MODES`."""
    src_seq: np.ndarray
    """``seq`` of the last input the tick accepted (-1 before the first; -2 at catch-up rows)."""
    bypass: np.ndarray
    """Compensation off (the tick's bypass mask at that step)."""
    emit: np.ndarray
    """An output was sent (False for the steps computed to catch up after a stall)."""
    flags: np.ndarray | None = None
    """The tick's output flags as :data:`~motcomp.record.frames.FLAG_BITS` (0 at catch-up
    rows): comparable with a recording's bit for bit."""
    lag_s: np.ndarray | None = None
    """What the input's reconstruction adds to the delay beyond the smallest transit, after the
    step (s; :attr:`~motcomp.core.shaper.ReferenceShaper.lag_s`)."""
    rejected: dict[str, int] = field(default_factory=dict)
    """Input frames the replay's tick rejected, by reason (those that occurred)."""
    timings: dict[str, float] = field(default_factory=dict)


def initial_position(plan: TickPlan, inp: InputStream, axes: ResolvedAxes,
                     params: TickParams) -> np.ndarray:
    """Where a warm start puts the compensator at rest: the first frame (accepted by the tick,
    :func:`~motcomp.replay.plan.first_position`) within the limits, neutral for the axes it
    does not carry and undriven axes; zeros for a cold start."""
    p = np.zeros(len(AXES))
    if not plan.warm:
        return p
    pos = first_position(inp, int(plan.frame[0]), params)
    assert pos is not None, "a warm plan starts at a frame the tick accepts"
    for a, v in pos.items():
        if axes.driven[a]:
            p[a] = min(max(v, float(axes.limits.p_min[a])), float(axes.limits.p_max[a]))
    return p


def run_ticks(plan: TickPlan, inp: InputStream, cfg: ServiceConfig,
              progress: Callable[[float], None] | None = None,
              until_row: int | None = None) -> EngineResult:
    """Run the plan through the tick (see the module docstring), up to ``until_row`` (the
    rows from it on are left NaN: a trial).  The frames of :attr:`TickPlan.absent` are left
    out of their ticks.

    A warm plan starts at rest at :func:`initial_position`, with no start-up blend until the
    first frame is accepted.  Catch-up rows must be consecutive periods ending just before a
    tick (as :func:`~motcomp.replay.plan.build_plan` makes them).  The ticks compute in the
    floating-point mode the recorded service's loop did (:attr:`TickPlan.flushed`,
    :func:`~motcomp.core.fpmode.flush_subnormals`).
    """
    t0 = time.perf_counter()
    axes = resolve_axes(cfg)
    params, state = new_tick(cfg, axes)
    current = params
    if plan.warm:
        warm_start(state, params, initial_position(plan, inp, axes, params).tolist())
        current = replace(params, shaper=replace(params.shaper, startup_s=0.0))
    known = recorded_bypass_axes(plan, axes)
    if plan.bypass0 is not None:
        _set_recorded_bypass(state, plan.bypass0, known)
    n = plan.rows
    emit = plan.emit
    ticks = np.flatnonzero(emit)
    skipped = _skipped(plan, ticks)
    if until_row is not None:
        skipped = skipped[ticks < until_row]
        ticks = ticks[ticks < until_row]
    absent = frozenset(plan.absent)
    # what happens between ticks, by tick number: parking, then a bypass switch
    hooks: dict[int, list[Callable[[], None]]] = {}

    def at(row: int, fn: Callable[[], None]) -> None:
        k = int(np.searchsorted(ticks, row))  # the first tick at or after ``row``
        if k < ticks.size:
            hooks.setdefault(k, []).append(fn)

    if plan.park is not None:
        row_p, park_ns = plan.park
        at(row_p, lambda: park(state, params, park_ns))
    bypass_from: list[tuple[int, np.ndarray]] = [(0, state.comp.bypass.copy())]
    for row_b, mask in plan.bypass_events:
        def switch(mask: np.ndarray = mask, row_b: int = row_b) -> None:
            _set_recorded_bypass(state, mask, known)
            k = int(np.searchsorted(ticks, row_b))
            bypass_from.append((int(ticks[k]) - int(skipped[k]), state.comp.bypass.copy()))
        at(row_b, switch)
    u = np.full((n, len(AXES)), np.nan)
    ref = np.full((n, len(AXES)), np.nan)
    limited = np.zeros((n, len(AXES)), dtype=bool)
    mode = np.zeros(n, dtype=np.int8)
    src_seq = np.full(n, -2, dtype=np.int64)
    flags = np.zeros(n, dtype=np.int64)
    lag = np.full(n, np.nan)
    flag_bit = FLAG_BITS
    data, bounds = inp.data, inp.bounds
    warm_pending = plan.warm
    shaper = state.shaper
    mode_index = _MODE_INDEX
    with subnormals_flushed(plan.flushed):  # the recorded loop's mode
        for b0 in range(0, ticks.size, _BLOCK):
            if progress is not None:
                progress(b0 / max(ticks.size, 1))
            rows = ticks[b0:b0 + _BLOCK]
            fr = plan.frame[rows]
            assert plan.frame_lo is not None
            first = plan.frame_lo[rows]
            has = fr >= 0
            lo = np.where(has, first, -1).tolist()
            hi = (fr + 1).tolist()
            now_l = plan.now_ns[rows].tolist()
            rx_l = (plan.rx_ns[rows] if plan.rx_ns is not None else np.zeros(rows.size, np.int64)
                    ).tolist()
            skip_l = skipped[b0:b0 + _BLOCK].tolist()
            u_b: array[float] = array("d")
            ref_b: array[float] = array("d")
            lim_b: array[int] = array("b")
            mode_b: array[int] = array("b")
            src_b: array[int] = array("q")
            flag_b: array[int] = array("q")
            lag_b: array[float] = array("d")
            for i in range(rows.size):
                hook = hooks.get(b0 + i)
                if hook is not None:
                    for fn in hook:
                        fn()
                o = lo[i]
                frames = ([data[bounds[k]:bounds[k + 1]] for k in range(o, hi[i])
                           if not absent or k not in absent] if o >= 0 else None)
                out = step(state, current, now_l[i], frames, skip_l[i], now_l[i] + rx_l[i])
                if warm_pending and state.accepted:
                    warm_pending = False
                    current = params
                u_b.extend(out.u)
                ref_b.extend(shaper.ref)
                lim_b.extend(out.limited)
                mode_b.append(mode_index[out.mode])
                src_b.append(out.src_seq)
                flag_b.append(sum(flag_bit.get(f, 0) for f in out.flags))
                lag_b.append(shaper.lag_s)
            m = rows.size
            u[rows] = np.frombuffer(u_b, dtype=np.float64).reshape(m, len(AXES))
            ref[rows] = np.frombuffer(ref_b, dtype=np.float64).reshape(m, len(AXES))
            limited[rows] = np.frombuffer(lim_b, dtype=np.int8).reshape(m, len(AXES)) != 0
            mode[rows] = np.frombuffer(mode_b, dtype=np.int8)
            src_seq[rows] = np.frombuffer(src_b, dtype=np.int64)
            flags[rows] = np.frombuffer(flag_b, dtype=np.int64)
            lag[rows] = np.frombuffer(lag_b, dtype=np.float64)
    bypass = np.zeros((n, len(AXES)), dtype=bool)
    for (r0, mask), (r1, _) in zip(bypass_from, [*bypass_from[1:], (n, None)], strict=True):
        bypass[r0:r1] = mask
    if progress is not None:
        progress(1.0)
    rejected = {k: v for k, v in state.rejected_by_reason.items() if v}
    return EngineResult(ref, u, limited, mode, src_seq, bypass, emit.copy(), flags, lag,
                        rejected,
                        {"engine_s": time.perf_counter() - t0,
                         "us_per_tick": (time.perf_counter() - t0) / max(ticks.size, 1) * 1e6})


def _skipped(plan: TickPlan, ticks: np.ndarray) -> np.ndarray:
    """Per tick: the catch-up rows just before it (its missed deadlines, up to
    ``MAX_CATCH_UP``), after checking that they are consecutive periods ending one period
    before the tick."""
    cu = np.flatnonzero(~plan.emit)
    cu = cu[cu < (ticks[-1] if ticks.size else 0)]  # trailing catch-up rows: no tick follows
    if cu.size:
        step_ns = plan.now_ns[cu + 1] - plan.now_ns[cu]
        assert np.all(step_ns == plan.period_ns), "catch-up rows must be consecutive periods"
    before = np.cumsum(~plan.emit)[ticks]  # catch-up rows up to each tick
    return np.diff(before, prepend=0)


def recorded_bypass_axes(plan: TickPlan, axes: ResolvedAxes) -> tuple[bool, ...]:
    """Axes the recorded bypass applies to: driven here, and driven by the recorded service."""
    known = plan.bypass_axes if plan.bypass_axes is not None else [True] * len(AXES)
    return tuple(bool(d and k) for d, k in zip(axes.driven, known, strict=True))


def _set_recorded_bypass(state: TickState, mask: np.ndarray, known: tuple[bool, ...]) -> None:
    """The recorded bypass mask (the PID's, then the prediction's, :class:`TickPlan`) on the
    axes it applies to; the others keep theirs."""
    n = len(AXES)
    pid, off = mask[:n], mask[n:2 * n] if mask.size >= 2 * n else np.zeros(n, dtype=bool)
    set_bypass(state, [bool(m) if k else bool(b) for m, k, b in zip(
        pid, known, state.comp.bypass, strict=True)],
        [bool(m) if k else bool(o) for m, k, o in zip(off, known, state.prediction_off,
                                                       strict=True)])

