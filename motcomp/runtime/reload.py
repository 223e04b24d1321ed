"""Live reload of the service's configuration (SIGHUP, ``motcomp reload``, ``motcomp profile``).

1. :func:`prepare_config` / :func:`prepare_profile` read and validate the new config in the main
   thread, away from the loop: TOML, schema, every axis resolved (models, gains from rules,
   limits), keys that need a restart unchanged, the set of driven axes unchanged, and the
   stability of every new gain/model pair checked (a dry-run compensator).
2. :meth:`motcomp.runtime.service.Service.apply_config` swaps the result in between two ticks:
   one ``Compensator.reconfigure`` (bumpless: the integrator is re-seeded so that the raw output
   is continuous; the limiter keeps the output within the limits through any change) and one
   assignment of the tick's parameters.
3. An invalid config changes nothing; the reason is returned (``motcomp reload`` exits non-zero
   with it).  Every attempt is logged with the config's hash and kept in the status; systemd is
   told ``RELOADING=1`` ... ``READY=1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from motcomp.config import (
    RESTART_KEYS,
    ResolvedAxes,
    ServiceConfig,
    config_hash,
    new_tick,
    parse_config,
    read_toml,
    resolve_axes,
)
from motcomp.core.tick import TickParams
from motcomp.errors import ConfigError

__all__ = ["Prepared", "prepare_config", "prepare_profile", "restart_changes"]


@dataclass(frozen=True)
class Prepared:
    """A validated config, ready to swap in."""

    cfg: ServiceConfig
    axes: ResolvedAxes
    params: TickParams
    digest: str


def _get(cfg: ServiceConfig, dotted: str) -> Any:
    obj: Any = cfg
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj.model_dump() if hasattr(obj, "model_dump") else obj


def restart_changes(old: ServiceConfig, new: ServiceConfig) -> list[str]:
    """Keys of :data:`RESTART_KEYS` whose values differ."""
    return [k for k in RESTART_KEYS if _get(old, k) != _get(new, k)]


def _refuse_restart_keys(old: ServiceConfig, new: ServiceConfig, where: str) -> None:
    changed = restart_changes(old, new)
    if changed:
        raise ConfigError(f"{where}: {', '.join(changed)} cannot change live (restart the "
                          "service)")


def _prepare(old: ServiceConfig, old_axes: ResolvedAxes, new: ServiceConfig, where: str
             ) -> Prepared:
    _refuse_restart_keys(old, new, where)
    axes = resolve_axes(new)
    if axes.driven != old_axes.driven:
        raise ConfigError(f"{where}: the set of driven axes cannot change live")
    params, _ = new_tick(new, axes)  # builds a compensator: checks every new gain/model pair
    return Prepared(new, axes, params, config_hash(new))


def prepare_config(old: ServiceConfig, old_axes: ResolvedAxes, path: Path | None) -> Prepared:
    """Read and validate the config file ``path`` against the running one.

    Raises
    ------
    ConfigError
        Nothing may change (the message names the file, key and value).
    """
    if path is None:
        raise ConfigError("no config file to reload (the service was started without one)")
    data = read_toml(path)
    try:  # a key that needs a restart is the first thing to say (before what follows from it)
        shallow = ServiceConfig.model_validate(data)
    except ValidationError:
        pass  # parse_config says what is wrong
    else:
        _refuse_restart_keys(old, shallow, str(path))
    return _prepare(old, old_axes, parse_config(data, str(path)), str(path))


def prepare_profile(old: ServiceConfig, old_axes: ResolvedAxes, name: str | None) -> Prepared:
    """The running config with ``name`` as its active profile (None: none).

    Raises
    ------
    ConfigError
        If the profile is not defined.
    """
    if name is not None and name not in old.profiles:
        raise ConfigError(f"profile {name!r} is not defined; profiles: "
                          f"{', '.join(old.profiles) or 'none'}")
    return _prepare(old, old_axes, old.model_copy(update={"profile": name}), "config")
