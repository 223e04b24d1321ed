"""Per-axis limits as written in TOML files, with the unit in every key name.

Translational axes (``rails_*``, ``hex_x/y/z``) take ``pos_min_m``, ``pos_max_m``,
``vel_max_m_s``, ``acc_max_m_s2``; rotational axes (``hex_roll/pitch/yaw``) take
``pos_min_rad``, ``pos_max_rad``, ``vel_max_rad_s``, ``acc_max_rad_s2``.  Giving metres to a
rotation (or radians to a translation) is an error, which catches unit mix-ups at load time.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, field_validator

from motcomp.core.axes import ROTATIONAL
from motcomp.core.saturation import AxisLimits
from motcomp.errors import ConfigError

__all__ = ["LimitsConfig", "axis_limits"]

_LIN = ("pos_min_m", "pos_max_m", "vel_max_m_s", "acc_max_m_s2")
_ROT = ("pos_min_rad", "pos_max_rad", "vel_max_rad_s", "acc_max_rad_s2")


class LimitsConfig(BaseModel):
    """Limits of one axis; exactly the four keys of the axis' unit family must be given."""

    model_config = ConfigDict(extra="forbid", frozen=True)

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
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError(f"must be a finite number, got {v!r}")
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
        for key, val in ((want[2], v_max), (want[3], a_max)):
            if not val > 0:
                raise ConfigError(f"limits of {axis}: {key} must be > 0, got {val}")
        return p_min, p_max, v_max, a_max


def axis_limits(per_axis: dict[str, LimitsConfig]) -> AxisLimits:
    """:class:`AxisLimits` for the axes of ``per_axis`` (in its order)."""
    names = tuple(per_axis)
    rows = [per_axis[a].resolve(a) for a in names]
    arr = np.array(rows, dtype=float).reshape(len(names), 4)
    return AxisLimits(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], names)
