"""The compensator's reference at every row of a :class:`~motcomp.replay.plan.TickPlan`,
computed as :class:`~motcomp.runtime.shaper.ReferenceShaper` would, but in bulk.

The shaper has two regimes.  *Live and settled* (mode ``""``) -- nearly every tick of a session
-- is a closed form of the last frames::

    on a frame:  offset = min(offset + OFFSET_LEAK (now - offset_at), now - t)   (sequential)
                 per axis: slope = (v - v_prev) / dt if 0 < dt <= stale_after_s else 0
                           period = dt if period == 0 else period + 0.05 (dt - period)
    per tick:    tau = (now - offset) - t_frame
                 c = 1.5 period
                 bound = min(max(max_extrapolation_s, c) if late <= c else 2 c, age + c)
                 ref = v + slope * (tau if 0 < tau < bound else bound if tau >= bound else 0)
                 (age = now - the arrival of the last frame, late = its transit - offset)

which is evaluated here with numpy for all the ticks of a live stretch, with the *same*
floating-point operations in the same order (so the result is bit for bit the shaper's); only
the two recursions (offset, period) run as a plain loop over the frames.  Everything else --
start-up and rejoin blends, stale hold and ramp, parking -- runs through a real
``ReferenceShaper`` tick by tick; its state is handed over at the boundaries (the shaper's own
attributes: this module and the shaper are tested together).  Long stale stretches whose
reference cannot change (holding, or ramp finished) are filled without stepping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from motcomp.config import ResolvedAxes, ServiceConfig
from motcomp.core.axes import AXES
from motcomp.record.session import InputStream
from motcomp.replay.plan import TickPlan
from motcomp.runtime.service import Service
from motcomp.runtime.shaper import OFFSET_LEAK, ReferenceShaper

__all__ = ["MODES", "ReplayShaper", "make_shaper", "reconstruct"]

MODES = ("", "rejoin", "stale", "parking")
"""Row modes (index = code in the mode array)."""
_CODE = {m: i for i, m in enumerate(MODES)}


@dataclass
class _Live:
    live: list[float]
    t_frame: list[float]
    slope: list[float]
    period: list[float]
    offset: float
    offset_at: float
    last_input_s: float
    excess: float


class ReplayShaper(ReferenceShaper):
    """The service's shaper, with its live state exported and imported between ticks."""

    def export_live(self) -> _Live:
        assert self._offset is not None and self.last_input_s is not None
        return _Live(self.live[:], self._t_frame[:], self._slope[:], self._period[:],
                     self._offset, self._offset_at, self.last_input_s, self._excess)

    def import_live(self, st: _Live, ref: list[float]) -> None:
        self.live, self._t_frame, self._slope, self._period = (
            st.live[:], st.t_frame[:], st.slope[:], st.period[:])
        self._offset, self._offset_at, self.last_input_s = st.offset, st.offset_at, \
            st.last_input_s
        self._excess = st.excess
        self.ref = ref
        self._blend_offset = None
        self._stale_since = None
        self._move = None

    def stale_fill_end(self, now: np.ndarray, j: int, stop: int) -> int:
        """While stale, after the row ``j - 1``: the first row in ``[j, stop)`` at which
        :meth:`reference` may return another value than at ``j - 1`` (holding: until ``hold_s``
        has passed; ramping: never once the ramp is over), or ``j``."""
        if self._stale_since is None or self.parking:
            return j
        if self._move is None:
            held = now[j:stop] - self._stale_since >= self.hold_s
            return j + (int(np.argmax(held)) if held.any() else stop - j)
        _, done = self._move.at(float(now[j - 1]))
        return stop if done else j


def make_shaper(cfg: ServiceConfig, axes: ResolvedAxes) -> ReplayShaper:
    """A shaper built exactly as :class:`~motcomp.runtime.service.Service` builds its own."""
    return ReplayShaper(axes.driven, Service._ramp_speeds(cfg, axes), cfg.loop.stale_after_s,
                        cfg.loop.hold_s, cfg.loop.rejoin_s, cfg.loop.startup_s,
                        cfg.input.reconstruction == "linear", cfg.input.max_extrapolation_s)


def frame_args(inp: InputStream, f: int) -> tuple[dict[str, float], float | None]:
    """``(pos, t)`` of input ``f`` as the service's ``on_input`` receives them."""
    row = inp.pos[f]
    pos = {AXES[a]: float(row[a]) for a in np.flatnonzero(~np.isnan(row))}
    t = float(inp.t[f])
    return pos, (None if math.isnan(t) else t)


