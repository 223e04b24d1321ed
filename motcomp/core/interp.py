"""One axis' samples as a curve: knots, the quintic between them, the cubic beyond the newest,
and the fade that hides a correction (the ``smooth`` input reconstruction's interpolation:
:mod:`motcomp.core.shaper` composes it with :mod:`~motcomp.core.timeline` and
:mod:`~motcomp.core.playback`).

Contract
--------
* :func:`knot` gives a sample ``(t, v)`` its slope, acceleration and jerk from the cubic through
  it and up to three samples before it (:func:`stencil`: each at least :data:`STENCIL_S` before
  the next): exact on cubics, causal (never revised by a later sample).
* :func:`quintic` between two knots meets each with its value, slope and acceleration
  (continuous to the acceleration; exact on cubics).
* :func:`extrapolate` beyond the newest knot follows its Taylor cubic for ``bound`` s, then the
  parabola reached there (no velocity step).
* :class:`Curve` holds an axis' knots and plays them back at an instant: interpolated where
  samples lie on both sides, extrapolated beyond the newest; when a sample arrives under an
  extrapolation, the difference in value, and in slope beyond what the samples' rounding (of
  their values and their stamps) explains (:func:`beyond_rounding`), is added to a correction
  that fades out through a critically damped triple pole (:func:`fade_transition`): the played
  value never steps, and the samples' rounding is not integrated into a slow excursion
  (docs/WIRE.md, "Late frames").

Nothing here reads a clock or knows about frames, senders or modes.
"""

from __future__ import annotations

import math
from typing import Final

from mypy_extensions import mypyc_attr

from motcomp.core.minjerk import min_jerk, min_jerk_rate

__all__ = ["FIX_FLOOR", "HISTORY", "ROUNDING_SLOPE", "STENCIL_S", "Curve", "Knot", "Transition",
           "beyond_rounding", "extrapolate", "fade_transition", "float32_ulp", "hermite", "knot",
           "pole_transition", "quintic", "segment", "stencil", "value_ulp"]

STENCIL_S: Final = 5e-3
"""A knot's derivatives are taken from samples at least this far apart (the sample itself from
the one before it only where its value carries a float32's rounding): as exact on cubics, and
a 1 kHz sender's value noise reaches the jerk over 100 times less than over one period, a
float32's the slope 5 times less."""
HISTORY = 64
"""Knots kept per axis before the one the playback is in (trimmed in batches once twice as
many): a stencil (three knots 5 ms apart) never reaches further back."""
MAX_KNOTS = 4096
"""At most this many knots per axis, whatever the playback does (a burst of 2048 frames fits)."""
FIX_POLE_FACTOR = 6.0
"""The correction's fade is a triple pole at ``-FIX_POLE_FACTOR / blend_s``: within 6 % of its
start after ``blend_s``, 0.05 % after twice it."""
ROUNDING_SLOPE: Final = 4.0
"""A slope difference within this many times a sample's rounding per sample spacing is that
rounding (the quintic's slope between two samples moves by up to 1.9 times theirs per spacing,
the extrapolation's about as much with the samples before)."""
FIX_FLOOR = 1e-12
"""A correction below this (axis units, and its rate times the blend time) is dropped."""


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Knot:
    """A sample: instant ``t``, value ``v``, and the slope ``m``, acceleration ``a`` and jerk
    ``j`` there (:func:`knot`).  A class, not a tuple: compiled, its floats are unboxed."""

    t: float
    v: float
    m: float
    a: float
    j: float

    def __init__(self, t: float, v: float, m: float, a: float, j: float) -> None:
        self.t, self.v, self.m, self.a, self.j = t, v, m, a, j

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Knot) and self.fields() == other.fields()

    __hash__ = None  # type: ignore[assignment]  # mutable-looking, compared by value

    def fields(self) -> tuple[float, float, float, float, float]:
        return self.t, self.v, self.m, self.a, self.j

    def __repr__(self) -> str:
        return f"Knot{self.fields()!r}"


