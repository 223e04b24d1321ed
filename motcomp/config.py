"""The service configuration: TOML, validated by pydantic, frozen.

Every key carries its unit in its name; unknown keys are rejected; errors name the file, the key
path and the offending value.  ``config/motcomp.toml`` documents every key.  Keys are either
*live* (a reload applies them between two ticks) or *restart* (transport endpoints, the loop
rate...): :data:`RESTART_KEYS` lists the latter, and a reload that changes one is refused.

Per axis (``[axes.<name>]``, names from :data:`motcomp.core.axes.AXES`): the internal model
(``model``, a compact spec; non-P1D models are reduced with ``to_p1d()``), the tuning (``rule``,
or explicit ``gains``), ``bypass``, and the limits (``pos_min_m``... or ``pos_min_rad``...).
A ``[defaults]`` table supplies any of these for every axis.  Axes not listed are not driven:
they stay at neutral and are sent as such.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from motcomp.core.axes import AXES
from motcomp.core.compensator import Compensator
from motcomp.core.models import P1D, ProcessModel, parse_model
from motcomp.core.pid import PIDGains
from motcomp.core.saturation import AxisLimits
from motcomp.core.shaper import ShaperParams
from motcomp.core.tick import TickParams, TickState
from motcomp.core.tuning import RULES, tune
from motcomp.errors import ConfigError
from motcomp.limits_config import LimitsConfig

__all__ = [
    "RESTART_KEYS",
    "AxisConfig",
    "ProfileConfig",
    "ResolvedAxes",
    "ServiceConfig",
    "config_hash",
    "load_config",
    "merge",
    "parse_config",
    "read_toml",
    "resolve_axes",
]

_STRICT = ConfigDict(extra="forbid", frozen=True)


def _finite(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError(f"must be a finite number, got {v!r}")
    return v


class GainsConfig(BaseModel):
    """Explicit PID gains, parallel form (see :mod:`motcomp.core.pid`)."""

    model_config = _STRICT
    kp: float = Field(ge=0)
    ki_per_s: float = Field(0.0, ge=0)
    kd_s: float = Field(0.0, ge=0)
    tf_s: float = Field(0.0, ge=0)
    b: float = 1.0
    c: float = 1.0

    @field_validator("*")
    @classmethod
    def _finite_values(cls, v: float) -> float:
        return _finite(v)

    def to_gains(self) -> PIDGains:
        return PIDGains.from_config(self.model_dump())


class TuningConfig(BaseModel):
    """What a scenario profile may set, for every axis or for one: the tuning and bypass."""

    model_config = _STRICT
    rule: str | None = None
    filter_n: float | None = Field(None, gt=0)
    gains: GainsConfig | None = None
    bypass: bool | None = None

    @field_validator("rule")
    @classmethod
    def _rule(cls, v: str | None) -> str | None:
        if v is not None and v not in RULES:
            raise ValueError(f"unknown rule {v!r}; rules: {', '.join(RULES)}")
        return v

    @model_validator(mode="after")
    def _one_tuning(self) -> TuningConfig:
        if self.rule is not None and self.gains is not None:
            raise ValueError("give either rule or gains, not both")
        return self


class AxisConfig(TuningConfig, LimitsConfig):
    """One axis: model, tuning, bypass and limits (tuning keys from :class:`TuningConfig`, limit
    keys from :class:`LimitsConfig`)."""

    model_config = _STRICT
    model: str | None = None

    @field_validator("model")
    @classmethod
    def _model(cls, v: str | None) -> str | None:
        if v is not None:
            parse_model(v)  # raises ConfigError (a ValueError) with the reason
        return v


class ProfileConfig(TuningConfig):
    """A named scenario (e.g. normal driving, fast manoeuvres): tuning for all axes, and per
    axis under ``axes``."""

    description: str = ""
    axes: dict[str, TuningConfig] = {}


SLICE_MIN_US = 100.0
"""The scheduler slices the kernel takes (``loop.slice_us``; 0 = its default)."""
SLICE_MAX_US = 100_000.0


class LoopConfig(BaseModel):
    """The fixed-rate loop and the behaviour on missing input and at stop."""

    model_config = _STRICT
    rate_hz: float = Field(1000.0, ge=50.0, le=2000.0)
    sync_to_input: bool = False
    poll_us: float = Field(50.0, ge=10.0, le=1000.0)
    spin_us: float = Field(200.0, ge=0.0, le=2000.0)
    sleep_max_us: float = Field(100.0, ge=0.0, le=100_000.0)
    stale_after_s: float = Field(0.05, gt=0.0, le=10.0)
    hold_s: float = Field(0.5, ge=0.0, le=60.0)
    ramp_speed_fraction: float = Field(0.25, gt=0.0, le=1.0)
    rejoin_s: float = Field(0.5, ge=0.0, le=10.0)
    startup_s: float = Field(1.0, ge=0.0, le=30.0)
    park_timeout_s: float = Field(15.0, gt=0.0, le=120.0)
    bypass_fade_s: float = Field(0.5, ge=0.0, le=10.0)
    realtime_priority: int = Field(0, ge=0, le=99)
    slice_us: float = Field(100.0, ge=0.0, le=SLICE_MAX_US)
    cpu: int = Field(-1, ge=-1)

    @field_validator("slice_us")
    @classmethod
    def _slice_range(cls, v: float) -> float:
        if 0.0 < v < SLICE_MIN_US:
            raise ValueError(f"the kernel takes a slice of 0 (its default) or "
                             f"{SLICE_MIN_US:g}-{SLICE_MAX_US:g} us, got {v:g}")
        return v


class InputConfig(BaseModel):
    """Where setpoints come from and how strictly they are checked."""

    model_config = _STRICT
    key: str = "sim/motion/setpoint"
    reject_beyond_fraction: float = Field(0.25, ge=0.0, le=10.0)
    reconstruction: Literal["linear", "hold"] = "linear"
    max_extrapolation_s: float = Field(0.02, ge=0.0, le=1.0)
    max_frame_bytes: int = Field(4096, ge=64, le=1_048_576)


class CanConfig(BaseModel):
    """CAN output (frames defined by a DBC file)."""

    model_config = _STRICT
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate_bps: int = Field(1_000_000, gt=0)
    dbc: str = "motcomp.dbc"
    send_every: int = Field(4, ge=1, le=100)


class OutputConfig(BaseModel):
    """Where corrected setpoints go."""

    model_config = _STRICT
    transport: Literal["zenoh", "can", "both"] = "zenoh"
    key: str = "platform/setpoint"
    can: CanConfig = CanConfig()


class StatusConfig(BaseModel):
    model_config = _STRICT
    key: str = "motcomp/status"
    period_s: float = Field(1.0, gt=0.0, le=60.0)
    window_s: float = Field(10.0, gt=0.0, le=600.0)
    saturation_tolerance: float = Field(1e-4, ge=0.0, le=1.0)


class AdminConfig(BaseModel):
    """Admin endpoints (bypass, reload): off unless enabled."""

    model_config = _STRICT
    enabled: bool = False
    key: str = "motcomp/admin"


class ZenohConfig(BaseModel):
    """Session settings; command-line -c/-e/-l flags override them."""

    model_config = _STRICT
    config_file: str = ""
    connect: list[str] = []
    listen: list[str] = []
    multicast_scouting: bool = False


class FeedbackConfig(BaseModel):
    model_config = _STRICT
    key: str = "platform/feedback"


class ServiceConfig(BaseModel):
    """The whole file."""

    model_config = _STRICT
    loop: LoopConfig = LoopConfig()
    input: InputConfig = InputConfig()
    output: OutputConfig = OutputConfig()
    feedback: FeedbackConfig = FeedbackConfig()
    status: StatusConfig = StatusConfig()
    admin: AdminConfig = AdminConfig()
    zenoh: ZenohConfig = ZenohConfig()
    defaults: AxisConfig = AxisConfig()
    axes: dict[str, AxisConfig] = {}
    profile: str | None = None
    profiles: dict[str, ProfileConfig] = {}

    @model_validator(mode="after")
    def _axes(self) -> ServiceConfig:
        for name in self.axes:
            if name not in AXES:
                raise ValueError(f"unknown axis {name!r}; axes: {', '.join(AXES)}")
        if not self.axes:
            raise ValueError("no axis configured: add at least one [axes.<name>] table")
        for pname, prof in self.profiles.items():
            for name in prof.axes:
                if name not in self.axes:
                    raise ValueError(f"profiles.{pname}.axes.{name}: not a configured axis; "
                                     f"axes: {', '.join(self.axes)}")
        if self.profile is not None and self.profile not in self.profiles:
            raise ValueError(f"profile {self.profile!r} is not defined; profiles: "
                             f"{', '.join(self.profiles) or 'none'}")
        return self


RESTART_KEYS: tuple[str, ...] = (
    "loop.rate_hz", "loop.sync_to_input", "loop.poll_us", "loop.spin_us", "loop.sleep_max_us",
    "loop.realtime_priority", "loop.slice_us", "loop.cpu", "input", "output", "feedback",
    "status.key", "status.period_s", "status.window_s", "admin", "zenoh",
)
"""Top-level keys (or sub-keys) that a live reload may not change: they need a restart."""


@dataclass(frozen=True)
class ResolvedAxes:
    """Per-axis objects for the compensator, in :data:`AXES` order (all eight axes)."""

    names: tuple[str, ...]
    driven: tuple[bool, ...]
    models: tuple[P1D, ...]
    plants: tuple[ProcessModel, ...]
    gains: tuple[PIDGains, ...]
    limits: AxisLimits
    bypass: tuple[bool, ...]
    warnings: tuple[str, ...]


_UNDRIVEN_LIMITS = (-1.0, 1.0, 1.0, 1.0)  # an undriven axis is held at neutral


def _merged(defaults: AxisConfig, axis: AxisConfig) -> dict[str, Any]:
    out = defaults.model_dump(exclude_none=True)
    out.update(axis.model_dump(exclude_none=True))
    return out


_TUNING_KEYS = ("rule", "filter_n", "gains", "bypass")


def _tuning_layers(cfg: ServiceConfig, name: str, profile: str | None) -> list[dict[str, Any]]:
    """The tuning keys of an axis from the lowest to the highest precedence: ``[defaults]``,
    ``[axes.<name>]``, the active profile, the profile's ``axes.<name>``."""
    layers = [cfg.defaults.model_dump(exclude_none=True),
              cfg.axes[name].model_dump(exclude_none=True)]
    if profile is not None:
        prof = cfg.profiles[profile]
        layers.append(prof.model_dump(include=set(_TUNING_KEYS), exclude_none=True))
        if name in prof.axes:
            layers.append(prof.axes[name].model_dump(exclude_none=True))
    return [{k: v for k, v in layer.items() if k in _TUNING_KEYS} for layer in layers]


