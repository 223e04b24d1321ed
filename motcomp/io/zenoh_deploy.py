"""The files of a zenoh deployment (credentials, TLS keys and certificates), checked the same
way by ``motcomp run`` before it opens its session and by ``motcomp config check``.

Rules, each problem named with its file, the zenoh key that names it and what is wrong:

- the zenoh config (``[zenoh] config_file``, relative to the service's TOML file) exists, is a
  regular file readable by this process, parses (zenoh's own parser) and is not writable by
  group or others;
- every file it names (:data:`FILE_KEYS`) likewise exists, is a regular readable file, not
  writable by group or others; relative names are taken from the working directory, as zenoh
  takes them;
- a secret -- the credentials dictionary, a private key, or the zenoh config itself when it
  holds a password or a private key inline (:data:`INLINE_SECRETS`) -- gives group and others
  no access at all (mode 600 or stricter);
- every endpoint the service listens on or connects to (``-l``/``-e``, ``[zenoh] listen`` and
  ``connect``, or the zenoh config's own) uses a protocol the zenoh config allows
  (``transport/link/protocols``: the shipped TLS config allows ``tls`` only, and zenoh refuses
  to open a ``tcp/`` listener with it) -- :func:`check_endpoints`.

Readability is that of the calling user: run ``motcomp config check`` as the service's user.
:func:`probe` (``config check`` only) then opens a session as the service will, with its
listeners moved to an ephemeral loopback port and no outgoing connection, so that zenoh itself
reads the access-control rules, the credentials and the TLS material.
"""

from __future__ import annotations

import json
import os
import stat
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from motcomp.errors import ConfigError, TransportError
from motcomp.io.zenoh_io import ZenohEndpoints, open_session, zenoh_text

if TYPE_CHECKING:
    from motcomp.config import ZenohConfig

__all__ = [
    "FILE_KEYS",
    "INLINE_SECRETS",
    "check_deployment",
    "check_endpoints",
    "check_service_zenoh",
    "deployment_problems",
    "probe",
    "service_endpoints",
]

FILE_KEYS: dict[str, bool] = {
    "transport/auth/usrpwd/dictionary_file": True,
    "transport/link/tls/root_ca_certificate": False,
    "transport/link/tls/listen_private_key": True,
    "transport/link/tls/listen_certificate": False,
    "transport/link/tls/connect_private_key": True,
    "transport/link/tls/connect_certificate": False,
    "transport/auth/pubkey/public_key_file": False,
    "transport/auth/pubkey/private_key_file": True,
    "transport/auth/pubkey/known_keys_file": False,
}
"""zenoh config keys that name a file (zenoh 1.x), and whether the file is a secret."""

INLINE_SECRETS = ("transport/auth/usrpwd/password", "transport/auth/pubkey/private_key_pem")
"""Keys whose value makes the zenoh config file itself a secret."""


def service_endpoints(zenoh_cfg: ZenohConfig, service_config: Path) -> ZenohEndpoints:
    """The endpoints of the service config's ``[zenoh]`` section; a relative ``config_file``
    is taken from the directory of the service's TOML file ``service_config``."""
    path = zenoh_cfg.config_file
    if path and not Path(path).is_absolute():
        path = str(service_config.resolve().parent / path)
    return ZenohEndpoints(path, tuple(zenoh_cfg.connect), tuple(zenoh_cfg.listen),
                          zenoh_cfg.multicast_scouting)


def _file_problems(path: Path, what: str, secret: bool) -> list[str]:
    """Problems of one file (``what`` names it: the key, or ``[zenoh] config_file``)."""
    where = f"{path} ({what})"
    try:
        st = path.stat()
    except FileNotFoundError:
        return [f"{where}: does not exist"]
    except OSError as exc:
        return [f"{where}: cannot be inspected: {exc.strerror}"]
    if not stat.S_ISREG(st.st_mode):
        return [f"{where}: not a regular file"]
    out = []
    if not os.access(path, os.R_OK):
        out.append(f"{where}: not readable by this user (uid {os.geteuid()}); the service's "
                   f"user must be able to read it")
    mode = stat.S_IMODE(st.st_mode)
    if secret and mode & 0o077:
        out.append(f"{where}: mode {mode:04o} gives group/others access to a secret; make it "
                   f"owned by the service's user with mode 600 (chmod 600 {path})")
    elif mode & 0o022:
        out.append(f"{where}: mode {mode:04o} lets group/others write it (chmod go-w {path})")
    return out


def _value(cfg: Any, key: str) -> Any:
    return json.loads(cfg.get_json(key))


