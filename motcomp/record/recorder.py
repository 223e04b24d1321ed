"""``motcomp record``: write what crosses the wire to MCAP, in a process of its own.

::

    zenoh subscribers (callbacks: stamp time.time_ns(), append to a bounded queue)
        -> main thread: drain the queue every few ms -> SessionWriter (mcap.Writer)
           -> a chunk is compressed and written when it is full or every flush_s (then fsync)
           -> a new part when rotation is due

The recorder never runs in the control loop: a chunk flush takes a few milliseconds.  Memory
is bounded -- the queue (:attr:`RecordOptions.queue_max` messages; beyond it messages are
dropped and counted), one open chunk, and the per-chunk indexes the MCAP summary needs.
SIGTERM/SIGINT (or ``duration_s``) finish the file cleanly (summary and footer); a file cut
short by a crash or power loss is readable up to its last complete chunk, which is at most
``flush_s`` old.  The file format is specified in docs/RECORDING.md.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from motcomp import __version__
from motcomp.errors import ConfigError, MotcompError, TransportError
from motcomp.io.zenoh_io import ZenohEndpoints, connected_peers, first_reply, open_session
from motcomp.record.frames import frame_time_and_seq
from motcomp.record.session import DEFAULT_KEYS

__all__ = ["RecordOptions", "RecordSummary", "SessionWriter", "default_compression", "record"]

log = logging.getLogger("motcomp.record")

METADATA_NAME = "motcomp"
CONFIG_ATTACHMENT = "config.json"


def default_compression() -> str:
    """``zstd`` if the zstandard package is there, else ``lz4``, else ``none``."""
    for name, module in (("zstd", "zstandard"), ("lz4", "lz4.frame")):
        try:
            __import__(module)
            return name
        except ImportError:
            continue
    return "none"


def part_path(path: Path, index: int) -> Path:
    """``FILE.mcap`` -> ``FILE-0001.mcap`` for part 1."""
    return path.with_name(f"{path.stem}-{index:04d}{path.suffix}")


class SessionWriter:
    """Writes a recording in the layout of docs/RECORDING.md, rotating into parts if asked.

    Parameters
    ----------
    path
        The file; with rotation the parts are ``<stem>-0001<suffix>``, ``-0002``...
    keys
        The keys recorded (one channel each, declared up front; other keys met later -- from
        wildcard subscriptions -- get their channel on first use).
    info
        Extra metadata (``config_hash``, ``config_path``) for the ``motcomp`` record.
    config_json
        The effective config, attached as ``config.json`` to every part.
    """

    def __init__(self, path: str | Path, keys: Sequence[str], info: dict[str, str] | None = None,
                 config_json: bytes | None = None, compression: str | None = None,
                 chunk_bytes: int = 1 << 20, rotate_bytes: int = 0, rotate_s: float = 0.0,
                 flush_s: float = 1.0, fsync: bool = True,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.path = Path(path)
        self.keys = list(keys)
        self.info = dict(info or {})
        self.config_json = config_json
        self.compression = compression or default_compression()
        if self.compression not in ("zstd", "lz4", "none"):
            raise ConfigError(f"compression must be zstd, lz4 or none, got {self.compression!r}")
        self.chunk_bytes = int(chunk_bytes)
        self.rotate_bytes = int(rotate_bytes)
        self.rotate_s = float(rotate_s)
        self.flush_ns = int(flush_s * 1e9) if flush_s > 0 else 0
        self.fsync = fsync
        self.clock = clock
        self.started = datetime.now(UTC).isoformat()
        self.parts: list[Path] = []
        self.counts: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self._writer: Any = None
        self._file: IO[bytes] | None = None
        self._channels: dict[str, int] = {}
        self._part_t0 = 0
        self._last_flush = 0
        self._since_check = 0
        self._open()

    @property
    def rotating(self) -> bool:
        return self.rotate_bytes > 0 or self.rotate_s > 0

    def _open(self) -> None:
        from mcap.writer import CompressionType, Writer

        path = part_path(self.path, len(self.parts) + 1) if self.rotating else self.path
        if not path.parent.is_dir():  # a typo'd directory is not created behind the user
            raise TransportError(f"{path}: cannot write: directory {path.parent} does not exist")
        try:
            self._file = path.open("wb")
        except OSError as exc:
            raise TransportError(f"{path}: cannot write: {exc.strerror}") from None
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}[self.compression]
        w = Writer(self._file, chunk_size=self.chunk_bytes, compression=comp)
        w.start(profile="", library=f"motcomp {__version__}")
        meta = {"version": __version__, "started": self.started, "keys": json.dumps(self.keys),
                **self.info}
        if self.rotating:
            meta["part"] = str(len(self.parts) + 1)
        w.add_metadata(METADATA_NAME, meta)
        now = self.clock()
        if self.config_json is not None:
            w.add_attachment(now, now, CONFIG_ATTACHMENT, "application/json", self.config_json)
        self._writer = w
        self._channels = {}
        for key in self.keys:
            if not any(c in key for c in "*$?"):
                self._channel(key)
        self.parts.append(path)
        self._part_t0 = now
        self._last_flush = now

    def attach_service(self, info: dict[str, str], config_json: bytes | None) -> None:
        """The service's metadata (and config) learnt after the file was opened: written into
        the open part now (a later metadata record replaces the first for readers) and into
        every later part."""
        self.info.update(info)
        if config_json is not None:
            self.config_json = config_json
        meta = {"version": __version__, "started": self.started, "keys": json.dumps(self.keys),
                **self.info}
        if self.rotating:
            meta["part"] = str(len(self.parts))
        self._writer.add_metadata(METADATA_NAME, meta)
        if config_json is not None:
            now = self.clock()
            self._writer.add_attachment(now, now, CONFIG_ATTACHMENT, "application/json",
                                        config_json)

    def _channel(self, key: str) -> int:
        cid = self._channels.get(key)
        if cid is None:
            cid = self._writer.register_channel(topic=key, message_encoding="msgpack",
                                                schema_id=0, metadata={"zenoh_key": key})
            self._channels[key] = cid
        return cid

    def write(self, key: str, log_ns: int, payload: bytes) -> None:
        """One message as received: ``publish_time`` and ``sequence`` from the frame's own
        ``t`` and ``seq`` when it has them (docs/RECORDING.md)."""
        t_ns, seq = frame_time_and_seq(payload)
        if seq is None:
            seq = self._seq.get(key, 0)
            self._seq[key] = seq + 1
        self.write_raw(key, log_ns, log_ns if t_ns is None else t_ns, seq, payload)

    def write_raw(self, key: str, log_ns: int, publish_ns: int, sequence: int,
                  payload: bytes) -> None:
        """One message with its fields already known."""
        self._writer.add_message(self._channel(key), log_time=log_ns, data=payload,
                                 publish_time=publish_ns, sequence=sequence & 0xFFFFFFFF)
        self.counts[key] = self.counts.get(key, 0) + 1
        self._since_check += 1
        if self._since_check >= 64:
            self._since_check = 0
            self.tick(log_ns)

    def tick(self, now_ns: int | None = None) -> None:
        """Periodic work: time-based chunk flush and rotation."""
        now = self.clock() if now_ns is None else now_ns
        if self.rotating and (
                (self.rotate_s > 0 and now - self._part_t0 >= self.rotate_s * 1e9) or
                (self.rotate_bytes > 0 and self._file is not None and
                 self._file.tell() >= self.rotate_bytes)):
            self._finish()
            self._open()
            return
        if self.flush_ns and now - self._last_flush >= self.flush_ns:
            self.flush()
            self._last_flush = now

    def flush(self) -> None:
        """Close the open chunk and push it to disk (so that a crash loses at most what came
        after)."""
        if self._writer is None or self._file is None:
            return
        if hasattr(self._writer, "flush"):
            self._writer.flush()
        self._file.flush()
        if self.fsync:
            with contextlib.suppress(OSError):  # e.g. a pipe
                os.fsync(self._file.fileno())

    def _finish(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._writer = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def close(self) -> None:
        """Finish the file (summary, footer); safe to call twice."""
        self._finish()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class RecordOptions:
    """What ``motcomp record`` does (see the module docstring)."""

    out: Path
    keys: list[str] = field(default_factory=lambda: list(DEFAULT_KEYS.values()))
    duration_s: float = 0.0
    rotate_mb: float = 0.0
    rotate_s: float = 0.0
    compression: str | None = None
    chunk_kb: int = 1024
    flush_s: float = 1.0
    status_key: str = DEFAULT_KEYS["status"]
    status_timeout_s: float = 0.5
    """Each query of the service's status waits this long (0: never ask, attach no config)."""
    status_retry_s: float = 2.0
    """Until the config is attached: ask again this often, besides taking it from the status
    frames the service publishes (when the status key is recorded)."""
    extra_info: dict[str, str] = field(default_factory=dict)
    """Metadata entries of the caller's, written with the service's when the recording ends
    (they may be filled while it runs)."""
    queue_max: int = 200_000
    poll_s: float = 0.005


