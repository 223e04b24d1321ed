"""zenoh adapters: session opening from the usual flags, input source, sink, queryables.

Library facts this module relies on (zenoh-python 1.x): a ``RingChannel(n)`` subscriber keeps
the newest ``n`` samples (older ones are dropped) and ``try_recv()`` never blocks (a full
``FifoChannel`` would block zenoh's network thread); publishers for the data path are
``express`` with ``CongestionControl.DROP`` and real-time priority; queryables are served with a
channel handler polled from a Python thread, so no Python callback ever runs on a zenoh thread
(a process whose callback subscriber is still declared at exit can hang). Sessions are closed in
``finally``/``with``. Never fork after ``zenoh.open()``.

motcomp's commands run zenoh's tasks on one thread (:data:`ONE_THREAD`, set by
:func:`use_one_zenoh_thread` unless the environment sets ``ZENOH_RUNTIME``): zenoh's default
spreads them over five runtimes and six threads, which wake one another for every frame.  Nothing
of motcomp blocks a zenoh thread (channels that drop, never a full FIFO of the data path), so one
thread serves every link (docs/DEPLOYMENT.md, "zenoh's threads").
"""

from __future__ import annotations

import argparse
import json
import os
import re
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from motcomp.core.tick import TickOutput
from motcomp.errors import ConfigError, NoAnswerError, TransportError
from motcomp.io.wire import encode_output

__all__ = [
    "MAX_BURST",
    "ONE_THREAD",
    "NoPeerError",
    "ZenohEndpoints",
    "ZenohSink",
    "ZenohSource",
    "add_zenoh_args",
    "endpoints_from_args",
    "open_session",
    "use_one_zenoh_thread",
    "wait_for_subscriber",
]

ZENOH_RUNTIME_ENV = "ZENOH_RUNTIME"
"""The environment variable zenoh reads its task runtimes' settings from (RON), once, when the
process first uses them."""
ONE_THREAD = ("(rx: (handover: app), acc: (handover: app), tx: (handover: app), "
              "net: (handover: app))")
"""zenoh's receiving, accepting, transmitting and network runtimes handed over to its application
runtime (one worker thread by default): all of zenoh's tasks on one thread."""


def use_one_zenoh_thread() -> str:
    """Have this process run zenoh's tasks on one thread (:data:`ONE_THREAD`), unless the
    environment already sets ``ZENOH_RUNTIME``; returns the setting in force.  Call it before
    the process opens its first session (the commands do, at start); child processes inherit it."""
    return os.environ.setdefault(ZENOH_RUNTIME_ENV, ONE_THREAD)


class NoPeerError(TransportError):
    """Nobody was reachable: no subscriber matched a publisher, or no service answered a
    query, within the time allowed (the message names the key and the endpoints tried)."""


@dataclass(frozen=True)
class ZenohEndpoints:
    """Where a session listens and connects; ``config_file`` is a zenoh JSON5 file applied
    first, the other fields override it."""

    config_file: str = ""
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool | None = False
    mode: str = "peer"
    extra: dict[str, Any] = field(default_factory=dict)

    def describe(self) -> str:
        """The endpoints in words, for messages (``connect tcp/...; listen tcp/...``)."""
        parts = []
        if self.connect:
            parts.append("connect " + ", ".join(self.connect))
        if self.listen:
            parts.append("listen " + ", ".join(self.listen))
        if self.config_file:
            parts.append(f"zenoh config {self.config_file}")
        if self.multicast_scouting:
            parts.append("multicast scouting")
        if not parts:
            return "no endpoint (give -e/--connect ENDPOINT; multicast scouting is off)"
        return "; ".join(parts)


def add_zenoh_args(p: argparse.ArgumentParser) -> None:
    """zenoh's usual flags: ``-c/--zenoh-config``, ``-e/--connect``, ``-l/--listen``."""
    g = p.add_argument_group("zenoh")
    g.add_argument("-c", "--zenoh-config", metavar="FILE", help="zenoh config file (JSON5)")
    g.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    g.add_argument("--scouting", action="store_true",
                   help="enable multicast scouting (off by default: explicit endpoints)")