def deployment_problems(zenoh_file: str) -> list[str]:
    """Every problem of the zenoh config ``zenoh_file`` and the files it names (empty list:
    none; an empty ``zenoh_file`` has none)."""
    import zenoh

    if not zenoh_file:
        return []
    path = Path(zenoh_file)
    out = _file_problems(path, "[zenoh] config_file", secret=False)
    if out:
        return out
    try:
        cfg = zenoh.Config.from_file(str(path))
    except Exception as exc:  # zenoh raises its own ZError
        return [f"{path} ([zenoh] config_file): does not parse: {zenoh_text(exc)}"]
    inline = [k for k in INLINE_SECRETS if _value(cfg, k)]
    if inline:
        out += [p + f" (it holds {', '.join(inline)})"
                for p in _file_problems(path, "[zenoh] config_file", secret=True)]
    for key, secret in FILE_KEYS.items():
        name = _value(cfg, key)
        if name:
            out += _file_problems(Path(name).absolute(), key, secret)
    return out


def check_deployment(zenoh_file: str) -> None:
    """Raise :class:`ConfigError` listing every problem :func:`deployment_problems` finds."""
    problems = deployment_problems(zenoh_file)
    if problems:
        raise ConfigError(f"zenoh deployment, {len(problems)} problem"
                          f"{'s' if len(problems) > 1 else ''}:\n  " + "\n  ".join(problems))


def endpoint_problems(ep: ZenohEndpoints) -> list[str]:
    """Endpoints of ``ep`` whose protocol its zenoh config does not allow, in words (empty:
    none, or the config restricts no protocol)."""
    import zenoh

    if not ep.config_file:
        return []
    try:
        cfg = zenoh.Config.from_file(ep.config_file)
    except Exception:  # deployment_problems says why it does not parse
        return []
    allowed = _value(cfg, "transport/link/protocols")
    if not allowed:
        return []
    out = []
    for role, given in (("listen", ep.listen), ("connect", ep.connect)):
        endpoints = list(given)
        if not endpoints:
            configured = _value(cfg, f"{role}/endpoints")
            endpoints = (configured.get(ep.mode, []) if isinstance(configured, dict)
                         else configured or [])
        for e in endpoints:
            proto = str(e).split("/", 1)[0]
            if proto not in allowed:
                out.append(f"{role} endpoint {e!r}: protocol {proto!r} is not allowed by "
                           f"{ep.config_file} (transport/link/protocols = {allowed}): use "
                           + " or ".join(f"{p}/" for p in allowed) + " endpoints")
    return out


def check_endpoints(ep: ZenohEndpoints) -> None:
    """Raise :class:`ConfigError` listing every endpoint :func:`endpoint_problems` finds."""
    problems = endpoint_problems(ep)
    if problems:
        raise ConfigError(f"zenoh endpoints, {len(problems)} problem"
                          f"{'s' if len(problems) > 1 else ''}:\n  " + "\n  ".join(problems))


def probe(ep: ZenohEndpoints) -> str:
    """Open and close a session of ``ep`` (the service's endpoints) listening on an ephemeral
    loopback port of each protocol it listens on, connecting nowhere; a summary of what was
    checked, or :class:`ConfigError` naming what zenoh refused."""
    import zenoh

    listen = list(ep.listen)
    if not listen and ep.config_file:
        configured = _value(zenoh.Config.from_file(ep.config_file), "listen/endpoints")
        listen = configured.get(ep.mode, []) if isinstance(configured, dict) else configured
    protocols = sorted({e.split("/", 1)[0] for e in listen or ["tcp/"]})
    local = [f"{proto}/127.0.0.1:0" for proto in protocols]
    trial = replace(ep, connect=(), listen=(), multicast_scouting=False,
                    extra={**ep.extra, "listen/endpoints": local, "connect/endpoints": [],
                           "scouting/gossip/enabled": False})
    try:
        with open_session(trial):
            pass
    except TransportError as exc:
        raise ConfigError(f"zenoh refuses the deployment ({ep.config_file or 'no config file'}"
                          f", listening on {', '.join(protocols)}): {exc}") from None
    return (f"zenoh: a session opens with "
            f"{ep.config_file or 'zenoh' + chr(39) + 's default settings'} (listening on "
            f"{', '.join(protocols)}; credentials, access control and TLS material read by "
            f"zenoh)")


def check_service_zenoh(zenoh_cfg: ZenohConfig, service_config: Path) -> str:
    """``motcomp config check``'s zenoh part: :func:`check_deployment` then :func:`probe` of
    the service's endpoints; the summary, or :class:`ConfigError`."""
    ep = service_endpoints(zenoh_cfg, service_config)
    check_deployment(ep.config_file)
    check_endpoints(ep)
    return probe(ep)