@dataclass
class RecordSummary:
    parts: list[Path]
    counts: dict[str, int]
    dropped: int
    duration_s: float
    status: dict[str, Any] | None
    config_missing: str | None = None
    """Why the recording holds no config (None: it holds the service's)."""
    keys: tuple[str, ...] = ()
    """The keys subscribed to (a key of no message is said)."""
    unreached: str | None = None
    """The endpoints, where no zenoh peer was connected at any time of the recording."""

    def text(self) -> str:
        lines = [f"recorded {sum(self.counts.values())} messages in {self.duration_s:.1f} s to "
                 + ", ".join(str(p) for p in self.parts)]
        if self.unreached is not None:
            lines.append(f"  no zenoh peer was reachable ({self.unreached}) at any time of the "
                         "recording: is the service running and the endpoint right?")
        lines += [f"  {k}: {n}" for k, n in sorted(self.counts.items())]
        lines += [f"  {k}: nothing came (a service whose output goes over CAN alone sends no "
                  f"commands on zenoh: output.transport = \"both\", docs/DEPLOYMENT.md)"
                  if k == DEFAULT_KEYS["output"] else f"  {k}: nothing came"
                  for k in self.keys if "*" not in k and not self.counts.get(k)]
        lines.append(f"  config: not recorded ({self.config_missing})" if self.config_missing
                     else "  config: the service's, attached")
        lines.append(f"  dropped (queue full): {self.dropped}")
        return "\n".join(lines)


