"""Frequency-domain evaluation of the pseudo open-loop compensator.

For a PID ``C`` (split into the reference path ``Cr`` and the model path ``Cy`` when setpoint
weights are used), the internal model ``M`` and the real platform ``P``::

    F = u/r = Cr / (1 + Cy M)             command transfer (the compensator as a prefilter)
    T = y/r = P F                         delivered response
    S = 1 / (1 + Cy M)                    sensitivity of the internal loop, Ms = max |S|

Both a continuous-time evaluation (``s = j w``, exact delays) and one at the loop rate
(``z = e^{j w h}``: exact ZOH models with sub-sample delays, and the *implemented* discrete PID of
:mod:`motcomp.core.compensator`) are provided; below a few Hz they agree to a fraction of a ms.

With a predictive prefilter ``F_pred`` (:mod:`motcomp.core.predictor`) before the compensator,
the command is ``F = F_pred Cr / (1 + Cy M)`` and ``T = P F``; without a PID (the axis bypassed)
``Cr / (1 + Cy M)`` is 1 and ``F = F_pred`` (or 1).

Phases are unwrapped without ambiguity: ``arg T = arg P + arg Cr - arg(1 + Cy M) + arg F_pred``,
where the first two are exact from poles and zeros, the third is unwrapped along a dense grid
that starts where ``1 + Cy M ~ K ki / (j w)`` (phase -90 deg) or, without integral action,
~ ``1 + kp K``, and the last is unwrapped along a dense grid from DC, where it is 0
(:func:`predictor_phase`).

Stability of the discrete internal loop is decided from the roots of its characteristic
polynomial (:func:`motcomp.core.loop.stability`), never from a frequency grid alone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from motcomp.core.bandlimit import BandLimitParams, band_limit_freqresp
from motcomp.core.loop import Poly, model_tf, pid_tf, stability
from motcomp.core.lti import (
    ComplexArray,
    FloatArray,
    rational_phase_continuous,
    rational_phase_discrete,
)
from motcomp.core.models import P1D, ProcessModel
from motcomp.core.pid import PIDGains
from motcomp.core.predictor import PredictorParams, predictor_freqresp
from motcomp.errors import ConfigError

__all__ = [
    "BAND_HZ",
    "HF_FROM_HZ",
    "REPORT_FREQS_HZ",
    "Evaluation",
    "LoopResponse",
    "evaluate",
    "loop_response",
    "noise_figures",
    "pid_continuous",
    "predictor_phase",
]

REPORT_FREQS_HZ: tuple[float, ...] = (0.2, 0.5, 1.0, 2.0)
"""Frequencies at which phase delays are reported (the paper's driver band)."""
BAND_HZ: tuple[float, float] = (0.1, 2.0)
"""The driver band: steering inputs live in 0-2 Hz (paper)."""
HF_FROM_HZ = 10.0
"""Lower edge of the high-frequency range where the command's gain is bounded: no driver
input lives there, only the input stream's irregularities."""


def pid_continuous(g: PIDGains) -> tuple[Poly, Poly]:
    """``((num_r, den), (num_y, den))`` of ``Cr(s)`` and ``Cy(s)`` in s.

    ``Cy(s) = kp + ki/s + kd s/(1 + tf s)`` and ``Cr`` the same with ``kp b`` and ``kd c``;
    common denominator ``s (1 + tf s)``.
    """
    den = np.polymul([1.0, 0.0], [g.tf, 1.0])

    def num(kp: float, kd: float) -> FloatArray:
        # kp s (1 + tf s) + ki (1 + tf s) + kd s^2
        return np.polyadd(np.polyadd(np.polymul([kp, 0.0], [g.tf, 1.0]),
                                     np.polymul([g.ki], [g.tf, 1.0])), [kd, 0.0, 0.0])

    return (num(g.kp * g.b, g.kd * g.c), den), (num(g.kp, g.kd), den)


@dataclass(frozen=True)
class LoopResponse:
    """Responses on a frequency grid ``f`` (Hz)."""

    f: FloatArray
    plant: ComplexArray  # P
    command: ComplexArray  # F = F_pred Cr / (1 + Cy M)  (F_pred = 1 without prediction)
    delivered: ComplexArray  # T = P F
    sensitivity: ComplexArray  # S = 1 / (1 + Cy M)  (1 in bypass)
    plant_phase: FloatArray  # unwrapped arg P
    delivered_phase: FloatArray  # unwrapped arg T

    def phase_delay(self, which: str = "delivered") -> FloatArray:
        ph = self.delivered_phase if which == "delivered" else self.plant_phase
        return np.asarray(-ph / (2.0 * np.pi * self.f))


def default_grid(rate_hz: float | None, extra: ArrayLike = ()) -> FloatArray:
    """Log grid from 1 mHz to the Nyquist frequency (or 500 Hz), with ``extra`` points merged."""
    top = 0.5 * rate_hz * 0.999 if rate_hz else 500.0
    base = np.geomspace(1e-3, top, 6000)
    return np.unique(np.concatenate([base, np.asarray(extra, dtype=float)]))


PHASE_STEPS = 1 << 14
"""Points of the uniform grid (0 to the highest frequency asked) along which
:func:`predictor_phase` unwraps."""


def predictor_phase(p: PredictorParams, f_hz: ArrayLike) -> FloatArray:
    """Unwrapped ``arg F_pred`` (rad) on ``f_hz`` (Hz, below ``p.rate_hz / 2``), 0 at DC.

    The phase is unwrapped along the union of ``f_hz`` and a uniform grid of
    :data:`PHASE_STEPS` points from 0 Hz, where ``F_pred(1) = 1``: a step of the uniform grid
    turns each pole factor ``1/(z - a)`` by at most ``dtheta / (1 - a)``.
    """
    f = np.atleast_1d(np.asarray(f_hz, dtype=float))
    if f.size == 0:
        return np.zeros(0)
    top = float(np.max(f))
    if not top < p.rate_hz / 2:
        raise ConfigError(f"frequency grid reaches the Nyquist frequency {p.rate_hz / 2} Hz")
    fine = np.unique(np.concatenate([np.linspace(0.0, top, PHASE_STEPS), f]))
    ph = np.unwrap(np.angle(predictor_freqresp(p, fine)))
    ph = ph - 2.0 * np.pi * round(float(ph[0]) / (2.0 * np.pi))  # arg F(1) = 0
    return np.asarray(np.interp(f, fine, ph))


def loop_response(gains: PIDGains | None, model: P1D | None, plant: ProcessModel,
                  f_hz: ArrayLike, rate_hz: float | None = None,
                  predictor: PredictorParams | None = None) -> LoopResponse:
    """Responses of the compensated loop on the ascending grid ``f_hz`` (must start low,
    below ~0.01 Hz, for the unwrapping).

    ``rate_hz=None`` evaluates in continuous time; otherwise at the discrete rate.
    ``gains=None`` is the bypassed axis (no PID: ``Cr / (1 + Cy M) = 1``, ``model`` unused);
    ``predictor`` multiplies the command and the delivered response (evaluated at its own
    rate, in continuous time too).
    """
    f = np.asarray(f_hz, dtype=float)
    if f.ndim != 1 or f.size < 2 or np.any(np.diff(f) <= 0) or f[0] <= 0:
        raise ConfigError("frequency grid must be positive and strictly ascending")
    if gains is not None and model is None:
        raise ConfigError("a PID needs its internal model")
    w = 2.0 * np.pi * f
    ones: ComplexArray = np.ones(f.size, dtype=complex)
    cr: ComplexArray = ones
    cy: ComplexArray = ones
    m: ComplexArray = ones
    arg_cr: FloatArray = np.zeros(f.size)
    arg_p: FloatArray
    if rate_hz is None:
        p = plant.freqresp(f)
        arg_p = plant.phase(f)
        if gains is not None:
            assert model is not None
            (nr, dr), (ny, dy) = pid_continuous(gains)
            s = 1j * w
            cr = np.polyval(nr, s) / np.polyval(dr, s)
            cy = np.polyval(ny, s) / np.polyval(dy, s)
            m = model.freqresp(f)
            arg_cr = rational_phase_continuous(nr, dr, w)
    else:
        dt = 1.0 / rate_hz
        theta = w * dt
        if np.any(theta >= np.pi):
            raise ConfigError(f"frequency grid reaches the Nyquist frequency {rate_hz / 2} Hz")
        z = np.exp(1j * theta)
        pd = plant.discretize(rate_hz)
        pn, pden = pd.tf()
        p = np.asarray(np.polyval(pn, z) / np.polyval(pden, z), dtype=complex)
        arg_p = rational_phase_discrete(pn, pden, theta)
        if gains is not None:
            assert model is not None
            (nr, dr), (ny, dy) = pid_tf(gains, dt)
            cr = np.asarray(np.polyval(nr, z) / np.polyval(dr, z), dtype=complex)
            cy = np.asarray(np.polyval(ny, z) / np.polyval(dy, z), dtype=complex)
            nm, dm = model_tf(model, dt)
            m = np.asarray(np.polyval(nm, z) / np.polyval(dm, z), dtype=complex)
            arg_cr = rational_phase_discrete(nr, dr, theta)
    one_plus: ComplexArray
    arg_loop: FloatArray
    if gains is None:
        one_plus = ones
        arg_loop = np.zeros(f.size)
    else:
        assert model is not None
        one_plus = 1.0 + cy * m
        arg_loop = np.unwrap(np.angle(one_plus))
        # anchor at the low-frequency asymptote (-pi/2 with integral action, 0 without)
        expected0 = -np.pi / 2 if gains.ki > 0 else float(np.angle(1.0 + gains.kp * model.K))
        arg_loop = arg_loop + 2.0 * np.pi * round((expected0 - arg_loop[0]) / (2.0 * np.pi))
    f_cmd: ComplexArray = np.asarray(cr / one_plus, dtype=complex)
    arg_pred: FloatArray = np.zeros(f.size)
    if predictor is not None:
        f_cmd = f_cmd * predictor_freqresp(predictor, f)
        arg_pred = predictor_phase(predictor, f)
    t = p * f_cmd
    return LoopResponse(
        f=f, plant=p, command=f_cmd, delivered=t, sensitivity=1.0 / one_plus,
        plant_phase=np.asarray(arg_p),
        delivered_phase=np.asarray(arg_p + arg_cr - arg_loop + arg_pred),
    )


@dataclass
class Evaluation:
    """Metrics of one design (SI units unless the name says ms, Hz or dB)."""

    rate_hz: float | None
    uncorrected_phase_delay_ms: dict[str, float]
    uncorrected_max_delay_ms: float
    uncorrected_gain_error_db: float
    phase_delay_ms: dict[str, float]
    max_residual_delay_ms: float
    max_residual_delay_hz: float
    gain_error_db: float
    peak_gain_db: float
    peak_gain_hz: float
    peak_command_gain: float
    peak_command_gain_hz: float
    hf_command_gain: float
    """Largest ``|F|`` at or above ``hf_from_hz``: what an irregularity of the input (jitter,
    steps, quantisation) reaches the platform multiplied by."""
    hf_from_hz: float
    ms: float
    stable: bool
    max_pole_modulus: float
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _key(f: float) -> str:
    return f"{f:g}"


def evaluate(gains: PIDGains | None, model: P1D | None, plant: ProcessModel | None = None,
             rate_hz: float | None = 1000.0, band_hz: tuple[float, float] = BAND_HZ,
             report_hz: tuple[float, ...] = REPORT_FREQS_HZ,
             hf_from_hz: float = HF_FROM_HZ,
             predictor: PredictorParams | None = None) -> Evaluation:
    """All frequency-domain metrics of a design.

    Parameters
    ----------
    gains, model
        The compensator (PID gains and its internal P1D model); ``gains=None``: the axis is
        bypassed (no PID; the internal loop is then reported stable, ``Ms = 1``).
    plant
        The real platform; defaults to ``model`` (exact model).
    predictor
        The predictive prefilter before the compensator, if any: it multiplies the command and
        the delivered response.
    rate_hz
        Loop rate for the discrete evaluation, or None for continuous time (stability is then
        still judged on the discrete loop at 1 kHz, the service's default rate).
    band_hz
        Band of the residual-delay and gain-error metrics.
    hf_from_hz
        Lower edge of the high-frequency range of :attr:`Evaluation.hf_command_gain`.

    Notes
    -----
    The residual delay is the largest ``|tau_phi|`` over the band: a phase *lead* (negative
    delay) is an error too.
    """
    plant = plant or model
    if plant is None:
        raise ConfigError("evaluate needs a plant or a model")
    lo, hi = band_hz
    if not 0 < lo < hi:
        raise ConfigError(f"band must satisfy 0 < low < high, got {band_hz}")
    band = np.geomspace(lo, hi, 400)
    top_rate = rate_hz if rate_hz or predictor is None else predictor.rate_hz
    grid = default_grid(top_rate, np.concatenate([band, report_hz, [hf_from_hz]]))
    resp = loop_response(gains, model, plant, grid, rate_hz, predictor)
    tau = resp.phase_delay("delivered")
    tau_p = resp.phase_delay("plant")
    idx = {f: int(np.searchsorted(grid, f)) for f in report_hz}
    in_band = (grid >= lo * (1 - 1e-12)) & (grid <= hi * (1 + 1e-12))
    mag_db = 20.0 * np.log10(np.abs(resp.delivered))
    plant_db = 20.0 * np.log10(np.abs(resp.plant))
    resid = np.abs(tau[in_band])
    i_res = int(np.argmax(resid))
    i_peak = int(np.argmax(mag_db))
    cmd = np.abs(resp.command)
    i_cmd = int(np.argmax(cmd))
    hf = grid >= hf_from_hz * (1 - 1e-12)
    stable, rho = (True, 0.0) if gains is None or model is None else \
        stability(gains, model, rate_hz or 1000.0)
    notes = []
    if not stable:
        notes.append(f"internal loop UNSTABLE at {rate_hz or 1000.0:g} Hz "
                     f"(pole modulus {rho:.4f})")
    return Evaluation(
        rate_hz=rate_hz,
        uncorrected_phase_delay_ms={_key(f): float(tau_p[i]) * 1e3 for f, i in idx.items()},
        uncorrected_max_delay_ms=float(np.max(np.abs(tau_p[in_band]))) * 1e3,
        uncorrected_gain_error_db=float(np.max(np.abs(plant_db[in_band]))),
        phase_delay_ms={_key(f): float(tau[i]) * 1e3 for f, i in idx.items()},
        max_residual_delay_ms=float(resid[i_res]) * 1e3,
        max_residual_delay_hz=float(grid[in_band][i_res]),
        gain_error_db=float(np.max(np.abs(mag_db[in_band]))),
        peak_gain_db=float(mag_db[i_peak]),
        peak_gain_hz=float(grid[i_peak]),
        peak_command_gain=float(cmd[i_cmd]),
        peak_command_gain_hz=float(grid[i_cmd]),
        hf_command_gain=float(np.max(cmd[hf])) if np.any(hf) else 0.0,
        hf_from_hz=float(hf_from_hz),
        ms=float(np.max(np.abs(resp.sensitivity))),
        stable=stable,
        max_pole_modulus=rho,
        notes=notes,
    )


def residual_lag_s(gains: PIDGains, model: P1D) -> float:
    """Low-frequency residual lag ``1/(K ki)`` of the corrected response (exact model)."""
    if gains.ki <= 0:
        return math.inf
    return 1.0 / (model.K * gains.ki)


NOISE_RMS_M = 1e-7
"""The input noise of the noise figures: 0.1 um RMS, white, one value a tick (float32 rounding
at 2.6 m is 0.07 um RMS; epoch-second stamps at 1 m/s, 0.07 um)."""
NOISE_ACC_ABOVE_HZ = 5.0


def noise_figures(gains: PIDGains | None, model: P1D | None, rate_hz: float,
                  band: BandLimitParams | None = None,
                  predictor: PredictorParams | None = None,
                  hf_from_hz: float = HF_FROM_HZ) -> dict[str, float]:
    """What white noise on the input values does to the command, through the band limit, the
    prefilter and the compensator: ``N = L F_pred Cr / (1 + Cy M)`` at the loop rate.

    Returns ``hf_gain`` (max ``|N|`` at and above ``hf_from_hz``: um of command per um of input
    noise there), ``rms_gain`` (command noise RMS per input noise RMS, white over the whole
    band up to the loop's Nyquist frequency), and for :data:`NOISE_RMS_M` of input noise the
    command's ``acc_hf_rms_m_s2`` (acceleration above 5 Hz) and ``jerk_rms_m_s3`` (third
    difference), as :func:`motcomp.core.quality.command_quality` measures them.
    """
    n = 20000
    f = np.arange(1, n) * (0.5 * rate_hz / n)  # uniform up to Nyquist (excluded)
    if gains is None:
        cmd: ComplexArray = np.ones(f.size, dtype=complex)
        if predictor is not None:
            cmd = predictor_freqresp(predictor, f)
    else:
        assert model is not None
        cmd = loop_response(gains, model, model, f, rate_hz, predictor).command
    resp = cmd * band_limit_freqresp(band, f)
    zi = np.exp(-2j * np.pi * f / rate_hz)
    diff = np.abs((1.0 - zi) * rate_hz)
    power = np.abs(resp) ** 2

    def rms(weight: FloatArray, where: np.ndarray | None = None) -> float:
        w = power * weight if where is None else np.where(where, power * weight, 0.0)
        return float(np.sqrt(np.mean(w)))  # the mean over a uniform grid of (0, pi)

    return {
        "hf_gain": float(np.max(np.abs(resp[f >= hf_from_hz]))),
        "rms_gain": rms(np.ones(f.size)),
        "acc_hf_rms_m_s2": NOISE_RMS_M * rms(diff ** 4, f >= NOISE_ACC_ABOVE_HZ),
        "jerk_rms_m_s3": NOISE_RMS_M * rms(diff ** 6),
    }
