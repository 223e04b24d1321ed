"""The service configuration: TOML, validated by pydantic, frozen.

Every key carries its unit in its name; unknown keys are rejected; errors name the file, the key
path and the offending value.  ``config/motcomp.toml`` documents every key.  Keys are either
*live* (a reload applies them between two ticks) or *restart* (transport endpoints, the loop
rate...): :data:`RESTART_KEYS` lists the latter, and a reload that changes one is refused.

Per axis (``[axes.<name>]``, names from :data:`motcomp.core.axes.AXES`): the internal model
(``model``, a compact spec; non-P1D models are reduced with ``to_p1d()``), the tuning (``rule``,
or explicit ``gains``), ``bypass``, the predictive prefilter (``prediction``, as ``motcomp
design`` writes it, and ``predict`` to switch it), and the limits (``pos_min_m``... or
``pos_min_rad``...).
A ``[defaults]`` table supplies any of these for every axis.  Axes not listed are not driven:
they stay at neutral and are sent as such.

The hardware envelope (``[envelope.<name>]``, the same four limit keys) is what the platform
itself allows; it is a restart key, and every axis' limits must lie inside it (:func:`parse_config`
refuses a config, a reload or a profile otherwise, naming the key, its value and the bound).  The
tick clamps its every output to it as a second, independent layer
(:mod:`motcomp.core.envelope`).  The service starts only with an envelope for every driven axis
read from files that only root or the service user can write (:func:`check_envelope`);
offline tools (replay, design) take :data:`~motcomp.limits_config.PLAUSIBLE` for an axis
without one.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import math
import os
import re
import stat
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from motcomp.core.axes import AXES
from motcomp.core.bandlimit import BAND_HZ_DEFAULT, band_limit_params
from motcomp.core.blend import BLEND_ACC_SHARE
from motcomp.core.compensator import Compensator
from motcomp.core.envelope import EnvelopeParams
from motcomp.core.loop import stability
from motcomp.core.minjerk import move_duration
from motcomp.core.models import P1D, ProcessModel, parse_model
from motcomp.core.pid import PIDGains
from motcomp.core.predictor import MonitorParams, PredictorParams
from motcomp.core.saturation import AxisLimits
from motcomp.core.shaper import ShaperParams
from motcomp.core.tick import TickParams, TickState
from motcomp.core.tuning import RULES, tune
from motcomp.errors import ConfigError
from motcomp.limits_config import PLAUSIBLE, LimitsConfig, limit_keys

__all__ = [
    "RESTART_KEYS",
    "AxisConfig",
    "CommentedInclude",
    "ConfigSources",
    "Override",
    "ProfileConfig",
    "ResolvedAxes",
    "ServiceConfig",
    "check_envelope",
    "config_hash",
    "config_sources",
    "envelope_params",
    "load_config",
    "merge",
    "parse_config",
    "read_toml",
    "resolve_axes",
    "source_report",
]

_STRICT = ConfigDict(extra="forbid", frozen=True, strict=True)
"""Every table: no unknown key, and each value of its key's type as TOML writes it (a boolean is
not a number, a string not a boolean: no coercion)."""


def _array(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v


_Band = Annotated[tuple[float, float], BeforeValidator(_array)]
"""A TOML array of two numbers (strict validation takes a tuple only)."""


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


class PredictionTable(BaseModel):
    """An axis' predictive prefilter (:class:`motcomp.core.predictor.PredictorParams`), as
    ``motcomp design`` writes it."""

    model_config = _STRICT
    pole_hz: float
    rate_hz: float
    band_hz: _Band = (0.1, 2.0)
    coeffs: list[float]

    @model_validator(mode="after")
    def _valid(self) -> PredictionTable:
        self.to_params()  # raises ConfigError (a ValueError) with the reason
        return self

    def to_params(self) -> PredictorParams:
        return PredictorParams(pole_hz=self.pole_hz, coeffs=tuple(self.coeffs),
                               rate_hz=self.rate_hz, band_hz=self.band_hz)


class PredictionConfig(BaseModel):
    """The band monitor and the fallback of every predicted axis
    (:class:`motcomp.core.predictor.MonitorParams`)."""

    model_config = _STRICT
    fallback_ratio: float = Field(0.3, gt=0.0, le=10.0)
    resume_ratio: float = Field(0.15, gt=0.0, le=10.0)
    resume_after_s: float = Field(0.5, ge=0.0, le=60.0)
    fade_out_s: float = Field(0.02, ge=0.0, le=10.0)
    fade_in_s: float = Field(0.5, ge=0.0, le=10.0)
    floor: float = Field(1e-4, gt=0.0, le=1.0)

    @model_validator(mode="after")
    def _valid(self) -> PredictionConfig:
        self.to_params()
        return self

    def to_params(self) -> MonitorParams:
        return MonitorParams(**self.model_dump())


class TuningConfig(BaseModel):
    """What a scenario profile may set, for every axis or for one: the tuning, bypass and
    whether a configured prediction is used."""

    model_config = _STRICT
    rule: str | None = None
    filter_n: float | None = Field(None, gt=0)
    gains: GainsConfig | None = None
    bypass: bool | None = None
    predict: bool | None = None

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


class ForcedConfig(BaseModel):
    """``forced = { model = "...", why = "..." }``: the mark ``motcomp identify --force`` puts
    on a fragment it wrote against its own refusal; the service and ``motcomp config check``
    warn while the axis' model is that ``model``."""

    model_config = _STRICT
    model: str
    why: str