def service_info(status: dict[str, Any] | None) -> tuple[dict[str, str], bytes | None]:
    """Metadata entries and the config attachment from a status reply.

    The config file named in the status (the config in force: the start-up file or the last
    accepted ``reload --config``), with the status' active profile, is read and attached only if
    it still hashes to the config the service runs (it may have been edited since)."""
    if not status:
        return {}, None
    cfg = status.get("config") or {}
    info = {}
    if isinstance(cfg.get("hash"), str):
        info["config_hash"] = cfg["hash"]
    if isinstance(cfg.get("path"), str):
        info["config_path"] = cfg["path"]
    attachment = None
    path = cfg.get("path")
    if isinstance(path, str) and Path(path).is_file():
        from motcomp.config import config_hash, load_config

        try:
            loaded = load_config(path)
        except MotcompError as exc:
            log.warning("config %s named by the service does not load: %s", path, exc)
        else:
            profile = status.get("profile", loaded.profile)  # `motcomp profile` switches it
            if profile != loaded.profile and (profile is None or profile in loaded.profiles):
                loaded = loaded.model_copy(update={"profile": profile})
            if config_hash(loaded) == cfg.get("hash"):
                attachment = json.dumps(loaded.model_dump(mode="json"), indent=1).encode()
            else:
                log.warning("config %s changed since the service loaded it (hash %s, service "
                            "%s): not attached", path, config_hash(loaded), cfg.get("hash"))
    return info, attachment


