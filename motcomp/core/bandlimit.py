"""The reference band limit: a 4th-order Bessel low-pass on the tick grid, per axis.

What a sender's stream carries above the driver's band is not motion cueing: float32 rounding
(0.24 um at 2.6 m), the rounding of epoch-second stamps times the speed (0.24 us x 1 m/s), an
irregular sampling's interpolation error, each 0.01-0.1 um a sample, white up to the input's
Nyquist frequency.  The compensator multiplies the command's content above 10 Hz by up to its
``hf_command_gain`` (5-60), and the jerk of white noise grows with the cube of frequency: 0.04 um
at 1 kHz through the 60x rails tuning is a jerk of 9 000 m/s^3, the command chatters at its
acceleration limit.  The band limit removes that content before the compensator sees it, at a
known price::

    L(s) = 105 / ((s D)^4 + 10 (s D)^3 + 45 (s D)^2 + 105 (s D) + 105)

the Bessel polynomial normalised to the group delay ``D`` at DC: maximally flat delay, so that in
the driver's band (0-3 Hz) ``L`` *is* a pure delay of ``D`` (to 1e-4 of it at 48 Hz), which the
design cancels like any other (``motcomp design --input-band-hz``); its step response overshoots
by 0.8 % (1.1 % once discretised, 48 Hz at 1 kHz).  The -3 dB frequency is
``2.1139 / (2 pi D)``: ``band_hz = 48`` costs ``D = 7.0 ms``.  It is realised by the bilinear
transform at the loop rate (which keeps the group delay at DC) as two second-order sections in
transposed direct form II, with the DC gain exactly 1, and seeded at rest on the first value
(:meth:`BandLimit.reset`), so that starting it is no step.

:func:`band_limit_freqresp` is the exact response of the discrete realisation, for the design's
noise figures (docs/WIRE.md, docs/TUNING.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from mypy_extensions import mypyc_attr
from numpy.typing import ArrayLike

from motcomp.core.lti import ComplexArray
from motcomp.core.native import frozen_reduce
from motcomp.errors import ConfigError

__all__ = ["BAND_HZ_DEFAULT", "BESSEL_W3DB", "BandLimit", "BandLimitParams", "band_limit_freqresp",
           "band_limit_params"]

BAND_HZ_DEFAULT = 48.0
"""The shipped band limit (``input.band_hz``): 7.0 ms of delay, -0.011 dB at 3 Hz."""
BESSEL4 = (1.0, 10.0, 45.0, 105.0, 105.0)
"""The 4th-order Bessel polynomial, unit group delay at DC."""
BESSEL_W3DB = 2.113917674904216
"""Its -3 dB angular frequency (rad/s, unit delay)."""

Section = tuple[float, float, float, float, float]
"""``(b0, b1, b2, a1, a2)`` of ``(b0 + b1 z^-1 + b2 z^-2) / (1 + a1 z^-1 + a2 z^-2)``."""


@dataclass(frozen=True)
class BandLimitParams:
    """A designed band limit: its -3 dB frequency, loop rate, delay (s) and sections."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return frozen_reduce(self)

    band_hz: float
    rate_hz: float
    delay_s: float
    sections: tuple[Section, Section]


