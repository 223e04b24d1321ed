"""Tuning rules of the pseudo open-loop PID from a P1D model ``K e^{-Td s}/(1 + Tp1 s)``.

Each rule gives the standard form ``Kc (1 + 1/(Ti s) + Td_pid s)``; gains are returned in the
canonical parallel form (:class:`~motcomp.core.pid.PIDGains`) with a derivative filter.
With ``K``, ``L = Td`` and ``T = Tp1`` of the model and ``r = L/T``:

``zn`` (Ziegler-Nichols)
    ``Kc = 1.2 T/(K L)``, ``Ti = 2 L``, ``Td_pid = 0.5 L``
``cc`` (Cohen-Coon)
    ``Kc = (1/K)(T/L)(4/3 + r/4)``, ``Ti = L (32 + 6 r)/(13 + 8 r)``, ``Td_pid = 4 L/(11 + 2 r)``
``amigo`` (Astrom & Hagglund, 2004)
    ``Kc = (0.2 + 0.45 T/L)/K``, ``Ti = L (0.4 L + 0.8 T)/(L + 0.1 T)``,
    ``Td_pid = 0.5 L T/(0.3 L + T)``
``simc`` (Skogestad, 2003; tight, ``tc = L``; a PI)
    ``Kc = T/(K (tc + L))``, ``Ti = min(T, 4 (tc + L))``

Ziegler-Nichols and Cohen-Coon are written in the paper in parallel form ("Ti = 2 Td / Kp"
meaning ``ki = Kp / (2 Td)``): the list above is the same thing in standard form.

The derivative filter is ``tf = Td_pid / N`` with ``N = 10`` by default.

Applicability
-------------
ZN and CC suit lag-dominated plants, ``Tp1/Td`` above about 5-10 (the rails: ~10.6).  For a
delay-dominated plant (the hexapod: ``Tp1/Td`` ~ 0.07) they give a tiny ``Kc`` and the
compensator then makes the apparent lag much *worse* (the integral's residual lag ``1/(K ki)``
grows to hundreds of ms).  :func:`tune` returns warnings for that, and :func:`check_lag`
compares the compensated and uncompensated low-frequency lag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from motcomp.core.models import P1D
from motcomp.core.pid import PIDGains
from motcomp.errors import ConfigError

__all__ = ["RULES", "Tuning", "standard_form", "tune"]

RULES: tuple[str, ...] = ("zn", "cc", "amigo", "simc")
RULE_NAMES: dict[str, str] = {
    "zn": "Ziegler-Nichols",
    "cc": "Cohen-Coon",
    "amigo": "AMIGO",
    "simc": "SIMC (tight, PI)",
}
MIN_LAG_RATIO = 5.0
"""Below this ``Tp1/Td`` the step-response rules ZN and CC do not apply."""


@dataclass(frozen=True)
class Tuning:
    """A rule's result: gains, the standard form it came from, and warnings."""

    rule: str
    gains: PIDGains
    standard: dict[str, float]
    warnings: list[str] = field(default_factory=list)


def standard_form(rule: str, model: P1D) -> dict[str, float]:
    """``{"Kc", "Ti", "Td"}`` (Td = derivative time) of ``rule`` for ``model``.

    Raises
    ------
    ConfigError
        For an unknown rule or a model without dead time (all four rules divide by Td).
    """
    K, L, T = model.K, model.Td, model.Tp1
    if rule not in RULES:
        raise ConfigError(f"unknown tuning rule {rule!r}; rules: {', '.join(RULES)}")
    if L <= 0:
        raise ConfigError(f"tuning rule {rule} needs a dead time Td > 0, model has Td={L}")
    if rule == "zn":
        return {"Kc": 1.2 * T / (K * L), "Ti": 2.0 * L, "Td": 0.5 * L}
    if rule == "cc":
        r = L / T
        return {
            "Kc": (1.0 / K) * (T / L) * (4.0 / 3.0 + L / (4.0 * T)),
            "Ti": L * (32.0 + 6.0 * r) / (13.0 + 8.0 * r),
            "Td": 4.0 * L / (11.0 + 2.0 * r),
        }
    if rule == "amigo":
        return {
            "Kc": (0.2 + 0.45 * T / L) / K,
            "Ti": L * (0.4 * L + 0.8 * T) / (L + 0.1 * T),
            "Td": 0.5 * L * T / (0.3 * L + T),
        }
    # simc, tight: tc = L
    tc = L
    return {"Kc": T / (K * (tc + L)), "Ti": min(T, 4.0 * (tc + L)), "Td": 0.0}


def tune(rule: str, model: P1D, filter_n: float = 10.0) -> Tuning:
    """Gains of ``rule`` for ``model`` with derivative filter ``tf = Td_pid / filter_n``.

    Warnings are returned (never raised) when the rule does not apply to the plant; they say so
    loudly because the consequence (a *larger* delay on the platform) is not obvious.
    """
    if not (math.isfinite(filter_n) and filter_n > 0):
        raise ConfigError(f"derivative filter N must be finite and > 0, got {filter_n}")
    std = standard_form(rule, model)
    if std["Kc"] <= 0:
        raise ConfigError(f"rule {rule} gives Kc={std['Kc']:.4g} <= 0 for {model}: a negative "
                          "plant gain K cannot be compensated by these rules")
    gains = PIDGains.from_standard(Kc=std["Kc"], Ti=std["Ti"], Td=std["Td"], N=filter_n)
    warnings: list[str] = []
    ratio = model.Tp1 / model.Td
    if rule in ("zn", "cc") and ratio < MIN_LAG_RATIO:
        warnings.append(
            f"WARNING: {RULE_NAMES[rule]} assumes a lag-dominated plant (Tp1/Td > {MIN_LAG_RATIO:g}"
            f"-10); this plant has Tp1/Td = {ratio:.3g} (delay-dominated). The rule gives "
            f"Kc = {std['Kc']:.3g} and the compensated response will lag MORE than the plant "
            "alone. Use bypass on this axis, or --rule optimal."
        )
    elif ratio < 1.0:
        warnings.append(
            f"WARNING: delay-dominated plant (Tp1/Td = {ratio:.3g}): phase-delay compensation "
            f"can gain at most about Tp1 = {model.Tp1 * 1e3:.1f} ms here; the pure delay "
            f"Td = {model.Td * 1e3:.1f} ms cannot be compensated. Consider bypass on this axis."
        )
    lag = check_lag(gains, model)
    if lag is not None:
        warnings.append(lag)
    return Tuning(rule=rule, gains=gains, standard=std, warnings=warnings)


def check_lag(gains: PIDGains, model: P1D) -> str | None:
    """A warning if the compensator's low-frequency residual lag exceeds the plant's own.

    With the model exact, the corrected low-frequency lag is ``Td_eff = 1/(K ki)``: the error
    integral must build up before the command leads.  If that is larger than the plant's lag
    ``Td + Tp1``, compensation makes the platform *later*.
    """
    if gains.ki <= 0:
        return None
    residual = 1.0 / (model.K * gains.ki)
    plant = model.Td + model.Tp1
    if residual > plant:
        return (
            f"WARNING: these gains leave a low-frequency lag of 1/(K ki) = {residual * 1e3:.1f} ms,"
            f" more than the uncompensated {plant * 1e3:.1f} ms: compensation would make the "
            "platform later. Do not use them; bypass this axis."
        )
    return None