def record(opts: RecordOptions, endpoints: ZenohEndpoints,
           stop: threading.Event | None = None) -> RecordSummary:
    """Record until ``stop`` (SIGTERM/SIGINT in the main thread) or ``opts.duration_s``."""
    import msgpack

    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    queue: deque[tuple[str, int, bytes]] = deque()
    dropped = [0]
    qmax = opts.queue_max

    def on_sample(sample: Any) -> None:
        t = time.time_ns()
        if len(queue) >= qmax:
            dropped[0] += 1
            return
        queue.append((str(sample.key_expr), t, sample.payload.to_bytes()))

    status: dict[str, Any] | None = None
    missing: str | None = None if opts.status_timeout_s > 0 else "not asked (--status-timeout 0)"
    watch = opts.status_timeout_s > 0  # until the service's config is settled

    def ask() -> dict[str, Any] | None:
        nonlocal missing
        try:
            raw = first_reply(session, opts.status_key, None, opts.status_timeout_s)
            st = msgpack.unpackb(raw, raw=False)
        except (TransportError, ValueError, msgpack.UnpackException) as exc:
            missing = f"no status from the service on {opts.status_key!r}: {exc}"
            return None
        queue.append((opts.status_key, time.time_ns(), raw))
        return st if isinstance(st, dict) else None

    def settle(st: dict[str, Any]) -> bool:
        """Take the service's metadata and config from one status; True once settled (the
        config attached, or refused for a reason the log gives)."""
        nonlocal status, missing
        info, attachment = service_info(st)
        if not info:
            missing = "the service's status names no config"
            return False
        status = st
        writer.attach_service(info, attachment)
        missing = None if attachment is not None else (
            f"the config file {info.get('config_path')!r} named by the service is not the one "
            "it runs (changed or unreadable since it loaded it)")
        if attachment is not None:
            log.info("config attached: %s (hash %s), from the service's status %.1f s into the "
                     "recording", info.get("config_path"), info.get("config_hash"),
                     time.monotonic() - t0)
        return True

    with open_session(endpoints) as session:
        subs = []
        try:
            for key in opts.keys:
                subs.append(session.declare_subscriber(key, on_sample))
            first = ask() if watch else None
            writer = SessionWriter(opts.out, opts.keys, None, None, opts.compression,
                                   opts.chunk_kb * 1024, int(opts.rotate_mb * 1e6),
                                   opts.rotate_s, opts.flush_s)
            t0 = time.monotonic()
            if first is not None and settle(first):
                watch = False
            next_ask = t0 + opts.status_retry_s
            peer_seen, next_peers = False, t0
            log.info("recording %s to %s", ", ".join(opts.keys), writer.path)
            try:
                while not stop.is_set():
                    now = time.monotonic()
                    if opts.duration_s > 0 and now - t0 >= opts.duration_s:
                        break
                    while queue:
                        key, t_ns, payload = queue.popleft()
                        writer.write(key, t_ns, payload)
                        if watch and key == opts.status_key:
                            watch = not settle(_status_of(payload))
                    if watch and now >= next_ask:  # the status key may not be recorded
                        st = ask()
                        watch = not (st is not None and settle(st))
                        next_ask = time.monotonic() + opts.status_retry_s
                    if not peer_seen and now >= next_peers:
                        peer_seen = connected_peers(session) > 0
                        next_peers = now + 0.5
                    writer.tick()
                    stop.wait(opts.poll_s)
            finally:
                peer_seen = peer_seen or connected_peers(session) > 0
                for s in subs:
                    s.undeclare()
                subs = []
                while queue:
                    key, t_ns, payload = queue.popleft()
                    writer.write(key, t_ns, payload)
                    if watch and key == opts.status_key:
                        watch = not settle(_status_of(payload))
                end_info = dict(opts.extra_info)
                if missing is not None:
                    if opts.status_timeout_s > 0:
                        log.warning("recorded without the service's config (%s): a replay "
                                    "needs --config FILE", missing)
                    end_info["config_missing"] = missing
                if end_info:
                    writer.attach_service(end_info, None)
                writer.close()
        finally:
            for s in subs:
                s.undeclare()
    return RecordSummary(writer.parts, dict(writer.counts), dropped[0], time.monotonic() - t0,
                         status, missing, tuple(opts.keys),
                         None if peer_seen else endpoints.describe())


def _status_of(payload: bytes) -> dict[str, Any]:
    """A status frame as a dict ({} if it is not one)."""
    import msgpack

    try:
        st = msgpack.unpackb(payload, raw=False)
    except (ValueError, msgpack.UnpackException):
        return {}
    return st if isinstance(st, dict) else {}