def band_limit_params(band_hz: float, rate_hz: float, key: str = "input.band_hz"
                      ) -> BandLimitParams | None:
    """The band limit with -3 dB at ``band_hz`` at the loop rate ``rate_hz`` (None for 0: off).

    Raises
    ------
    ConfigError
        If ``band_hz`` (named ``key`` in the message) is negative, not finite, or above a
        quarter of the loop rate (the bilinear transform would bend its response too far from
        the Bessel's).
    """
    if not (math.isfinite(band_hz) and band_hz >= 0.0):
        raise ConfigError(f"{key} must be a finite number >= 0, got {band_hz!r}")
    if band_hz == 0.0:
        return None
    if not band_hz <= rate_hz / 4.0:
        raise ConfigError(f"{key} = {band_hz:g} Hz must be at most a quarter of the loop "
                          f"rate ({rate_hz / 4.0:g} Hz)")
    delay = BESSEL_W3DB / (2.0 * math.pi * band_hz)
    # poles of the analog prototype scaled to the delay, in conjugate pairs
    poles = np.roots(np.array(BESSEL4)) / delay
    pairs = sorted((p for p in poles if p.imag > 0.0), key=lambda p: abs(p.imag))
    c = 2.0 * rate_hz  # bilinear: s = c (1 - z^-1) / (1 + z^-1)
    sections = []
    for p in pairs:
        # 1 / (s^2 - 2 Re(p) s + |p|^2) -> bilinear, then DC gain 1
        w2 = float(abs(p) ** 2)
        re2 = float(-2.0 * p.real)
        a0 = c * c + re2 * c + w2
        a1 = (2.0 * w2 - 2.0 * c * c) / a0
        a2 = (c * c - re2 * c + w2) / a0
        g = (1.0 + a1 + a2) / 4.0  # numerator (1 + z^-1)^2, DC gain 1
        sections.append((g, 2.0 * g, g, a1, a2))
    return BandLimitParams(band_hz, rate_hz, delay, (sections[0], sections[1]))


def band_limit_freqresp(p: BandLimitParams | None, f_hz: ArrayLike) -> ComplexArray:
    """The discrete band limit's response at ``f_hz`` (1 where it is off)."""
    f = np.asarray(f_hz, dtype=float)
    if p is None:
        return np.ones(f.shape, dtype=complex)
    zi = np.exp(-2j * np.pi * f / p.rate_hz)
    h = np.ones(f.shape, dtype=complex)
    for b0, b1, b2, a1, a2 in p.sections:
        h = h * (b0 + b1 * zi + b2 * zi * zi) / (1.0 + a1 * zi + a2 * zi * zi)
    return np.asarray(h, dtype=complex)


_Plan = tuple[int, float, float, float, float, float, float, float, float, float, float]


@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class BandLimit:
    """The band limits' state for ``n`` axes; :meth:`step` filters one tick's values."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._state = [[0.0] * 4 for _ in range(n)]  # per axis: (s1, s2) of each section
        self._seeded = [False] * n
        self._bands: tuple[BandLimitParams | None, ...] = ()
        self._plan: list[_Plan] = []

    def reset(self) -> None:
        """Forget the state: each axis starts at rest on its next value."""
        self._seeded = [False] * self.n

    def step(self, bands: tuple[BandLimitParams | None, ...], x: list[float]) -> list[float]:
        """The values of this tick's ``x`` (one per axis), each through its axis' band limit
        (``bands``, None: passed through), in place of ``x``."""
        if bands is not self._bands:  # per axis: (index, coefficients), built once per bands
            self._bands = bands
            self._plan = [(i, *p.sections[0], *p.sections[1])
                          for i, p in enumerate(bands) if p is not None]
        state, seeded = self._state, self._seeded
        for i, b0, b1, b2, a1, a2, c0, c1, c2, d1, d2 in self._plan:
            v = x[i]
            s = state[i]
            if not seeded[i]:  # at rest on v: both sections' output is v
                seeded[i] = True
                s[1] = b2 * v - a2 * v
                s[0] = b1 * v - a1 * v + s[1]
                s[3] = c2 * v - d2 * v
                s[2] = c1 * v - d1 * v + s[3]
            y = b0 * v + s[0]
            s[0] = b1 * v - a1 * y + s[1]
            s[1] = b2 * v - a2 * y
            w = c0 * y + s[2]
            s[2] = c1 * y - d1 * w + s[3]
            s[3] = c2 * y - d2 * w
            if w - w != 0.0:  # not finite: never kept, start again at rest on v
                seeded[i] = False
                w = v
            x[i] = w
        return x