def resolve_axes(cfg: ServiceConfig, profile: str | None = "") -> ResolvedAxes:
    """Models, gains, limits and bypass of all eight axes.

    An axis not listed under ``[axes]`` is *undriven*: bypassed, unit model, and held at
    neutral by the service.  ``profile`` selects a scenario profile (default: the config's
    active ``profile``; None: none); its tuning keys override those of ``[defaults]`` and of the
    axis, the highest layer that sets ``rule`` or ``gains`` deciding the tuning.

    Raises
    ------
    ConfigError
        Naming the axis and the key.
    """
    if profile == "":
        profile = cfg.profile
    if profile is not None and profile not in cfg.profiles:
        raise ConfigError(f"profile {profile!r} is not defined; profiles: "
                          f"{', '.join(cfg.profiles) or 'none'}")
    models: list[P1D] = []
    plants: list[ProcessModel] = []
    gains: list[PIDGains] = []
    bypass: list[bool] = []
    driven: list[bool] = []
    rows: list[tuple[float, float, float, float]] = []
    warnings: list[str] = []
    for name in AXES:
        if name not in cfg.axes:
            models.append(P1D(K=1.0, Td=0.0, Tp1=0.01))
            plants.append(models[-1])
            gains.append(PIDGains(kp=1.0))
            bypass.append(True)
            driven.append(False)
            rows.append(_UNDRIVEN_LIMITS)
            continue
        merged = _merged(cfg.defaults, cfg.axes[name])
        where = f"axes.{name}"
        spec = merged.get("model")
        if spec is None:
            raise ConfigError(f"{where}.model: missing (no model given for this axis nor in "
                              "[defaults])")
        plant = parse_model(spec)
        try:
            model = plant.to_p1d()
        except ConfigError as exc:
            raise ConfigError(f"{where}.model: {exc}") from None
        layers = _tuning_layers(cfg, name, profile)
        for layer in layers:
            if "gains" in layer and "rule" in layer:
                raise ConfigError(f"{where}: give either rule or gains, not both")
        tuning_layer: dict[str, Any] = next(
            (ly for ly in reversed(layers) if "gains" in ly or "rule" in ly), {})
        bypass_on = next((ly["bypass"] for ly in reversed(layers) if "bypass" in ly), False)
        filter_n = next((ly["filter_n"] for ly in reversed(layers) if "filter_n" in ly), 10.0)
        if "gains" in tuning_layer:
            g = GainsConfig(**tuning_layer["gains"]).to_gains()
        else:
            tuning = tune(tuning_layer.get("rule", "zn"), model, filter_n=filter_n)
            g = tuning.gains
            if not bypass_on:  # a bypassed axis is not compensated
                warnings += [f"{name}: {w}" for w in tuning.warnings]
        limits_cfg = LimitsConfig(**{k: v for k, v in merged.items()
                                     if k in LimitsConfig.model_fields})
        try:
            rows.append(limits_cfg.resolve(name))
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        models.append(model)
        plants.append(plant)
        gains.append(g)
        bypass.append(bool(bypass_on))
        driven.append(True)
    arr = np.array(rows, dtype=float)
    limits = AxisLimits(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], AXES)
    return ResolvedAxes(AXES, tuple(driven), tuple(models), tuple(plants), tuple(gains), limits,
                        tuple(bypass), tuple(warnings))


