"""Plant presets shipped in ``config/plants/``: a model and typical limits for an axis group;
and :func:`plant_source`, what a command's ``--plant`` / ``--model`` / ``--axis`` designate.

A preset file holds ``description``, ``model`` (the compact spec of
:func:`motcomp.core.models.parse_model`), ``axes`` and ``limits`` (one table for all its axes, or
one table per axis), with the unit in every limit key (:mod:`motcomp.limits_config`).

``--plant`` also takes a config fragment (``[axes.<name>]`` tables, as ``motcomp identify``
writes ``<axis>.toml``) or a whole service config: the axis' ``model`` (or ``[defaults]``
``model``) and, if given, its limits, in the config's own keys.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from motcomp.core.axes import AXES, AXIS_INDEX
from motcomp.core.models import ProcessModel, parse_model
from motcomp.core.saturation import AxisLimits
from motcomp.errors import ConfigError
from motcomp.limits_config import LimitsConfig, axis_limits
from motcomp.resources import config_dir

__all__ = ["DEFAULT_AXIS", "PlantSource", "Preset", "input_lag_comment", "list_presets",
           "load_preset", "pairing_phase_of", "plant_source"]

DEFAULT_AXIS = "rails_y"
"""The axis a design is for when nothing names one (a model spec, or a preset that has it)."""


class _PresetFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)
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


def _message(path: Path, prefix: str, exc: ValidationError, root: type[BaseModel]) -> str:
    from motcomp.config import validation_message

    loc, msg = validation_message(exc, root)
    where = (prefix + loc).rstrip(".") or "<top>"
    return f"{path}: {where}: {msg}"


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
        raise ConfigError(_message(path, "", exc, _PresetFile)) from None
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


@dataclass(frozen=True)
class PlantSource:
    """A platform model and the config axis it is for.

    ``limits`` are the axis' limits (a one-axis :class:`AxisLimits`) when the source gives
    them; ``label`` names the source in reports (``rails preset``, ``rails_y.toml``...).
    """

    model: ProcessModel
    axis: str
    limits: AxisLimits | None
    label: str
    pairing_phase_ms: float | None = None
    """For a fragment identified through the stack: the pairing's phase its comment names
    (:func:`input_lag_comment`), which the design's input lag adds to the playback lag."""


def plant_source(plant: str | None = None, model: str | None = None,
                 axis: str | None = None) -> PlantSource:
    """What ``--plant NAME|FILE``, ``--model SPEC`` and ``--axis NAME`` designate.

    * a preset name or preset file: its model; the axis is ``axis`` (one of the preset's),
      else :data:`DEFAULT_AXIS` if the preset has it, else its first; its limits;
    * a ``.toml`` file with ``[axes.<name>]`` tables (the fragment ``motcomp identify`` writes,
      or a service config, includes merged): the ``model`` of ``[axes.<axis>]`` (or of
      ``[defaults]``) and its limits if it sets them; ``axis`` may be omitted when the file
      holds one axis;
    * a model spec: that model, for ``axis`` or :data:`DEFAULT_AXIS`, without limits.

    Raises
    ------
    ConfigError
        Naming the file and key: unknown preset or axis, several axes and no ``axis``, no model
        for the axis, a bad value.
    """
    if axis is not None and axis not in AXIS_INDEX:
        raise ConfigError(f"--axis: unknown axis {axis!r}; axes: {', '.join(AXES)}")
    if plant:
        path = Path(plant)
        if path.suffix == ".toml":
            from motcomp.config import read_toml

            raw = read_toml(path)
            if isinstance(raw.get("axes"), dict):
                return _fragment_source(path, raw, axis)
        preset = load_preset(plant)
        axis = axis or (DEFAULT_AXIS if DEFAULT_AXIS in preset.axes else preset.axes[0])
        return PlantSource(preset.model, axis, preset.axis_limits(axis),
                           f"{preset.name} preset")
    if model:
        return PlantSource(parse_model(model), axis or DEFAULT_AXIS, None, f"model {model}")
    raise ConfigError("give --plant NAME|FILE or --model SPEC")


def _fragment_source(path: Path, raw: dict[str, object], axis: str | None) -> PlantSource:
    from motcomp.config import AxisConfig

    tables = raw["axes"]
    assert isinstance(tables, dict)
    if axis is None:
        if len(tables) != 1:
            found = ", ".join(tables) or "none"
            raise ConfigError(f"{path}: axes: holds {found}; choose one with --axis NAME")
        axis = next(iter(tables))
        if axis not in AXIS_INDEX:
            raise ConfigError(f"{path}: axes.{axis}: unknown axis; axes: {', '.join(AXES)}")
    if axis not in tables:
        raise ConfigError(f"{path}: axes.{axis}: no such table; axes in the file: "
                          f"{', '.join(tables) or 'none'}")
    checked = []
    for where, table in ((f"axes.{axis}", tables[axis]), ("defaults", raw.get("defaults", {}))):
        try:
            checked.append(AxisConfig.model_validate(table))
        except ValidationError as exc:
            raise ConfigError(_message(path, f"{where}.", exc, AxisConfig)) from None
    cfg, base = checked
    spec = cfg.model or base.model
    if spec is None:
        raise ConfigError(f"{path}: axes.{axis}.model: missing (no model for {axis} in the file "
                          "nor in its [defaults])")
    given = {k: v for k, v in cfg.model_dump(exclude_none=True).items()
             if k in LimitsConfig.model_fields}
    limits = None
    if given:
        try:
            limits = axis_limits({axis: LimitsConfig(**given)})
        except ConfigError as exc:
            raise ConfigError(f"{path}: axes.{axis}: {exc}") from None
    return PlantSource(parse_model(spec), axis, limits, path.name,
                       pairing_phase_of(path.read_text()))


_INPUT_LAG_HINT = re.compile(r"^# Design it with --input-lag-ms = the config's "
                             r"input\.playback_lag_s \+ (-?[0-9.]+) ms", re.M)


def input_lag_comment(phase_ms: Any) -> list[str]:
    """The comment line naming the input lag to design a model identified through the stack
    with: the playback lag plus the pairing's phase, which its Td does not hold
    (docs/TUNING.md); none without a phase.  :func:`pairing_phase_of` reads it back."""
    if not isinstance(phase_ms, int | float) or not math.isfinite(phase_ms):
        return []
    return [f"# Design it with --input-lag-ms = the config's input.playback_lag_s + "
            f"{phase_ms:.2f} ms, the pairing's phase (outside this Td: docs/TUNING.md)."]


def pairing_phase_of(text: str) -> float | None:
    """The pairing's phase (ms) a fragment's :func:`input_lag_comment` names, or None."""
    m = _INPUT_LAG_HINT.search(text)
    return float(m.group(1)) if m else None
