"""The pseudo open-loop PID compensator, discrete time, all axes at once.

The PID is closed around an *internal model* M of the platform, never around measured motion;
its output goes to the real platform P.  Per axis::

                  +--------------------------------------------------------------------+
                  |                          compensator                               |
     r[k]         |  e = r - y_c             v                     u                   |      y
  -------------->(+)------> PID C ---------+---> SAT(pos,vel,acc) --+------------------|--> P
  motion cueing   | ^ -                    |                        |                  |platform
  setpoint        | |                      |     (v - u) deficit     |                  |
                  | |                      +--------(+)<------------+                  |
                  | |                      |         |                                 |
                  | |     y_aw = M (v - u) |  anti-windup filter <--+                  |
                  | |                      v         |                                 |
                  | +-- y_c = y_m + y_aw --(+)<------+      y_m = M u  <---------------+
                  |      (= M v)                   internal P1D model, fed with the    |
                  |                                SATURATED command u: it mirrors the |
                  |                                platform; K e^{-Td s}/(1 + Tp1 s)   |
                  +--------------------------------------------------------------------+

Unsaturated, ``u = v = C (r - M u)``: the compensator is the prefilter ``F = C/(1 + C M)`` and
the delivered motion is ``y = P F r`` (``C M/(1 + C M)`` when ``P = M``).  Nothing measured is fed
back, so a model error cannot destabilise anything; it only spoils the inversion.

Saturation and anti-windup
--------------------------
The internal model ``y_m = M u`` is advanced with the *saturated* command, so it mirrors what the
platform receives (:attr:`Compensator.model_output`).  Anti-windup is *model recovery*
(Zaccarian & Teel, "Modern Anti-windup Synthesis", 2011; for a stable plant it is also the IMC
anti-windup of Zheng, Kothare & Morari, 1994): a copy of the model driven by the deficit
``v - u`` adds ``y_aw = M (v - u)`` to the fed-back signal, so the PID sees
``y_m + y_aw = M v`` and its loop stays linear, stable whatever the limits do; the deficit left
by a saturation fades with the platform's own time constant instead of being "caught up" by the
PID.  Back-calculation was measured and rejected: with the model inside the loop *and* a
high-gain tuning (Ziegler-Nichols, Ms ~ 4.8), an acceleration limit turns the loop into a
relay-with-delay that limit-cycles (see docs/ANTIWINDUP.md).  The limiter itself meets its target
without overshoot (:func:`~motcomp.core.saturation.limit_axis`).

Since ``M`` is linear, ``y_m + y_aw`` is computed as one model fed with ``v``; ``y_m`` is kept
separately as the platform mirror.

Discrete algorithm, sample period ``h`` (``k`` = this tick)
------------------------------------------------------------
Sign convention, used once here and nowhere else: ``error = reference - model_output``.

::

    y_c[k]  = xc[k]                                  fed-back model output (M v)
    e[k]    = r[k] - y_c[k]
    R[k]    = a_d R[k-1] + (r[k] - r[k-1])/(tf+h)    filtered derivatives of r and y_c,
    Y[k]    = a_d Y[k-1] + (y_c[k] - y_c[k-1])/(tf+h)  a_d = tf/(tf+h)
    D[k]    = kd (c R[k] - Y[k])                     (= a_d D[k-1] + kd/(tf+h) (w[k] - w[k-1])
                                                       with w = c r - y_c, while kd, c hold)
    v[k]    = kp (b r[k] - y_c[k]) + I[k] + D[k]       raw PID output
    u[k]    = SAT(v[k])                              (or SAT(bypass target), see below)
    I[k+1]  = I[k] + ki h e[k]                       forward Euler
    xc[k+1] = phi xc[k] + g0 v[k-d+1] + g1 v[k-d]    exact ZOH, sub-sample delay
    xm[k+1] = phi xm[k] + g0 u[k-d+1] + g1 u[k-d]    the platform mirror, fed with u

Forward-Euler integral: ``v[k]`` never depends on ``v[k]`` (no algebraic loop).  Derivative:
backward difference of a first-order filtered derivative, stable for every ``tf >= 0``; the
reference and the model output are filtered apart, so that a change of ``kd`` or ``c`` takes
effect without a kick.
The transfer functions of exactly this algorithm are in :mod:`motcomp.design.frequency`.

Rules for edge cases
--------------------
* Rate: fixed at construction (``rate_hz``); ``rate_hz <= 0`` or non-finite raises
  :class:`~motcomp.errors.ConfigError`.  One :meth:`Compensator.step` is one sample on a uniform
  grid; what a caller does about missed deadlines is its own rule (the service's, stated once:
  :mod:`motcomp.core.tick`, "catch-up").
* Non-finite reference on an axis: the last finite reference of that axis is used instead; the
  axis is flagged :data:`NONFINITE`.  A NaN never reaches the state or the output.
* Limits: inverted or empty ranges are rejected when :class:`AxisLimits` is built; see
  :mod:`motcomp.core.saturation` for the guarantee on the output sequence.
* Start: :meth:`reset` puts every state at rest at a given position, so the first output equals
  that position: no kick.
* Gains: every gain/model pair is checked for stability of the discrete internal loop (from its
  poles, :mod:`motcomp.core.loop`) when set; an unstable pair raises
  :class:`~motcomp.errors.ConfigError` and changes nothing.
* Gain or model change (:meth:`set_gains`, :meth:`set_models`, :meth:`reconfigure`): each
  axis whose PID or internal model changed takes the state its new internal loop would have
  reached on the references it was given (the last ``history_s`` of them, re-run from the loop's
  steady state on their ramp at the start), so that its path goes on as if the new parameters
  had always run; the command blends out its difference to that path in position, velocity and
  acceleration over ``fade_s`` or longer (within :data:`DIFFERENCE_ACC_SHARE` of the limit), as
  a switch does.  Re-seeding the integrator alone kept the raw output's level but started the
  new loop's transient from the old one's state: switching the rails to ZN gains in mid-slalom
  rode the acceleration limit for 200-230 ticks (docs/TUNING.md, "Changing gains while
  moving").  An axis in an input-loss window keeps its raw output instead (the integrator
  re-seeded): its target is the reference and its PID started over at rest there.
* Bypass (compensation off) per axis (:meth:`set_bypass`): the PID always runs on, closed around its
  internal model as when compensating (its output ``v`` depends on the reference alone: the
  compensated path, whatever is sent), and the command's target is the blend ``r + w (v - r)`` of
  the reference and that path, ``w`` = 1 compensating, 0 bypassed.  A switch moves ``w`` to its end
  along a minimum-jerk weight over ``fade_s`` or longer, so that the gap ``v - r`` at the switch and
  its rate take at most :data:`BLEND_ACC_SHARE` of the axis' acceleration limit
  (:func:`weight_duration`); and it blends out the command's own difference to that target at the
  switch, in position and velocity (a limiter that was acting, a window's speed cap), over the
  shortest time within :data:`DIFFERENCE_ACC_SHARE` of the limit (:mod:`motcomp.core.blend`,
  continuous to the jerk).  The weight is smooth and so is the compensated path of a smooth
  reference: the command lies between the two paths but for the difference blended out, bumpless
  both ways (docs/TUNING.md, "Switching compensation on and off").
* Input loss (:meth:`open_window`, the tick's rule: :mod:`motcomp.core.tick`): each axis is held
  in a window, the hull of its command, its braking point ``u + v |v| / (2 a_max)`` and the
  reference (widened by later references and the reach of their motion, :meth:`widen_window`), by
  the limiter itself: the window's bounds replace the axis' position limits and the ramp's peak
  speed its velocity limit, so that the limiter's braking condition, which keeps the end of the
  range, keeps the window's edge. The braking point is reachable from ``(u, v)`` at ``a_max`` (the
  exact discrete distance is ``v^2/(2 a_max) - a_max h^2/2`` at most,
  :mod:`motcomp.core.saturation`), so the command never goes beyond it. Meanwhile the target is
  the reference (``w`` = 0 at once), and the PID starts over at rest at the held reference (its
  output is that reference while it holds: the compensated path of the reference from the loss on,
  not its response to the step the hold makes of a moving reference, which rang for 0.2 s at tens
  of m/s^2 and leaked through the weight at the rejoin). :meth:`close_window` switches
  compensation back on as a switch out of bypass does, but with no ``fade_s`` floor: within the
  hold the two paths meet at rest and the switch is immediate; during the ramp to neutral the
  weight moves as fast as their gap and its rate allow (docs/TUNING.md, "Switching compensation on
  and off").  The target's rate at a switch is the difference of its last two values, so both are
  always of the path the target follows: at the loss the target changes path at once, and its
  last value is restated on the new one (``previous``), else a window closed at the next step
  read the jump between the paths as a velocity.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from math import isfinite

import numpy as np
from mypy_extensions import mypyc_attr
from numpy.typing import ArrayLike

from motcomp.core.blend import (
    BLEND_ACC_SHARE,
    BLEND_TERMS,
    blend_coefficients,
    blend_duration,
    horner,
)
from motcomp.core.loop import stability
from motcomp.core.lti import FloatArray
from motcomp.core.minjerk import PEAK_ACC_FACTOR, PEAK_DEPART_FACTOR, min_jerk_between
from motcomp.core.models import P1D, p1d_coefficients
from motcomp.core.pid import PIDGains
from motcomp.core.saturation import (
    AxisLimits,
    Track,
    at_rest,
    axis_constants,
    check_position,
    limit_axis,
)
from motcomp.errors import ConfigError

DIFFERENCE_ACC_SHARE = 0.5
"""A switch blends out the command's difference to its target (in position and velocity) with at
most this share of the axis' acceleration limit, over the shortest blend within it (module
docstring): a velocity difference ``dv`` travels about ``0.8 dv^2 / (share a_max)`` on (a quarter
carried a 0.7 m/s difference 0.3 m beyond a 0.4 m slalom after a 62 ms input loss)."""

__all__ = ["DIFFERENCE_ACC_SHARE", "NONFINITE", "Compensator", "CompensatorState",
           "weight_duration"]

NONFINITE = 8
"""Flag bit: the reference was not finite and the last finite one was held."""


def weight_duration(gap: float, rate: float, acc: float) -> float:
    """The shortest ``T`` over which a minimum-jerk weight, moving a target from one path to
    another that lies ``gap`` away and departs at ``rate``, adds at most ``acc`` to the
    target's acceleration: ``PEAK_ACC_FACTOR |gap| / T^2 + PEAK_DEPART_FACTOR |rate| / T``
    (the peaks of ``(w gap)''`` and ``(w rate t)''``, summed; 0 for two paths that meet at
    rest)."""
    if acc <= 0.0:
        return 0.0
    b = PEAK_DEPART_FACTOR * abs(rate)
    return (b + math.sqrt(b * b + 4.0 * acc * PEAK_ACC_FACTOR * abs(gap))) / (2.0 * acc)


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
@dataclass
class CompensatorState:
    """A copy of every state of the compensator (for tests, replay and snapshots)."""

    k: int
    r: FloatArray
    xc: FloatArray
    xm: FloatArray
    integral: FloatArray
    deriv: FloatArray
    deriv_r: FloatArray
    deriv_y: FloatArray
    history_c: FloatArray
    history_m: FloatArray
    u: FloatArray
    v: FloatArray
    tracker: FloatArray
    """(n, 5): per axis, the limiter's :data:`~motcomp.core.saturation.Track`."""
    raw: FloatArray
    bypass: np.ndarray
    weight: FloatArray
    """Per axis, the weight of the compensated path in the command's target (module docstring)."""
    weight_from: FloatArray
    weight_to: FloatArray
    weight_progress: FloatArray
    weight_step: FloatArray
    target: FloatArray
    """Per axis, the last two targets before the difference blended out (previous first)."""
    blend: FloatArray
    """(n, BLEND_TERMS): per axis, the coefficients of the difference being blended out
    (:mod:`motcomp.core.blend`; used while ``blend_progress`` < 1)."""
    blend_progress: FloatArray
    blend_step: FloatArray


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class Compensator:
    """Pseudo open-loop PID with saturation for ``n`` axes (see the module docstring).

    Parameters
    ----------
    models
        Internal P1D model of each axis.
    gains
        PID gains of each axis.
    limits
        Position/velocity/acceleration limits of each axis.
    rate_hz
        Loop rate; one :meth:`step` per sample.
    position
        Initial position of each axis (default: 0); every state starts at rest there.
    fade_s
        Duration of the fade when an axis enters bypass.
    history_s
        Longest model dead time the delay line can hold after a live model change (default: the
        largest initial dead time plus 100 ms, at least 250 ms).

    Notes
    -----
    The state lives in flat lists allocated once and changed in place; parameters are rebuilt
    between two steps, never during one.
    """

    def __init__(
        self,
        models: Sequence[P1D],
        gains: Sequence[PIDGains],
        limits: AxisLimits,
        rate_hz: float,
        position: ArrayLike | None = None,
        fade_s: float = 0.5,
        history_s: float | None = None,
    ) -> None:
        if not (isinstance(rate_hz, int | float) and math.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError(f"compensator rate must be a positive finite number of Hz, "
                              f"got {rate_hz!r}")
        n = limits.size
        if len(models) != n or len(gains) != n:
            raise ConfigError(f"{len(models)} models and {len(gains)} gain sets for {n} axes")
        self.n = n
        self.names = limits.names
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.set_fade(fade_s)
        max_td = max(m.Td for m in models)
        hist_s = history_s if history_s is not None else max(max_td + 0.1, 0.25)
        if hist_s < max_td:
            raise ConfigError(f"history_s={hist_s} is shorter than the largest dead time {max_td}")
        length = 1
        while length < math.ceil(hist_s * self.rate_hz) + 2:
            length *= 2
        self._hist_len = length
        self._mask = length - 1
        self._limits = limits
        zeros = [0.0] * n
        (self._r, self._u, self._v, self._xc, self._xm, self._y_last, self._deriv, self._dr,
         self._raw, self._integral, self._r_prev) = ([0.0] * n for _ in range(11))
        self._w = [1.0] * n  # the compensated path's weight in the target, its blend's ends,
        self._w_from = [1.0] * n
        self._w_to = [1.0] * n
        self._w_progress = [1.0] * n  # progress (0 -> 1; 1: none) and its step per sample
        self._w_step = [1.0] * n
        self._tgt = [0.0] * n  # the last target before the difference blended out,
        self._tgt_prev = [0.0] * n  # the one before
        self._e = [[0.0] * BLEND_TERMS for _ in range(n)]  # the difference blended out,
        self._e_progress = [1.0] * n  # its progress and step
        self._e_step = [1.0] * n
        self._dy = [0.0] * n
        self.deviation = [0.0] * n
        """Per axis, emitted command minus its target at the last step (0 when feasible)."""
        self._track: list[Track] = [at_rest(0.0)] * n  # the limiter's view of its target
        self._hist_c = zeros * length  # axis i at [i * length, (i + 1) * length)
        self._hist_m = zeros * length
        self._hist_r = zeros * length  # the references stepped with (a gain change re-runs them)
        self._bypass = [False] * n
        self._lim: list[tuple[float, ...]] = []
        self._window: list[tuple[float, ...] | None] = [None] * n
        """Per axis, the limiter's constants with a window's bounds (:meth:`open_window`)."""
        self._window_speed = [0.0] * n
        self._window_ref = [0.0] * n
        """Per axis, the reference the window last took in (:meth:`widen_window`)."""
        self._set_lim(limits)
        self._models: tuple[P1D, ...] = ()
        self._gains: tuple[PIDGains, ...] = ()
        self._model_p: list[tuple[float, float, float, int, int]] = []
        self._gain_p: list[tuple[float, ...]] = []
        self._set_models(models)
        self._set_gains(gains)
        self.flags: list[int] = [0] * n
        self.moving = 0
        """Bit ``i`` set: axis ``i``'s last step blended between compensation and bypass (its
        weight or the difference it blends out still moving)."""
        self.reset(np.zeros(n) if position is None else position)

    # --- configuration ------------------------------------------------------------------------
    @property
    def models(self) -> tuple[P1D, ...]:
        return self._models

    @property
    def gains(self) -> tuple[PIDGains, ...]:
        return self._gains

    @property
    def limits(self) -> AxisLimits:
        return self._limits

    @property
    def bypass(self) -> np.ndarray:
        return np.array(self._bypass, dtype=bool)

    def _set_lim(self, limits: AxisLimits) -> None:
        self._lim = axis_constants(limits, self.dt_s)
        for i, win in enumerate(self._window):  # a window open keeps its bounds, within the new
            if win is not None:                 # range
                self._set_window(i, win[2], win[3])

    # --- the window (input loss) ----------------------------------------------------------------
    @property
    def window(self) -> list[tuple[float, float] | None]:
        """Per axis, the bounds of the input-loss window (:meth:`open_window`; None: none)."""
        return [None if w is None else (w[2], w[3]) for w in self._window]

    def open_window(self, axes: Sequence[bool], reference: Sequence[float],
                    speed: Sequence[float], previous: Sequence[float] | None = None) -> None:
        """The input is lost: hold each of ``axes`` within the hull of its command ``u``, its
        braking point ``u + v |v| / (2 a_max)`` (``v`` the command's velocity) and
        ``reference``, at no more than ``speed`` (the ramp's peak speed) once it has braked to
        it, its target the reference itself (the PID runs on, as in bypass).

        The limiter brakes at the braking point as at an end stop: it lies within the reach of
        braking at ``a_max`` from ``(u, v)`` (:mod:`motcomp.core.saturation`), so the command
        never travels further in the direction of its velocity; a speed above ``speed`` is
        braked at ``a_max`` (the acceleration limit wins).  Kept until :meth:`close_window`;
        :meth:`widen_window` lets the reference through.  The PID starts over at rest at
        ``reference`` (:meth:`_pid_at_rest`): its path is the compensated path of the reference
        from the loss on, not of the step the hold made of it.  ``previous`` is that reference
        at the last step (default: the last one this compensator was given; a caller whose
        reference changes path at the loss, as the tick's prediction held off, gives the new
        path's): the target's last value restated on its new path, so that its velocity at a
        switch back (:meth:`_blend_to`, the window closed at the next step) is the reference's,
        not the jump between the two paths."""
        for i, on in enumerate(axes):
            if not on:
                continue
            self._weight_at(i, 0.0)
            self._tgt[i] = self._r[i] if previous is None else previous[i]
            self._pid_at_rest(i, reference[i])
            u, v, lim = self._u[i], self._v[i], self._lim[i]
            stop = u + v * abs(v) * lim[8]  # lim[8] = 1 / (2 a_max)
            r = reference[i]
            cap = speed[i]
            self._window_speed[i] = cap if 0.0 < cap < lim[4] else lim[4]
            self._window_ref[i] = r
            self._set_window(i, min(u, stop, r), max(u, stop, r))

    def widen_window(self, reference: Sequence[float]) -> None:
        """Widen each open window to take in ``reference`` and, where the command follows it
        (on the last one, at a speed from which this step is within ``a_max``), the reach of
        its motion: one more step of it and its braking distance at half ``a_max``,
        ``r + v h + v |v| / a_max`` (``v`` its velocity since the last call, at most the ramp's
        peak speed).  A target moving on at the window's very edge would be braked there as at
        an end stop, at ``a_max``: the reach keeps a ramp to neutral feasible, so a command that
        follows it passes it as it is, never braked and never beyond it; a command that does not
        (braking, returning, catching up) keeps the edge at the reference.  Allocates only when
        a bound moves."""
        for i, win in enumerate(self._window):
            if win is not None:
                r = reference[i]
                step = r - self._window_ref[i]
                self._window_ref[i] = r
                lim = self._lim[i]  # h, 1 / h, ..., lim[5] = a_max h, lim[8] = 1 / (2 a_max)
                h = lim[0]
                # on the reference, at a speed from which its step is within a_max: the limiter
                # passes it as it is if the edge lets it (else it keeps the edge at the
                # reference, which brakes a command that would pass it)
                if self.deviation[i] != 0.0 or abs(step - self._v[i] * h) > lim[5] * h:
                    reach = r
                else:
                    # a ramp moves at most at its peak speed: a step beyond (the reference
                    # brought within the limits at the ramp's start, a stall's catch-up) is no
                    # speed
                    cap = self._window_speed[i] * h
                    step = cap if step > cap else -cap if step < -cap else step
                    reach = r + step + step * abs(step) * lim[1] * lim[1] * 2.0 * lim[8]
                lo, hi = (r, reach) if reach >= r else (reach, r)
                if lo < win[2] or hi > win[3]:
                    self._set_window(i, min(lo, win[2]), max(hi, win[3]))

    def close_window(self) -> None:
        """The input is live again: every axis back to its limits, and the compensated ones
        to their compensation as out of a bypass, over the shortest weight blend their gap and
        its rate allow (no ``fade_s`` floor; module docstring)."""
        for i in range(self.n):
            if self._window[i] is not None:
                self._window[i] = None
                if not self._bypass[i]:
                    self._blend_to(i, 1.0, 0.0)

    def _set_window(self, i: int, lo: float, hi: float) -> None:
        lim = self._lim[i]
        lo = min(max(lo, lim[2]), lim[3])
        hi = min(max(hi, lo), lim[3])
        self._window[i] = (*lim[:2], lo, hi, self._window_speed[i], *lim[5:])

    def _set_models(self, models: Sequence[P1D]) -> None:
        if len(models) != self.n:
            raise ConfigError(f"{len(models)} models for {self.n} axes")
        params = []
        for name, m in zip(self.names, models, strict=True):
            if not isinstance(m, P1D):
                raise ConfigError(f"internal model of {name} must be P1D, got {m.kind}; "
                                  "use model.to_p1d()")
            phi, g0, g1, d = p1d_coefficients(m, self.dt_s)
            if d + 1 >= self._hist_len:
                raise ConfigError(f"dead time of {name} ({m.Td} s) exceeds the delay line "
                                  f"({(self._hist_len - 2) * self.dt_s:.3f} s)")
            # read offsets of u[k-d+1] and u[k-d] relative to the write slot k
            params.append((phi, g0, g1, 1 - d, -d))
        self._model_p = params
        self._models = tuple(models)

    def _check_stable(self, models: Sequence[P1D], gains: Sequence[PIDGains]) -> None:
        """Reject a gain/model pair whose discrete internal loop is not stable."""
        for name, m, g in zip(self.names, models, gains, strict=True):
            stable, rho = stability(g, m, self.rate_hz)
            if not stable:
                raise ConfigError(
                    f"gains of {name} (kp={g.kp:.6g}, ki={g.ki:.6g}, kd={g.kd:.6g}, tf={g.tf:.6g})"
                    f" make the internal loop unstable at {self.rate_hz:g} Hz with model {m} "
                    f"(largest pole modulus {rho:.4f} >= 1)"
                )

    def _set_gains(self, gains: Sequence[PIDGains]) -> None:
        if len(gains) != self.n:
            raise ConfigError(f"{len(gains)} gain sets for {self.n} axes")
        self._check_stable(self._models, gains)
        h = self.dt_s
        params: list[tuple[float, ...]] = []
        for g in gains:
            params.append((g.kp, g.ki * h, g.tf / (g.tf + h), 1.0 / (g.tf + h), g.kd, g.b, g.c))
        self._gain_p = params
        self._gains = tuple(gains)

    def set_gains(self, gains: Sequence[PIDGains]) -> None:
        """Change gains between two steps, bumplessly (:meth:`_retune`)."""
        before = (list(self._gain_p), list(self._model_p))
        old_raw = self._virtual_raw()
        self._set_gains(gains)
        self._retune(before, old_raw)

    def _retune(self, before: tuple[list[tuple[float, ...]], list[tuple[float, float, float,
                                                                            int, int]]],
                old_raw: list[float]) -> None:
        """After new gains or models (``before``: the old ones): each axis whose PID or internal
        model changed takes the state its new internal loop would have reached on the
        references it was given (:meth:`_rerun`), and the command blends out its difference to
        that path in position, velocity and acceleration over ``fade_s`` or longer
        (:meth:`_blend_difference`), as at a switch out of bypass.  An axis in an input-loss
        window, whose target is the reference and whose PID started over at rest there, keeps
        its raw output instead: the derivative carried over to the new ``kd`` and ``c``, the
        integrator re-seeded (module docstring)."""
        gain_p, model_p = before
        for i in range(self.n):
            if self._gain_p[i] == gain_p[i] and self._model_p[i] == model_p[i]:
                continue
            if self._window[i] is not None:
                g = self._gains[i]
                self._deriv[i] = g.kd * (g.c * self._dr[i] - self._dy[i])
                gp = self._gain_p[i]
                self._integral[i] = (old_raw[i] - gp[0] * (gp[5] * self._r[i] - self._y_last[i])
                                     - self._deriv[i])
                continue
            self._blend_difference(i, self._rerun(i), self.fade_s)

    def _rerun(self, i: int) -> float:
        """Axis ``i``'s PID and internal loop (not the platform mirror) as if the present gains
        and model had run since the oldest reference still held (the delay line's length: 0.5 s
        at least), from their steady state on that reference's ramp there (at rest without an
        integrator); its target's last two values on that path.  Returns the command's
        acceleration less that path's target's at the last step (second differences).  What is
        left of the start's transient (the reference's curvature there) is in the difference
        :meth:`_blend_difference` blends out."""
        k = self._k
        length, mask = self._hist_len, self._mask
        base = i * length
        hr, hc = self._hist_r, self._hist_c
        j0 = k - (length - 1)  # before the first step: at rest where reset put it
        r0 = hr[base + (j0 & mask)]
        slope = hr[base + ((j0 + 1) & mask)] - r0  # a step's
        kp, kih, ad, q, kd, b, c = self._gain_p[i]
        phi, g0, g1, off0, off1 = self._model_p[i]
        # the loop's steady state on the ramp r0 + slope (j - j0) (docs/TUNING.md): its model
        # output lags the reference by a constant ``lag``, its output and integrator are affine
        gain = g0 + g1
        if kih > 0.0 and gain != 0.0:
            beta = slope * (1.0 - phi) / gain  # the output's step: its DC gain times it is slope
            lag = (beta - kp * (b - 1.0) * slope) / kih
            alpha = ((1.0 - phi) * (r0 - lag) + slope - beta * (g0 * off0 + g1 * off1)) / gain
        else:  # no steady state on a ramp without an integrator: at rest
            slope = beta = 0.0
            lag = r0 - self._models[i].K * r0
            alpha = r0
        for j in range(j0 - length + 1, j0 + 1):
            hc[base + (j & mask)] = alpha + beta * (j - j0)
        xc = r0 - lag
        y_last = xc - slope
        dr = dy = slope * self.rate_hz
        d = kd * (c * dr - dy)
        integral = alpha - kp * (b * r0 - xc) - d
        r_prev = r0 - slope
        v = alpha
        w = self._w[i]
        tgt = tgt_prev = tgt_prev2 = r0
        for j in range(j0, k):
            r = hr[base + (j & mask)]
            y = xc
            dr = ad * dr + q * (r - r_prev)
            dy = ad * dy + q * (y - y_last)
            y_last = y
            d = kd * (c * dr - dy)
            v = kp * (b * r - y) + integral + d
            integral += kih * (r - y)
            hc[base + (j & mask)] = v
            xc = phi * y + g0 * hc[base + ((j + off0) & mask)] + g1 * hc[base + ((j + off1) & mask)]
            tgt_prev2, tgt_prev = tgt_prev, tgt
            tgt = v if w >= 1.0 else r if w <= 0.0 else r + w * (v - r)
            r_prev = r
        self._xc[i], self._y_last[i] = xc, y_last
        self._dr[i], self._dy[i], self._deriv[i] = dr, dy, d
        self._integral[i], self._raw[i] = integral, v
        self._tgt_prev[i], self._tgt[i] = tgt_prev, tgt
        hm = self._hist_m
        u_acc = (hm[base + ((k - 1) & mask)] - 2.0 * hm[base + ((k - 2) & mask)]
                 + hm[base + ((k - 3) & mask)])
        return (u_acc - (tgt - 2.0 * tgt_prev + tgt_prev2)) * self.rate_hz * self.rate_hz

    def set_models(self, models: Sequence[P1D]) -> None:
        """Change internal models between two steps, bumplessly: the platform mirror keeps its
        state and command history, only its coefficients change; the internal loop of each
        changed axis as for a gain change (:meth:`_retune`)."""
        self._check_stable(models, self._gains)
        before = (list(self._gain_p), list(self._model_p))
        old_raw = self._virtual_raw()
        self._set_models(models)
        self._retune(before, old_raw)

    def reconfigure(self, models: Sequence[P1D], gains: Sequence[PIDGains],
                    limits: AxisLimits | None = None) -> None:
        """Change models, gains and limits together between two steps, bumplessly.

        Everything is validated first (stability of each new pair included); on error nothing
        changes.
        """
        if len(models) != self.n or len(gains) != self.n:
            raise ConfigError(f"{len(models)} models and {len(gains)} gain sets for {self.n} axes")
        self._check_stable(models, gains)
        if limits is not None and limits.size != self.n:
            raise ConfigError(f"limits for {limits.size} axes, compensator has {self.n}")
        before = (list(self._gain_p), list(self._model_p))
        old_raw = self._virtual_raw()
        self._set_models(models)
        self._set_gains(gains)
        self._retune(before, old_raw)
        if limits is not None:
            self.set_limits(limits)

    def set_limits(self, limits: AxisLimits) -> None:
        """Change limits between two steps (see :mod:`motcomp.core.saturation` for an axis that
        is outside the new range)."""
        if limits.size != self.n:
            raise ConfigError(f"limits for {limits.size} axes, compensator has {self.n}")
        self._set_lim(limits)
        self._limits = limits

    def set_fade(self, fade_s: float) -> None:
        """Shortest duration of a switch between compensation and bypass (s, >= 0)."""
        if not (math.isfinite(fade_s) and fade_s >= 0):
            raise ConfigError(f"bypass fade time must be finite and >= 0 s, got {fade_s!r}")
        self.fade_s = float(fade_s)

    def set_bypass(self, bypass: ArrayLike) -> None:
        """Turn compensation off (True) or on (False) per axis, bumplessly (a blend of the
        command's target between the reference and the compensated path, module docstring)."""
        new = np.array(bypass, dtype=bool).reshape(self.n).tolist()
        for i in range(self.n):
            if new[i] == bool(self._bypass[i]):
                continue
            if self._window[i] is None:
                self._blend_to(i, 0.0 if new[i] else 1.0, self.fade_s)
        self._bypass[:] = new

    def _blend_to(self, i: int, end: float, shortest: float) -> None:
        """Start moving axis ``i``'s weight from where it is to ``end`` over ``shortest`` or
        longer (:func:`weight_duration`), and blending out the command's difference to its
        target (module docstring)."""
        a_max = float(self._limits.a_max[i])
        k = self._k
        v_prev = self._hist_c[i * self._hist_len + ((k - 2) & self._mask)] if k > 1 \
            else self._raw[i]
        gap = self._raw[i] - self._r[i]
        rate = (gap - (v_prev - self._r_prev[i])) * self.rate_hz
        length = max(shortest, weight_duration(gap, rate, BLEND_ACC_SHARE * a_max))
        step = self.dt_s / length if length > 0.0 else 1.0
        if step >= 1.0:
            self._weight_at(i, end)
        else:
            self._w_from[i] = self._w[i]
            self._w_to[i] = end
            self._w_progress[i] = step  # s = 0 at the last step
            self._w_step[i] = step
        self._blend_difference(i)

    def _blend_difference(self, i: int, acc: float = 0.0, shortest: float = 0.0) -> None:
        """Start blending out axis ``i``'s command's difference to its target at the last step,
        in position and velocity (the target's velocity from its last two values) and
        acceleration ``acc`` (carried within twice the budget), over ``shortest`` or the
        shortest time within :data:`DIFFERENCE_ACC_SHARE` of its acceleration limit if longer
        (module docstring)."""
        share = DIFFERENCE_ACC_SHARE * float(self._limits.a_max[i])
        g = self._u[i] - self._tgt[i]
        rate = self._v[i] - (self._tgt[i] - self._tgt_prev[i]) * self.rate_hz
        length = blend_duration(g, rate, share, shortest)
        moves = g != 0.0 or rate != 0.0 or acc != 0.0
        step = self.dt_s / length if length > 0.0 and moves else 1.0
        if step < 1.0:
            self._e[i] = blend_coefficients(g, rate, acc, 0.0, length, share)
            self._e_progress[i] = step  # s = 0 at the last step, where g and rate were read
            self._e_step[i] = step

    def _weight_at(self, i: int, w: float) -> None:
        """Axis ``i``'s weight at ``w`` at once, no blend."""
        self._w[i] = self._w_from[i] = self._w_to[i] = w
        self._w_progress[i] = 1.0
        self._e[i] = [0.0] * BLEND_TERMS
        self._e_progress[i] = 1.0

    # --- state --------------------------------------------------------------------------------
    def reset(self, position: ArrayLike) -> None:
        """Put every state at rest at ``position`` (finite, within the limits): the next output
        equals ``position`` if the reference does."""
        p = check_position(self._limits, position).tolist()
        n = self.n
        self._k = 0
        zeros = [0.0] * n
        for buf, values in ((self._u, p), (self._v, zeros), (self.deviation, zeros),
                            (self._xm, [m.K * pi for m, pi in zip(self._models, p, strict=True)])):
            buf[:] = values
        for i in range(n):
            self._weight_at(i, 0.0 if self._bypass[i] else 1.0)
            self._pid_at_rest(i, p[i])
        self._tgt[:] = p
        self._tgt_prev[:] = p
        self._track[:] = [at_rest(pi) for pi in p]
        self._window[:] = [None] * n
        self._hist_m[:] = [x for pi in p for x in [pi] * self._hist_len]
        self._hist_r[:] = self._hist_m
        self.flags = [0] * n

    def _pid_at_rest(self, i: int, r: float) -> None:
        """Axis ``i``'s PID and its internal model at rest at the reference ``r``: its next
        output is ``r`` if the reference is (the platform mirror, the limiter and the weight
        keep their state)."""
        y = self._models[i].K * r
        self._r[i] = self._r_prev[i] = r
        self._xc[i] = self._y_last[i] = y
        self._deriv[i] = self._dr[i] = self._dy[i] = 0.0
        self._raw[i] = r
        base = i * self._hist_len
        for k in range(base, base + self._hist_len):
            self._hist_c[k] = r
        gp = self._gain_p[i]
        self._integral[i] = r - gp[0] * (gp[5] * r - y)

    def _virtual_raw(self) -> list[float]:
        """``kp (b r - y) + I + D`` with the latest state (what a gain change keeps of an axis
        in an input-loss window, :meth:`_retune`)."""
        return [gp[0] * (gp[5] * r - y) + i + d for gp, r, y, i, d in
                zip(self._gain_p, self._r, self._y_last, self._integral, self._deriv, strict=True)]

    def state(self) -> CompensatorState:
        """A copy of the complete state."""
        return CompensatorState(
            k=self._k, r=np.array(self._r), xc=np.array(self._xc), xm=np.array(self._xm),
            integral=np.array(self._integral), deriv=np.array(self._deriv),
            deriv_r=np.array(self._dr), deriv_y=np.array(self._dy),
            history_c=np.array(self._hist_c).reshape(self.n, self._hist_len),
            history_m=np.array(self._hist_m).reshape(self.n, self._hist_len),
            u=np.array(self._u), v=np.array(self._v),
            tracker=np.array(self._track), raw=np.array(self._raw),
            bypass=np.array(self._bypass, dtype=bool),
            weight=np.array(self._w), weight_from=np.array(self._w_from),
            weight_to=np.array(self._w_to), weight_progress=np.array(self._w_progress),
            weight_step=np.array(self._w_step),
            blend_progress=np.array(self._e_progress), blend_step=np.array(self._e_step),
            target=np.array([self._tgt_prev, self._tgt]),
            blend=np.array(self._e),
        )

    @property
    def output(self) -> FloatArray:
        """The last emitted command."""
        return np.array(self._u)

    @property
    def model_output(self) -> FloatArray:
        """The platform mirror ``y_m = M u``: the internal model's prediction of the platform
        position given the commands actually sent (updated by each step)."""
        return np.array(self._xm)

    @property
    def raw_output(self) -> FloatArray:
        """The raw (unsaturated) PID output of the last step."""
        return np.array(self._raw)

    # --- the tick -----------------------------------------------------------------------------
    def step(self, reference: Sequence[float] | np.ndarray) -> list[float]:
        """Advance one sample with the motion-cueing setpoint ``reference``; return the command.

        ``reference`` is a sequence of ``n`` floats (list or array).  The returned list is owned
        by the caller.  :attr:`flags` holds the per-axis bits of this step (saturation bits of
        :mod:`motcomp.core.saturation` and :data:`NONFINITE`).
        """
        ref: Sequence[float] = (reference.tolist() if isinstance(reference, np.ndarray)
                                else reference)
        if len(ref) != self.n:
            raise ValueError(f"reference has {len(ref)} values for {self.n} axes")
        k = self._k
        mask = self._mask
        rr, xcs, xms, ys, ints, ds, drs, dys = (self._r, self._xc, self._xm, self._y_last,
                                                self._integral, self._deriv, self._dr, self._dy)
        rps = self._r_prev
        us, vs, trk, raws = self._u, self._v, self._track, self._raw
        hcs, hms, hrs, hist_len = self._hist_c, self._hist_m, self._hist_r, self._hist_len
        ws, wf, wt, wp, wstep = (self._w, self._w_from, self._w_to, self._w_progress,
                                 self._w_step)
        tgs, tps, es, eps, estep = (self._tgt, self._tgt_prev, self._e, self._e_progress,
                                    self._e_step)
        out = [0.0] * self.n
        flags = [0] * self.n
        dev = self.deviation
        windows = self._window
        moving = 0
        for i, ((kp, kih, ad, q, kd, b, c), (phi, g0, g1, off0, off1), lim) in enumerate(zip(
                self._gain_p, self._model_p, self._lim, strict=True)):
            win = windows[i]
            if win is not None:
                lim = win
            r = ref[i]
            r_prev = rr[i]
            rps[i] = r_prev
            if isfinite(r):
                rr[i] = r
                fl = 0
            else:
                r = r_prev
                fl = NONFINITE
            y = xcs[i]  # y_m + y_aw = M v
            dr = ad * drs[i] + q * (r - r_prev)
            dy = ad * dys[i] + q * (y - ys[i])
            drs[i] = dr
            dys[i] = dy
            ys[i] = y
            d = kd * (c * dr - dy)
            ds[i] = d
            v = kp * (b * r - y) + ints[i] + d  # error = reference - model_output, in b r - y
            e = 0.0
            if win is not None:
                target = r  # input lost: the shaper's hold and ramp, not compensated
            else:
                progress = wp[i]
                if progress < 1.0:  # a switch (module docstring)
                    moving |= 1 << i
                    w = min_jerk_between(wf[i], wt[i], progress)
                    progress += wstep[i]
                    wp[i] = min(progress, 1.0)
                    ws[i] = w if progress < 1.0 else wt[i]
                else:
                    w = ws[i]
                progress = eps[i]
                if progress < 1.0:
                    moving |= 1 << i
                    e = horner(es[i], progress)
                    eps[i] = min(progress + estep[i], 1.0)
                target = v if w >= 1.0 else r if w <= 0.0 else r + w * (v - r)
            tps[i] = tgs[i]
            tgs[i] = target
            target += e
            u, vs[i], trk[i], sat = limit_axis(target, us[i], vs[i], trk[i], lim)
            us[i] = u
            dev[i] = u - target
            raws[i] = v
            ints[i] += kih * (r - y)
            base = i * hist_len
            slot = base + (k & mask)
            slot0 = base + ((k + off0) & mask)
            slot1 = base + ((k + off1) & mask)
            hcs[slot] = v
            xcs[i] = phi * y + g0 * hcs[slot0] + g1 * hcs[slot1]
            hms[slot] = u
            hrs[slot] = r
            xms[i] = phi * xms[i] + g0 * hms[slot0] + g1 * hms[slot1]
            out[i] = u
            flags[i] = fl | sat
        self._k = k + 1
        self.flags = flags
        self.moving = moving
        return out

    def run(self, references: ArrayLike) -> tuple[FloatArray, np.ndarray]:
        """Step through a ``(samples, n)`` array of references; return commands and flags."""
        ref = np.asarray(references, dtype=float)
        if ref.ndim != 2 or ref.shape[1] != self.n:
            raise ConfigError(f"references must have shape (samples, {self.n}), got {ref.shape}")
        out = np.empty_like(ref)
        flags = np.empty(ref.shape, dtype=np.int64)
        rows = ref.tolist()
        for i, row in enumerate(rows):
            out[i] = self.step(row)
            flags[i] = self.flags
        return out, flags