class AxisConfig(TuningConfig, LimitsConfig):
    """One axis: model, tuning, bypass and limits (tuning keys from :class:`TuningConfig`, limit
    keys from :class:`LimitsConfig`)."""

    model_config = _STRICT
    model: str | None = None
    prediction: PredictionTable | None = None
    forced: ForcedConfig | None = None

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
    spin_us: float = Field(50.0, ge=0.0, le=2000.0)
    sleep_max_us: float = Field(0.0, ge=0.0, le=100_000.0)
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
    cpu_latency_us: int = Field(0, ge=-1, le=1_000_000)

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
    reconstruction: Literal["smooth", "linear", "hold"] = "smooth"
    max_extrapolation_s: float = Field(0.02, ge=0.0, le=1.0)
    lead_s: float = Field(0.0, ge=0.0, le=0.1)
    playback_lag_s: float = Field(0.0017, ge=0.0, le=0.1)
    band_hz: float = Field(BAND_HZ_DEFAULT, ge=0.0, le=1000.0)
    axis_band_hz: dict[str, float] = Field(default_factory=dict)
    max_frame_bytes: int = Field(4096, ge=64, le=1_048_576)

    @model_validator(mode="after")
    def _axis_bands(self) -> InputConfig:
        for name, hz in self.axis_band_hz.items():
            if name not in AXES:
                raise ValueError(f"input.axis_band_hz: unknown axis {name[:40]!r}; axes: "
                                 f"{', '.join(AXES)}")
            if not (math.isfinite(hz) and 0.0 <= hz <= 1000.0):
                raise ValueError(f"input.axis_band_hz.{name} must be 0-1000 Hz, got {hz!r}")
        return self

    def bands_hz(self) -> tuple[float, ...]:
        """Each axis' band limit (Hz, 0: none), in :data:`AXES` order."""
        return tuple(self.axis_band_hz.get(a, self.band_hz) for a in AXES)


class CanConfig(BaseModel):
    """CAN output (frames defined by a DBC file)."""

    model_config = _STRICT
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate_bps: int = Field(1_000_000, gt=0)
    dbc: str = "motcomp.dbc"
    send_every: int = Field(4, ge=1, le=100)

    @field_validator("interface")
    @classmethod
    def _known_interface(cls, v: str) -> str:
        from can.interfaces import VALID_INTERFACES

        if v not in VALID_INTERFACES:
            near = difflib.get_close_matches(v, sorted(VALID_INTERFACES), n=1)
            raise ValueError("not a python-can interface"
                             + (f"; did you mean {near[0]!r}?" if near else "")
                             + f" (python-can's: {', '.join(sorted(VALID_INTERFACES))})")
        return v


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
    status_key: str = "platform/status"
    """The platform's own status (docs/WIRE.md); the service shows its stack figures."""


SUPERVISION_PERIOD_MAX_S = 10.0
"""Longest ``supervision.period_s`` (the service's rings hold twice that, and more)."""


class SupervisionConfig(BaseModel):
    """The platform model's supervision (docs/SUPERVISION.md): an estimate of each driven
    axis' platform from ordinary driving, judged against the model the compensator runs."""

    model_config = _STRICT
    enabled: bool = True
    window_s: float = Field(15.0, ge=10.0, le=60.0)
    """Each estimate reads the last this long of outputs and feedback."""
    period_s: float = Field(2.0, ge=0.5, le=SUPERVISION_PERIOD_MAX_S)
    """An estimate every this long."""
    band_hz: _Band = (0.1, 2.0)
    """The driver's band: the mismatch is judged at the motion's centre frequency in it."""
    delay_bound_ms: float = Field(2.5, gt=0.0, le=100.0)
    """An alarm when the residual delay in the band exceeds this..."""
    gain_bound: float = Field(0.1, gt=0.0, le=1.0)
    """... or the gain error in the band this ..."""
    hold_s: float = Field(6.0, ge=0.0, le=600.0)
    """... on every informative estimate for this long (and it clears the same way)."""
    min_motion: float = Field(0.05, gt=0.0)
    """Least RMS of the command's acceleration in the band for a window to be judged."""
    max_delay_se_ms: float = Field(1.0, gt=0.0)
    """Largest standard error of the residual delay for a window to be judged."""
    max_limited_share: float = Field(0.5, ge=0.0, le=1.0)
    """A window in which the limiter acted on more of the ticks is not judged (the estimate
    uses the command the platform received, limited or not: only a command that rides its
    limits most of the time says too little)."""

    @model_validator(mode="after")
    def _band(self) -> SupervisionConfig:
        lo, hi = self.band_hz
        if not (0 < lo < hi <= 20):
            raise ValueError(f"band_hz must be 0 < low < high <= 20 Hz, got {list(self.band_hz)}")
        return self


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
    prediction: PredictionConfig = PredictionConfig()
    supervision: SupervisionConfig = SupervisionConfig()
    defaults: AxisConfig = AxisConfig()
    axes: dict[str, AxisConfig] = {}
    profile: str | None = None
    profiles: dict[str, ProfileConfig] = {}
    envelope: dict[str, LimitsConfig] = {}
    """The hardware envelope per axis (restart only; see the module docstring)."""

    @model_validator(mode="after")
    def _axes(self) -> ServiceConfig:
        for name in self.axes:
            if name not in AXES:
                raise ValueError(f"axes.{name}: unknown axis; axes: {', '.join(AXES)}")
        for name in self.envelope:
            if name not in AXES:
                raise ValueError(f"envelope.{name}: unknown axis; axes: {', '.join(AXES)}")
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
    "loop.realtime_priority", "loop.slice_us", "loop.cpu", "loop.cpu_latency_us", "input",
    "output", "feedback", "status.key", "status.period_s", "status.window_s", "admin", "zenoh",
    "envelope", "supervision.window_s",
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
    prediction: tuple[PredictorParams | None, ...] = ()
    """Per axis, the predictive prefilter (None: none)."""
    predict: tuple[bool, ...] = ()
    """Per axis, whether its prefilter is used (``predict``, default true)."""
    envelope: tuple[tuple[float, float, float, float] | None, ...] = ()
    """Per axis, the hardware envelope ``(p_min, p_max, v_max, a_max)`` (None: none given)."""


