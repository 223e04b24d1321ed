"""Excitation signals for identifying one axis, within its position, velocity and acceleration
limits.

Three kinds, each a position command (m or rad) about neutral (0):

``noise``
    Pseudo-white Gaussian noise (seeded) through a 4th-order Butterworth low-pass at the band
    (default 4 Hz on the rails, 10 Hz on the hexapod: the paper's choice).  A flat position
    spectrum up to the band.
``sweep``
    A logarithmic swept sine from ``f_min`` to ``f_max`` (default 0.1 Hz to the band), phase
    ``2 pi f0 T (k^(t/T) - 1) / ln k`` with ``k = f1/f0``.  Its amplitude follows the
    instantaneous frequency so that every limit is used where it binds:
    ``A(f) ~ min(p_lim, v_max / w, a_max / w^2)`` (a smooth minimum: position-limited at low
    frequency, acceleration-limited at high frequency), instead of one amplitude that the
    highest frequency would force down to millimetres.
``multisine``
    A periodic sum of cosines on the exact lines ``k / period`` between ``f_min`` and
    ``f_max`` (period default ``1 / f_min``: 10 s for 0.1 Hz), amplitudes shaped like the sweep's,
    phases by Schroeder's rule generalised to unequal powers (Schroeder 1970):
    ``phi_k = -2 pi sum_{l<k} (k - l) p_l`` with ``p_l`` the power fractions.  The rule is applied
    to the position, velocity and acceleration spectra in turn and the one giving the largest
    usable amplitude (the best crest factor where it matters) is kept.  Every whole period
    between the fades carries exactly the designed lines.

Every signal holds neutral for ``hold_s`` at both ends, fades in and out over ``fade_s`` with a
raised cosine (zero value and slope at the joins), lasts exactly ``duration_s`` and is then scaled
by one factor so that ``usage`` (default 0.9) of the tightest limit is reached.  The limits are
then *verified on the samples* with the same finite differences as the compensator's limiter
(:mod:`motcomp.core.saturation`): ``v[k] = (u[k] - u[k-1]) / h``,
``a[k] = (v[k] - v[k-1]) / h``, neutral before the first and after the last sample.

Outputs
-------
:func:`write_csv` writes ``t,cmd``; :func:`write_setpoint_stream` writes the service's input
frames ``{"seq": k, "t": t_k, "pos": {axis: cmd_k}}`` as concatenated msgpack maps (read back
with ``msgpack.Unpacker``), one per sample, ``seq`` from 0, ``t`` from 0 s.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal as sps

from motcomp.core.axes import AXIS_INDEX
from motcomp.core.lti import FloatArray
from motcomp.errors import ConfigError

__all__ = [
    "KINDS",
    "AxisRange",
    "Excitation",
    "atomic_write",
    "check_limits",
    "default_band_hz",
    "excitation",
    "read_setpoint_stream",
    "schroeder_phases",
    "write_csv",
    "write_setpoint_stream",
]

KINDS: tuple[str, ...] = ("noise", "sweep", "multisine")


@dataclass(frozen=True)
class AxisRange:
    """Limits of one axis (axis units: m or rad), neutral 0 strictly inside."""

    p_min: float
    p_max: float
    v_max: float
    a_max: float

    def __post_init__(self) -> None:
        for name in ("p_min", "p_max", "v_max", "a_max"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"limit {name} must be finite, got {getattr(self, name)!r}")
        if not self.p_min < 0 < self.p_max:
            raise ConfigError(f"position limits [{self.p_min}, {self.p_max}] must contain "
                              "neutral (0) strictly inside")
        if not (self.v_max > 0 and self.a_max > 0):
            raise ConfigError(f"velocity and acceleration limits must be > 0, got "
                              f"v_max={self.v_max}, a_max={self.a_max}")

    @property
    def p_lim(self) -> float:
        """Largest symmetric excursion about neutral."""
        return min(self.p_max, -self.p_min)


def default_band_hz(axis: str) -> float:
    """The paper's excitation band: 4 Hz for the rails (3-5 Hz), 10 Hz for the hexapod."""
    if axis not in AXIS_INDEX:
        raise ConfigError(f"unknown axis {axis!r}; axes are {', '.join(AXIS_INDEX)}")
    return 4.0 if axis.startswith("rails") else 10.0