def _format_error(source: str, exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    value = err.get("input")
    shown = "" if isinstance(value, dict) else f" (got {value!r})"
    more = f" [and {exc.error_count() - 1} more]" if exc.error_count() > 1 else ""
    return f"{source}: {loc or '<top>'}: {msg}{shown}{more}"


def parse_config(data: dict[str, Any], source: str = "<config>") -> ServiceConfig:
    """Validate a parsed TOML document.

    Raises
    ------
    ConfigError
        ``"<source>: <key.path>: <reason> (got <value>)"``.
    """
    try:
        cfg = ServiceConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_error(source, exc)) from None
    try:
        resolve_axes(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return cfg


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Deep merge: tables merge key by key, anything else in ``over`` replaces ``base``."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def read_toml(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A TOML file with its ``include`` files merged underneath it.

    ``include = ["a.toml", ...]`` (paths relative to the including file) are read first, in
    order, each merged over the previous; the including file is merged last, so its keys win.
    This is how an identification result (a fragment with ``[axes.<name>] model = ...``) is
    combined with a site config.

    Raises
    ------
    ConfigError
        Naming the file: unreadable, not TOML, an include cycle or a bad ``include`` value.
    """
    p = Path(path).resolve()
    if p in _seen:
        chain = " -> ".join(str(s) for s in (*_seen, p))
        raise ConfigError(f"{p}: include cycle ({chain})")
    try:
        text = p.read_text()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    inc = data.pop("include", [])
    if isinstance(inc, str):
        inc = [inc]
    if not isinstance(inc, list) or not all(isinstance(i, str) for i in inc):
        raise ConfigError(f"{p}: include: must be a file name or a list of them, got {inc!r}")
    merged: dict[str, Any] = {}
    for name in inc:
        merged = merge(merged, read_toml(p.parent / name, (*_seen, p)))
    return merge(merged, data)


def load_config(path: str | Path) -> ServiceConfig:
    """Read (with includes) and validate a TOML config file (see module docstring)."""
    return parse_config(read_toml(path), str(path))


def config_hash(cfg: ServiceConfig) -> str:
    """Short stable hash of the effective config (shown in the status and the logs)."""
    text = json.dumps(cfg.model_dump(mode="json"), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def tick_params(cfg: ServiceConfig, axes: ResolvedAxes) -> TickParams:
    """The tick's parameters of a config (:mod:`motcomp.core.tick`): input accepted, and the
    reference kept, within each axis' limits widened by ``input.reject_beyond_fraction`` of its
    range."""
    f = cfg.input.reject_beyond_fraction
    lim = axes.limits
    lo = tuple(float(a - f * (b - a)) for a, b in zip(lim.p_min, lim.p_max, strict=True))
    hi = tuple(float(b + f * (b - a)) for a, b in zip(lim.p_min, lim.p_max, strict=True))
    loop = cfg.loop
    shaper = ShaperParams(
        driven=axes.driven, ramp_speed=tuple(loop.ramp_speed_fraction * float(v)
                                             for v in lim.v_max),
        reach_lo=lo, reach_hi=hi, stale_after_s=loop.stale_after_s, hold_s=loop.hold_s,
        rejoin_s=loop.rejoin_s, startup_s=loop.startup_s,
        linear=cfg.input.reconstruction == "linear",
        max_extrapolation_s=cfg.input.max_extrapolation_s)
    return TickParams(loop.rate_hz, shaper, cfg.status.saturation_tolerance,
                      cfg.input.max_frame_bytes)


def new_tick(cfg: ServiceConfig, axes: ResolvedAxes | None = None
             ) -> tuple[TickParams, TickState]:
    """Parameters and a fresh state (compensator at rest at neutral, the config's bypass) of a
    config's tick."""
    axes = axes if axes is not None else resolve_axes(cfg)
    comp = Compensator(axes.models, axes.gains, axes.limits, cfg.loop.rate_hz,
                       fade_s=cfg.loop.bypass_fade_s, history_s=0.5)
    comp.set_bypass(axes.bypass)
    return tick_params(cfg, axes), TickState(comp, axes.driven)