_UNDRIVEN_LIMITS = (-1.0, 1.0, 1.0, 1.0)  # an undriven axis is held at neutral


def _merged(defaults: AxisConfig, axis: AxisConfig) -> dict[str, Any]:
    out = defaults.model_dump(exclude_none=True)
    out.update(axis.model_dump(exclude_none=True))
    return out


_TUNING_KEYS = ("rule", "filter_n", "gains", "bypass", "predict")


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


BYPASS_STAND_IN_RULE = "amigo"
"""The rule whose gains stand in for a bypassed axis' own gains when those make the internal
loop unstable with its model (:func:`_bypassed_gains`)."""


def _bypassed_gains(name: str, gains: PIDGains, model: P1D, rate_hz: float, filter_n: float,
                    warnings: list[str]) -> PIDGains:
    """A bypassed axis' gains: its own, or -- when they make the internal loop unstable with its
    model (gains designed for a model a retune replaced, the design recommending bypass) --
    :data:`BYPASS_STAND_IN_RULE`'s for that model, with a warning.  The axis is not compensated
    either way; those gains are what a ``bypass off`` of that axis would compensate with."""
    if stability(gains, model, rate_hz)[0]:
        return gains
    stand_in = tune(BYPASS_STAND_IN_RULE, model, filter_n=filter_n).gains
    warnings.append(
        f"{name}: bypassed, and its gains (kp={gains.kp:.4g}, ki={gains.ki:.4g}, "
        f"kd={gains.kd:.4g}) make the internal loop unstable with its model {model.spec()} "
        f"(gains designed for another model): not used; the {BYPASS_STAND_IN_RULE} rule's gains "
        f"for this model stand in, which a `motcomp bypass off --axes {name}` would compensate "
        "with (`motcomp design --plant` designs gains for this model)")
    return stand_in


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
    prediction: list[PredictorParams | None] = []
    predict: list[bool] = []
    driven: list[bool] = []
    rows: list[tuple[float, float, float, float]] = []
    warnings: list[str] = []
    envelope = _envelope_rows(cfg)
    for name in AXES:
        if name not in cfg.axes:
            models.append(P1D(K=1.0, Td=0.0, Tp1=0.01))
            plants.append(models[-1])
            gains.append(PIDGains(kp=1.0))
            bypass.append(True)
            prediction.append(None)
            predict.append(False)
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
        predict_on = next((ly["predict"] for ly in reversed(layers) if "predict" in ly), True)
        table = cfg.axes[name].prediction or cfg.defaults.prediction
        pred = table.to_params() if table is not None else None
        if pred is not None and abs(pred.rate_hz - cfg.loop.rate_hz) > 1e-9 * cfg.loop.rate_hz:
            raise ConfigError(f"{where}.prediction.rate_hz: designed for {pred.rate_hz:g} Hz, "
                              f"the loop runs at {cfg.loop.rate_hz:g} Hz (loop.rate_hz): design "
                              "it again for this rate (motcomp design --rate)")
        if "gains" in tuning_layer:
            g = GainsConfig(**tuning_layer["gains"]).to_gains()
            if bypass_on:
                g = _bypassed_gains(name, g, model, cfg.loop.rate_hz, filter_n, warnings)
        else:
            tuning = tune(tuning_layer.get("rule", "zn"), model, filter_n=filter_n)
            g = tuning.gains
            if not bypass_on:  # a bypassed axis is not compensated
                warnings += [f"{name}: {w}" for w in tuning.warnings]
        forced = merged.get("forced")
        if forced is not None and parse_model(forced["model"]).spec() == plant.spec():
            warnings.append(f"{name}: its model {plant.spec()} was written by `motcomp identify "
                            f"--force` against identify's refusal ({forced['why']}): check it "
                            "before relying on it (docs/IDENTIFICATION.md)")
        limits_cfg = LimitsConfig(**{k: v for k, v in merged.items()
                                     if k in LimitsConfig.model_fields})
        try:
            rows.append(limits_cfg.resolve(name))
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        _inside_envelope(cfg, name, rows[-1], envelope[AXES.index(name)])
        models.append(model)
        plants.append(plant)
        gains.append(g)
        bypass.append(bool(bypass_on))
        prediction.append(pred)
        predict.append(bool(predict_on) and pred is not None)
        driven.append(True)
    arr = np.array(rows, dtype=float)
    limits = AxisLimits(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], AXES)
    warnings += _parking_warnings(cfg, driven, limits)
    return ResolvedAxes(AXES, tuple(driven), tuple(models), tuple(plants), tuple(gains), limits,
                        tuple(bypass), tuple(warnings), tuple(prediction), tuple(predict),
                        envelope)


def _envelope_rows(cfg: ServiceConfig) -> tuple[tuple[float, float, float, float] | None, ...]:
    """Per axis (:data:`AXES` order), its envelope checked as limits are (None: none)."""
    out: list[tuple[float, float, float, float] | None] = []
    for name in AXES:
        env = cfg.envelope.get(name)
        if env is None:
            out.append(None)
            continue
        try:
            out.append(env.resolve(name))
        except ConfigError as exc:
            raise ConfigError(f"envelope.{name}: {exc}") from None
    return tuple(out)


