"""Per-axis limits as written in TOML files, with the unit in every key name.

Translational axes (``rails_*``, ``hex_x/y/z``) take ``pos_min_m``, ``pos_max_m``,
``vel_max_m_s``, ``acc_max_m_s2``; rotational axes (``hex_roll/pitch/yaw``) take
``pos_min_rad``, ``pos_max_rad``, ``vel_max_rad_s``, ``acc_max_rad_s2``.  Giving metres to a
rotation (or radians to a translation) is an error, which catches unit mix-ups at load time.

Every number is checked for plausibility, whatever table it is in (an axis' limits, ``[defaults]``,
the hardware ``[envelope]``, a plant preset): finite, and within what a motion platform can be
(:data:`PLAUSIBLE`): ``|pos| <= 10 m`` or ``3.2 rad`` (a turn of slightly more than pi either
way), ``0 < vel <= 10 m/s`` or ``10 rad/s``, ``0 < acc <= 100 m/s^2`` (about 10 g) or
``200 rad/s^2``.  A value beyond is a typo or an attack, never a platform.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator

from motcomp.core.axes import ROTATIONAL
from motcomp.core.saturation import AxisLimits
from motcomp.errors import ConfigError

__all__ = ["LIMIT_KEYS", "PLAUSIBLE", "LimitsConfig", "axis_limits", "limit_keys"]

_LIN = ("pos_min_m", "pos_max_m", "vel_max_m_s", "acc_max_m_s2")
_ROT = ("pos_min_rad", "pos_max_rad", "vel_max_rad_s", "acc_max_rad_s2")
LIMIT_KEYS = (*_LIN, *_ROT)
"""Every limit key, translations first."""

PLAUSIBLE: dict[str, tuple[float, float, str]] = {
    "pos_min_m": (-10.0, 10.0, "m"), "pos_max_m": (-10.0, 10.0, "m"),
    "vel_max_m_s": (0.0, 10.0, "m/s"), "acc_max_m_s2": (0.0, 100.0, "m/s^2"),
    "pos_min_rad": (-3.2, 3.2, "rad"), "pos_max_rad": (-3.2, 3.2, "rad"),
    "vel_max_rad_s": (0.0, 10.0, "rad/s"), "acc_max_rad_s2": (0.0, 200.0, "rad/s^2"),
}
"""Per limit key, ``(lowest, highest, unit)`` a motion platform can have (a velocity or an
acceleration above its lowest, 0)."""


def limit_keys(axis: str) -> tuple[str, str, str, str]:
    """The four limit keys of ``axis`` (``pos_min``, ``pos_max``, ``vel_max``, ``acc_max``)."""
    return _ROT if axis in ROTATIONAL else _LIN


class LimitsConfig(BaseModel):
    """Limits of one axis; exactly the four keys of the axis' unit family must be given."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    pos_min_m: float | None = None
    pos_max_m: float | None = None
    vel_max_m_s: float | None = None
    acc_max_m_s2: float | None = None
    pos_min_rad: float | None = None
    pos_max_rad: float | None = None
    vel_max_rad_s: float | None = None
    acc_max_rad_s2: float | None = None

    @field_validator(*_LIN, *_ROT)
    @classmethod
    def _plausible(cls, v: float | None, info: ValidationInfo) -> float | None:
        if v is None:
            return v
        if not math.isfinite(v):
            raise ValueError(f"must be a finite number, got {v!r}")
        name = str(info.field_name)
        lo, hi, unit = PLAUSIBLE[name]
        if name.startswith(("vel", "acc")):  # a speed or an acceleration: > 0
            if not lo < v <= hi:
                raise ValueError(f"lies outside ({lo:g}, {hi:g}] {unit}, the plausible range "
                                 "of a motion platform")
        elif not lo <= v <= hi:
            raise ValueError(f"lies outside [{lo:g}, {hi:g}] {unit}, the plausible range of a "
                             "motion platform")
        return v

    def resolve(self, axis: str) -> tuple[float, float, float, float]:
        """``(p_min, p_max, v_max, a_max)`` for ``axis``, checking the unit family and order."""
        want, other = (_ROT, _LIN) if axis in ROTATIONAL else (_LIN, _ROT)
        given_other = [k for k in other if getattr(self, k) is not None]
        if given_other:
            unit = "rad" if axis in ROTATIONAL else "m"
            raise ConfigError(f"limits of {axis}: {', '.join(given_other)} use the wrong unit; "
                              f"{axis} is in {unit}: use {', '.join(want)}")
        missing = [k for k in want if getattr(self, k) is None]
        if missing:
            raise ConfigError(f"limits of {axis}: missing {', '.join(missing)}")
        p_min, p_max, v_max, a_max = (float(getattr(self, k)) for k in want)
        if not p_min < p_max:
            raise ConfigError(f"limits of {axis}: {want[0]}={p_min} must be < {want[1]}={p_max}")
        if not p_max > 0 or not p_min < 0:
            raise ConfigError(f"limits of {axis}: neutral (0) must lie strictly inside "
                              f"[{p_min}, {p_max}]")
        return p_min, p_max, v_max, a_max  # a speed and an acceleration are > 0 (_plausible)


def axis_limits(per_axis: dict[str, LimitsConfig]) -> AxisLimits:
    """:class:`AxisLimits` for the axes of ``per_axis`` (in its order)."""
    names = tuple(per_axis)
    rows = [per_axis[a].resolve(a) for a in names]
    arr = np.array(rows, dtype=float).reshape(len(names), 4)
    return AxisLimits(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], names)
