"""A recorded session as numpy arrays: :func:`read_session`.

Every stream keeps, per message, the recorder's ``log_ns`` (receive time, ns since the epoch),
the ``publish_ns`` and ``sequence`` of the MCAP message, and its decoded fields:

=================  =========================================================================
stream             fields
=================  =========================================================================
``inputs``         the raw payloads (:meth:`InputStream.payload`: what a replay's tick reads),
                   and for analysis ``seq`` (int64), ``t`` (s, NaN without ``t``), ``pos``
                   (n x 8, NaN where the frame does not carry the axis), ``decoded`` (those
                   could be read; whether the service accepts a frame is the tick's call)
``outputs``        ``seq``, ``t`` (the tick's time), ``src_seq``, ``pos`` (n x 8), ``flags``
                   (bit field, :data:`motcomp.record.frames.FLAG_BITS`), ``valid``
``feedback``       ``t``, ``pos``, ``acc`` (n x 8), ``valid``
``status``         list of ``(log_ns, dict)``
=================  =========================================================================

Axis columns are in :data:`motcomp.core.axes.AXES` order.  For identification,
:meth:`Session.identification_data` gives ``(t, cmd, acc)`` of one axis: the feedback times,
the command in force at each (the last output sent before it) and the measured acceleration;
:meth:`Session.identification_columns` adds, per sample, whether the axis was bypassed or
limited.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import re
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from motcomp.core.axes import AXIS_INDEX
from motcomp.errors import DataError
from motcomp.record.frames import (
    FLAG_BITS,
    FeedbackColumns,
    InputColumns,
    OutputColumns,
    decode_rows,
)
from motcomp.record.mcapio import MessageBatch, ScanResult, message_counts, metadata_dict, scan

__all__ = [
    "DEFAULT_KEYS",
    "FeedbackStream",
    "IdentificationColumns",
    "InputStream",
    "OutputStream",
    "RawStream",
    "Session",
    "output_in_force",
    "read_session",
    "session_parts",
]

log = logging.getLogger("motcomp.record")

DEFAULT_KEYS = {"input": "sim/motion/setpoint", "output": "platform/setpoint",
                "feedback": "platform/feedback", "status": "motcomp/status"}
"""The keys motcomp records by default, by role (the service config's defaults)."""


@dataclass
class RawStream:
    """Messages of one key, undecoded."""

    key: str
    log_ns: np.ndarray
    publish_ns: np.ndarray
    payloads: list[bytes] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.log_ns.size)

    def payload(self, i: int) -> bytes:
        """The recorded bytes of message ``i``."""
        return self.payloads[i]


@dataclass
class InputStream(RawStream):
    """Input frames: their payloads in one buffer (``data[bounds[i]:bounds[i + 1]]`` is frame
    ``i``; an hour at 1 kHz is 3.6 M frames, kept without an object each) and columns decoded
    for analysis."""

    data: bytes = b""
    bounds: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    seq: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    decoded: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def payload(self, i: int) -> bytes:
        return self.data[int(self.bounds[i]):int(self.bounds[i + 1])]


@dataclass
class OutputStream(RawStream):
    seq: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    src_seq: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    flags: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    valid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rx: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """ns after ``t`` the tick took its input frames (0: at ``t``, or not recorded)."""


@dataclass
class FeedbackStream(RawStream):
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    acc: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    valid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


