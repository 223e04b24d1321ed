"""PID gains: one canonical (parallel) form, and conversions to and from the standard form.

Canonical form used everywhere in code (parallel, filtered derivative, setpoint weights)::

    u = kp (b r - y) + ki/s (r - y) + kd s / (1 + tf s) (c r - y)

* ``kp`` (dimensionless), ``ki`` (1/s), ``kd`` (s), ``tf`` (s): derivative filter time constant;
* ``b``, ``c``: setpoint weights of the proportional and derivative terms (1 = plain PID on the
  error ``e = r - y``, what the paper uses).

Standard (ISA, "ideal") form: ``Kc (1 + 1/(Ti s) + Td s / (1 + (Td/N) s))``.  Conversion::

    kp = Kc,   ki = Kc / Ti,   kd = Kc * Td,   tf = Td / N
    Kc = kp,   Ti = kp / ki,   Td = kd / kp,   N = Td / tf

Examples
--------
>>> g = PIDGains.from_standard(Kc=2.0, Ti=0.5, Td=0.1, N=10)
>>> (g.kp, g.ki, g.kd, round(g.tf, 12))
(2.0, 4.0, 0.2, 0.01)
>>> g.to_standard()["Ti"]
0.5
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

from motcomp.errors import ConfigError

__all__ = ["CONFIG_KEYS", "PIDGains"]

CONFIG_KEYS = {"kp": "kp", "ki": "ki_per_s", "kd": "kd_s", "tf": "tf_s", "b": "b", "c": "c"}
"""The one spelling of the gains outside Python (config, ``design --json``, reports), with
units in the names, per attribute of :class:`PIDGains`."""


@dataclass(frozen=True)
class PIDGains:
    """Parallel PID gains (see module docstring for the form and units).

    Raises
    ------
    ConfigError
        If a gain is non-finite, ``kp``, ``ki``, ``kd`` or ``tf`` is negative, or ``kd > 0`` with
        ``tf == 0`` while ``allow_unfiltered`` is False (an unfiltered derivative amplifies
        noise without bound; the discrete form is then ``kd/h`` times a difference).
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0
    tf: float = 0.0
    b: float = 1.0
    c: float = 1.0

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd", "tf", "b", "c"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ConfigError(f"PID gain {name} must be a finite number, got {value!r}")
        for name in ("kp", "ki", "kd", "tf"):
            if getattr(self, name) < 0:
                raise ConfigError(f"PID gain {name} must be >= 0, got {getattr(self, name)!r}")

    # --- conversions --------------------------------------------------------------------------
    @classmethod
    def from_standard(cls, Kc: float, Ti: float = math.inf, Td: float = 0.0,
                      N: float = math.inf, b: float = 1.0, c: float = 1.0) -> PIDGains:
        """From the standard form ``Kc (1 + 1/(Ti s) + Td s/(1 + Td/N s))``.

        ``Ti = inf`` means no integral action, ``N = inf`` no derivative filter.
        """
        if not Ti > 0:
            raise ConfigError(f"standard-form Ti must be > 0 (inf for none), got {Ti!r}")
        if not N > 0:
            raise ConfigError(f"standard-form N must be > 0 (inf for no filter), got {N!r}")
        ki = 0.0 if math.isinf(Ti) else Kc / Ti
        tf = 0.0 if math.isinf(N) else Td / N
        return cls(kp=Kc, ki=ki, kd=Kc * Td, tf=tf, b=b, c=c)

    def to_standard(self) -> dict[str, float]:
        """``{"Kc", "Ti", "Td", "N"}``; ``Ti = inf`` without integral, ``N = inf`` unfiltered.

        Raises
        ------
        ConfigError
            If ``kp == 0`` (a pure I or ID controller has no standard form).
        """
        if self.kp == 0:
            raise ConfigError("kp = 0 has no standard (Kc, Ti, Td) form")
        Ti = math.inf if self.ki == 0 else self.kp / self.ki
        Td = self.kd / self.kp
        N = math.inf if self.tf == 0 else (Td / self.tf if Td > 0 else math.inf)
        return {"Kc": self.kp, "Ti": Ti, "Td": Td, "N": N}

    def with_filter(self, tf: float) -> PIDGains:
        """Same gains with derivative filter time ``tf`` (s)."""
        return replace(self, tf=tf)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_config(self) -> dict[str, float]:
        """The gains under the service config's keys (:data:`CONFIG_KEYS`): what ``[axes.<name>.
        gains]`` takes and what ``motcomp design --json`` prints."""
        return {key: float(getattr(self, name)) for name, key in CONFIG_KEYS.items()}

    @classmethod
    def from_config(cls, values: dict[str, Any]) -> PIDGains:
        """From a map with the config's keys (``kp`` required; the rest default).

        Raises
        ------
        ConfigError
            If a key is unknown or a gain is invalid.
        """
        names = {key: name for name, key in CONFIG_KEYS.items()}
        unknown = sorted(set(values) - set(names))
        if unknown or "kp" not in values:
            raise ConfigError(f"PID gains need kp and take {', '.join(names)}; got "
                              f"{', '.join(map(str, values)) or 'nothing'}")
        return cls(**{names[k]: v for k, v in values.items()})

    def tracking_time_s(self) -> float:
        """Back-calculation tracking time ``Tt`` (Astrom & Hagglund): ``sqrt(Ti Td)`` for a PID,
        ``Ti`` for a PI; ``inf`` without integral action."""
        if self.ki == 0:
            return math.inf
        Ti = self.kp / self.ki if self.kp > 0 else 1.0 / self.ki
        Td = self.kd / self.kp if self.kp > 0 else 0.0
        return math.sqrt(Ti * Td) if Td > 0 else Ti