def reconstruct(plan: TickPlan, inp: InputStream, cfg: ServiceConfig, axes: ResolvedAxes,
                progress: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """``(ref, mode)``: the reference (rows x 8) and the shaper's mode code (:data:`MODES`) of
    every row of the plan."""
    n = plan.rows
    now = plan.now_ns.astype(np.float64) / 1e9  # = now_ns / 1e9 in Python, exactly
    ref = np.zeros((n, len(AXES)), order="F")
    mode = np.zeros(n, dtype=np.int8)
    sh = make_shaper(cfg, axes)
    loop = cfg.loop
    if plan.warm:  # mid-run: no start-up blend
        sh.configure(sh.ramp_speed, loop.stale_after_s, loop.hold_s, loop.rejoin_s, 0.0)
    frame = plan.frame
    frame_rows = np.flatnonzero(frame >= 0)
    # stale rows: no frame for stale_after_s (the same test as ReferenceShaper.is_stale)
    k = np.searchsorted(frame_rows, np.arange(n), side="right") - 1
    last_in = np.where(k >= 0, now[frame_rows[np.maximum(k, 0)]], now[0])
    breaks = np.flatnonzero(now - last_in > loop.stale_after_s)
    if plan.park is not None:
        breaks = np.union1d(breaks, [plan.park[0]])
    driven = [a for a in range(len(AXES)) if axes.driven[a]]
    cap_max = cfg.input.max_extrapolation_s
    linear = cfg.input.reconstruction == "linear"
    j = 0
    first_seen = False
    while j < n:
        if progress is not None:
            progress(j / n)
        if plan.park is not None and j == plan.park[0]:
            sh.park(plan.park[1])
        f = int(frame[j])
        if f >= 0:
            pos, t = frame_args(inp, f)
            sh.on_input(pos, float(now[j]), t)
            if plan.warm and not first_seen:
                first_seen = True
                sh.configure(sh.ramp_speed, loop.stale_after_s, loop.hold_s, loop.rejoin_s,
                             loop.startup_s)
        r, m = sh.reference(float(now[j]))
        ref[j] = r
        mode[j] = _CODE[m]
        j += 1
        if j >= n:
            break
        if m == "stale":  # fill rows whose reference cannot change
            b = np.searchsorted(frame_rows, j)
            nxt = int(frame_rows[b]) if b < frame_rows.size else n
            if plan.park is not None and plan.park[0] >= j:
                nxt = min(nxt, plan.park[0])
            stop = sh.stale_fill_end(now, j, nxt)
            if stop > j:
                ref[j:stop] = r
                mode[j:stop] = _CODE["stale"]
                j = stop
            continue
        if m != "" or sh.parking or sh.last_input_s is None:
            continue
        b = np.searchsorted(breaks, j)
        j1 = int(breaks[b]) if b < breaks.size else n
        if j1 <= j:
            continue
        st = _live_stretch(sh.export_live(), j, j1, now, frame, inp, driven, linear,
                           cfg.loop.stale_after_s, cap_max, ref)
        sh.import_live(st, ref[j1 - 1].tolist())
        j = j1
    return ref, mode


def _offsets(off0: float, at0: float, now_f: np.ndarray, transit: np.ndarray) -> np.ndarray:
    """The clock-offset recursion of ``ReferenceShaper.on_input`` over a stretch of frames::

        off = min(off + OFFSET_LEAK * (now - off_at), transit)      (transit < off: transit)

    bit for bit.  When every value lies in one binade (the usual case: the loop's monotonic
    clock minus the sender's wall clock) each addition rounds to the same grid, ``fl(off + c) =
    off + round(c / ulp) ulp``, so the recursion is a min-plus scan over integers:
    ``O_k = S_k + min(O_0, min_{j<=k} (T_j - S_j))`` with ``S`` the cumulated increments.
    Otherwise (or if an increment is an exact half-ulp tie) it runs as a loop."""
    n = now_f.size
    at_prev = np.empty(n)
    at_prev[0] = at0
    at_prev[1:] = now_f[:-1]
    c = OFFSET_LEAK * (now_f - at_prev)
    vals = np.concatenate([[off0], transit])
    _, e = np.frexp(vals)
    if n and vals[0] != 0.0 and np.all(e == e[0]) and np.all(np.sign(vals) == np.sign(vals[0])):
        ulp = math.ldexp(1.0, int(e[0]) - 53)
        q = c / ulp
        if not np.any(q - np.floor(q) == 0.5):
            S = np.cumsum(np.rint(q).astype(np.int64))
            T = (transit / ulp).astype(np.int64)
            O0 = int(off0 / ulp)
            O = S + np.minimum(np.minimum.accumulate(T - S), O0)
            return np.asarray(O * ulp)
    offs = np.empty(n)
    off = off0
    for i, (tr, inc) in enumerate(zip(transit.tolist(), c.tolist(), strict=True)):
        if tr < off:
            off = tr
        else:
            o2 = off + inc
            off = o2 if o2 < tr else tr
        offs[i] = off
    return offs


def _periods(p0: float, dt: np.ndarray, fresh: np.ndarray) -> np.ndarray:
    """The average-interval recursion (``period += 0.05 (dt - period)`` on fresh frames, ``dt``
    when it was 0) with ``lfilter``: equal to the shaper's to an ulp or two.  The period only
    enters the extrapolation's bound (1.5 periods), so this changes a reference by at most an
    ulp of its value, and only at ticks where that bound binds (a frame later than 1.5 periods
    beyond the fastest transit, at the tick it arrives)."""
    from scipy.signal import lfilter

    out = np.empty(dt.size)
    idx = np.flatnonzero(fresh)
    if not idx.size:
        out[:] = p0
        return out
    d = dt[idx]
    p = np.empty(idx.size)
    if p0 == 0.0:
        p[0] = d[0]
        if idx.size > 1:
            p[1:], _ = lfilter([0.05], [1.0, -0.95], d[1:], zi=[0.95 * d[0]])
    else:
        p[:], _ = lfilter([0.05], [1.0, -0.95], d, zi=[0.95 * p0])
    if idx.size == dt.size:
        return p
    k = np.cumsum(fresh) - 1  # the last fresh frame at or before each frame
    out[:] = np.where(k >= 0, p[np.maximum(k, 0)], p0)
    return out


def _live_stretch(st: _Live, j0: int, j1: int, now: np.ndarray, frame: np.ndarray,
                  inp: InputStream, driven: list[int], linear: bool, stale_after_s: float,
                  cap_max: float, ref: np.ndarray) -> _Live:
    """Fill ``ref[j0:j1]`` (live, settled rows) and return the shaper state after them.

    Per-frame arrays get the state in front as a "frame -1" (index 0), so that every row reads
    its values by index; axes carried by the same frames share their timing arrays, and each
    axis is computed on its own (1-D, contiguous) to keep temporaries small."""
    has_frame = frame[j0:j1] >= 0
    fr = j0 + np.flatnonzero(has_frame)
    F = frame[fr]
    now_f = now[fr]
    t_in = inp.t[F]
    t_eff = np.where(np.isnan(t_in), now_f, t_in)  # t = now if t_sender is None else t_sender
    out = _Live(st.live[:], st.t_frame[:], st.slope[:], st.period[:], st.offset, st.offset_at,
                st.last_input_s, st.excess)
    kf = np.cumsum(has_frame)  # frames up to each row: 0 = none yet in the stretch
    if F.size:
        transit = now_f - t_eff
        offs = _offsets(st.offset, st.offset_at, now_f, transit)
        excess = transit - offs
        out.offset, out.offset_at, out.last_input_s = float(offs[-1]), float(now_f[-1]), \
            float(now_f[-1])
        out.excess = float(excess[-1])
        t_now = now[j0:j1] - np.concatenate([[st.offset], offs])[kf]
        age = now[j0:j1] - np.concatenate([[st.last_input_s], now_f])[kf]
        late = np.concatenate([[st.excess], excess])[kf]
    else:
        t_now = now[j0:j1] - st.offset
        age = now[j0:j1] - st.last_input_s
        late = np.full(j1 - j0, st.excess)
    cols = {a: inp.pos[:, a][F] for a in driven}
    groups: dict[tuple[bytes, float, float], list[int]] = {}
    for a in driven:
        nan = np.isnan(cols[a])
        key = (nan.tobytes() if nan.any() else b"", st.t_frame[a], st.period[a])
        groups.setdefault(key, []).append(a)
    for (_, tf0, p0), members in groups.items():
        carried = ~np.isnan(cols[members[0]])
        idx = None if carried.all() else np.flatnonzero(carried)
        if idx is None:
            k = kf
            t = np.concatenate([[tf0], t_eff])
        else:  # frames carrying these axes, up to each row
            rows_of = np.zeros(j1 - j0, dtype=np.int64)
            rows_of[fr[idx] - j0] = 1
            k = np.cumsum(rows_of)
            t = np.concatenate([[tf0], t_eff[idx]])
        dt = t[1:] - t[:-1]
        fresh = ((dt > 0.0) & (dt <= stale_after_s)) if linear else np.zeros(dt.size, bool)
        per = np.concatenate([[p0], _periods(p0, dt, fresh)])
        if linear:
            tau = t_now - t[k]
            cap = 1.5 * per[k]
            bound = np.minimum(np.where(late <= cap, np.maximum(cap_max, cap), cap + cap),
                               age + cap)
            # tau if 0 < tau < bound else bound if tau >= bound else 0  (bound >= 0): a clip
            ext = np.minimum(np.maximum(tau, 0.0), bound)
        for a in members:
            v = np.empty(t.size)
            v[0] = st.live[a]
            v[1:] = cols[a] if idx is None else cols[a][idx]
            slope = np.empty(t.size)
            slope[0] = st.slope[a]
            slope[1:] = 0.0
            np.divide(v[1:] - v[:-1], dt, out=slope[1:], where=fresh)
            out.live[a], out.slope[a] = float(v[-1]), float(slope[-1])
            out.t_frame[a], out.period[a] = float(t[-1]), float(per[-1])
            col = ref[j0:j1, a]
            if not linear:
                col[:] = v[k]
                continue
            np.multiply(slope[k], ext, out=col)
            col += v[k]
    return out