def stencil(h: list[Knot], end: int, t: float, spaced: bool) -> list[Knot]:
    """The (up to) three knots before ``h[end]`` (or before a new sample at ``end``), at ``t``,
    that its derivatives are computed from: each at least :data:`STENCIL_S` before the next,
    going back (the first knot if none is that far); the first one too where ``spaced`` (the
    values carry a float32's rounding), else the knot just before whatever its time."""
    out: list[Knot] = []
    t_next = t if spaced else math.inf
    j = end - 1
    while j >= 0 and len(out) < 3:
        if t_next - h[j].t >= STENCIL_S or j == 0:
            out.append(h[j])
            t_next = h[j].t
        j -= 1
    out.reverse()
    return out


def knot(before: list[Knot], t: float, v: float) -> Knot:
    """The sample ``(t, v)`` with the slope, acceleration and jerk at ``t`` of the polynomial
    through it and the (up to three, time-ordered) knots ``before`` it: a cubic, exact on
    cubics; fewer knots give a lower degree (one: a line; none: at rest)."""
    if len(before) >= 3:  # the usual case, written out: Newton's divided differences
        k1, k2, k3 = before[-1], before[-2], before[-3]
        t1, v1, t2, v2, t3, v3 = k1.t, k1.v, k2.t, k2.v, k3.t, k3.v
        f01 = (v - v1) / (t - t1)
        f12 = (v1 - v2) / (t1 - t2)
        f23 = (v2 - v3) / (t2 - t3)
        f012 = (f01 - f12) / (t - t2)
        f123 = (f12 - f23) / (t1 - t3)
        f0123 = (f012 - f123) / (t - t3)
        d1 = t - t1
        d2 = t - t2
        return Knot(t, v, f01 + f012 * d1 + f0123 * d1 * d2,
                    2.0 * f012 + 2.0 * f0123 * (d1 + d2), 6.0 * f0123)
    ts = [t]
    f = [v]  # Newton divided differences about the newest: f[0], f[0,1], f[0,1,2]
    col = [v]
    for k in range(len(before) - 1, -1, -1):
        tk = before[k].t
        new = [before[k].v]
        for j in range(len(col)):
            new.append((col[j] - new[j]) / (ts[-1 - j] - tk))
        ts.append(tk)
        col = new
        f.append(col[-1])
    f += [0.0] * (4 - len(f))
    d1 = t - ts[1] if len(ts) > 1 else 0.0
    d2 = t - ts[2] if len(ts) > 2 else 0.0
    return Knot(t, v, f[1] + f[2] * d1 + f[3] * d1 * d2, 2.0 * f[2] + 2.0 * f[3] * (d1 + d2),
                6.0 * f[3])


def segment(h: list[Knot], tau: float) -> int:
    """The index ``j`` of the knots ``h[j], h[j + 1]`` (at least 2, time-ordered) around
    ``tau``: the last ``j`` with ``h[j].t <= tau`` (0 before the first, ``len(h) - 2`` after
    the newest)."""
    j = len(h) - 2
    while j > 0 and tau < h[j].t:
        j -= 1
    return j


def quintic(h: list[Knot], tau: float) -> tuple[float, float]:
    """Value and slope at ``tau`` of the quintic Hermite between the two knots of ``h`` (at
    least 2, time-ordered) around it (``tau`` clamped to their span)."""
    j = segment(h, tau)
    return hermite(h[j], h[j + 1], tau)


def hermite(k0: Knot, k1: Knot, tau: float) -> tuple[float, float]:
    """Value and slope at ``tau`` of the quintic Hermite from ``k0`` to ``k1`` that meets each
    with its value, slope and acceleration (``tau`` clamped to their span)."""
    t0, v0, m0, a0 = k0.t, k0.v, k0.m, k0.a
    t1, v1, m1, a1 = k1.t, k1.v, k1.m, k1.a
    span = t1 - t0
    x = min(max((tau - t0) / span, 0.0), 1.0)
    m0 *= span
    m1 *= span
    a0 *= span * span
    a1 *= span * span
    x2 = x * x
    x3 = x2 * x
    y = 1.0 - x
    s = min_jerk(x)  # H3, and H0 = 1 - s
    value = (v0 + (v1 - v0) * s + m0 * x * (1.0 - x2 * (6.0 - 8.0 * x + 3.0 * x2))
             + 0.5 * a0 * x2 * y ** 3 + x3 * (m1 * (-4.0 + 7.0 * x - 3.0 * x2)
                                              + 0.5 * a1 * (1.0 - 2.0 * x + x2)))
    ds = min_jerk_rate(x)
    slope = ((v1 - v0) * ds + m0 * (1.0 - x2 * (18.0 - 32.0 * x + 15.0 * x2))
             + 0.5 * a0 * x * y * y * (2.0 - 5.0 * x)
             + m1 * x2 * (-12.0 + 28.0 * x - 15.0 * x2)
             + 0.5 * a1 * x2 * (3.0 - 8.0 * x + 5.0 * x2)) / span
    return value, slope


