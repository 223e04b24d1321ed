"""Live reload of the service's configuration (SIGHUP, ``motcomp reload``).

1. The new file is read and validated in the main thread, away from the loop: TOML, schema,
   every axis resolved (models, gains from rules, limits), keys that need a restart unchanged,
   and the stability of every new gain/model pair checked.
2. The swap is a closure queued to the loop, which runs it between two ticks: one
   ``Compensator.reconfigure`` (bumpless: the integrator is re-seeded so that the raw output is
   continuous; the limiter keeps the output within the limits through any change) and plain
   reference assignments for the rest.
3. An invalid config changes nothing; the reason is returned (and ``motcomp reload`` exits
   non-zero with it).  Every attempt is logged with the config's hash and kept in the status.
   systemd is told ``RELOADING=1`` ... ``READY=1``.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from motcomp.config import RESTART_KEYS, ServiceConfig, config_hash, load_config, resolve_axes
from motcomp.core.compensator import Compensator
from motcomp.errors import ConfigError, MotcompError, ServiceError

if TYPE_CHECKING:
    from motcomp.runtime.service import Service

__all__ = ["reload_service", "restart_changes", "switch_profile"]

log = logging.getLogger("motcomp.service")


def _get(cfg: ServiceConfig, dotted: str) -> Any:
    obj: Any = cfg
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj.model_dump() if hasattr(obj, "model_dump") else obj


def restart_changes(old: ServiceConfig, new: ServiceConfig) -> list[str]:
    """Keys of :data:`RESTART_KEYS` whose values differ."""
    return [k for k in RESTART_KEYS if _get(old, k) != _get(new, k)]


def _apply(svc: Service, new: ServiceConfig, attempt: dict[str, Any]) -> None:
    """Validate ``new`` against the running service and swap it in between two ticks.

    Raises
    ------
    MotcompError
        Nothing changed.
    """
    changed = restart_changes(svc.cfg, new)
    if changed:
        raise ConfigError(f"{attempt.get('path') or 'config'}: {', '.join(changed)} cannot "
                          "change live (restart the service)")
    axes = resolve_axes(new)
    if axes.driven != svc.axes.driven:
        raise ConfigError(f"{attempt.get('path') or 'config'}: the set of driven axes cannot "
                          "change live")
    # dry run: validates every new model/gain pair (stability) without touching the loop
    Compensator(axes.models, axes.gains, axes.limits, new.loop.rate_hz,
                fade_s=new.loop.bypass_fade_s, history_s=0.5)
    digest = config_hash(new)
    attempt["hash"] = digest
    applied = threading.Event()

    def swap() -> None:  # runs in the loop thread, between two ticks
        svc.comp.reconfigure(axes.models, axes.gains, axes.limits)
        svc.comp.set_fade(new.loop.bypass_fade_s)
        svc.comp.set_bypass(axes.bypass)
        svc.shaper.configure([new.loop.ramp_speed_fraction * float(v)
                              for v in axes.limits.v_max],
                             new.loop.stale_after_s, new.loop.hold_s, new.loop.rejoin_s,
                             new.loop.startup_s)
        svc.validator.set_limits(list(axes.limits.p_min), list(axes.limits.p_max))
        svc.cfg = new
        svc.axes = axes
        svc._set_bypass_flags()
        applied.set()

    svc.commands.append(swap)
    if not applied.wait(2.0):
        raise ServiceError("the loop did not apply the new config within 2 s")
    svc.config_version += 1
    svc.config_id = digest
    attempt.update(ok=True, version=svc.config_version, profile=new.profile)
    for w in axes.warnings:
        log.warning("%s", w)


def _attempt(svc: Service, attempt: dict[str, Any], build: Any, what: str) -> dict[str, Any]:
    svc.notifier.reloading()
    try:
        _apply(svc, build(), attempt)
        log.info("%s ok: %s (hash %s, version %d, profile %s)", what, attempt.get("path") or "-",
                 attempt["hash"], svc.config_version, attempt.get("profile"))
    except MotcompError as exc:
        attempt.update(ok=False, error=str(exc))
        log.error("%s rejected: %s (running config %s kept)", what, exc, svc.config_id)
    finally:
        svc.notifier.ready()
    svc.reloads.append(attempt)
    return {"ok": attempt["ok"], **{k: v for k, v in attempt.items() if k != "ok"}}


def reload_service(svc: Service, path: str | None = None) -> dict[str, Any]:
    """Validate and apply a new config file; returns ``{"ok": bool, ...}`` (never raises for a
    bad config)."""
    source = Path(path) if path else svc.config_path
    attempt: dict[str, Any] = {"t": time.time(), "kind": "reload",
                               "path": str(source) if source else None}

    def build() -> ServiceConfig:
        if source is None:
            raise ConfigError("no config file to reload (the service was started without one)")
        return load_config(source)

    return _attempt(svc, attempt, build, "reload")


def switch_profile(svc: Service, name: str | None) -> dict[str, Any]:
    """Make ``name`` the active scenario profile (None: none), bumplessly; the rest of the
    running config is unchanged.  Returns ``{"ok": bool, ...}``."""
    attempt: dict[str, Any] = {"t": time.time(), "kind": "profile", "path": None}

    def build() -> ServiceConfig:
        if name is not None and name not in svc.cfg.profiles:
            raise ConfigError(f"profile {name!r} is not defined; profiles: "
                              f"{', '.join(svc.cfg.profiles) or 'none'}")
        return svc.cfg.model_copy(update={"profile": name})

    return _attempt(svc, attempt, build, f"switch to profile {name}")
