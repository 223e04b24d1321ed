"""Live reload of the service's configuration (SIGHUP, ``motcomp reload``, ``motcomp profile``).

1. :func:`prepare_config` / :func:`prepare_profile` read and validate the new config away from
   the loop, in a child process (:class:`Preparer`: the service's interpreter lock stays with
   the loop; a file that hangs or bloats the reader costs the child, which is killed after
   :data:`PREPARE_TIMEOUT_S`): the file and its includes confined to the config directory and
   size-capped (:mod:`motcomp.runtime.confine`), TOML, schema, every axis resolved (models,
   gains from rules, limits), keys that need a restart unchanged, the set of driven axes
   unchanged, and the stability of every new gain/model pair checked (a dry-run compensator).
2. :meth:`motcomp.runtime.service.Service.apply_config` swaps the result in between two ticks:
   one ``Compensator.reconfigure`` (bumpless: the integrator is re-seeded so that the raw output
   is continuous; the limiter keeps the output within the limits through any change) and one
   assignment of the tick's parameters.
3. An invalid config changes nothing; every reason is returned, what is wrong with the file
   itself first, then the keys that would need a restart (``motcomp reload`` exits 2 with
   them).  Every attempt is logged with the config's hash and kept in the status; systemd is
   told ``RELOADING=1`` ... ``READY=1``.
"""

from __future__ import annotations

import pickle
import subprocess
import threading
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
from motcomp.runtime import child
from motcomp.runtime.confine import Confinement

__all__ = ["PREPARE_TIMEOUT_S", "Prepared", "Preparer", "prepare_config", "prepare_profile",
           "restart_changes"]

PREPARE_TIMEOUT_S = 10.0
"""Longest a reload or profile switch may take to prepare; then it is refused and the child
process that prepares it is killed (a new one is started for the next)."""


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
    try:  # builds a compensator: checks every new gain/model pair
        params, _ = new_tick(new, axes)
    except ConfigError as exc:  # said with the file, as every other refusal
        raise ConfigError(f"{where}: {exc}") from None
    return Prepared(new, axes, params, config_hash(new))


def prepare_config(old: ServiceConfig, old_axes: ResolvedAxes, path: Path | None,
                   confinement: Confinement | None) -> Prepared:
    """Read and validate the config file ``path`` against the running one; ``path`` and its
    includes are read only as ``confinement`` allows (None: the service has no config
    directory, nothing is read).

    Raises
    ------
    ConfigError
        Nothing may change (the message names the file, key and value), or a file is refused
        (the message names the request key or include and the rule, nothing read).
    """
    if path is None:
        raise ConfigError("no config file to reload (the service was started without one)")
    if confinement is None:
        raise ConfigError(f"reload path {str(path)[:200]!r}: refused: the service was started "
                          "without a config file, so it has no config directory to read from")
    path = confinement.check(path)
    data = read_toml(path)
    where = str(path)
    errors: list[str] = []
    new: ServiceConfig | None = None
    try:  # what is wrong with the file itself comes first: a restart would not cure it
        new = parse_config(data, where)
    except ConfigError as exc:
        errors.append(str(exc))
    try:
        shallow = new if new is not None else ServiceConfig.model_validate(data)
    except ValidationError:
        shallow = None  # nothing to compare: parse_config said what is wrong
    changed = [] if shallow is None else restart_changes(old, shallow)
    if changed:
        errors.append(f"{where}: {', '.join(changed)} cannot change live (restart the "
                      "service)")
    if len(errors) > 1:
        raise ConfigError(f"{len(errors)} problems: " + "; ".join(
            f"({k}) {e}" for k, e in enumerate(errors, 1)))
    if errors:
        raise ConfigError(errors[0])
    assert new is not None
    return _prepare(old, old_axes, new, where)


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


# --- the child process -------------------------------------------------------------------------
def _handle(request: tuple[Any, ...]) -> tuple[str, Any]:
    """One request ``(kind, old cfg, old axes, arg, confinement)`` in the child:
    ``("ok", Prepared)`` or ``("error", text)``."""
    kind, old, old_axes, arg, confinement = request
    try:
        if kind == "ping":
            return ("ok", None)
        if kind == "config":
            return ("ok", prepare_config(old, old_axes, arg, confinement))
        return ("ok", prepare_profile(old, old_axes, arg))
    except ConfigError as exc:
        return ("error", str(exc))
    except Exception as exc:  # a bug: said, the child goes on
        return ("error", f"internal error: {type(exc).__name__}: {exc}")


def serve() -> None:
    """The child's main: answer requests on stdin until stdin closes."""
    child.serve(_handle)


class Preparer:
    """Prepares reloads and profile switches in a child process (started on first use or by
    :meth:`start`; one request at a time; thread-safe)."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()

    def start(self, wait: bool = False) -> None:
        """Start the child now, if it is not running (it imports for a second or two); with
        ``wait``, return once it answers.

        Raises
        ------
        ConfigError
            ``wait`` and the child did not answer within :data:`PREPARE_TIMEOUT_S`.
        """
        if wait:
            self._call(("ping", None, None, None, None))
        else:
            with self._lock:
                self._start()

    def _start(self) -> subprocess.Popen[bytes]:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            return proc
        self._proc = child.spawn("from motcomp.runtime.reload import serve; serve()")
        return self._proc

    def close(self) -> None:
        """Stop the child (safe to call twice)."""
        with self._lock:
            proc, self._proc = self._proc, None
        if proc is not None:
            proc.kill()
            proc.wait()
            for f in (proc.stdin, proc.stdout):
                if f is not None:
                    f.close()

    def prepare_config(self, old: ServiceConfig, old_axes: ResolvedAxes, path: Path | None,
                       confinement: Confinement | None) -> Prepared:
        """:func:`prepare_config` in the child."""
        return self._ask(("config", old, old_axes, path, confinement))

    def prepare_profile(self, old: ServiceConfig, old_axes: ResolvedAxes, name: str | None
                        ) -> Prepared:
        """:func:`prepare_profile` in the child."""
        return self._ask(("profile", old, old_axes, name, None))

    def _ask(self, request: tuple[Any, ...]) -> Prepared:
        value = self._call(request)
        assert isinstance(value, Prepared)
        return value

    def _call(self, request: tuple[Any, ...]) -> Any:
        with self._lock:
            proc = self._start()
            try:
                reply = child.ask(proc, request, PREPARE_TIMEOUT_S)
            except (OSError, EOFError, pickle.PickleError, TimeoutError) as exc:
                proc.kill()
                proc.wait()
                self._proc = None
                what = (f"took longer than {PREPARE_TIMEOUT_S:g} s"
                        if isinstance(exc, TimeoutError) else "failed")
                raise ConfigError(f"preparing the config {what} (the reader process was "
                                  "stopped; the running config stays)") from None
        kind, value = reply
        if kind != "ok":
            raise ConfigError(value)
        return value
