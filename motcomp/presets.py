"""Plant presets shipped in ``config/plants/``: a model and typical limits for an axis group.

A preset file holds ``description``, ``model`` (the compact spec of
:func:`motcomp.core.models.parse_model`), ``axes`` and ``limits`` (one table for all its axes, or
one table per axis), with the unit in every limit key (:mod:`motcomp.limits_config`).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel, ConfigDict, ValidationError

from motcomp.core.axes import AXIS_INDEX
from motcomp.core.models import ProcessModel, parse_model
from motcomp.core.saturation import AxisLimits
from motcomp.errors import ConfigError
from motcomp.limits_config import LimitsConfig, axis_limits
from motcomp.resources import config_dir

__all__ = ["Preset", "list_presets", "load_preset"]


class _PresetFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    description: str
    model: str
    axes: list[str]
    limits: dict[str, LimitsConfig] | LimitsConfig


@dataclass(frozen=True)
class Preset:
    """A loaded plant preset."""

    name: str
    description: str
    model: ProcessModel
    axes: tuple[str, ...]
    limits: AxisLimits

    def axis_limits(self, axis: str) -> AxisLimits:
        """Limits of one of the preset's axes, as a one-axis :class:`AxisLimits`."""
        if axis not in self.axes:
            raise ConfigError(f"preset {self.name} has no axis {axis}; axes: {self.axes}")
        i = self.axes.index(axis)
        lim = self.limits
        return AxisLimits(lim.p_min[i:i + 1], lim.p_max[i:i + 1], lim.v_max[i:i + 1],
                          lim.a_max[i:i + 1], (axis,))


def list_presets() -> list[str]:
    """Names of the shipped presets."""
    return sorted(p.stem for p in (config_dir() / "plants").glob("*.toml"))


def load_preset(name_or_path: str) -> Preset:
    """Load a preset by name (``rails``, ``hexapod``) or from a TOML file path.

    Raises
    ------
    ConfigError
        Naming the file, key and value.
    """
    path = Path(name_or_path)
    if path.suffix != ".toml":
        path = config_dir() / "plants" / f"{name_or_path}.toml"
        if not path.is_file():
            raise ConfigError(f"unknown plant preset {name_or_path!r}; presets: "
                              f"{', '.join(list_presets())}")
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    try:
        doc = _PresetFile.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise ConfigError(f"{path}: {where}: {err['msg']} (got {err.get('input')!r})") from None
    unknown = [a for a in doc.axes if a not in AXIS_INDEX]
    if unknown:
        raise ConfigError(f"{path}: axes: unknown axis {unknown[0]!r}")
    try:
        model = parse_model(doc.model)
        if isinstance(doc.limits, LimitsConfig):
            per_axis = {a: doc.limits for a in doc.axes}
        else:
            missing = [a for a in doc.axes if a not in doc.limits]
            if missing:
                raise ConfigError(f"limits: no table for {missing[0]}")
            per_axis = {a: doc.limits[a] for a in doc.axes}
        limits = axis_limits(per_axis)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return Preset(name=path.stem, description=doc.description, model=model,
                  axes=tuple(doc.axes), limits=limits)