def output_in_force(to: np.ndarray, lost_from: np.ndarray, times: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Index of the output in force at each of ``times`` (the last output whose time ``to``,
    increasing, is not after it), and whether it is known (not before the first output, not
    from ``lost_from`` of the output on, where outputs were lost: infinity if none were)."""
    k = np.searchsorted(to, times, side="right") - 1
    known = (k >= 0) & (times < lost_from[np.maximum(k, 0)])
    return k, known


def pairing_phase_ms(t: np.ndarray, t_in_force: np.ndarray) -> float:
    """The pairing's phase (ms): the median time from the output in force to the sample it is
    paired with (``t``; nan if none).  It is part of the stack's delay that a fit on the paired
    samples reads as the model's hold, not as ``Td`` (docs/SUPERVISION.md, "The stack's
    share"); the median, as a stall holds an old output in force."""
    return float(np.median(t - t_in_force)) * 1e3 if t.size else math.nan


@dataclass
class Session:
    """A recording (one file or the parts of a rotated one), decoded; see the module
    docstring."""

    paths: list[Path]
    keys: dict[str, str]
    metadata: dict[str, Any]
    config_json: dict[str, Any] | None
    inputs: InputStream | None
    outputs: OutputStream | None
    feedback: FeedbackStream | None
    status: list[tuple[int, dict[str, Any]]]
    other: dict[str, RawStream]
    warnings: list[str]
    truncated: bool
    messages: int
    damaged: bool = False
    """A read stopped at a corrupt chunk (:attr:`truncated` too), not where a file ends."""

    @property
    def name(self) -> str:
        first = str(self.paths[0])
        return first if len(self.paths) == 1 else f"{first} (+{len(self.paths) - 1} parts)"

    def config(self) -> Any:
        """The service's effective config recorded with the session, or None.

        Raises
        ------
        ConfigError
            If the attached config does not validate.
        """
        if self.config_json is None:
            return None
        from motcomp.config import parse_config

        return parse_config(self.config_json, f"{self.name}: attachment config.json")

    def duration_s(self) -> float:
        times = [s.log_ns for s in (self.inputs, self.outputs, self.feedback) if s is not None
                 and len(s)]
        if not times:
            return 0.0
        return float((max(int(t[-1]) for t in times) - min(int(t[0]) for t in times)) / 1e9)

    def _outputs_of(self, axis: str, clock: str
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(t, cmd, flags, lost_from)`` of the valid outputs of ``axis`` in time order;
        ``lost_from[j]`` is the estimated time of the first output the recorder lost after
        output ``j`` (a jump in ``seq``), else infinity."""
        if axis not in AXIS_INDEX:
            raise DataError(f"unknown axis {axis!r}")
        if clock not in ("frame", "log"):
            raise DataError(f"clock must be 'frame' or 'log', got {clock!r}")
        if self.outputs is None or self.feedback is None or not len(self.outputs) or \
                not len(self.feedback):
            missing = [f"{role} ({self.keys.get(role, DEFAULT_KEYS[role])})"
                       for role, s in (("output", self.outputs), ("feedback", self.feedback))
                       if s is None or not len(s)]
            raise DataError(f"{self.name}: identification needs recorded outputs and feedback; "
                            f"no messages on {' and '.join(missing)}")
        i = AXIS_INDEX[axis]
        out = self.outputs
        t_out = out.t if clock == "frame" else out.log_ns / 1e9
        ok = out.valid & np.isfinite(out.pos[:, i]) & np.isfinite(t_out)
        to, cmd, flags, seq = t_out[ok], out.pos[ok, i], out.flags[ok], out.seq[ok]
        order = np.argsort(to, kind="stable")
        to, cmd, flags, seq = to[order], cmd[order], flags[order], seq[order]
        lost_from = np.full(to.size, np.inf)
        ds = np.diff(seq)
        lost = np.flatnonzero(ds > 1)
        lost_from[lost] = to[lost] + (to[lost + 1] - to[lost]) / ds[lost]
        return to, cmd, flags, lost_from


    def config_hashes(self) -> list[str]:
        """The hashes of the configs the service ran during the recording, as its recorded
        statuses name them, in the order they first appear (more than one: it was reloaded to
        another config)."""
        seen: dict[str, None] = {}
        for _, st in self.status:
            cfg = st.get("config")
            if isinstance(cfg, dict) and isinstance(cfg.get("hash"), str):
                seen.setdefault(cfg["hash"])
        return list(seen)

    def command_in_force(self, axis: str, times: np.ndarray, clock: str = "frame",
                         bridge_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``(cmd, known)``: the output position of ``axis`` in force at each of ``times`` (s
        on ``clock``, see :meth:`identification_columns`), and whether it is known (NaN where
        not: before the first output, or where the recorder lost outputs).

        With ``bridge_s`` > 0, outputs the recorder lost between two it kept at most
        ``bridge_s`` apart are taken on the line joining those two, at instants spread evenly
        between them (``known`` stays False there): off the lost commands by at most
        ``a bridge_s**2 / 8`` for an axis whose acceleration stays within ``a``.

        Raises
        ------
        DataError
            If the session lacks outputs or feedback, the axis or the clock is unknown.
        """
        to, cmd, _, lost_from = self._outputs_of(axis, clock)
        times = np.asarray(times, dtype=float)
        k, known = output_in_force(to, lost_from, times)
        k0 = np.maximum(k, 0)
        out = np.where(known, cmd[k0], np.nan)
        if bridge_s > 0 and to.size > 1:
            k1 = np.minimum(k0 + 1, to.size - 1)
            span = to[k1] - to[k0]
            b = np.flatnonzero(~known & (k >= 0) & (k0 + 1 < to.size) & (span <= bridge_s))
            if b.size:
                step = lost_from[k0[b]] - to[k0[b]]  # the period of the outputs in the span
                j = np.floor((times[b] - to[k0[b]]) / step)  # the lost output in force
                frac = np.clip(j / np.round(span[b] / step), 0.0, 1.0)  # of the seq step
                out[b] = cmd[k0[b]] + (cmd[k1[b]] - cmd[k0[b]]) * frac
        return out, known

    def identification_columns(self, axis: str, clock: str = "frame") -> IdentificationColumns:
        """What the platform received and what it did, per feedback sample of ``axis``.

        At each feedback time, the command in force is the last output whose time is not after
        it; the flags say whether that output had the axis in bypass, and whether any output
        since the previous feedback sample limited it.  ``clock`` is ``"frame"`` (the outputs'
        tick time ``t`` and the feedback's ``t``) or ``"log"`` (the recorder's receive times).
        Feedback without a finite time, before the first output, or whose command in force is
        unknown (outputs the recorder lost: a jump in the outputs' ``seq``) is left out
        (counted in :attr:`IdentificationColumns.unknown`).

        Raises
        ------
        DataError
            If the session lacks outputs or feedback, the axis or the clock is unknown.
        """
        to, cmd, flags, lost_from = self._outputs_of(axis, clock)
        i = AXIS_INDEX[axis]
        fb = self.feedback
        assert fb is not None
        t_fb = fb.t if clock == "frame" else fb.log_ns / 1e9
        ok_f = fb.valid & np.isfinite(fb.acc[:, i]) & np.isfinite(t_fb)
        fb_index = np.flatnonzero(ok_f)
        tf, acc = t_fb[ok_f], fb.acc[ok_f, i]
        k, known = output_in_force(to, lost_from, tf)
        unknown = int(np.count_nonzero(~known & (k >= 0)))
        k, tf, acc, fb_index = k[known], tf[known], acc[known], fb_index[known]
        sat_bit, bypass_bit = FLAG_BITS[f"sat:{axis}"], FLAG_BITS[f"bypass:{axis}"]
        sat_count = np.concatenate([[0], np.cumsum((flags & sat_bit) != 0)])
        # outputs (k_prev, k], and at least k itself
        k_prev = np.concatenate([k[:1] - 1, k[:-1]])
        limited = sat_count[k + 1] - sat_count[np.minimum(k_prev + 1, k)] > 0
        bypassed = (flags[k] & bypass_bit) != 0
        start = min(float(to[0]), float(tf[0])) if tf.size else float(to[0])
        return IdentificationColumns(axis=axis, clock=clock, t=tf, cmd=cmd[k], t_out=to[k],
                                     acc=acc,
                                     bypassed=bypassed, limited=limited, feedback_index=fb_index,
                                     start_s=start, unknown=unknown)

    def identification_data(self, axis: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t, cmd, acc)`` of ``axis``: feedback times (s), the output position in force at
        each (the last output whose tick time ``t`` is not after it) and the feedback
        acceleration; see :meth:`identification_columns` (frame clock) for what is left out.

        Raises
        ------
        DataError
            If the session lacks outputs or feedback, or the axis is unknown.
        """
        c = self.identification_columns(axis)
        return c.t, c.cmd, c.acc


@dataclass(frozen=True)
class IdentificationColumns:
    """One axis per feedback sample (:meth:`Session.identification_columns`)."""

    axis: str
    clock: str
    t: np.ndarray
    """Feedback time (s, on ``clock``)."""
    cmd: np.ndarray
    """Output position in force (m or rad)."""
    t_out: np.ndarray
    """That output's time (s, on ``clock``): on the frame clock, ``t - t_out`` is the
    pairing's phase."""
    acc: np.ndarray
    """Measured acceleration (m/s^2 or rad/s^2)."""
    bypassed: np.ndarray
    """The output in force carries ``bypass:<axis>`` (compensation off)."""
    limited: np.ndarray
    """An output since the previous feedback sample carries ``sat:<axis>``."""
    feedback_index: np.ndarray
    """Index of each sample's message in :attr:`Session.feedback`."""
    start_s: float
    """Earliest output or feedback time (s, on ``clock``): the recording's start."""
    unknown: int
    """Feedback samples left out because the command in force was lost."""


def session_parts(path: str | Path) -> list[Path]:
    """The files of a recording: ``path`` itself, or, if it does not exist, the parts
    ``<stem>-0001<suffix>``, ``<stem>-0002<suffix>``... that rotation wrote.

    Raises
    ------
    DataError
        If neither exists.
    """
    p = Path(path)
    if p.is_file():
        return [p]
    pat = re.compile(re.escape(p.stem) + r"-(\d{4,})" + re.escape(p.suffix) + "$")
    parts = sorted((int(m.group(1)), c) for c in p.parent.glob(f"{p.stem}-*{p.suffix}")
                   if (m := pat.match(c.name)))
    if not parts:
        raise DataError(f"{p}: no such recording (nor rotated parts {p.stem}-0001{p.suffix}...)")
    return [c for _, c in parts]


def _concat(chunks: list[np.ndarray], empty: np.ndarray) -> np.ndarray:
    return np.concatenate(chunks) if chunks else empty


def _prefetch(it: Iterator[Any], depth: int = 2) -> Iterator[Any]:
    """Run ``it`` in a thread, ``depth`` items ahead: file reading and decompression (which
    release the GIL) overlap with the decoding of the previous batch."""
    q: queue.Queue[Any] = queue.Queue(depth)
    stop = threading.Event()
    end = object()

    def produce() -> None:
        try:
            for item in it:
                while not stop.is_set():
                    try:
                        q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(end)
        except BaseException as exc:  # handed to the consumer
            q.put(exc)

    th = threading.Thread(target=produce, name="motcomp-read", daemon=True)
    th.start()
    try:
        while True:
            item = q.get()
            if item is end:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        th.join(timeout=5)


class _Collector:
    """Decodes the batches of one key into its stream's columns: straight into arrays of the
    final size when the file's summary gives the message count, else batch by batch (joined at
    the end)."""

    def __init__(self, key: str, role: str | None, total: int | None, acc: bool,
                 windows: np.ndarray | None = None) -> None:
        self.key, self.role, self.total, self.acc = key, role, total, acc
        self.windows = windows  # [start, end, start, end...] log ns: decode only these
        self.segments: list[tuple[Any, np.ndarray, np.ndarray, int]] = []
        self.n = 0  # rows used in the last segment
        self.data: list[bytes] = []  # input payloads, one buffer per batch
        self.lengths: list[np.ndarray] = []

    def _new(self, n: int) -> Any:
        if self.role == "input":
            return InputColumns(n)
        if self.role == "output":
            return OutputColumns(n)
        if self.role == "feedback":
            return FeedbackColumns(n, self.acc)
        return []

    def add(self, mb: MessageBatch) -> None:
        if self.windows is not None:
            sel = np.searchsorted(self.windows, mb.log_ns, side="right") % 2 == 1
            if not sel.all():
                mb = MessageBatch(mb.channel, mb.buf, mb.offset[sel], mb.length[sel],
                                  mb.log_ns[sel], mb.publish_ns[sel] if mb.publish_ns.size
                                  else mb.publish_ns)
        m = len(mb)
        if not m:
            return
        if not self.segments or self.n + m > self.segments[-1][1].size:
            size = self.total if (self.total and not self.segments and m <= self.total) else m
            self.segments.append((self._new(size), np.zeros(size, np.int64),
                                  np.zeros(size, np.int64), 0))
            self.n = 0
        ex, log_ns, pub_ns, _ = self.segments[-1]
        log_ns[self.n:self.n + m] = mb.log_ns
        if mb.publish_ns.size:
            pub_ns[self.n:self.n + m] = mb.publish_ns
        if isinstance(ex, list):
            ex += [mb.payload(i) for i in range(m)]
        else:
            if self.role == "input":
                mv = memoryview(mb.buf.data)
                self.data.append(b"".join([mv[o:o + n] for o, n in zip(
                    mb.offset.tolist(), mb.length.tolist(), strict=True)]))
                self.lengths.append(mb.length.astype(np.int64))
            decode_rows(mb.buf, mb.offset, mb.length, ex, row0=self.n)
        self.n += m
        self.segments[-1] = (ex, log_ns, pub_ns, self.n)

    def finish(self, warnings: list[str]) -> RawStream:
        segs = self.segments

        def cat(get: Any, empty: np.ndarray) -> np.ndarray:
            parts = [get(seg)[:seg[3]] for seg in segs]
            return parts[0] if len(parts) == 1 else _concat(parts, empty)

        base: dict[str, Any] = dict(key=self.key, log_ns=cat(lambda x: x[1], np.zeros(0, np.int64)),
                                    publish_ns=cat(lambda x: x[2], np.zeros(0, np.int64)))
        if self.role == "input":
            bounds = np.zeros(sum(x.size for x in self.lengths) + 1, np.int64)
            np.cumsum(_concat(self.lengths, np.zeros(0, np.int64)), out=bounds[1:])
            data = b"".join(self.data)
            self.data.clear()
            return InputStream(**base, data=data, bounds=bounds,
                               seq=cat(lambda x: x[0].seq, np.zeros(0, np.int64)),
                               t=cat(lambda x: x[0].t, np.zeros(0)),
                               pos=cat(lambda x: x[0].pos, np.zeros((0, 8))),
                               decoded=cat(lambda x: x[0].decoded, np.zeros(0, bool)))
        if self.role == "output":
            bad = sum(seg[0].bad for seg in segs)
            if bad:
                warnings.append(f"{self.key}: {bad} output frames could not be decoded")
            return OutputStream(
                **base, seq=cat(lambda x: x[0].seq, np.zeros(0)).astype(np.int64),
                t=cat(lambda x: x[0].t, np.zeros(0)),
                src_seq=cat(lambda x: x[0].src_seq, np.zeros(0)).astype(np.int64),
                pos=cat(lambda x: x[0].pos, np.zeros((0, 8))),
                flags=cat(lambda x: x[0].flags, np.zeros(0, np.int64)),
                valid=cat(lambda x: x[0].valid, np.zeros(0, bool)),
                rx=cat(lambda x: x[0].rx, np.zeros(0, np.int64)))
        if self.role == "feedback":
            return FeedbackStream(**base, t=cat(lambda x: x[0].t, np.zeros(0)),
                                  pos=cat(lambda x: x[0].pos, np.zeros((0, 8))),
                                  acc=cat(lambda x: x[0].acc, np.zeros((0, 8))),
                                  valid=cat(lambda x: x[0].valid, np.zeros(0, bool)))
        return RawStream(**base, payloads=[p for seg in segs for p in seg[0]])


def read_session(path: str | Path | Sequence[str | Path], keys: dict[str, str] | None = None,
                 other_keys: bool = True, acc: bool = True, publish: bool = True,
                 feedback_windows: tuple[int, float] | None = None) -> Session:
    """Read a recording written by ``motcomp record`` (or any MCAP file of msgpack frames on
    motcomp's keys).

    ``keys`` maps roles (``input``, ``output``, ``feedback``, ``status``) to keys; the default
    takes them from the recorded config, else :data:`DEFAULT_KEYS`.  ``acc=False`` skips the
    feedback accelerations (left NaN), ``other_keys=False`` the keys of no role,
    ``publish=False`` the messages' publish times (left empty); ``feedback_windows=(n, s)``
    keeps only the feedback inside ``n`` windows of ``s`` seconds spread evenly over the
    session (enough for delay estimates, and much faster on long recordings; all of it if the
    file has no summary).  A truncated file is read up to
    its last complete chunk, with a warning (logged and kept in :attr:`Session.warnings`)
    naming the file and the number of messages recovered.

    Raises
    ------
    DataError
        If a file cannot be read, is not MCAP, or is unfinished with no message recovered.
    """
    paths = (session_parts(path) if isinstance(path, str | Path)
             else [Path(p) for p in path])
    warnings: list[str] = []
    metadata: dict[str, Any] = {}
    config_json: dict[str, Any] | None = None
    results: list[ScanResult] = []
    status: list[tuple[int, dict[str, Any]]] = []
    roles = dict(DEFAULT_KEYS)
    explicit = dict(keys or {})
    roles.update(explicit)
    counts: dict[str, Any] | None = {}
    span = [None, None]
    for p in paths:
        c = message_counts(p)
        if c is None or counts is None:
            counts = None
            continue
        first, last = c.pop("")
        span = [first if span[0] is None else span[0], last]
        for k, n in c.items():
            counts[k] = counts.get(k, 0) + n
    fb_windows = None
    if feedback_windows is not None and counts is not None and span[0] is not None:
        n_w, len_s = feedback_windows
        t0, t1 = int(span[0]), int(span[1])
        if (t1 - t0) / 1e9 > 2 * n_w * len_s:
            centres = t0 + (np.arange(n_w) + 0.5) / n_w * (t1 - t0)
            half = len_s * 1e9 / 2
            fb_windows = np.column_stack([centres - half, centres + half]).ravel()
    collectors: dict[str, _Collector] = {}
    for p in paths:
        res = ScanResult(p)
        results.append(res)
        for batch in _prefetch(scan(p, None, result=res, publish=publish, check_crc=True)):
            if not metadata:
                metadata = metadata_dict(res)
            if config_json is None:
                config_json = _config_attachment(res, warnings)
                if config_json is not None and not explicit:
                    roles.update(_keys_of(config_json))
            role_of = {v: k for k, v in roles.items()}
            for mb in batch:
                topic = mb.channel.topic
                role = role_of.get(topic)
                if mb.channel.message_encoding != "msgpack" and role is not None:
                    source = metadata_dict(res, "motcomp_export").get("source")
                    raise DataError(
                        f"{p}: {topic} is {mb.channel.message_encoding!r}, not msgpack: "
                        + (f"an export for viewers (motcomp export); read the recording it "
                           f"was made from, {source}" if source else
                           "not a recording of motcomp record"))
                if role == "status":
                    for i in range(len(mb)):
                        try:
                            obj = msgpack.unpackb(mb.payload(i), raw=False, strict_map_key=False)
                        except Exception:  # a bad status frame is skipped
                            continue
                        if isinstance(obj, dict):
                            status.append((int(mb.log_ns[i]), obj))
                    continue
                if role is None and not other_keys:
                    continue
                col = collectors.get(topic)
                if col is None:
                    windowed = role == "feedback" and fb_windows is not None
                    col = _Collector(topic, role, None if windowed or not counts else
                                     counts.get(topic), acc, fb_windows if windowed else None)
                    collectors[topic] = col
                col.add(mb)
        if not metadata:
            metadata = metadata_dict(res)
        if config_json is None:
            config_json = _config_attachment(res, warnings)
        if res.truncated and not res.complete:
            if not res.messages:
                meta = metadata_dict(res)
                raise DataError(
                    f"{p}: unfinished recording ({res.truncated}) with no complete chunk: no "
                    "message to read"
                    + (f" (started {meta['started']}: the recorder stopped before it wrote "
                       "its first chunk, at most --flush-s after the start)"
                       if meta.get("started") else ""))
            what = "damaged recording" if res.damaged else "unfinished recording"
            msg = (f"{p}: {what} ({res.truncated}); recovered {res.messages} messages from "
                   f"{res.chunks} complete chunks before it")
            warnings.append(msg)
            log.warning("%s", msg)
    streams: dict[str, Any] = {}
    other: dict[str, RawStream] = {}
    for key, col in collectors.items():
        stream = col.finish(warnings)
        if col.role in ("input", "output", "feedback"):
            streams[col.role] = stream
        else:
            other[key] = stream
    return Session(paths=paths, keys=roles, metadata=metadata, config_json=config_json,
                   inputs=streams.get("input"), outputs=streams.get("output"),
                   feedback=streams.get("feedback"), status=status, other=other,
                   warnings=warnings, truncated=any(r.truncated and not r.complete
                                                    for r in results),
                   messages=sum(r.messages for r in results),
                   damaged=any(r.damaged for r in results))


def _config_attachment(res: ScanResult, warnings: list[str]) -> dict[str, Any] | None:
    for name, _media, data in res.attachments:
        if name == "config.json":
            try:
                obj = json.loads(data)
            except ValueError:
                warnings.append(f"{res.path}: attachment config.json is not JSON")
                return None
            return obj if isinstance(obj, dict) else None
    return None


def _keys_of(cfg: dict[str, Any]) -> dict[str, str]:
    out = {}
    for role, section in (("input", "input"), ("output", "output"), ("feedback", "feedback"),
                          ("status", "status")):
        key = cfg.get(section, {}).get("key") if isinstance(cfg.get(section), dict) else None
        if isinstance(key, str):
            out[role] = key
    return out