def _inside_envelope(cfg: ServiceConfig, name: str, row: tuple[float, float, float, float],
                     env: tuple[float, float, float, float] | None) -> None:
    """Refuse limits of ``name`` outside its envelope, naming the key that sets them."""
    if env is None:
        return
    keys = limit_keys(name)
    for j, (key, value, bound) in enumerate(zip(keys, row, env, strict=True)):
        if (value < bound) if j == 0 else (value > bound):
            given = getattr(cfg.axes[name], key) is not None
            where = f"axes.{name}.{key}" if given else f"defaults.{key}"
            raise ConfigError(f"{where} = {value!r} lies outside envelope.{name}.{key} = "
                              f"{bound!r} (the hardware envelope, a restart key)")


def validation_message(exc: ValidationError, root: type[BaseModel], index: int = 0
                       ) -> tuple[str, str]:
    """``(dotted key, "<reason> (got <value>)")`` of the ``index``-th error of validating
    ``root``; an unknown key is named with the keys its table takes that come close ("did you
    mean")."""
    err = exc.errors()[index]
    loc = ".".join(str(p) for p in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden" and err["loc"]:
        msg = f"unknown key {err['loc'][-1]!r}" + _did_you_mean(err["loc"], root)
    value = err.get("input")
    return loc, msg + ("" if isinstance(value, dict) else f" (got {_toml_text(value)})")


def _toml_text(value: Any) -> str:
    """A value as TOML writes it (``true``, ``"yes"``, ``[1, 2]``), for messages."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_text(v) for v in value) + "]"
    return repr(value)


def _did_you_mean(loc: tuple[Any, ...], root: type[BaseModel]) -> str:
    """``"; did you mean 'x'?"`` for an unknown key at ``loc`` below ``root``, from the keys
    its table takes ("" if none is close)."""
    import difflib
    import typing

    model: Any = root
    for part in loc[:-1]:
        field = model.model_fields.get(part) if isinstance(model, type) and issubclass(
            model, BaseModel) else None
        if field is None:  # a table of named entries (axes.<axis>): its values' model
            continue
        ann = field.annotation
        args = [a for a in typing.get_args(ann) if a is not type(None)] or [ann]
        if typing.get_origin(ann) is dict:
            args = [typing.get_args(ann)[1]]
        model = next((a for a in args if isinstance(a, type) and issubclass(a, BaseModel)),
                     None)
        if model is None:
            return ""
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        return ""
    close = difflib.get_close_matches(str(loc[-1]), list(model.model_fields), n=3, cutoff=0.6)
    return f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""


@dataclass(frozen=True)
class _Origin:
    """Which file of a config and its includes holds each value (``read``'s provenance)."""

    top: Path
    files: dict[KeyPath, Path]

    def source(self, key: str, source: str) -> str:
        """``source``, or the included file that holds ``key`` (a dotted key path), naming
        ``source`` as its includer."""
        parts = tuple(key.split("."))
        f = next((self.files[parts[:k]] for k in range(len(parts), 0, -1)
                  if parts[:k] in self.files), None)
        if f is None:  # a table: the file of its values, if one holds them all
            below = {v for k, v in self.files.items() if k[:len(parts)] == parts}
            f = below.pop() if len(below) == 1 else None
        if f is None or f == self.top:
            return source
        return f"{_shown(f, self.top)} (included by {source})"


_KEY_PREFIX = re.compile(r"([A-Za-z_][\w-]*(?:\.[\w-]+)*): ")
"""A message that begins with the dotted key it is about (the config's own checks)."""


MORE_ERRORS = 4
"""A config refused names this many of its errors beyond the first."""


def parse_config(data: dict[str, Any], source: str = "<config>",
                 origin: _Origin | None = None) -> ServiceConfig:
    """Validate a parsed TOML document (``origin``: which file holds each value, for the
    message).

    Raises
    ------
    ConfigError
        ``"<file>: <key.path>: <reason> (got <value>)"``: the file of ``origin`` that holds the
        key, else ``source``.
    """
    def where(key: str) -> str:
        return source if origin is None else origin.source(key, source)

    try:
        cfg = ServiceConfig.model_validate(data)
    except ValidationError as exc:
        loc, msg = validation_message(exc, ServiceConfig)
        key = loc or (m.group(1) if (m := _KEY_PREFIX.match(msg)) else "")
        at = f"{loc}: " if loc else "" if key else "<top>: "  # else the message names it
        others = [validation_message(exc, ServiceConfig, i)
                  for i in range(1, min(exc.error_count(), 1 + MORE_ERRORS))]
        more = "".join(f"; also {where(k)}: {k or '<top>'}: {m}" for k, m in others) + (
            f" [and {exc.error_count() - 1 - MORE_ERRORS} more]"
            if exc.error_count() > 1 + MORE_ERRORS else "")
        raise ConfigError(f"{where(key)}: {at}{msg}{more}") from None
    try:
        resolve_axes(cfg)
    except ConfigError as exc:
        m = _KEY_PREFIX.match(str(exc))
        raise ConfigError(f"{where(m.group(1) if m else '')}: {exc}") from None
    return cfg


# --- includes and provenance ----------------------------------------------------------------

_WHOLE = frozenset({"gains", "prediction"})
"""Tables that a higher file replaces as a whole instead of key by key: a gain set (and a
prefilter) is one design, and a site's ``gains = { kp, ki_per_s, kd_s, tf_s }`` must not keep an
included file's b and c."""
_EITHER = {"rule": "gains", "gains": "rule"}
"""Keys that exclude each other in one table: a higher file's ``rule`` displaces a lower file's
``gains``, and the reverse."""
_FRAGMENT_KEYS = frozenset({"axes"})
"""A file whose own keys are only these is a *fragment* (what ``motcomp identify`` and ``motcomp
design --out`` write): a value of it that another file overrides is reported as lost."""
_REPORTED_AXIS_KEYS = ("model", "gains", "rule", "bypass", "prediction")
_COMMENTED_INCLUDE = re.compile(r"^\s*#+\s*include\s*=(.*)$")

KeyPath = tuple[str, ...]


@dataclass(frozen=True)
class Override:
    """A value of a lower file that a higher one replaces (dotted keys, e.g.
    ``axes.rails_y.model``; ``upper_key`` differs from ``key`` when a ``rule`` displaces
    ``gains`` or the reverse)."""

    key: str
    lower: Path
    lower_value: Any
    upper_key: str
    upper: Path
    upper_value: Any


@dataclass(frozen=True)
class CommentedInclude:
    """A ``# include = [...]`` line: ``names`` are the files it would include (empty if the
    rest of the line is not TOML)."""

    file: Path
    line: int
    text: str
    names: tuple[str, ...]


@dataclass(frozen=True)
class ConfigSources:
    """Where the values of a config file come from once its includes are merged.

    ``files`` lists every file read, lowest precedence first (the file itself last), ``own``
    each one's own values; ``sources`` maps the dotted key of every effective value to its file
    (a ``gains`` table is one value); ``parents`` maps an included file to the file that
    includes it.
    """

    path: Path
    files: tuple[Path, ...]
    own: dict[Path, dict[str, Any]]
    parents: dict[Path, Path]
    fragments: frozenset[Path]
    sources: dict[str, Path]
    overrides: tuple[Override, ...]
    commented_includes: tuple[CommentedInclude, ...]


class _Trace:
    """The provenance of one merge of ``over`` onto ``base``: the entries of ``base_src`` whose
    values ``over`` replaces are removed (the caller then adds ``over_src``) and recorded in
    ``overrides`` when the value changes."""

    def __init__(self, base_src: dict[KeyPath, Path], over_src: dict[KeyPath, Path],
                 overrides: list[Override]) -> None:
        self.base_src, self.over_src, self.overrides = base_src, over_src, overrides

    def lose(self, lost: KeyPath, by: KeyPath, old: Any, new: Any) -> None:
        n = len(lost)
        gone = {k: f for k, f in self.base_src.items() if k[:n] == lost}
        upper = self.over_src.get(by) or next(
            (f for k, f in self.over_src.items() if k[:len(by)] == by), None)
        for k in gone:
            del self.base_src[k]
        if upper is None or (lost == by and old == new):
            return
        for lower in dict.fromkeys(gone.values()):
            self.overrides.append(Override(".".join(lost), lower, old, ".".join(by), upper, new))


def _merge(base: dict[str, Any], over: dict[str, Any], trace: _Trace | None,
           prefix: KeyPath = ()) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        path = (*prefix, key)
        rival = _EITHER.get(key)
        if rival is not None and rival in out and rival not in over:
            if trace is not None:
                trace.lose((*prefix, rival), path, out[rival], value)
            del out[rival]
        if isinstance(value, dict) and isinstance(out.get(key), dict) and key not in _WHOLE:
            out[key] = _merge(out[key], value, trace, path)
        else:
            if key in out and trace is not None:
                trace.lose(path, path, out[key], value)
            out[key] = value
    return out


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Deep merge: tables merge key by key, anything else in ``over`` replaces ``base``; a
    ``gains`` table is replaced as a whole, and ``rule`` and ``gains`` displace each other (a
    table takes one of them, from the higher file)."""
    return _merge(base, over, None)


def _leaves(data: dict[str, Any], prefix: KeyPath = ()) -> list[KeyPath]:
    out: list[KeyPath] = []
    for key, value in data.items():
        path = (*prefix, key)
        if isinstance(value, dict) and key not in _WHOLE:
            out += _leaves(value, path)
        else:
            out.append(path)
    return out


def _commented_includes(path: Path, text: str) -> list[CommentedInclude]:
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        m = _COMMENTED_INCLUDE.match(line)
        if m is None:
            continue
        try:
            value = tomllib.loads(f"include ={m.group(1)}")["include"]
        except tomllib.TOMLDecodeError:
            value = []
        names = [value] if isinstance(value, str) else value if isinstance(value, list) else []
        found.append(CommentedInclude(path, number, line.strip(),
                                      tuple(n for n in names if isinstance(n, str))))
    return found


class _Reader:
    """Reads a file with its includes, keeping the provenance of every value."""

    def __init__(self) -> None:
        self.files: list[Path] = []
        self.own: dict[Path, dict[str, Any]] = {}
        self.parents: dict[Path, Path] = {}
        self.fragments: set[Path] = set()
        self.overrides: list[Override] = []
        self.commented: list[CommentedInclude] = []

    def read(self, p: Path, seen: tuple[Path, ...]) -> tuple[dict[str, Any], dict[KeyPath, Path]]:
        if p in seen:
            chain = " -> ".join(str(s) for s in (*seen, p))
            raise ConfigError(f"{p}: include cycle ({chain})")
        try:
            text = p.read_text()
        except OSError as exc:
            by = f" (included by {seen[-1]})" if seen else ""
            raise ConfigError(f"{p}: cannot read: {exc.strerror}{by}") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML: {exc}") from None
        self.commented += _commented_includes(p, text)
        inc = data.pop("include", [])
        if isinstance(inc, str):
            inc = [inc]
        if not isinstance(inc, list) or not all(isinstance(i, str) for i in inc):
            raise ConfigError(f"{p}: include: must be a file name or a list of them, got {inc!r}")
        merged: dict[str, Any] = {}
        src: dict[KeyPath, Path] = {}
        for name in inc:
            child = (p.parent / name).resolve()
            self.parents.setdefault(child, p)
            data_i, src_i = self.read(child, (*seen, p))
            merged = _merge(merged, data_i, _Trace(src, src_i, self.overrides))
            src.update(src_i)
        if seen and data and set(data) <= _FRAGMENT_KEYS:
            self.fragments.add(p)
        own = dict.fromkeys(_leaves(data), p)
        merged = _merge(merged, data, _Trace(src, own, self.overrides))
        src.update(own)
        self.files.append(p)
        self.own[p] = data
        return merged, src


def read_toml(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A TOML file with its ``include`` files merged underneath it.

    ``include = ["a.toml", ...]`` (paths relative to the including file) are read first, in
    order, each merged over the previous (:func:`merge`); the including file is merged last, so
    its keys win.  This is how an identification result or a design (a fragment with
    ``[axes.<name>]`` tables) is combined with a site config; :func:`config_sources` tells which
    file each value comes from.

    Raises
    ------
    ConfigError
        Naming the file: unreadable, not TOML, an include cycle or a bad ``include`` value.
    """
    return _Reader().read(Path(path).resolve(), tuple(_seen))[0]


def config_sources(path: str | Path) -> ConfigSources:
    """Read ``path`` as :func:`read_toml` does and say where each value comes from: the file of
    every effective key, the values overridden by a higher file, the commented-out ``include``
    lines.

    Raises
    ------
    ConfigError
        As :func:`read_toml`.
    """
    reader = _Reader()
    top = Path(path).resolve()
    _, src = reader.read(top, ())
    return ConfigSources(top, tuple(reader.files), reader.own, reader.parents,
                         frozenset(reader.fragments),
                         {".".join(k): f for k, f in src.items()}, tuple(reader.overrides),
                         tuple(reader.commented))


def _same_value(key: str, a: Any, b: Any) -> bool:
    if key.split(".")[-1] == "model" and isinstance(a, str) and isinstance(b, str):
        try:
            return parse_model(a).spec() == parse_model(b).spec()
        except ConfigError:
            return False
    return bool(a == b)


def _shown(p: Path, top: Path) -> str:
    return str(p.relative_to(top.parent)) if p.is_relative_to(top.parent) else str(p)


def _brief(value: Any) -> str:
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {v!r}" for k, v in value.items()) + " }"
    return json.dumps(value) if isinstance(value, str | bool) else repr(value)


def source_report(path: str | Path, cfg: ServiceConfig | None = None
                  ) -> tuple[list[str], list[str]]:
    """What ``motcomp config check`` says about where the axes' values come from.

    Returns ``(lines, warnings)``: one line per driven axis naming the file of its ``model``
    and of its tuning (``gains`` or ``rule``, through ``[defaults]`` and the active profile as
    :func:`resolve_axes` takes them); a warning for each value of a fragment (a file of only
    ``[axes.*]`` tables, as ``motcomp identify`` and ``motcomp design --out`` write) that a
    higher file overrides with another value (both files and the key named), and for each
    commented-out ``include`` line in ``path`` (or naming a file that exists): the usual ways an
    identified model or a designed tuning is silently lost.

    Raises
    ------
    ConfigError
        As :func:`load_config`.
    """
    top = Path(path).resolve()
    srcs = config_sources(top)
    cfg = cfg if cfg is not None else load_config(path)

    def name(p: Path) -> str:
        return _shown(p, top)

    lines = [f"sources: {', '.join(name(f) for f in srcs.files)} (lowest first)"]
    warnings = []
    bypassed = dict(zip(AXES, resolve_axes(cfg).bypass, strict=True))
    for axis in (a for a in AXES if a in cfg.axes):
        model_key = next((k for k in (f"axes.{axis}.model", "defaults.model")
                          if k in srcs.sources), None)
        layers = [f"axes.{axis}", "defaults"]
        if cfg.profile is not None:
            layers[:0] = [f"profiles.{cfg.profile}.axes.{axis}", f"profiles.{cfg.profile}"]
        tuning_key = next((f"{layer}.{k}" for layer in layers for k in ("gains", "rule")
                           if f"{layer}.{k}" in srcs.sources), None)
        bypass_key = next((f"{layer}.bypass" for layer in layers
                           if f"{layer}.bypass" in srcs.sources), None)
        model_file = srcs.sources[model_key] if model_key else None
        parts = [f"model from {name(model_file)}" if model_file else "no model"]
        if bypassed[axis]:
            parts.append(f"BYPASS from {name(srcs.sources[bypass_key])}" if bypass_key
                         else "not compensated")
        elif tuning_key is None:
            parts.append("rule zn (built-in default)")
        else:
            kind = tuning_key.rsplit(".", 1)[1]
            tuning_file = srcs.sources[tuning_key]
            parts.append(f"{kind} from {name(tuning_file)}"
                         + ("" if tuning_key.startswith("axes.") else f" ({tuning_key})"))
            designed_for = srcs.own[tuning_file].get("axes", {}).get(axis, {}).get("model")
            effective = cfg.axes[axis].model or cfg.defaults.model
            if (kind == "gains" and model_file in srcs.fragments and tuning_file != model_file
                    and not _same_value("model", designed_for, effective)):
                warnings.append(
                    f"warning: axes.{axis}: the model comes from {name(model_file)} but the gains "
                    f"({tuning_key}) from {name(tuning_file)}: gains designed for another model; "
                    f"`motcomp design --plant {name(model_file)} --axis {axis} --out FILE` "
                    "designs them for this one (include FILE after it)")
        pred_key = next((f"{layer}.prediction" for layer in ("axes." + axis, "defaults")
                         if f"{layer}.prediction" in srcs.sources), None)
        if pred_key is not None:
            parts.append(f"prediction from {name(srcs.sources[pred_key])}")
            off_key = next((f"{layer}.predict" for layer in ("axes." + axis, "defaults")
                            if f"{layer}.predict" in srcs.sources), None)
            predict = cfg.axes[axis].predict
            if predict is None:
                predict = cfg.defaults.predict
            if off_key is not None and predict is False:
                parts.append(f"UNUSED (predict = false from {name(srcs.sources[off_key])})")
        lines.append(f"  {axis:<10} {', '.join(parts)}")
    for o in srcs.overrides:
        key_parts = o.key.split(".")
        if (o.lower not in srcs.fragments or len(key_parts) != 3 or key_parts[0] != "axes"
                or key_parts[2] not in _REPORTED_AXIS_KEYS
                or (o.key == o.upper_key and _same_value(o.key, o.lower_value, o.upper_value))):
            continue
        ancestors = []
        p = o.lower
        while p in srcs.parents:
            p = srcs.parents[p]
            ancestors.append(p)
        fix = (f"delete {o.upper_key} from {name(o.upper)}" if o.upper in ancestors
               else f"include {name(o.lower)} after {name(o.upper)}")
        by = "" if o.key == o.upper_key else f"{o.upper_key} in "
        warnings.append(f"warning: {o.key} from {name(o.lower)} ({_brief(o.lower_value)}) is "
                        f"overridden by {by}{name(o.upper)} ({_brief(o.upper_value)}) and not "
                        f"used; to use it, {fix}")
    for c in srcs.commented_includes:
        existing = [n for n in c.names if (c.file.parent / n).is_file()]
        if c.file != top and not existing:
            continue
        what = ", ".join(c.names) or "the files it names"
        state = f" ({', '.join(existing)} exists)" if existing else ""
        warnings.append(f"warning: {name(c.file)}:{c.line}: include is commented out "
                        f"({c.text}): {what} is not read{state}, so no model or gains of it "
                        "are used")
    return lines, warnings


def _unsafe(p: Path, what: str) -> str | None:
    """Why ``p`` could be changed by someone else than root and the service user, or None."""
    try:
        st = p.stat()
    except OSError as exc:
        return f"{p}: cannot stat the {what}: {exc.strerror}"
    if st.st_uid not in (0, os.geteuid()):
        return (f"{p}: the {what} is owned by uid {st.st_uid}, neither root nor the service "
                f"user (uid {os.geteuid()})")
    sticky_dir = stat.S_ISDIR(st.st_mode) and st.st_mode & stat.S_ISVTX
    if st.st_mode & 0o022 and not sticky_dir:
        return (f"{p}: the {what} is writable by group or others (mode "
                f"{stat.S_IMODE(st.st_mode):04o}): chmod go-w {p}")
    return None


def check_envelope(path: str | Path, cfg: ServiceConfig | None = None,
                   allow_writable: bool = False) -> tuple[list[str], list[str]]:
    """The start-up check of the hardware envelope of the config file ``path``.

    Every driven axis must have an ``[envelope.<axis>]``; each file that sets an envelope key
    (an included one too), and its directory, must be owned by root or the service user (the
    current user) and not writable by group or others (a directory with the sticky bit may be).
    ``allow_writable`` turns the file findings into warnings (a checkout of the sources run
    by a developer).  Returns ``(lines, warnings)`` for ``motcomp config check``.

    Raises
    ------
    ConfigError
        A driven axis without an envelope; a file finding unless ``allow_writable``.
    """
    cfg = cfg if cfg is not None else load_config(path)
    missing = [a for a in AXES if a in cfg.axes and a not in cfg.envelope]
    if missing:
        keys = ", ".join(limit_keys(missing[0]))
        raise ConfigError(f"{path}: envelope.{missing[0]}: missing: every driven axis needs its "
                          f"hardware envelope ([envelope.{missing[0]}] {keys})"
                          + (f"; missing too: {', '.join(missing[1:])}" if missing[1:] else ""))
    files = sorted({f for k, f in config_sources(path).sources.items()
                    if k.startswith("envelope.")})
    findings = [w for f in files for w in (_unsafe(f, "envelope file"),
                                           _unsafe(f.parent, "envelope file's directory")) if w]
    if findings and not allow_writable:
        raise ConfigError(f"{findings[0]}; the hardware envelope must come from files that "
                          "only root or the service user can change"
                          + (f" [and {len(findings) - 1} more]" if findings[1:] else ""))
    shown = ", ".join(str(f) for f in files)
    lines = [f"envelope of {', '.join(a for a in AXES if a in cfg.envelope)} from {shown}"]
    return lines, [f"warning: {w} (allowed: --allow-writable-envelope)" for w in findings]


def load_config(path: str | Path) -> ServiceConfig:
    """Read (with includes) and validate a TOML config file (see module docstring); an error
    in a value names the file that holds it."""
    top = Path(path).resolve()
    data, origin = _Reader().read(top, ())
    return parse_config(data, str(path), _Origin(top, origin))


def config_hash(cfg: ServiceConfig) -> str:
    """Short stable hash of the effective config (shown in the status and the logs)."""
    text = json.dumps(cfg.model_dump(mode="json"), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _band_key(inp: InputConfig, axis: str) -> str:
    return f"input.axis_band_hz.{axis}" if axis in inp.axis_band_hz else "input.band_hz"


PARK_SETTLE_S = 0.5
"""``loop.park_timeout_s`` must exceed the longest ramp to neutral by this much (the command's
settle after the ramp: some tens of milliseconds measured)."""


def _ramp_limits(loop: LoopConfig, limits: AxisLimits
                 ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Each axis' peak speed of a ramp to neutral (the shaper's ``ramp_speed``:
    ``ramp_speed_fraction`` of ``vel_max``) and peak acceleration of its ramps and blends
    (``blend_acc``: :data:`~motcomp.core.blend.BLEND_ACC_SHARE` of ``acc_max``)."""
    return (tuple(loop.ramp_speed_fraction * float(v) for v in limits.v_max),
            tuple(BLEND_ACC_SHARE * float(a) for a in limits.a_max))


def _parking_warnings(cfg: ServiceConfig, driven: Sequence[bool], limits: AxisLimits
                      ) -> list[str]:
    """One warning per driven axis that cannot park within ``loop.park_timeout_s`` from
    anywhere in its range: its ramp to neutral from the farther position limit
    (:func:`_ramp_limits`) plus :data:`PARK_SETTLE_S` exceeds it, so that a stop from there
    would end mid-ramp (exit 1)."""
    loop = cfg.loop
    speed, acc = _ramp_limits(loop, limits)
    out = []
    for i, name in enumerate(AXES):
        if not driven[i]:
            continue
        far = max(abs(float(limits.p_min[i])), abs(float(limits.p_max[i])))
        v = float(limits.v_max[i])
        ramp = move_duration(far, speed[i], acc[i])
        if ramp + PARK_SETTLE_S > loop.park_timeout_s:
            out.append(
                f"{name}: loop.park_timeout_s = {loop.park_timeout_s:g} s is shorter than its "
                f"ramp to neutral from its position limit {far:g} ({ramp:.2f} s at "
                f"loop.ramp_speed_fraction = {loop.ramp_speed_fraction:g} of its vel_max "
                f"{v:g}): a stop from there would end mid-ramp (exit 1); give park_timeout_s "
                f">= {math.ceil((ramp + PARK_SETTLE_S) * 10.0) / 10.0:g} or a larger "
                "ramp_speed_fraction")
    return out


def tick_params(cfg: ServiceConfig, axes: ResolvedAxes) -> TickParams:
    """The tick's parameters of a config (:mod:`motcomp.core.tick`): input accepted, and the
    reference kept, within each axis' limits widened by ``input.reject_beyond_fraction`` of its
    range."""
    f = cfg.input.reject_beyond_fraction
    lim = axes.limits
    lo = tuple(float(a - f * (b - a)) for a, b in zip(lim.p_min, lim.p_max, strict=True))
    hi = tuple(float(b + f * (b - a)) for a, b in zip(lim.p_min, lim.p_max, strict=True))
    loop = cfg.loop
    ramp_speed, blend_acc = _ramp_limits(loop, lim)
    shaper = ShaperParams(
        driven=axes.driven, ramp_speed=ramp_speed,
        reach_lo=lo, reach_hi=hi, home_lo=tuple(float(v) for v in lim.p_min),
        home_hi=tuple(float(v) for v in lim.p_max), stale_after_s=loop.stale_after_s,
        hold_s=loop.hold_s,
        rejoin_s=loop.rejoin_s, startup_s=loop.startup_s,
        reconstruction=cfg.input.reconstruction, tick_s=1.0 / loop.rate_hz,
        max_extrapolation_s=cfg.input.max_extrapolation_s, lead_s=cfg.input.lead_s,
        playback_lag_s=cfg.input.playback_lag_s,
        blend_acc=blend_acc,
        blend_jerk=tuple(a / m.Tp1 for a, m in zip(blend_acc, axes.models, strict=True)),
        band=tuple(band_limit_params(hz, loop.rate_hz, _band_key(cfg.input, a)) if d else None
                   for a, hz, d in zip(AXES, cfg.input.bands_hz(), axes.driven, strict=True)))
    return TickParams(loop.rate_hz, shaper, cfg.status.saturation_tolerance,
                      cfg.input.max_frame_bytes, prediction=axes.prediction,
                      predict=axes.predict, monitor=cfg.prediction.to_params(),
                      envelope=envelope_params(axes, loop.rate_hz))


def envelope_params(axes: ResolvedAxes, rate_hz: float) -> EnvelopeParams:
    """The envelope guard's parameters (:mod:`motcomp.core.envelope`): each driven axis'
    ``[envelope]``, or :data:`~motcomp.limits_config.PLAUSIBLE` without one (an offline tool;
    the service refuses to start so, :func:`check_envelope`); an undriven axis at neutral."""
    rows = []
    for name, driven, env in zip(axes.names, axes.driven,
                                 axes.envelope or (None,) * len(axes.names), strict=True):
        if not driven:
            rows.append((0.0, 0.0, 0.0, 0.0))
        elif env is not None:
            rows.append(env)
        else:
            keys = limit_keys(name)
            rows.append((PLAUSIBLE[keys[0]][0], PLAUSIBLE[keys[1]][1], PLAUSIBLE[keys[2]][1],
                         PLAUSIBLE[keys[3]][1]))
    lo, hi, v, a = (tuple(float(r[j]) for r in rows) for j in range(4))
    return EnvelopeParams(lo, hi, v, a, rate_hz)


def new_tick(cfg: ServiceConfig, axes: ResolvedAxes | None = None
             ) -> tuple[TickParams, TickState]:
    """Parameters and a fresh state (compensator at rest at neutral, the config's bypass) of a
    config's tick."""
    axes = axes if axes is not None else resolve_axes(cfg)
    comp = Compensator(axes.models, axes.gains, axes.limits, cfg.loop.rate_hz,
                       fade_s=cfg.loop.bypass_fade_s, history_s=0.5)
    comp.set_bypass(axes.bypass)
    return tick_params(cfg, axes), TickState(comp, axes.driven)