@dataclass(frozen=True)
class Excitation:
    """A generated, scaled and verified excitation."""

    axis: str
    kind: str
    rate_hz: float
    t: FloatArray
    cmd: FloatArray
    limits: AxisRange
    scale: float
    """Factor applied to the unit-shaped signal."""
    peaks: dict[str, float]
    """Largest position excursion, speed and acceleration reached (from the samples)."""
    usage: dict[str, float]
    """Each peak as a fraction of its limit (the largest equals the requested usage)."""
    params: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return {
            "axis": self.axis, "kind": self.kind, "rate_hz": self.rate_hz,
            "duration_s": self.t.size / self.rate_hz, "samples": int(self.t.size),
            "limits": {"p_min": self.limits.p_min, "p_max": self.limits.p_max,
                       "v_max": self.limits.v_max, "a_max": self.limits.a_max},
            "peaks": self.peaks, "usage": self.usage, **self.params,
        }


def _derivatives(x: FloatArray, rate_hz: float) -> tuple[FloatArray, FloatArray]:
    """``v[k] = (x[k]-x[k-1])/h`` and ``a[k] = (v[k]-v[k-1])/h`` with neutral rest around ``x``."""
    padded = np.concatenate([[0.0, 0.0], x, [0.0, 0.0]])
    v = np.diff(padded) * rate_hz
    a = np.diff(v) * rate_hz
    return v, a


def check_limits(cmd: FloatArray, rate_hz: float, limits: AxisRange) -> dict[str, float]:
    """Peaks of ``cmd``; raises if any sample breaks a limit (by more than rounding).

    Raises
    ------
    ConfigError
        Naming the quantity, the sample, the value and the limit.
    """
    v, a = _derivatives(cmd, rate_hz)
    tol = 1e-9
    checks = (
        ("position", cmd, limits.p_min, limits.p_max),
        ("velocity", v, -limits.v_max, limits.v_max),
        ("acceleration", a, -limits.a_max, limits.a_max),
    )
    for name, x, lo, hi in checks:
        bad = np.nonzero((x < lo - tol * abs(lo)) | (x > hi + tol * abs(hi)))[0]
        if bad.size:
            k = int(bad[0])
            raise ConfigError(f"excitation breaks the {name} limit at sample {k}: {x[k]:.6g} "
                              f"outside [{lo:.6g}, {hi:.6g}]")
    return {"position": float(np.max(np.abs(cmd))), "velocity": float(np.max(np.abs(v))),
            "acceleration": float(np.max(np.abs(a)))}


def _scale_factor(x: FloatArray, rate_hz: float, limits: AxisRange, usage: float) -> float:
    v, a = _derivatives(x, rate_hz)
    ratios = []
    if x.max() > 0:
        ratios.append(limits.p_max / x.max())
    if x.min() < 0:
        ratios.append(limits.p_min / x.min())
    ratios.append(limits.v_max / max(float(np.max(np.abs(v))), 1e-300))
    ratios.append(limits.a_max / max(float(np.max(np.abs(a))), 1e-300))
    return usage * min(ratios)


def _fade(n: int, n_fade: int) -> FloatArray:
    env = np.ones(n)
    if n_fade > 0:
        ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(n_fade) / n_fade)
        env[:n_fade] = ramp
        env[n - n_fade:] = ramp[::-1]
    return env


def _limit_shape(f_hz: FloatArray, limits: AxisRange) -> FloatArray:
    """The largest sine amplitude the limits allow, ``min(p_lim, v_max/w, a_max/w^2)``, as a
    smooth minimum (a 4-norm of the reciprocals, at most 16 % below the sharp one at a corner).

    Smooth because a corner in a sweep's envelope is a step in its slope, which the second
    difference turns into an acceleration spike of ``slope step / h``.
    """
    w = 2.0 * np.pi * np.asarray(f_hz, dtype=float)
    inv = ((1.0 / limits.p_lim) ** 4 + (w / limits.v_max) ** 4 + (w**2 / limits.a_max) ** 4)
    return np.asarray(inv ** -0.25)


def _noise(n: int, rate_hz: float, band_hz: float, seed: int) -> FloatArray:
    rng = np.random.default_rng(seed)
    settle = math.ceil(4.0 * rate_hz / band_hz)
    sos = sps.butter(4, band_hz, btype="low", fs=rate_hz, output="sos")
    w = rng.standard_normal(n + settle)
    return np.asarray(sps.sosfilt(sos, w)[settle:])