def endpoints_from_args(args: argparse.Namespace, base: ZenohEndpoints | None = None
                        ) -> ZenohEndpoints:
    """Flags override ``base`` (typically from the service config)."""
    base = base or ZenohEndpoints()
    return ZenohEndpoints(
        config_file=args.zenoh_config or base.config_file,
        connect=tuple(args.connect) or base.connect,
        listen=tuple(args.listen) or base.listen,
        multicast_scouting=True if args.scouting else base.multicast_scouting,
        mode=base.mode,
    )


def zenoh_text(exc: BaseException) -> str:
    """A zenoh error's message without the Rust source locations and wrappers it carries."""
    text = str(exc)
    m = re.search(r'msg: "(.*?)"(?:, location|\s*})', text, re.S)
    if m:
        text = m.group(1)
    text = re.sub(r"\s+at /\S+?\.rs:\d+\.?", "", text)
    text = re.sub(r"\[([^\[\]]*)\]\s*$", r"\1", text.strip())
    return text.rstrip(".")


def _bad_endpoint(ep: ZenohEndpoints) -> str:
    """The first endpoint zenoh refuses, in words (empty if each is accepted alone)."""
    import zenoh

    for role, endpoints in (("connect", ep.connect), ("listen", ep.listen)):
        for e in endpoints:
            try:
                zenoh.Config().insert_json5(f"{role}/endpoints", json.dumps([e]))
            except Exception as exc:
                return f"{role} endpoint {e!r}: {zenoh_text(exc)}"
    return ""


_PORTED = ("tcp", "udp", "tls", "quic", "ws")
"""Locators whose address is ``host:port``."""


def _bad_port(endpoint: str) -> str:
    """Why an IP endpoint's port is not one (empty if it is, or the locator has no port):
    zenoh takes ``tcp/host:word`` and fails only when it resolves it, as an unreachable peer."""
    proto, _, rest = endpoint.partition("/")
    if proto not in _PORTED or not rest:
        return ""
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    host, colon, port = address.rpartition(":")
    if not colon or not host or (":" in host and not host.startswith("[")):
        return ""  # no port, or a bare IPv6 address: zenoh's own check tells
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        return f"port {port!r} is not a number 0-65535"
    return ""


def _config(ep: ZenohEndpoints) -> Any:
    import zenoh

    for role, endpoints in (("connect", ep.connect), ("listen", ep.listen)):
        for e in endpoints:
            if why := _bad_port(e):
                raise ConfigError(f"zenoh: {role} endpoint {e!r}: {why}")

    try:
        cfg = zenoh.Config.from_file(ep.config_file) if ep.config_file else zenoh.Config()
    except Exception as exc:  # zenoh raises its own ZError
        raise ConfigError(f"zenoh config {ep.config_file}: {zenoh_text(exc)}") from None
    try:
        cfg.insert_json5("mode", json.dumps(ep.mode))
        if ep.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(ep.connect)))
        if ep.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(ep.listen)))
        if ep.multicast_scouting is not None:
            cfg.insert_json5("scouting/multicast/enabled", json.dumps(ep.multicast_scouting))
        for key, value in ep.extra.items():
            cfg.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ConfigError(f"zenoh: {_bad_endpoint(ep) or f'{zenoh_text(exc)} ({ep.describe()})'}"
                          ) from None
    return cfg


@contextmanager
def open_session(ep: ZenohEndpoints) -> Iterator[Any]:
    """A zenoh session, closed on exit; library errors become :class:`TransportError`."""
    import zenoh

    cfg = _config(ep)
    try:
        session = zenoh.open(cfg)
    except Exception as exc:
        raise TransportError(f"cannot open a zenoh session ({ep.describe()}): "
                             f"{zenoh_text(exc)}") from exc
    try:
        yield session
    finally:
        session.close()


MAX_BURST = 2048
"""Input frames kept between two ticks: a stall of the loop of up to 2 s of a 1 kHz sender
is caught up with every sample (:data:`motcomp.core.tick.MAX_CATCH_UP`); longer keeps the
newest."""