def extrapolate(src: Knot, tau: float, bound: float) -> tuple[float, float]:
    """Value and slope at ``tau`` of the cubic that leaves ``src`` with its value, slope,
    acceleration and jerk; beyond ``bound`` after it, the parabola with the value, slope and
    acceleration reached there (continuous to the acceleration)."""
    t_n, v, s, a, j = src.t, src.v, src.m, src.a, src.j
    el = tau - t_n
    e = min(el, bound)
    value = v + e * (s + e * (0.5 * a + e * j / 6.0))
    slope = s + e * (a + 0.5 * j * e)
    if el <= bound:
        return value, slope
    acc = a + j * bound
    r = el - bound
    return value + r * (slope + 0.5 * acc * r), slope + acc * r


def float32_ulp(v: float) -> float:
    """The ulp of ``v`` as a float32 where ``v`` is one (a sender's float32 value), else 0."""
    m, e = math.frexp(v)
    m24 = m * 16777216.0
    return math.ldexp(1.0, e - 24) if m24 == math.floor(m24) and v != 0.0 else 0.0


def value_ulp(v: float) -> float:
    """A sender's value's rounding: its float32 ulp where it is a float32, else its ulp."""
    return float32_ulp(v) or math.ulp(v)


def beyond_rounding(ds: float, v: float, slope: float, t_res: float, spacing: float) -> float:
    """The part of a slope difference ``ds`` beyond what the rounding of a sample ``v`` explains
    over the samples' ``spacing``: its value's (the float32 ulp where it is one, else its ulp)
    and its stamp's (``slope`` times the stamp's resolution ``t_res``), :data:`ROUNDING_SLOPE`
    times per spacing, taken off its size (0 within it)."""
    if spacing <= 0.0:
        return ds
    e = ROUNDING_SLOPE * (value_ulp(v) + abs(slope) * t_res) / spacing
    return ds - e if ds > e else ds + e if ds < -e else 0.0


def pole_transition(dt: float, w: float, order: int) -> tuple[float, ...]:
    """``exp(A dt)`` (row-major, ``order`` x ``order``) of a state -- a value and its first
    ``order - 1`` derivatives -- under a critically damped pole of that order at ``-w``:
    ``exp(-w dt) sum_k (N dt)^k / k!`` over ``k < order``, ``N = A + w I`` nilpotent (``A``
    the companion matrix of ``(s + w)^order``)."""
    n = order
    nm = [0.0] * (n * n)
    for r in range(n - 1):
        nm[r * n + r] = w
        nm[r * n + r + 1] = 1.0
    for c in range(n):
        nm[(n - 1) * n + c] = -math.comb(n, c) * w ** (n - c)
    nm[(n - 1) * n + n - 1] += w
    e = math.exp(-w * dt)
    term = [1.0 if r == c else 0.0 for r in range(n) for c in range(n)]
    phi = [e * x for x in term]
    for k in range(1, n):
        nxt = [0.0] * (n * n)
        for r in range(n):
            for c in range(n):
                acc = 0.0
                for j in range(n):
                    acc += term[r * n + j] * nm[j * n + c]
                nxt[r * n + c] = acc * dt / k
        term = nxt
        for i in range(n * n):
            phi[i] += e * term[i]
    return tuple(phi)