def _sweep(n: int, rate_hz: float, f0: float, f1: float, limits: AxisRange) -> FloatArray:
    T = n / rate_hz
    t = np.arange(n) / rate_hz
    k = f1 / f0
    phase = 2.0 * np.pi * f0 * T * (k ** (t / T) - 1.0) / math.log(k)
    f_inst = f0 * k ** (t / T)
    return np.asarray(_limit_shape(f_inst, limits) * np.sin(phase))


def schroeder_phases(power: FloatArray) -> FloatArray:
    """Schroeder's low-crest-factor phases for lines of relative powers ``power``.

    ``phi_k = -2 pi sum_{l<k} (k - l) p_l``, ``p`` normalised to sum 1; for equal powers this is
    the classic ``-pi k (k - 1) / K``.
    """
    p = np.asarray(power, dtype=float)
    p = p / p.sum()
    k = np.arange(p.size)
    # sum_{l<k} (k - l) p_l = k * cumsum(p)[k-1] - cumsum(l p_l)[k-1]
    cp = np.concatenate([[0.0], np.cumsum(p)[:-1]])
    clp = np.concatenate([[0.0], np.cumsum(k * p)[:-1]])
    return np.asarray(-2.0 * np.pi * (k * cp - clp))


def _multisine(n: int, rate_hz: float, f0: float, f1: float, period_s: float,
               limits: AxisRange, fade: FloatArray) -> tuple[FloatArray, dict[str, Any]]:
    f_res = 1.0 / period_s
    k_lo = max(1, math.ceil(f0 / f_res - 1e-9))
    k_hi = math.floor(f1 / f_res + 1e-9)
    if k_hi < k_lo:
        raise ConfigError(f"multisine: no line k/{period_s:g} s between {f0:g} and {f1:g} Hz")
    lines = np.arange(k_lo, k_hi + 1) * f_res
    amp = _limit_shape(lines, limits)
    w = 2.0 * np.pi * lines
    t = np.arange(n) / rate_hz
    best: tuple[float, FloatArray, str] | None = None
    for name, weight in (("position", amp), ("velocity", amp * w), ("acceleration", amp * w**2)):
        phi = schroeder_phases(weight**2)
        x = np.zeros(n)
        for a_k, w_k, p_k in zip(amp, w, phi, strict=True):
            x += a_k * np.cos(w_k * t + p_k)
        x *= fade
        s = _scale_factor(x, rate_hz, limits, 1.0)
        if best is None or s > best[0]:
            best = (s, x, name)
    assert best is not None
    return best[1], {"lines_hz": [float(f) for f in lines], "period_s": period_s,
                     "phases_for": best[2]}