class ZenohSource:
    """The payloads on a key since the last call, oldest first, never blocking (a
    ``RingChannel(MAX_BURST)`` subscriber: a longer burst keeps its newest frames)."""

    def __init__(self, session: Any, key: str) -> None:
        import zenoh

        self.key = key
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(MAX_BURST))

    def drain(self) -> list[bytes]:
        out: list[bytes] = []
        recv = self._sub.try_recv
        while (sample := recv()) is not None:
            out.append(sample.payload.to_bytes())
        return out

    def close(self) -> None:
        self._sub.undeclare()


class ZenohSink:
    """Non-blocking publisher for the data path (express, drop on congestion, real time)."""

    def __init__(self, session: Any, key: str, realtime: bool = True) -> None:
        import zenoh

        self.key = key
        self._pub = session.declare_publisher(
            key, express=True, congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.REAL_TIME if realtime else zenoh.Priority.DATA)
        self.sent = 0
        self.errors = 0

    def put(self, payload: bytes) -> None:
        try:
            self._pub.put(payload)
            self.sent += 1
        except Exception:  # a closed session or a transport error must not stop the loop
            self.errors += 1

    def heard(self) -> bool:
        """Whether a subscriber of the key is reachable now (the publisher's matching status;
        True where zenoh cannot tell)."""
        try:
            return bool(self._pub.matching_status.matching)
        except Exception:  # a closed session: nothing to tell
            return True

    def send(self, out: TickOutput, t: float) -> None:
        """An :class:`~motcomp.io.ports.OutputPort`: the output frame of docs/WIRE.md."""
        self.put(encode_output(out.seq, t, out.src_seq, out.u, out.flags, out.rx_ns))

    def close(self) -> None:
        self._pub.undeclare()


ZENOH_TIMEOUT = "Timeout"
"""The error zenoh itself replies with when a queryable matched but did not answer in time."""


def query(session: Any, key: str, payload: bytes | None = None, timeout_s: float = 2.0
          ) -> list[bytes]:
    """Payloads of the replies to a query: none if no queryable matched.

    Raises
    ------
    NoAnswerError
        A queryable matched but did not answer within ``timeout_s`` (and none other did).
    TransportError
        The queryable replied with an error.
    """
    out: list[bytes] = []
    kwargs: dict[str, Any] = {"timeout": timeout_s}
    if payload is not None:
        kwargs["payload"] = payload
    late = False
    for reply in session.get(key, **kwargs):
        if reply.ok is not None:
            out.append(reply.ok.payload.to_bytes())
        elif (err := reply.err.payload.to_string()) == ZENOH_TIMEOUT:
            late = True
        else:
            raise TransportError(f"query {key}: {err}")
    if late and not out:
        raise NoAnswerError(f"query {key}: received, not answered within {timeout_s:g} s")
    return out


def first_reply(session: Any, key: str, payload: bytes | None = None, timeout_s: float = 2.0
                ) -> bytes:
    """The first reply to a query, or :class:`TransportError` if none came in time."""
    replies = query(session, key, payload, timeout_s)
    if not replies:
        raise TransportError(f"no reply to query {key} within {timeout_s} s")
    return replies[0]


def wait_for_subscriber(session: Any, key: str, timeout_s: float,
                        stop: threading.Event | None = None) -> bool:
    """Wait up to ``timeout_s`` for a subscriber matching ``key`` to be reachable (a
    publisher's matching status, zenoh 1.x); True as soon as one is, False on timeout or
    ``stop``."""
    pub = session.declare_publisher(key)
    try:
        t_end = time.monotonic() + timeout_s
        while True:
            if pub.matching_status.matching:
                return True
            if time.monotonic() >= t_end or (stop is not None and stop.is_set()):
                return False
            time.sleep(0.02)
    finally:
        pub.undeclare()


def connected_peers(session: Any) -> int:
    """How many zenoh peers and routers ``session`` is connected to now."""
    info = session.info
    return len(list(info.peers_zid())) + len(list(info.routers_zid()))


def free_tcp_port() -> int:
    """A free TCP port on the loopback (for tests and the demo)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def peers(ports: Sequence[int]) -> tuple[str, ...]:
    return tuple(loopback(p) for p in ports)