def fade_transition(dt: float, blend_s: float) -> tuple[float, ...]:
    """:func:`pole_transition` of a correction's (value, rate, acceleration): the critically
    damped triple pole at ``-FIX_POLE_FACTOR / blend_s``."""
    return pole_transition(dt, FIX_POLE_FACTOR / blend_s, 3)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Transition:
    """:func:`pole_transition` of the pole of ``order`` at ``-factor / settle_s`` (by default
    :func:`fade_transition`'s) for the last ``(dt, settle_s)`` asked, ``dt`` rounded to the ns
    (a tick's ``dt`` repeats; its float differs at rounding)."""

    def __init__(self, order: int = 3, factor: float = FIX_POLE_FACTOR) -> None:
        self.order = order
        self.factor = factor
        self.dt_ns = -1
        self.settle_s = 0.0
        self.phi: tuple[float, ...] = ()

    def of(self, dt: float, settle_s: float) -> tuple[float, ...]:
        ns = round(dt * 1e9)
        if ns != self.dt_ns or settle_s != self.settle_s:
            self.dt_ns, self.settle_s = ns, settle_s
            self.phi = pole_transition(ns * 1e-9, self.factor / settle_s, self.order)
        return self.phi


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Curve:
    """One axis' knots (time-ordered, newest last) and the correction being faded out.

    :meth:`add` takes a sample; :meth:`at` plays the curve back at an instant (see the module
    docstring); :meth:`clear` forgets everything (a restart of the axis' timeline).
    """

    def __init__(self) -> None:
        self.knots: list[Knot] = []
        self.extra: Knot | None = None
        """While extrapolating: the knot extrapolated from."""
        self.fix: list[float] | None = None
        """The correction (value, rate, acceleration) being faded out; None: none."""
        self.slope = 0.0
        """The curve's slope at the last instant played back."""
        self.t_res = 0.0
        """The newest sample's stamp resolution (s; 0: unstamped)."""

    def clear(self) -> None:
        self.knots = []
        self.extra = None
        self.fix = None
        self.slope = 0.0

    def add(self, t: float, v: float, min_dt: float, t_res: float = 0.0) -> None:
        """A sample ``v`` at ``t``, stamped to ``t_res`` s (0: unstamped).  Closer than
        ``min_dt`` after the newest knot it replaces it (the same sample again); before it, the
        history restarts at this sample.  Knots are dropped only once the playback has passed
        them (:meth:`at`)."""
        self.t_res = t_res
        h = self.knots
        if not h or t < h[-1].t:
            h.clear()
            h.append(knot(h, t, v))
        elif t - h[-1].t < min_dt:
            h[-1] = knot(stencil(h, len(h) - 1, h[-1].t, float32_ulp(v) > 0.0), h[-1].t, v)
        else:
            h.append(knot(stencil(h, len(h), t, float32_ulp(v) > 0.0), t, v))
            if len(h) > MAX_KNOTS:  # never played back (no playback yet): the newest only
                del h[:len(h) - HISTORY]

    def at(self, tau: float, bound: float, phi: tuple[float, ...], blend_s: float) -> float:
        """The value at ``tau``: interpolated, or extrapolated from the newest knot (for at most
        ``bound`` s on its cubic, then its parabola), plus the fading correction, advanced by the
        transition ``phi`` (:func:`fade_transition` of the time since the last call).  The
        knots must not be empty."""
        h = self.knots
        prev = self.extra
        if len(h) == 1:
            x, xs = h[0].v, 0.0
            src = None
        elif tau <= h[-1].t:
            j = segment(h, tau)
            x, xs = hermite(h[j], h[j + 1], tau)
            src = None
            if j > 2 * HISTORY:  # passed by the playback, and no stencil reaches them
                del h[:j - HISTORY]
        else:
            src = h[-1]
            x, xs = extrapolate(src, tau, bound)
        fix = self.fix
        if fix is not None:
            f, f1, f2 = fix
            fix[0] = phi[0] * f + phi[1] * f1 + phi[2] * f2
            fix[1] = phi[3] * f + phi[4] * f1 + phi[5] * f2
            fix[2] = phi[6] * f + phi[7] * f1 + phi[8] * f2
            if abs(fix[0]) < FIX_FLOOR and abs(fix[1]) * blend_s < FIX_FLOOR:
                self.fix = fix = None
        if prev is not None and (src is None or src.t != prev.t):
            xo, so = extrapolate(prev, tau, bound)  # the samples changed under it
            if fix is None:
                self.fix = fix = [0.0, 0.0, 0.0]
            fix[0] += xo - x  # continuous in position, added to what fades
            if len(h) > 1:
                j = len(h) - 2 if src is not None else segment(h, tau)
                fix[1] += beyond_rounding(so - xs, h[j + 1].v, xs, self.t_res,
                                          h[j + 1].t - h[j].t)
        self.extra = src
        if fix is None:
            self.slope = xs
            return x
        self.slope = xs + fix[1]
        return x + fix[0]