def excitation(kind: str, axis: str, limits: AxisRange, duration_s: float = 60.0,
               rate_hz: float = 1000.0, band_hz: float | None = None, f_min_hz: float = 0.1,
               f_max_hz: float | None = None, seed: int = 0, usage: float = 0.9,
               fade_s: float = 2.0, hold_s: float = 0.5, period_s: float | None = None
               ) -> Excitation:
    """Generate an excitation of ``kind`` (``noise``, ``sweep`` or ``multisine``) for ``axis``.

    Parameters
    ----------
    band_hz
        Low-pass band of the noise (default :func:`default_band_hz`); also the default
        ``f_max_hz`` of the sweep and multisine.
    f_min_hz, f_max_hz
        Frequency range of the sweep and multisine.
    seed
        Seed of the noise (the same seed gives the same samples).
    usage
        Fraction of the tightest limit reached (0 < usage <= 1).
    fade_s, hold_s
        Raised-cosine fade length and neutral hold at each end.
    period_s
        Multisine period (default ``1 / f_min_hz``).

    Raises
    ------
    ConfigError
        For an unknown kind or axis, non-positive or inconsistent frequencies, a duration too
        short for the holds and fades, or (never expected) a limit broken after scaling.
    """
    if kind not in KINDS:
        raise ConfigError(f"unknown excitation kind {kind!r}; kinds: {', '.join(KINDS)}")
    band = default_band_hz(axis) if band_hz is None else float(band_hz)
    f1 = band if f_max_hz is None else float(f_max_hz)
    for name, value in (("rate", rate_hz), ("duration", duration_s), ("band", band),
                        ("f_min", f_min_hz), ("f_max", f1)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"excitation {name} must be a positive finite number, got {value!r}")
    if not 0 < usage <= 1:
        raise ConfigError(f"usage must be in (0, 1], got {usage!r}")
    if fade_s < 0 or hold_s < 0:
        raise ConfigError(f"fade and hold must be >= 0 s, got fade={fade_s}, hold={hold_s}")
    nyq = rate_hz / 2.0
    if max(band, f1) >= 0.8 * nyq:
        raise ConfigError(f"excitation band {max(band, f1):g} Hz is too close to the Nyquist "
                          f"frequency {nyq:g} Hz of {rate_hz:g} Hz samples")
    if kind != "noise" and not f_min_hz < f1:
        raise ConfigError(f"f_min ({f_min_hz:g} Hz) must be below f_max ({f1:g} Hz)")
    n = round(duration_s * rate_hz)
    n_hold = round(hold_s * rate_hz)
    n_fade = round(fade_s * rate_hz)
    n_act = n - 2 * n_hold
    if n_act < 2 * n_fade + round(rate_hz):
        raise ConfigError(f"duration {duration_s:g} s is too short for {hold_s:g} s holds and "
                          f"{fade_s:g} s fades (at least 1 s of full amplitude is needed)")
    fade = _fade(n_act, n_fade)
    params: dict[str, Any] = {"seed": seed} if kind == "noise" else {}
    shape: FloatArray
    if kind == "noise":
        shape = _noise(n_act, rate_hz, band, seed) * fade
        params["band_hz"] = band
    elif kind == "sweep":
        shape = _sweep(n_act, rate_hz, f_min_hz, f1, limits) * fade
        params.update(f_min_hz=f_min_hz, f_max_hz=f1)
    else:
        period = 1.0 / f_min_hz if period_s is None else float(period_s)
        if not (math.isfinite(period) and period > 0):
            raise ConfigError(f"multisine period must be > 0 s, got {period!r}")
        shape, extra = _multisine(n_act, rate_hz, f_min_hz, f1, period, limits, fade)
        params.update(f_min_hz=f_min_hz, f_max_hz=f1, **extra)
    x = np.zeros(n)
    x[n_hold:n_hold + n_act] = shape
    scale = _scale_factor(x, rate_hz, limits, usage)
    cmd = x * scale
    peaks = check_limits(cmd, rate_hz, limits)
    ratio = {
        "position": max(float(cmd.max()) / limits.p_max, float(cmd.min()) / limits.p_min),
        "velocity": peaks["velocity"] / limits.v_max,
        "acceleration": peaks["acceleration"] / limits.a_max,
    }
    params.update(hold_s=hold_s, fade_s=fade_s)
    t = np.arange(n) / rate_hz
    return Excitation(axis=axis, kind=kind, rate_hz=float(rate_hz), t=t, cmd=cmd, limits=limits,
                      scale=float(scale), peaks=peaks, usage=ratio, params=params)


def atomic_write(path: Path, write: Callable[[Any], None], mode: str) -> None:
    """Write through a temporary file in the same directory, then rename: never half a file."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent or ".", prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as fh:
            write(fh)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 is for the temporary name only
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_csv(path: Path, exc: Excitation) -> None:
    """``t,cmd`` with a header, seconds and axis units, full precision."""
    def _w(fh: Any) -> None:
        fh.write("t,cmd\n")
        for ti, ui in zip(exc.t, exc.cmd, strict=True):
            fh.write(f"{ti:.6f},{ui:.12g}\n")
    atomic_write(path, _w, "w")


def write_setpoint_stream(path: Path, exc: Excitation) -> None:
    """The service's input frames, msgpack maps concatenated (``msgpack.Unpacker`` reads them)."""
    import msgpack

    packer = msgpack.Packer(use_bin_type=True)

    def _w(fh: Any) -> None:
        for k, (ti, ui) in enumerate(zip(exc.t, exc.cmd, strict=True)):
            fh.write(packer.pack({"seq": k, "t": float(ti), "pos": {exc.axis: float(ui)}}))
    atomic_write(path, _w, "wb")


def read_setpoint_stream(path: Path) -> list[dict[str, Any]]:
    """The frames of a stream file written by :func:`write_setpoint_stream`."""
    import msgpack

    with open(path, "rb") as fh:
        return list(msgpack.Unpacker(fh, raw=False))
